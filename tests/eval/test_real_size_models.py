"""The learned backends on real-size exports (random weights; issue 20): each loads, runs one
1242x375 keyframe, and gives outputs of the right shape, dtype and label range; a model of
another signature is refused with a message naming what it has.

The exports come from mogs_node/eval/real_size_models.py (cached in ``$MOGS_MODEL_CACHE`` or
``~/.cache/mogs-models``); without a cached export they need the ``models`` extra, else the
tests skip. Random weights: nothing here looks at what the masks or depths are.
"""

from __future__ import annotations

import numpy as np
import pytest

from mogs_node.depth_prior.depth_anything_onnx import DepthAnythingOnnx, DepthAnythingParams
from mogs_node.errors import ModelError
from mogs_node.ort import open_session
from mogs_node.segmentation.sam_onnx import SamOnnx, SamParams

pytestmark = [
    pytest.mark.slow,
    pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::UserWarning"),
]

H, W = 375, 1242


def _paths(name: str) -> dict[str, str]:
    from mogs_node.eval.real_size_models import ensure

    try:
        return ensure(name)
    except ImportError as err:
        pytest.skip(f"{name}: no cached export and the `models` extra is not installed ({err})")


@pytest.fixture(scope="module")
def rgb() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)


@pytest.mark.parametrize("name", ["depth_anything_vits", "depth_anything_vitb"])
def test_depth_anything_real_size(name: str, rgb: np.ndarray) -> None:
    path = _paths(name)["model_path"]
    net = DepthAnythingOnnx(DepthAnythingParams(model_path=path, input_size=140, threads=2))
    assert (net.input_name, net.output_name) == ("pixel_values", "predicted_depth")
    out = net.infer(rgb)
    assert out.net_hw == (140, 462)  # shorter side 140, both sides multiples of 14
    assert out.value.shape == (H, W) and out.value.dtype == np.float32
    assert out.confidence.shape == (H, W) and out.confidence.dtype == np.float32
    assert set(np.unique(out.confidence)) <= {0.0, 1.0}
    assert np.all(out.value[out.confidence == 0] == 0) and np.all(np.isfinite(out.value))
    if name == "depth_anything_vits":  # launch/learned.yaml's setting: the longer side at 518
        ub = DepthAnythingParams(
            model_path=path, input_size=518, resize_method="upper_bound", threads=2
        )
        out = DepthAnythingOnnx(ub).infer(rgb)
        assert out.net_hw == (154, 518) and out.value.shape == (H, W)
        assert out.value.dtype == np.float32 and np.all(np.isfinite(out.value))


@pytest.mark.parametrize("name", ["mobile_sam", "sam_vit_b"])
def test_sam_real_size(name: str, rgb: np.ndarray) -> None:
    # Random weights: nothing passes SAM's quality filters, so they are off here to give masks
    # to paint; launch/learned.yaml's prompts (square cells, 16 along the longer side, <= 16 run).
    params = SamParams(
        **_paths(name),
        threads=2,
        points_per_side=16,
        square_cells=True,
        max_prompts=16,
        pred_iou_thresh=0.0,
        stability_score_thresh=0.0,
    )
    sam = SamOnnx(params)
    # The official export fixes the prompt batch at 1; pruned of its full-size masks output and
    # with the batch axis freed, it was checked at start-up to give the file's outputs.
    assert sam.adapted and sam.batched and sam.batch == 8
    res = sam.generate(rgb)
    K = len(res.masks)
    assert res.masks.shape == (K, H, W) and res.masks.dtype == np.bool_
    assert res.labels.shape == (H, W) and res.labels.dtype == np.int32
    assert res.labels.min() >= -1 and res.labels.max() < K
    assert res.stats["n_prompts"] == 80  # 16 x 5 cells (the random frame has structure everywhere)
    assert 0 < res.stats["n_prompts_run"] <= 16
    assert res.stats["n_decoder_calls"] == np.ceil(res.stats["n_prompts_run"] / 8)
    assert K > 0 and res.stats["coverage"] == pytest.approx(np.mean(res.labels >= 0))
    assert res.stats["coverage"] > 0.5  # unfiltered masks of 16 prompts spread over the frame
    for k in np.unique(res.labels[res.labels >= 0]):
        assert np.all(res.masks[k][res.labels == k])
    assert res.iou.dtype == np.float32 and res.iou.shape == (K,)
    # Batched calls of the adapted decoder = the file's decoder, one prompt at a time.
    emb = sam.embed(rgb)
    pts = sam.prompt_points(rgb)[:3]
    low, iou = sam.decode(emb, pts, H, W)
    adapted = sam.decoder
    sam.decoder, sam.batched = open_session(params.decoder_path, threads=2), False  # the file's
    low1, iou1 = sam.decode(emb, pts, H, W)  # one call per prompt
    sam.decoder, sam.batched = adapted, True
    assert low.shape == low1.shape == (3, 4, 256, 256) and iou.shape == (3, 4)
    np.testing.assert_allclose(low, low1, atol=1e-4)
    np.testing.assert_allclose(iou, iou1, atol=1e-5)


def test_wrong_signatures_refused_naming_them() -> None:
    da = _paths("depth_anything_vits")["model_path"]
    sam = _paths("mobile_sam")
    with pytest.raises(ModelError, match="no input 'image'.*image-encoder export.*pixel_values"):
        SamOnnx(SamParams(encoder_path=da, decoder_path=sam["decoder_path"]))
    with pytest.raises(ModelError, match="no input 'image_embeddings'.*official SAM.*pixel_values"):
        SamOnnx(SamParams(encoder_path=sam["encoder_path"], decoder_path=da))
    with pytest.raises(ModelError, match="signature unknown.*point_coords.*known layouts"):
        DepthAnythingOnnx(DepthAnythingParams(model_path=sam["decoder_path"]))
