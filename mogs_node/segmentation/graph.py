"""Weight-free default segmenter: graph-based over-segmentation (DESIGN.md section 3).

Felzenszwalb-Huttenlocher graph segmentation (``cv2.ximgproc.segmentation``) or SLIC superpixels
produce an over-segmentation; MSC (paper III-B) then merges under-supported segments into objects,
so the segmenter should rather split too much than merge across depth discontinuities.

The default parameters suit KITTI-like driving scenes at 1242x375: the image is segmented at half
resolution (about 5x faster, the label image is upsampled with nearest neighbour), which yields
roughly 100-200 segments: road, facades, cars, poles and tree crowns split into a few parts each.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError
from mogs_node.geometry import check_array

__all__ = ["GraphSegParams", "require_ximgproc", "segment_graph"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GraphSegParams:
    """Parameters of the graph-based (or SLIC) over-segmentation."""

    method: str = "graph"  # "graph" (Felzenszwalb-Huttenlocher) or "slic" (SLIC superpixels)
    scale: float = 0.5  # processing resolution relative to the input (labels upsampled back)
    sigma: float = 0.8  # graph: Gaussian pre-smoothing sigma [px at processing resolution]
    k: float = 250.0  # graph: merge threshold; larger -> larger segments
    min_size_px: int = 120  # graph: smallest segment [px at processing resolution]
    slic_region_px: int = 40  # slic: superpixel size [px at processing resolution]
    slic_ruler: float = 10.0  # slic: compactness (LAB units per region size)
    slic_iterations: int = 5  # slic: number of iterations
    min_segment_px: int = 0  # segments smaller than this [px at input resolution] become -1

    def __post_init__(self) -> None:
        if self.method not in ("graph", "slic"):
            raise ConfigError(
                f"GraphSegParams.method: expected 'graph' or 'slic', got {self.method!r}"
            )
        if not 0.05 <= self.scale <= 1.0:
            raise ConfigError(f"GraphSegParams.scale: expected in [0.05, 1], got {self.scale}")
        if self.sigma < 0 or self.k <= 0 or self.min_size_px < 1:
            raise ConfigError("GraphSegParams: sigma >= 0, k > 0 and min_size_px >= 1 required")
        if self.slic_region_px < 2 or self.slic_iterations < 1 or self.min_segment_px < 0:
            raise ConfigError(
                "GraphSegParams: slic_region_px >= 2, slic_iterations >= 1, min_segment_px >= 0"
            )


def require_ximgproc(user: str) -> None:
    """Fail at start-up, naming the missing package, where OpenCV lacks its contrib modules.

    ``opencv-python(-headless)`` (what many images ship) has no ``cv2.ximgproc``; without this
    check the node would fail on every keyframe with an ``AttributeError`` (seen on a GPU machine).
    """
    if not hasattr(cv2, "ximgproc"):
        raise ConfigError(
            f"{user}: OpenCV {cv2.__version__} has no ximgproc module: install "
            "opencv-contrib-python-headless (a project dependency) instead of opencv-python"
            "(-headless), or choose another backend"
        )


def _compact_labels(labels: NDArray[np.integer], min_segment_px: int) -> NDArray[np.int32]:
    """Relabel to ids 0..n-1 in raster order of first appearance; tiny segments -> -1."""
    uniq, first, inverse, counts = np.unique(
        labels.ravel(), return_index=True, return_inverse=True, return_counts=True
    )
    keep = counts >= max(min_segment_px, 1)
    order = np.argsort(first, kind="stable")  # raster order of first appearance
    new_id = np.full(len(uniq), -1, dtype=np.int32)
    kept_in_order = order[keep[order]]
    new_id[kept_in_order] = np.arange(len(kept_in_order), dtype=np.int32)
    return new_id[inverse].reshape(labels.shape)


def segment_graph(
    rgb: NDArray[np.uint8], params: GraphSegParams = GraphSegParams()
) -> NDArray[np.int32]:
    """Over-segment an RGB image into an int32 label image.

    Args:
        rgb: ``[H, W, 3]`` uint8 colour image (``[H, W]`` grey is accepted too).
        params: segmentation parameters.

    Returns:
        ``[H, W]`` int32 labels, consecutive from 0 in raster order; -1 marks pixels in segments
        smaller than ``params.min_segment_px`` (none with the default 0).
    """
    img = np.asarray(rgb)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = check_array("rgb", img, shape=(None, None, 3), dtype=np.uint8)
    H, W = img.shape[:2]
    if H < 2 or W < 2:
        raise ConfigError(f"rgb: image too small ({W}x{H})")
    require_ximgproc(f"segment_graph (method {params.method!r})")
    img = np.ascontiguousarray(img)
    h, w = max(2, round(H * params.scale)), max(2, round(W * params.scale))
    small = img if (h, w) == (H, W) else cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    if params.method == "graph":
        seg = cv2.ximgproc.segmentation.createGraphSegmentation(
            sigma=float(params.sigma), k=float(params.k), min_size=int(params.min_size_px)
        )
        lab_small = seg.processImage(small)
    else:
        lab = cv2.cvtColor(small, cv2.COLOR_RGB2LAB)
        slic = cv2.ximgproc.createSuperpixelSLIC(
            lab,
            algorithm=cv2.ximgproc.SLIC,
            region_size=int(params.slic_region_px),
            ruler=float(params.slic_ruler),
        )
        slic.iterate(int(params.slic_iterations))
        slic.enforceLabelConnectivity(25)
        lab_small = slic.getLabels()
    lab_small = np.asarray(lab_small, dtype=np.int32)
    if (h, w) != (H, W):
        labels = cv2.resize(lab_small, (W, H), interpolation=cv2.INTER_NEAREST)
    else:
        labels = lab_small
    out = _compact_labels(labels, params.min_segment_px)
    log.debug("segment_graph: %d segments at %dx%d", int(out.max()) + 1, W, H)
    return out
