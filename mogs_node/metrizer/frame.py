"""The working set of one keyframe shared by the metrizer's stages, and its geometric helpers.

:class:`Frame` holds the sanitised inputs (flat arrays), the global affine (stage 3) and the
stage results as they are produced; :class:`StageTimer` times the stages. The helpers map a
per-object table to pixels, intersect rays with the accepted shapes (paper III-B, model depth
propagation) and convert calibrated values of the prior's space (eq. 6) to depth.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.depth_kind import DepthKind
from mogs_node.geometry import pixel_to_normalized
from mogs_node.metrizer import shapes
from mogs_node.metrizer.params import MetrizerParams

__all__ = [
    "Frame",
    "ShapeModels",
    "StageTimer",
    "f32_below",
    "far_and_norm",
    "model_agrees",
    "model_depth",
    "object_map",
    "pixel_xy",
    "prior_edges",
    "to_depth_inplace",
]

F64 = NDArray[np.float64]


@dataclass
class ShapeModels:
    """The accepted shape of every object (Algorithm 1; kind 0 = none), camera frame.

    Quadric ``x^T A x + b^T x + c = 0``; the model depth is used within ``[zlo, zhi]`` (the
    inlier depths widened by ``model_extrapolation``).
    """

    kind: NDArray[np.int8]  # [G] 0 none, 1 plane, 2 cylinder, 3 ellipsoid
    conf: F64  # [G] eq. (5) confidence
    A: F64  # [G, 3, 3]
    b: F64  # [G, 3]
    c: F64  # [G]
    zlo: F64  # [G]
    zhi: F64  # [G]

    @classmethod
    def none(cls, G: int) -> ShapeModels:
        """No shape for ``G`` objects."""
        return cls(
            np.zeros(G, np.int8),
            np.zeros(G),
            np.zeros((G, 3, 3)),
            np.zeros((G, 3)),
            np.zeros(G),
            np.zeros(G),
            np.zeros(G),
        )

    def take(self, ids: NDArray[np.intp]) -> ShapeModels:
        """The models of objects ``ids`` (renumbered ``0..len(ids)-1``)."""
        return ShapeModels(
            self.kind[ids],
            self.conf[ids],
            self.A[ids],
            self.b[ids],
            self.c[ids],
            self.zlo[ids],
            self.zhi[ids],
        )


@dataclass
class Frame:
    """Working set of one keyframe shared by the stages of :func:`metrize_depth` (flat arrays)."""

    p: MetrizerParams
    H: int
    W: int
    K: F64
    prior_kind: str
    prior: NDArray[np.float32]  # [HW] prior values (0 where no prior)
    conf: NDArray[np.float32]  # [HW] prior confidence
    has_prior: NDArray[np.bool_]  # [HW]
    all_prior: bool
    image: NDArray[np.uint8] | None  # [H, W, 3]
    z: F64  # [N] feature depths
    fpix: NDArray[np.intp]  # [N] flat pixel of each feature
    f_consistent: NDArray[np.bool_]  # [N] feature agrees with the globally aligned prior
    theta0: F64  # [2] global affine
    stats: dict[str, Any]
    G: int = 0  # objects after merging
    gobj: NDArray[np.intp] | None = None  # [HW] object per pixel
    feat_g: NDArray[np.intp] | None = None  # [N] object per feature
    n_feat_g: NDArray[np.int64] | None = None  # [G]
    sky: NDArray[np.bool_] | None = None  # [G]
    run_label: NDArray[np.intp] | None = None  # [R] object of each raster run of gobj
    run_len: NDArray[np.intp] | None = None  # [R] its length in pixels
    edges: NDArray[np.uint8] | None = None  # quarter-resolution depth-edge band of the prior
    t_abs_m: float = 0.0  # absolute part of T_s(z) used (see the consensus stage)
    up_cam: F64 | None = None  # [3] unit "up" in the camera frame (road plane), or None

    def in_edge_band(self, flat_idx: NDArray[np.intp]) -> NDArray[np.bool_]:
        """Whether flat pixels lie in the prior's depth-edge band (computed once, on demand)."""
        if self.edges is None:
            self.edges = prior_edges(self.prior, self.conf, self.H, self.W, self.p)
        v, u = np.divmod(flat_idx, self.W)
        h4, w4 = self.edges.shape
        return (
            self.edges[np.minimum(v * h4 // self.H, h4 - 1), np.minimum(u * w4 // self.W, w4 - 1)]
            > 0
        )

    def per_pixel(self, table: NDArray) -> NDArray:
        """``table[gobj]`` ``[HW]`` for a per-object ``table`` ``[G]``: the object map is
        piecewise constant, so its raster runs are expanded (``np.repeat``), which is cheaper
        than a per-pixel gather."""
        if self.run_label is None:
            g = self.gobj
            starts = np.concatenate([[0], np.flatnonzero(g[1:] != g[:-1]) + 1])
            self.run_label = g[starts]
            self.run_len = np.diff(np.append(starts, len(g)))
        return np.repeat(table[self.run_label], self.run_len)


class StageTimer:
    """Per-stage wall-clock (``ms``) and process CPU (``cpu_ms``) times in milliseconds."""

    def __init__(self) -> None:
        self.t0 = self.tic = time.perf_counter()
        self.c0 = self.ctic = time.process_time()
        self.ms: dict[str, float] = {}
        self.cpu_ms: dict[str, float] = {}

    def lap(self, name: str) -> None:
        now, cnow = time.perf_counter(), time.process_time()
        self.ms[name] = (now - self.tic) * 1e3
        self.cpu_ms[name] = (cnow - self.ctic) * 1e3
        self.tic, self.ctic = now, cnow

    def total(self) -> dict[str, float]:
        self.ms["total"] = (time.perf_counter() - self.t0) * 1e3
        self.cpu_ms["total"] = (time.process_time() - self.c0) * 1e3
        return self.ms


def far_and_norm(y: F64, kind: str, p: MetrizerParams) -> tuple[NDArray[np.bool_], F64]:
    """Globally aligned values ``y`` -> (far mask, positive normaliser in the same space)."""
    if kind == DepthKind.RELATIVE_INVERSE_DEPTH:
        return y <= 1.0 / (p.sky_depth_frac * p.d_max_m), np.clip(
            y, 1.0 / p.d_max_m, 1.0 / p.d_min_m
        )
    return y >= p.sky_depth_frac * p.d_max_m, np.clip(y, p.d_min_m, p.d_max_m)


def object_map(table: NDArray[np.intp], obj_i: NDArray[np.intp]) -> NDArray[np.intp]:
    """Object id per pixel ``[HW]`` from the compact labels ``obj_i`` ``[HW]`` and a look-up table
    ``[n_obj]`` (``obj_i`` itself when the table is the identity)."""
    if np.array_equal(table, np.arange(len(table))):
        return obj_i
    return np.take(table, obj_i)


def pixel_xy(flat_idx: NDArray[np.intp], W: int, K: F64) -> tuple[F64, F64]:
    """Normalised image coordinates (ray ``(x, y, 1)``) of flat pixel indices."""
    v, u = np.divmod(flat_idx, W)
    return pixel_to_normalized(K, u, v)


def model_depth(flat_idx, g, kind_g, Am, bm, cm, W, K) -> F64:
    """Ray-shape intersection depth (nearest positive root, ``inf`` on a miss) at flat pixels
    ``flat_idx`` of objects ``g``; planes in closed form, quadrics via :func:`shapes.ray_depth`."""
    x, y = pixel_xy(flat_idx, W, K)
    out = np.full(len(flat_idx), np.inf)
    plane = kind_g[g] == shapes.KIND_PLANE
    if plane.any():
        gp = g[plane]
        b = bm[gp]
        qb = b[:, 0] * x[plane] + b[:, 1] * y[plane] + b[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -cm[gp] / qb
        out[plane] = np.where(np.isfinite(t) & (t > 0), t, np.inf)
    qi = np.flatnonzero(~plane)
    if len(qi):  # few curved objects: one model at a time, no per-pixel gather of A
        gq = g[qi]
        order = np.argsort(gq, kind="stable")
        qi, gq = qi[order], gq[order]
        cuts = np.flatnonzero(np.diff(gq)) + 1
        for part in np.split(np.arange(len(qi)), cuts):
            k = gq[part[0]]
            rays = np.stack([x[qi[part]], y[qi[part]], np.ones(len(part))], 1)
            out[qi[part]] = shapes.ray_depth(Am[k], bm[k], cm[k], rays)
    return out


def prior_edges(
    prior: NDArray[np.float32], conf: NDArray[np.float32], H: int, W: int, p: MetrizerParams
) -> NDArray[np.uint8]:
    """Depth-edge neighbourhood of the prior (relative gradient), at quarter resolution."""
    x = prior if conf.min(initial=1.0) > 0 else np.where(conf > 0, prior, np.float32(0.0))
    x = x.reshape(H, W).astype(np.float32, copy=False)
    h4, w4 = max(1, H // 4), max(1, W // 4)
    xs = cv2.resize(x, (w4, h4), interpolation=cv2.INTER_AREA)
    gx = np.abs(cv2.Sobel(xs, cv2.CV_32F, 1, 0, ksize=3))
    gy = np.abs(cv2.Sobel(xs, cv2.CV_32F, 0, 1, ksize=3))
    rel = (gx + gy) / (32.0 * np.maximum(np.abs(xs), 1e-6))  # per full-resolution pixel
    r = max(1, round(p.prior_edge_radius / 4))
    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    return cv2.dilate((rel > p.prior_edge_rel).astype(np.uint8), k)


def to_depth_inplace(y: NDArray, kind: str, p: MetrizerParams) -> NDArray:
    """In-place :func:`depth_from_space` for large float32 arrays (finite input)."""
    if kind == DepthKind.RELATIVE_INVERSE_DEPTH:
        np.maximum(y, np.float32(1.0 / p.d_max_m), out=y)
        np.reciprocal(y, out=y)
    np.clip(y, np.float32(p.d_min_m), f32_below(p.d_max_m), out=y)
    return y


def f32_below(v: float) -> np.float32:
    """Largest float32 not above ``v``."""
    f = np.float32(v)
    return f if float(f) <= v else np.nextafter(f, np.float32(-np.inf))


def model_agrees(dm: F64, lo: F64, hi: F64, d_ref: F64, gate: float) -> NDArray[np.bool_]:
    """Model depth ``dm`` hit, within the shape's valid range ``[lo, hi]`` and within ``gate``
    (relative) of the reference depth ``d_ref`` (the globally aligned prior)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.isfinite(dm) & (dm >= lo) & (dm <= hi) & (np.abs(dm / d_ref - 1.0) <= gate)
