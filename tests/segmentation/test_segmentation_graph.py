"""Graph-based default segmenter: label image contract and region recovery on synthetic scenes."""

from __future__ import annotations

import numpy as np
import pytest

from mogs_node.errors import ConfigError, ShapeError
from mogs_node.segmentation.graph import GraphSegParams, segment_graph


def _blocks_image(
    rng: np.random.Generator, H: int = 120, W: int = 200
) -> tuple[np.ndarray, np.ndarray]:
    """A 2x3 grid of strongly different flat colours with mild noise; returns (rgb, gt_ids)."""
    colours = np.array(
        [
            [200, 30, 30],
            [30, 200, 30],
            [30, 30, 200],
            [220, 220, 40],
            [40, 220, 220],
            [120, 120, 120],
        ],
        np.float64,
    )
    gt = (np.arange(H)[:, None] * 2 // H) * 3 + (np.arange(W)[None, :] * 3 // W)
    img = colours[gt] + rng.normal(0, 4.0, (H, W, 3))
    return np.clip(img, 0, 255).astype(np.uint8), gt


@pytest.mark.parametrize("method", ["graph", "slic"])
def test_label_contract(method: str) -> None:
    rgb, _ = _blocks_image(np.random.default_rng(0))
    labels = segment_graph(rgb, GraphSegParams(method=method))
    assert labels.shape == rgb.shape[:2] and labels.dtype == np.int32
    ids = np.unique(labels)
    assert ids[0] >= 0
    np.testing.assert_array_equal(ids, np.arange(len(ids)))  # consecutive ids
    assert labels[0, 0] == 0  # raster order of first appearance


def _interior(gt: np.ndarray, g: int, margin: int = 3) -> np.ndarray:
    """Pixels of block ``g`` at least ``margin`` px from any other block (seams blur)."""
    import cv2

    m = (gt == g).astype(np.uint8)
    return cv2.erode(m, np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)).astype(bool)


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_graph_recovers_flat_regions(scale: float) -> None:
    rgb, gt = _blocks_image(np.random.default_rng(1))
    labels = segment_graph(rgb, GraphSegParams(scale=scale))
    # Each block's interior is one label, and different blocks get different labels; the
    # pre-smoothing may leave thin segments along the seams, which we do not count.
    main = []
    for g in range(6):
        vals, counts = np.unique(labels[_interior(gt, g)], return_counts=True)
        assert counts.max() / counts.sum() > 0.99
        main.append(vals[np.argmax(counts)])
    assert len(set(main)) == 6
    for lab in main:
        _, counts = np.unique(gt[labels == lab], return_counts=True)
        assert counts.max() / counts.sum() > 0.98


def test_slic_never_crosses_strong_edges() -> None:
    rgb, gt = _blocks_image(np.random.default_rng(2))
    labels = segment_graph(rgb, GraphSegParams(method="slic", scale=1.0, slic_region_px=20))
    for g in range(6):  # no superpixel reaches from one block's interior into another's
        inside = set(np.unique(labels[_interior(gt, g)]))
        for h in range(g + 1, 6):
            assert not inside & set(np.unique(labels[_interior(gt, h)]))
    assert len(np.unique(labels)) > 6  # superpixels over-segment


def test_small_segments_become_none() -> None:
    rgb = np.full((60, 80, 3), 100, np.uint8)
    rgb[20:24, 30:34] = (250, 0, 0)  # a 16-px blob
    labels = segment_graph(rgb, GraphSegParams(scale=1.0, min_size_px=5, min_segment_px=50))
    assert np.all(labels[20:24, 30:34] == -1)
    assert np.all(labels[:10] == 0)


def test_grey_input_accepted() -> None:
    grey = np.zeros((40, 60), np.uint8)
    grey[:, 30:] = 255
    labels = segment_graph(grey, GraphSegParams(scale=1.0, min_size_px=10))
    assert labels[0, 0] != labels[0, -1]


def test_bad_inputs() -> None:
    with pytest.raises(ShapeError, match="rgb"):
        segment_graph(np.zeros((10, 10, 3), np.float32))
    with pytest.raises(ShapeError, match="rgb"):
        segment_graph(np.zeros((10, 10, 4), np.uint8))
    with pytest.raises(ConfigError, match="method"):
        GraphSegParams(method="watershed")
    with pytest.raises(ConfigError, match="scale"):
        GraphSegParams(scale=2.0)
