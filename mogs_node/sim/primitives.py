"""The primitives of the synthetic world: finite planes, vertical cylinders, ellipsoids and yawed
boxes, each with exact ray intersection (float64), its image footprint for culling and its albedo.

Instance kinds: :data:`KIND_NAMES` (``mogs_node.sim.world``). Shading is Lambertian with a fixed sun
and view-independent albedo anchored in primitive-local coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mogs_node.geometry import (
    intersect_rays_plane,
    intersect_rays_quadric,
)
from mogs_node.sim import textures as tx

KIND_PLANE, KIND_CYLINDER, KIND_ELLIPSOID, KIND_BOX = 1, 2, 3, 4


_EDGES = np.array(
    [[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]]
)


_SUN = np.array([0.35, -0.45, 0.82]) / np.linalg.norm([0.35, -0.45, 0.82])


class _Yawed:
    """A primitive turned by ``yaw_rad`` about the world z axis."""

    yaw_rad: float

    @property
    def R(self) -> np.ndarray:
        """[3, 3] rotation local -> world."""
        c, s = np.cos(self.yaw_rad), np.sin(self.yaw_rad)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _shade(albedo: np.ndarray, normal: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Lambert with a fixed sun; the normal is flipped to face the viewer (two-sided surfaces)."""
    flip = np.where(np.einsum("ij,ij->i", normal, dirs) > 0, -1.0, 1.0)
    ndl = np.clip((normal @ _SUN) * flip, 0.0, 1.0)
    return albedo * (0.55 + 0.45 * ndl)[:, None].astype(np.float32)


def _footprint(
    depth: np.ndarray, dnorm: np.ndarray, cos_inc: np.ndarray, f_px: float
) -> np.ndarray:
    """Width (m) of one pixel's footprint on the surface: range / f, longer at grazing incidence."""
    return np.minimum(depth * dnorm / f_px / np.maximum(cos_inc, 0.2), 20.0)


