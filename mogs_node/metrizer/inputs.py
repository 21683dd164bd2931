"""The metrizer's inputs for one keyframe: one typed record, checked and sanitised in one place.

:class:`MetrizerInputs` replaces the nine-argument keyword dict that the node, the evaluations and
the benchmarks each built. It also unpacks as those keyword arguments
(``metrize_depth(**inputs)``), so existing callers keep working.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mogs_node.depth_kind import DepthKind
from mogs_node.errors import ConfigError, GeometryError
from mogs_node.geometry import check_array
from mogs_node.metrizer.alignment import PRIOR_KINDS

__all__ = ["MetrizerInputs"]

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class MetrizerInputs:
    """One keyframe's inputs to :func:`~mogs_node.metrizer.pipeline.metrize`.

    ``K`` ``[3, 3]`` intrinsics; ``labels`` ``[H, W]`` int instance masks (-1 = none);
    ``feature_uv_px`` ``[N, 2]`` feature pixels, ``feature_depth_m`` ``[N]`` their metric z-depth
    (camera frame), ``feature_weight`` ``[N]`` omega; ``prior`` ``[H, W]`` dense prior of kind
    ``prior_kind``, ``prior_confidence`` ``[H, W]`` in ``[0, 1]`` (0 = no prior); ``image_rgb``
    ``[H, W, 3]`` uint8 for eq. (10) and the fill, or None; ``T_world_cam`` ``[4, 4]`` the
    keyframe's pose (the road plane's "up", ``MetrizerParams.road_*``), or None;
    ``anchor_depth_m`` ``[H, W]`` a second, metric depth map (the weight-free flow prior beside a
    relative one) and ``anchor_confidence`` ``[H, W]``: dense metric anchors
    (:mod:`~mogs_node.metrizer.dense_anchors`, ``MetrizerParams.dense_anchor_*``), or None.
    """

    K: NDArray[np.floating]
    labels: NDArray[np.integer]
    feature_uv_px: NDArray[np.floating]
    feature_depth_m: NDArray[np.floating]
    feature_weight: NDArray[np.floating]
    prior: NDArray[np.floating]
    prior_confidence: NDArray[np.floating]
    prior_kind: str = "relative_inverse_depth"
    image_rgb: NDArray[np.uint8] | None = None
    T_world_cam: NDArray[np.floating] | None = None
    anchor_depth_m: NDArray[np.floating] | None = None
    anchor_confidence: NDArray[np.floating] | None = None

    # mapping protocol: ``metrize_depth(**inputs)`` and ``inputs["labels"]``
    def keys(self) -> Iterator[str]:
        return iter(f.name for f in fields(self))

    def __getitem__(self, name: str) -> Any:
        if name not in {f.name for f in fields(self)}:
            raise KeyError(name)
        return getattr(self, name)

    def checked(self, mode: str = "full", modes: tuple[str, ...] = ("full",)) -> MetrizerInputs:
        """These inputs with shapes, dtypes and intrinsics checked (one clear error naming the bad
        field) and ``K`` as float64."""
        if self.prior_kind not in PRIOR_KINDS:
            raise ConfigError(f"prior_kind: expected one of {PRIOR_KINDS}, got {self.prior_kind!r}")
        if mode not in modes:
            raise ConfigError(f"mode: expected one of {modes}, got {mode!r}")
        K = check_array("K", self.K, shape=(3, 3), dtype=np.number).astype(np.float64)
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise GeometryError(f"K: invalid intrinsics {K.tolist()}")
        labels = check_array("labels", self.labels, shape=(None, None), dtype=np.integer)
        H, W = labels.shape
        if H == 0 or W == 0:
            raise GeometryError("labels: empty image")
        prior = check_array("prior", self.prior, shape=(H, W), dtype=np.number)
        conf = check_array("prior_confidence", self.prior_confidence, shape=(H, W), dtype=np.number)
        uv = check_array("feature_uv_px", self.feature_uv_px, shape=(None, 2), dtype=np.number)
        n = len(uv)
        z = check_array("feature_depth_m", self.feature_depth_m, shape=(n,), dtype=np.number)
        w = check_array("feature_weight", self.feature_weight, shape=(n,), dtype=np.number)
        image = self.image_rgb
        if image is not None:
            image = check_array("image_rgb", image, shape=(H, W, 3), dtype=np.uint8)
        T = self.T_world_cam
        if T is not None:
            T = check_array("T_world_cam", T, shape=(4, 4), finite=True).astype(np.float64)
        ad, ac = self.anchor_depth_m, self.anchor_confidence
        if (ad is None) != (ac is None):
            raise ConfigError("anchor_depth_m and anchor_confidence: give both or neither")
        if ad is not None:
            ad = check_array("anchor_depth_m", ad, shape=(H, W), dtype=np.number)
            ac = check_array("anchor_confidence", ac, shape=(H, W), dtype=np.number)
        return MetrizerInputs(K, labels, uv, z, w, prior, conf, self.prior_kind, image, T, ad, ac)

    def sanitised(
        self, d_min_m: float, d_max_m: float
    ) -> tuple[F64, F64, F64, NDArray[np.float32], NDArray[np.float32]]:
        """Of these (checked) inputs: the usable features ``uv, z, w`` and the flat float32 prior
        and confidence (non-finite -> no prior).

        A depth-space prior (``relative_depth`` / ``metric``) has no value where it is not
        positive. Features with a non-finite value, outside the image or outside
        ``[d_min_m, d_max_m]`` are dropped; weights are clipped to be non-negative (plus 1e-6).
        """
        H, W = self.labels.shape
        kind, prior, conf = self.prior_kind, self.prior, self.prior_confidence
        prior = np.ascontiguousarray(prior, dtype=np.float32).ravel()
        conf = np.ascontiguousarray(conf, dtype=np.float32).ravel()
        good_p, good_c = np.isfinite(prior).all(), np.isfinite(conf).all()
        if not (good_p and good_c) or conf.min(initial=0.0) < 0 or conf.max(initial=0.0) > 1:
            good = np.isfinite(prior) & np.isfinite(conf)
            conf = np.where(good, np.clip(conf, 0.0, 1.0), 0.0).astype(np.float32)
            prior = np.where(good & (conf > 0), prior, 0.0).astype(np.float32)
        if kind in (DepthKind.RELATIVE_DEPTH, DepthKind.METRIC) and prior.min(initial=1.0) <= 0:
            conf = np.where(prior > 0, conf, 0.0).astype(np.float32)
        uv = self.feature_uv_px.astype(np.float64)
        z = self.feature_depth_m.astype(np.float64)
        w = self.feature_weight.astype(np.float64)
        with np.errstate(invalid="ignore"):
            keep = (
                np.all(np.isfinite(uv), axis=1)
                & np.isfinite(z)
                & np.isfinite(w)
                & (z >= d_min_m)
                & (z <= d_max_m)
                & (uv[:, 0] > -0.5)
                & (uv[:, 0] < W - 0.5)
                & (uv[:, 1] > -0.5)
                & (uv[:, 1] < H - 0.5)
            )
        w = np.maximum(w[keep], 0.0) + 1e-6
        return uv[keep], z[keep], w, prior, conf
