"""SAM ONNX backend: pre/post-processing and automatic mask generation on tiny exported models.

The tiny models (tests/_tiny_onnx.py) have the official export's input/output names and shapes and
compute discs around the prompt point, so every expectation below is exact geometry.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("onnx")
pytestmark = pytest.mark.filterwarnings(
    "ignore::DeprecationWarning", "ignore::UserWarning", "ignore:torch.tensor results"
)

sys.path.insert(0, str(Path(__file__).parents[1]))  # tests/: the helpers
import _tiny_onnx as _tiny_sam  # noqa: E402

from mogs_node.errors import ModelError  # noqa: E402
from mogs_node.segmentation.sam_onnx import (  # noqa: E402
    PIXEL_MEAN,
    PIXEL_STD,
    SamOnnx,
    SamParams,
    box_nms,
    grid_points,
    paint_masks,
    resized_hw,
    stability_score,
)

H, W = 240, 310
# SAM's own AMG prompt set: every grid prompt, none skipped (the cost cuts are tested apart).
EXACT_AMG = dict(flat_prompt_stride=1, skip_covered_prompts=False)


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> tuple[str, str]:
    return _tiny_sam.export(tmp_path_factory.mktemp("sam"))


@pytest.fixture(scope="module")
def sam(models) -> SamOnnx:
    enc, dec = models
    return SamOnnx(SamParams(encoder_path=enc, decoder_path=dec, points_per_side=4, **EXACT_AMG))


def test_grid_points_are_cell_centres() -> None:
    pts = grid_points(200, 300, 4)
    assert pts.shape == (16, 2)
    np.testing.assert_allclose(np.unique(pts[:, 0]), [37.5, 112.5, 187.5, 262.5])
    np.testing.assert_allclose(np.unique(pts[:, 1]), [25.0, 75.0, 125.0, 175.0])
    np.testing.assert_allclose(pts[1], [112.5, 25.0])  # row-major: u varies fastest


def test_preprocess_resize_normalise_pad(sam) -> None:
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    rgb[:] = rgb[:1, :1]  # constant colour: resizing must not change it
    x = sam.preprocess(rgb)
    h, w = resized_hw(H, W, 1024)
    assert x.shape == (1, 3, 1024, 1024) and (h, w) == (793, 1024)
    expect = (rgb[0, 0].astype(np.float32) - PIXEL_MEAN) / PIXEL_STD
    np.testing.assert_allclose(x[0, :, :h, :w].reshape(3, -1).mean(1), expect, rtol=1e-5)
    np.testing.assert_allclose(x[0, :, :h, :w].reshape(3, -1).std(1), 0, atol=1e-5)
    assert np.all(x[0, :, h:, :] == 0) and np.all(x[0, :, :, w:] == 0)  # zero padding


def test_decoder_mask_aligned_to_prompt(sam, models) -> None:
    from mogs_node.ort import open_session

    assert sam.adapted and not sam.batched  # pruned; the tiny graph reads the first prompt only
    exported = open_session(models[1])  # the file's decoder, with its full-size `masks` output
    emb = sam.embed(np.zeros((H, W, 3), np.uint8))
    assert emb.shape == (1, 256, 64, 64)
    scale = 1024 / max(H, W)
    for pt in ([100.0, 60.0], [250.0, 180.0]):
        low, iou = sam.decode(emb, np.array([pt]), H, W)
        assert low.shape == (1, 4, 256, 256) and iou.shape == (1, 4)
        np.testing.assert_allclose(iou[0], _tiny_sam.IOUS, atol=1e-3)
        coords = sam.to_model_coords(np.array([pt, [0.0, 0.0]]), H, W)[None].astype(np.float32)
        (full,) = exported.run(
            ["masks"],
            {
                "image_embeddings": emb,
                "point_coords": coords,
                "point_labels": np.array([[1.0, -1.0]], np.float32),
                "mask_input": np.zeros((1, 1, 256, 256), np.float32),
                "has_mask_input": np.zeros(1, np.float32),
                "orig_im_size": np.array([H, W], np.float32),
            },
        )
        for k in (1, 3):
            m = sam.upsample(low[0, k], H, W) > 0
            # Our upsampling of the low-res logits reproduces the export's mask_postprocessing.
            assert np.mean(m == (full[0, k] > 0)) > 0.999
            vv, uu = np.nonzero(m)
            # Disc around the prompt in original pixels, radius RADII[k] / scale (clipped
            # discs are not centred, so check the centre only where the disc is inside).
            r = _tiny_sam.RADII[k] / scale
            if pt[0] - r > 0 and pt[0] + r < W and pt[1] - r > 0 and pt[1] + r < H:
                assert abs(uu.mean() - pt[0]) < 1.0 and abs(vv.mean() - pt[1]) < 1.0
                assert m.sum() == pytest.approx(np.pi * r * r, rel=0.05)


def test_stability_score_and_nms_helpers() -> None:
    x = np.linspace(-10, 10, 101)[None, None, :].repeat(3, 1)  # [1, 3, 101]
    sharp = np.stack([x[0] * 10, x[0] * 0.1])  # [2, 3, 101]
    s = stability_score(sharp, 0.0, 1.0)
    assert s[0] > 0.95 and s[1] < 0.5
    boxes = np.array([[0, 0, 9, 9], [1, 1, 10, 10], [20, 20, 29, 29]], float)
    keep = box_nms(boxes, np.array([0.8, 0.9, 0.5]), 0.5)
    np.testing.assert_array_equal(keep, [1, 2])


def test_automatic_masks_filtered_nms_painted(sam) -> None:
    res = sam.generate(np.zeros((H, W, 3), np.uint8))
    p = sam.params
    assert res.stats["n_prompts"] == 16
    assert res.stats["n_candidates"] == 48  # outputs 1..3 of a multi-mask decoder
    # Output 2 is blurry (stability < 0.95) and output 0 is never used: only outputs 1 and 3.
    assert res.stats["n_after_filters"] == 32
    assert np.all(res.iou >= p.pred_iou_thresh) and np.all(res.stability >= 0.95)
    # After NMS no two kept masks overlap by box IoU above the threshold.
    from mogs_node.segmentation.sam_onnx import _boxes

    b = _boxes(res.masks)
    assert len(box_nms(b, res.iou, p.box_nms_thresh)) == len(b)
    assert len(res.masks) == 32  # 4x4 grid: discs far apart, box IoU < 0.7, nothing suppressed
    # Label image: int32, -1 = none, labels index the kept masks and lie inside them.
    assert res.labels.dtype == np.int32 and res.labels.shape == (H, W)
    for k in np.unique(res.labels[res.labels >= 0]):
        assert np.all(res.masks[k][res.labels == k])


def test_nms_suppresses_overlapping_masks(models) -> None:
    enc, dec = models
    dense = SamOnnx(
        SamParams(
            encoder_path=enc, decoder_path=dec, points_per_side=8, box_nms_thresh=0.3, **EXACT_AMG
        )
    )
    res = dense.generate(np.zeros((H, W, 3), np.uint8))
    assert res.stats["n_after_filters"] == 128
    assert 0 < res.stats["n_masks"] < 128
    from mogs_node.segmentation.sam_onnx import _boxes

    b = _boxes(res.masks)
    u0 = np.maximum(b[:, None, 0], b[None, :, 0])
    u1 = np.minimum(b[:, None, 2], b[None, :, 2])
    v0 = np.maximum(b[:, None, 1], b[None, :, 1])
    v1 = np.minimum(b[:, None, 3], b[None, :, 3])
    inter = np.clip(u1 - u0 + 1, 0, None) * np.clip(v1 - v0 + 1, 0, None)
    area = (b[:, 2] - b[:, 0] + 1) * (b[:, 3] - b[:, 1] + 1)
    iou = inter / (area[:, None] + area[None] - inter)
    np.fill_diagonal(iou, 0)
    assert iou.max() <= 0.3
    assert res.stats["coverage"] > 0.9


def test_painter_puts_near_masks_on_top() -> None:
    masks = np.zeros((3, 50, 60), bool)
    masks[0, 5:40, 5:55] = True  # large, reaches row 39
    masks[1, 20:48, 10:30] = True  # reaches row 47: nearest
    masks[2, 0:30, 25:45] = True  # reaches row 29: farthest
    labels, order = paint_masks(masks)
    np.testing.assert_array_equal(order, [2, 0, 1])
    assert labels[25, 20] == 1 and labels[25, 40] == 0 and labels[2, 30] == 2
    assert labels[45, 58] == -1
    depth = np.full((50, 60), 10.0)
    depth[masks[2]] = 3.0  # with a depth map, mask 2 is nearest
    labels_d, order_d = paint_masks(masks, depth)
    assert order_d[-1] == 2 and labels_d[25, 28] == 2


def test_missing_and_mismatched_models(models, tmp_path) -> None:
    enc, dec = models
    with pytest.raises(ModelError, match="not found"):
        SamOnnx(SamParams(encoder_path=enc, decoder_path=str(tmp_path / "missing.onnx")))
    with pytest.raises(ModelError, match="no input 'image'.*model has inputs.*point_coords"):
        SamOnnx(SamParams(encoder_path=dec, decoder_path=enc))  # swapped files
    with pytest.raises(ModelError, match="no input 'image_embeddings'.*official SAM"):
        SamOnnx(SamParams(encoder_path=enc, decoder_path=enc))  # an encoder as the decoder
    with pytest.raises(ModelError, match="input_image"):
        SamOnnx(SamParams(encoder_path=enc, decoder_path=dec, encoder_input="input_image"))


def test_prompt_cuts_fewer_decoder_calls_same_coverage(models) -> None:
    """Flat cells keep a coarser prompt grid and covered prompts are skipped: far fewer decoder
    calls, the label image still covers the frame."""
    enc, dec = models
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:, W // 2 :] = 200  # one vertical edge: structure in one column of cells only
    full = SamOnnx(
        SamParams(encoder_path=enc, decoder_path=dec, points_per_side=8, **EXACT_AMG)
    ).generate(rgb)
    cut = SamOnnx(SamParams(encoder_path=enc, decoder_path=dec, points_per_side=8))
    pts = cut.prompt_points(rgb)
    assert len(pts) < 64
    # The two columns of cells on the edge keep every prompt; the flat ones only the even rows
    # and columns (3 of the 6 flat columns, 4 of the 8 rows).
    assert np.sum(np.abs(pts[:, 0] - W / 2) < W / 8) == 16
    assert len(pts) == 16 + 3 * 4
    res = cut.generate(rgb)
    assert res.stats["n_prompts"] == len(pts)
    assert res.stats["n_decoder_calls"] < 0.5 * full.stats["n_decoder_calls"]
    assert full.stats["n_decoder_calls"] == 64
    assert full.stats["coverage"] == 1.0 and res.stats["coverage"] > 0.9
    assert res.labels.dtype == np.int32 and res.labels.shape == (H, W)


def test_square_cell_grid_and_coarse_to_fine_order() -> None:
    from mogs_node.segmentation.sam_onnx import coarse_to_fine, grid_shape

    assert grid_shape(375, 1242, 16, True) == (5, 16)  # 16 * 375 / 1242 = 4.8 rows
    assert grid_shape(1242, 375, 16, True) == (16, 5) and grid_shape(375, 1242, 16, False) == (
        16,
        16,
    )
    pts = grid_points(375, 1242, 16, square_cells=True)
    assert pts.shape == (80, 2)
    np.testing.assert_allclose(np.unique(pts[:, 1]), (np.arange(5) + 0.5) * 75.0)
    order = coarse_to_fine(pts)
    np.testing.assert_array_equal(np.sort(order), np.arange(80))  # a permutation
    centre = np.argmin(np.sum((pts - pts.mean(0)) ** 2, 1))
    assert order[0] == centre
    # Farthest-point order: each point is at least as far from those before it as any later one.
    for k in range(1, 80):
        d = np.min(np.linalg.norm(pts[order[k:], None] - pts[order[:k]][None], axis=2), axis=1)
        assert d[0] == pytest.approx(d.max())
    assert coarse_to_fine(np.zeros((0, 2))).shape == (0,)


def test_prompt_budget_bounds_decoder_work(models) -> None:
    enc, dec = models
    rgb = np.random.default_rng(1).integers(0, 256, (H, W, 3), dtype=np.uint8)
    capped = SamOnnx(
        SamParams(encoder_path=enc, decoder_path=dec, points_per_side=8, max_prompts=5, **EXACT_AMG)
    )
    res = capped.generate(rgb)
    assert res.stats["n_prompts"] == 64 and res.stats["n_prompts_run"] == 5
    assert res.stats["n_decoder_calls"] == 5  # the tiny decoder reads one prompt per call
    # The 5 prompts run are the first of the coarse-to-fine order: spread over the image.
    pts = capped.prompt_points(rgb)[:5]
    assert np.ptp(pts[:, 0]) > 0.6 * W and np.ptp(pts[:, 1]) > 0.6 * H
    with pytest.raises(Exception, match="max_prompts"):
        SamParams(max_prompts=-1)


def test_model_paths_with_variables_and_home(models, monkeypatch) -> None:
    """Launch files name models as ~/... or $VAR/...: both the session and the decoder's
    adaptation (which reads the file with the onnx package) expand them."""
    enc, dec = models
    folder = str(Path(dec).parent)
    monkeypatch.setenv("MOGS_TEST_MODELS", folder)
    monkeypatch.setenv("HOME", folder)
    sam = SamOnnx(
        SamParams(
            encoder_path="$MOGS_TEST_MODELS/" + Path(enc).name, decoder_path="~/" + Path(dec).name
        )
    )
    assert sam.adapted