def _unit_quadric_t(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Nearest ``t > 0`` with ``|o + t d| = 1`` (``d`` ``[N, k]``, ``o`` ``[k]``); inf on a miss.

    The fast kernel behind cylinders and ellipsoids (mapped to the unit circle / sphere);
    :func:`mogs_node.geometry.intersect_rays_quadric` is its reference (compared in the tests).
    """
    qa = np.einsum("ij,ij->i", d, d)
    hb = d @ o
    qc = float(o @ o) - 1.0
    disc = hb * hb - qa * qc
    hit = disc >= 0
    sq = np.sqrt(np.where(hit, disc, 0.0))
    q = -(hb + np.copysign(sq, hb))
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = q / qa
        t2 = qc / q
    t1 = np.where(np.isfinite(t1) & (t1 > 1e-9), t1, np.inf)
    t2 = np.where(np.isfinite(t2) & (t2 > 1e-9), t2, np.inf)
    return np.where(hit, np.minimum(t1, t2), np.inf)


def _facade_albedo(a: np.ndarray, b: np.ndarray, w: np.ndarray, seed: int) -> np.ndarray:
    """Bricks with mortar, a base colour per facade, and a grid of windows (strong corners).

    ``a`` / ``b``: position along / up the facade (m), ``w``: pixel footprint (m) for box filtering.
    """
    palette = np.array(
        [
            [0.72, 0.62, 0.5],
            [0.62, 0.42, 0.35],
            [0.8, 0.78, 0.7],
            [0.55, 0.55, 0.58],
            [0.7, 0.66, 0.55],
        ],
        dtype=np.float32,
    )
    base = palette[seed % len(palette)]
    row = np.floor(b / 0.25)
    shift = np.where(row % 2 == 0, 0.0, 0.25)
    brick = tx.hash_u01(np.floor((a + shift) / 0.5), row, seed=seed)
    mortar_v = tx.periodic_band_coverage(b, 0.0, 0.03, 0.25, w)
    mortar_u = tx.periodic_band_coverage(a + shift, 0.0, 0.03, 0.5, w)
    mortar = mortar_v + mortar_u - mortar_v * mortar_u
    k = (1.15 * mortar + (0.82 + 0.3 * brick) * (1 - mortar)).astype(np.float32)
    wall = base[None, :] * k[:, None]
    # windows: 3.2 m x 3.2 m cells from the first floor up, larger shop windows on the ground floor
    P_, first = 3.2, 3.2

    def rect(u0: float, u1: float, v0: float, v1: float) -> np.ndarray:
        upper = tx.periodic_band_coverage(b, v0, v1, P_, w) - tx.band_coverage(
            b, v0, v1, w
        )  # floors >= 1
        return tx.periodic_band_coverage(a, u0, u1, P_, w) * upper

    c_win = rect(0.8, 2.4, 1.0, 2.6)
    c_frame = rect(0.65, 2.55, 0.85, 2.75) - c_win
    c_shop = tx.periodic_band_coverage(a, 0.3, 2.9, P_, w) * tx.band_coverage(b, 0.4, 2.5, w)
    del first
    wh = tx.hash_u01(np.floor(a / P_), np.floor(b / P_), seed=seed + 7)
    glass = np.stack([0.1 + 0.15 * wh, 0.13 + 0.15 * wh, 0.18 + 0.17 * wh], -1).astype(np.float32)
    cg = (c_win + c_shop)[:, None]
    cf = c_frame[:, None]
    return wall * (1 - cg - cf) + glass * cg + 0.92 * cf


@dataclass(frozen=True)
class PlaneRect:
    """Finite rectangle: centre, in-plane unit axes ``u`` (along) and ``v`` (up), half sizes."""

    center: np.ndarray  # [3] m
    u: np.ndarray  # [3] unit
    v: np.ndarray  # [3] unit, orthogonal to u
    half_u_m: float
    half_v_m: float
    material: str = "facade"
    seed: int = 0
    kind: int = KIND_PLANE

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.u, self.v)
        return n / np.linalg.norm(n)

    def corners(self) -> np.ndarray:
        s = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
        return self.center + s[:, :1] * self.half_u_m * self.u + s[:, 1:] * self.half_v_m * self.v

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        n = self.normal
        t = intersect_rays_plane(o - self.center, d, n, 0.0)
        fin = np.isfinite(t)
        q = (o - self.center) + np.where(fin, t, 0.0)[:, None] * d
        inside = (np.abs(q @ self.u) <= self.half_u_m) & (np.abs(q @ self.v) <= self.half_v_m)
        return np.where(fin & inside, t, np.inf)

    def normals(self, P: np.ndarray) -> np.ndarray:
        return np.broadcast_to(self.normal, P.shape)

    def albedo(self, P: np.ndarray, w: np.ndarray) -> np.ndarray:
        q = P - self.center
        a = q @ self.u + self.half_u_m  # along, from the left edge
        b = q @ self.v + self.half_v_m  # up, from the bottom
        return _facade_albedo(a, b, w, self.seed)


@dataclass(frozen=True)
class Cylinder:
    """Vertical finite cylinder (no caps): axis through ``(x, y)``, radius, ``z0 <= z <= z1``."""

    center_xy: np.ndarray  # [2] m
    radius_m: float
    z0_m: float
    z1_m: float
    material: str = "pole"
    seed: int = 0
    kind: int = KIND_CYLINDER

    def corners(self) -> np.ndarray:
        r, (x, y) = self.radius_m, self.center_xy
        return np.array(
            [
                [x + sx * r, y + sy * r, z]
                for sx in (-1, 1)
                for sy in (-1, 1)
                for z in (self.z0_m, self.z1_m)
            ]
        )

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        oc = np.array([o[0] - self.center_xy[0], o[1] - self.center_xy[1]]) / self.radius_m
        t = _unit_quadric_t(oc, d[:, :2] / self.radius_m)
        z = o[2] + np.where(np.isfinite(t), t, 0.0) * d[:, 2]
        return np.where(np.isfinite(t) & (z >= self.z0_m) & (z <= self.z1_m), t, np.inf)

    def intersect_reference(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Slow reference: the general quadric of :func:`intersect_rays_quadric`, clipped in z."""
        oc = np.array([o[0] - self.center_xy[0], o[1] - self.center_xy[1], o[2]])
        t = intersect_rays_quadric(
            oc, d, np.diag([1.0, 1.0, 0.0]), np.zeros(3), -(self.radius_m**2)
        )
        z = o[2] + np.where(np.isfinite(t), t, 0.0) * d[:, 2]
        return np.where(np.isfinite(t) & (z >= self.z0_m) & (z <= self.z1_m), t, np.inf)

    def normals(self, P: np.ndarray) -> np.ndarray:
        n = np.zeros_like(P)
        n[:, :2] = P[:, :2] - self.center_xy
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    def albedo(self, P: np.ndarray, w: np.ndarray) -> np.ndarray:
        ang = np.arctan2(P[:, 1] - self.center_xy[1], P[:, 0] - self.center_xy[0])
        arc = (ang + np.pi) * self.radius_m
        z = P[:, 2]
        if self.material == "trunk":
            h = tx.filtered_cell_hash2(arc, z, 0.12, w, self.seed)
            n = tx.value_noise2(arc * 3, z, 0.5, self.seed + 1)
            k = (0.55 + 0.45 * h) * (0.8 + 0.4 * n)
            return np.stack([0.38 * k, 0.27 * k, 0.17 * k], -1)
        band = tx.filtered_cell_hash2(np.full_like(z, 0.3), z, 0.6, w, self.seed)
        k = 0.45 + 0.3 * band
        return np.stack([k, k, k * 1.05], -1)


@dataclass(frozen=True)
class Ellipsoid(_Yawed):
    """Ellipsoid ``|diag(1/r) R^T (x - c)| = 1`` with a yaw rotation ``R`` about z."""

    center: np.ndarray  # [3] m
    radii_m: np.ndarray  # [3] m, along the local x, y, z axes
    yaw_rad: float = 0.0
    material: str = "crown"
    seed: int = 0
    kind: int = KIND_ELLIPSOID
    color: tuple[float, float, float] = (0.3, 0.45, 0.2)

    @property
    def A(self) -> np.ndarray:
        R = self.R
        return R @ np.diag(1.0 / np.asarray(self.radii_m) ** 2) @ R.T

    def corners(self) -> np.ndarray:
        r = float(np.max(self.radii_m[:2]))
        rz = float(self.radii_m[2])
        return self.center + np.array(
            [[sx * r, sy * r, sz * rz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
        )

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        M = self.R / np.asarray(self.radii_m)[None, :]  # world offset -> unit-sphere coordinates
        return _unit_quadric_t((o - self.center) @ M, d @ M)

    def intersect_reference(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Slow reference: the general quadric of :func:`intersect_rays_quadric`."""
        return intersect_rays_quadric(o - self.center, d, self.A, np.zeros(3), -1.0)

    def normals(self, P: np.ndarray) -> np.ndarray:
        n = (P - self.center) @ self.A
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    def albedo(self, P: np.ndarray, w: np.ndarray) -> np.ndarray:
        q = (P - self.center) @ self.R  # local coordinates
        col = np.asarray(self.color, dtype=np.float32)
        if self.material == "car":
            rx, _, rz = (float(r) for r in self.radii_m)
            k = 0.9 + 0.2 * tx.filtered_cell_hash3(q[:, 0], q[:, 1], q[:, 2], 0.5, w, self.seed)
            body = col[None, :] * k[:, None]
            glass_col = np.array([0.12, 0.14, 0.17], dtype=np.float32) * (
                0.8 + 0.5 * tx.filtered_cell_hash2(q[:, 0], q[:, 2], 0.4, w, self.seed + 3)[:, None]
            )
            cg = tx.band_coverage(q[:, 2], 0.25 * rz, 0.8 * rz, w) * tx.band_coverage(
                q[:, 0], -0.6 * rx, 0.6 * rx, w
            )
            wheel_x = tx.band_coverage(q[:, 0], 0.46 * rx, 0.78 * rx, w) + tx.band_coverage(
                q[:, 0], -0.78 * rx, -0.46 * rx, w
            )
            cw = tx.band_coverage(q[:, 2], -2.0 * rz, -0.45 * rz, w) * wheel_x
            return body * (1 - cg - cw)[:, None] + glass_col * cg[:, None] + 0.06 * cw[:, None]
        size = 0.35 if self.material == "crown" else 0.25
        h = tx.filtered_cell_hash3(P[:, 0], P[:, 1], P[:, 2], size, w, self.seed)
        n = tx.value_noise3(P[:, 0], P[:, 1], P[:, 2], 1.2, self.seed + 1)
        k = (0.45 + 0.7 * h) * (0.75 + 0.5 * n)
        return col[None, :] * k[:, None]


@dataclass(frozen=True)
class Box(_Yawed):
    """Box with a yaw about z: centre, half sizes along its local x, y, z."""

    center: np.ndarray  # [3] m
    half_m: np.ndarray  # [3] m
    yaw_rad: float = 0.0
    material: str = "box"
    seed: int = 0
    kind: int = KIND_BOX
    color: tuple[float, float, float] = (0.5, 0.5, 0.45)

    def corners(self) -> np.ndarray:
        s = np.array(
            [[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64
        )
        return self.center + (s * self.half_m) @ self.R.T

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        R = self.R
        ol = (o - self.center) @ R
        dl = d @ R
        h = np.asarray(self.half_m)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / dl
            t1 = (-h - ol) * inv
            t2 = (h - ol) * inv
        t1 = np.where(np.isnan(t1), -np.inf, t1)
        t2 = np.where(np.isnan(t2), np.inf, t2)
        tmin = np.minimum(t1, t2).max(axis=1)
        tmax = np.maximum(t1, t2).min(axis=1)
        t = np.where(tmin > 1e-9, tmin, tmax)
        return np.where((tmax >= tmin) & (t > 1e-9), t, np.inf)

    def normals(self, P: np.ndarray) -> np.ndarray:
        q = (P - self.center) @ self.R / np.asarray(self.half_m)
        ax = np.argmax(np.abs(q), axis=1)
        n = np.zeros_like(P)
        n[np.arange(len(P)), ax] = np.sign(q[np.arange(len(P)), ax])
        return n @ self.R.T

    def albedo(self, P: np.ndarray, w: np.ndarray) -> np.ndarray:
        q = (P - self.center) @ self.R
        h = tx.filtered_cell_hash3(q[:, 0], q[:, 1], q[:, 2], 0.3, w, self.seed)
        k = 0.7 + 0.5 * h
        return np.asarray(self.color, dtype=np.float32)[None, :] * k[:, None]
