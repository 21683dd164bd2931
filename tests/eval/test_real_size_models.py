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


@pytest.mark.parametrize("name", ["mobile_sam", "sam_vit_b"])
def test_sam_real_size(name: str, rgb: np.ndarray) -> None:
    sam = SamOnnx(SamParams(**_paths(name), points_per_side=4, threads=2))
    assert not sam.batched  # the official decoder export takes one prompt per call
    res = sam.generate(rgb)
    K = len(res.masks)
    assert res.masks.shape == (K, H, W) and res.masks.dtype == np.bool_
    assert res.labels.shape == (H, W) and res.labels.dtype == np.int32
    assert res.labels.min() >= -1 and res.labels.max() < K
    assert res.stats["coverage"] == pytest.approx(np.mean(res.labels >= 0))
    assert 0 < res.stats["n_prompts_run"] <= res.stats["n_prompts"] <= 16
    assert res.stats["n_decoder_calls"] == res.stats["n_prompts_run"]
    assert res.iou.dtype == np.float32 and res.iou.shape == (K,)


def test_wrong_signatures_refused_naming_them() -> None:
    da = _paths("depth_anything_vits")["model_path"]
    sam = _paths("mobile_sam")
    with pytest.raises(ModelError, match="no input 'image'.*image-encoder export.*pixel_values"):
        SamOnnx(SamParams(encoder_path=da, decoder_path=sam["decoder_path"]))
    with pytest.raises(ModelError, match="no input 'image_embeddings'.*official SAM.*pixel_values"):
        SamOnnx(SamParams(encoder_path=sam["encoder_path"], decoder_path=da))
    with pytest.raises(ModelError, match="signature unknown.*point_coords.*known layouts"):
        DepthAnythingOnnx(DepthAnythingParams(model_path=sam["decoder_path"]))
