"""The synthetic driving world: finite primitives (``primitives``), a textured ground, and a vectorised
ray caster.

Primitives (instance kinds as in :data:`KIND_NAMES`): finite planes (building facades), vertical
cylinders (poles, tree trunks; caps not modelled, the camera is always below their tops),
ellipsoids (tree crowns, bushes, car bodies) and yawed boxes (utility boxes, kiosks). The ground is
the infinite plane z = 0, split into instances by the lateral offset from the road centreline: road
(lane markings included), left / right sidewalk, left / right terrain. The sky is at infinity.

Rendering (:meth:`World.render`) casts one ray per pixel centre. Rays are ``d = R_world_cam K^-1
[u, v, 1]``, so the ray parameter of a hit is its z-depth. Every primitive's axis-aligned bounding
box is projected into the image; primitives outside the view are culled and the others are
intersected only with the rays inside their projected box (exact intersection, float64), with a
z-buffer. Shading is Lambertian with a fixed sun and view-independent albedo anchored in world or
primitive-local coordinates, so a surface point has the same colour in every view.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from mogs_node.errors import ConfigError
from mogs_node.geometry import (
    PinholeCamera,
    check_array,
)
from mogs_node.sim import textures as tx
from mogs_node.sim.primitives import (
    _EDGES,
    KIND_BOX,
    KIND_CYLINDER,
    KIND_ELLIPSOID,
    KIND_PLANE,
    Box,
    Cylinder,
    Ellipsoid,
    PlaneRect,
    _footprint,
    _shade,
)

__all__ = [
    "KIND_BOX",
    "KIND_CYLINDER",
    "KIND_ELLIPSOID",
    "KIND_NAMES",
    "KIND_PLANE",
    "Box",
    "Centerline",
    "Cylinder",
    "Ellipsoid",
    "PlaneRect",
    "SimFrame",
    "World",
    "WorldParams",
    "generate_world",
]

KIND_NAMES = {
    KIND_PLANE: "plane",
    KIND_CYLINDER: "cylinder",
    KIND_ELLIPSOID: "ellipsoid",
    KIND_BOX: "box",
}

#: ground instance ids (always the first five instances of a world with a ground)
GROUND_ROAD, GROUND_SIDEWALK_L, GROUND_SIDEWALK_R, GROUND_TERRAIN_L, GROUND_TERRAIN_R = range(5)
N_GROUND = 5


# ------------------------------------------------------------------------------------ primitives


Primitive = PlaneRect | Cylinder | Ellipsoid | Box


# ------------------------------------------------------------------------------------ the ground


@dataclass(frozen=True)
class Centerline:
    """Road centreline polyline: points ``[K, 2]`` (m) at arc lengths ``s`` ``[K]``, z = 0."""

    xy: np.ndarray
    s: np.ndarray
    tree: cKDTree = field(repr=False, compare=False)

    @classmethod
    def from_points(cls, xy: np.ndarray, step_m: float = 0.2) -> Centerline:
        xy = check_array("xy", xy, shape=(None, 2), finite=True).astype(np.float64)
        seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        keep = np.concatenate([[True], seg > 1e-9])
        s, xy = s[keep], xy[keep]
        sr = np.arange(0.0, s[-1], step_m)
        xr = np.stack([np.interp(sr, s, xy[:, 0]), np.interp(sr, s, xy[:, 1])], -1)
        return cls(xr, sr, cKDTree(xr))

    @property
    def tangent(self) -> np.ndarray:
        t = np.gradient(self.xy, axis=0)
        return t / np.linalg.norm(t, axis=1, keepdims=True)

    def frame_at(self, s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Point, unit tangent and unit left normal (all [2]) at arc length ``s``."""
        i = int(np.clip(np.searchsorted(self.s, s), 1, len(self.s) - 1))
        p0, p1 = self.xy[i - 1], self.xy[i]
        t = (p1 - p0) / np.linalg.norm(p1 - p0)
        f = (s - self.s[i - 1]) / (self.s[i] - self.s[i - 1])
        return p0 + f * (p1 - p0), t, np.array([-t[1], t[0]])

    def _lookup(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Raster of the nearest centreline sample per cell (built once): (table, origin, cell)."""
        cache = self.__dict__.get("_lookup_cache")
        if cache is None:
            lo, hi = self.xy.min(0) - 80.0, self.xy.max(0) + 80.0
            cell = max(0.5, float(np.sqrt(np.prod(hi - lo) / 2e6)))
            nx, ny = (np.ceil((hi - lo) / cell).astype(int) + 1).tolist()
            gx, gy = np.meshgrid(
                lo[0] + cell * np.arange(nx), lo[1] + cell * np.arange(ny), indexing="ij"
            )
            _, idx = self.tree.query(np.stack([gx.ravel(), gy.ravel()], -1))
            cache = (idx.reshape(nx, ny).astype(np.int32), lo, cell)
            object.__setattr__(self, "_lookup_cache", cache)
        return cache

    def station(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Arc length ``s`` and signed lateral offset ``l`` (left positive) of points ``[N, 2]``.

        The reference sample is the nearest centreline point of the point's cell in a 0.5 m raster
        (a pure function of the world position, so textures stay consistent across views); ``s`` and
        ``l`` come from the projection onto that sample's tangent.
        """
        table, lo, cell = self._lookup()
        ij = np.floor((xy - lo) / cell + 0.5).astype(np.int64)
        ij[:, 0] = np.clip(ij[:, 0], 0, table.shape[0] - 1)
        ij[:, 1] = np.clip(ij[:, 1], 0, table.shape[1] - 1)
        idx = table[ij[:, 0], ij[:, 1]]
        tng = self._tangent_cached()[idx]
        q = xy - self.xy[idx]
        s = self.s[idx] + np.einsum("ij,ij->i", q, tng)
        lat = q[:, 1] * tng[:, 0] - q[:, 0] * tng[:, 1]
        return s, lat

    def _tangent_cached(self) -> np.ndarray:
        t = self.__dict__.get("_tangent_cache")
        if t is None:
            t = self.tangent
            object.__setattr__(self, "_tangent_cache", t)
        return t


@dataclass(frozen=True)
class WorldParams:
    """Layout of the generated world (lateral offsets from the road centreline, left positive)."""

    lane_half_width_m: float = 3.5  # edge lines at +-3.5 m, dashed centre line at 0
    road_half_width_m: float = 5.5  # parking lanes between the edge lines and the kerb
    sidewalk_outer_m: float = 8.5  # sidewalk between the kerb and this offset
    density: float = 1.0  # multiplies the number of objects per metre
    extend_m: float = 120.0  # world content beyond both ends of the driven path
    max_ground_depth_m: float = 400.0  # ground farther than this renders as sky


def _ground_albedo(
    s: np.ndarray,
    lat: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    w: np.ndarray,
    p: WorldParams,
    seed: int,
) -> np.ndarray:
    """Asphalt with lane markings, kerbs, paved sidewalks and grass, box-filtered over ``w`` (m)."""
    n_fine = tx.value_noise2(x, y, 0.35, seed)
    n_coarse = tx.value_noise2(x, y, 3.0, seed + 1)
    cells = tx.filtered_cell_hash2(x, y, 0.6, w, seed + 2)
    asphalt = (0.30 + 0.08 * n_fine + 0.08 * n_coarse + 0.07 * cells)[:, None] * np.ones(
        3, np.float32
    )
    lw = 0.08
    dash = tx.band_coverage(lat, -lw, lw, w) * tx.periodic_band_coverage(s, 0.0, 3.0, 9.0, w)
    lh = p.lane_half_width_m
    edge = tx.band_coverage(lat, lh - lw, lh + lw, w) + tx.band_coverage(lat, -lh - lw, -lh + lw, w)
    mark = np.clip(dash + edge, 0.0, 1.0)[:, None]
    rh = p.road_half_width_m
    kerb = (
        tx.band_coverage(lat, rh - 0.15, rh + 0.15, w)
        + tx.band_coverage(lat, -rh - 0.15, -rh + 0.15, w)
    )[:, None]
    # sidewalk tiles in (s, lat) coordinates with grout lines
    tile = tx.filtered_cell_hash2(s, lat, 0.6, w, seed + 3)
    gs, gl = (
        tx.periodic_band_coverage(s, 0.0, 0.04, 0.6, w),
        tx.periodic_band_coverage(lat, 0.0, 0.04, 0.6, w),
    )
    grout = gs + gl - gs * gl
    sv = 0.35 * grout + (0.55 + 0.2 * tile) * (1 - grout)
    paving = sv[:, None] * np.array([1.0, 0.97, 0.92], dtype=np.float32)
    k = (0.6 + 0.6 * cells) * (0.7 + 0.6 * n_coarse) * (0.8 + 0.4 * n_fine)
    grass = k[:, None] * np.array([0.26, 0.38, 0.16], dtype=np.float32)
    so = p.sidewalk_outer_m
    c_road = tx.band_coverage(lat, -rh, rh, w)[:, None]
    c_side = (tx.band_coverage(lat, rh, so, w) + tx.band_coverage(lat, -so, -rh, w))[:, None]
    c_grass = np.clip(1.0 - c_road - c_side, 0.0, 1.0)
    road = asphalt * (1 - mark) + 0.88 * mark
    out = road * c_road + paving * c_side + grass * c_grass
    return out * (1 - kerb) + 0.62 * kerb


# ------------------------------------------------------------------------------------ the world


@dataclass(frozen=True)
class SimFrame:
    """One rendered view with its ground truth."""

    index: int  # frame index in its sequence (-1 for an arbitrary view)
    stamp_ns: int
    T_world_cam: np.ndarray  # [4, 4] f64
    rgb: np.ndarray  # [H, W, 3] uint8
    depth_m: np.ndarray  # [H, W] f32 z-depth, inf on sky
    instance_id: np.ndarray  # [H, W] int32, -1 on sky
    instance_kind: np.ndarray  # [n_instances] int8: 1 plane, 2 cylinder, 3 ellipsoid, 4 box


@dataclass(frozen=True)
class World:
    """Primitives (instance id ``N_GROUND + index`` with a ground, else ``index``) and a ground."""

    primitives: tuple[Primitive, ...]
    centerline: Centerline | None = None
    params: WorldParams = field(default_factory=WorldParams)
    seed: int = 0

    @property
    def n_ground(self) -> int:
        return N_GROUND if self.centerline is not None else 0

    @property
    def instance_kind(self) -> np.ndarray:
        """int8 ``[n_instances]``: primitive kind of each instance id (ground ones are planes)."""
        kinds = [KIND_PLANE] * self.n_ground + [p.kind for p in self.primitives]
        return np.asarray(kinds, dtype=np.int8)

    def _aabb_corners(self) -> np.ndarray:
        if not self.primitives:
            return np.zeros((0, 8, 3))
        out = []
        for p in self.primitives:
            c = p.corners()
            lo, hi = c.min(0), c.max(0)
            out.append(
                np.array(
                    [
                        [x, y, z]
                        for x in (lo[0], hi[0])
                        for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])
                    ]
                )
            )
        return np.stack(out)

    def visible_boxes(
        self, T_world_cam: np.ndarray, camera: PinholeCamera
    ) -> list[tuple[int, int, int, int, int]]:
        """(primitive index, u0, u1, v0, v1): pixel boxes (ends exclusive) of unculled prims."""
        corners = self.__dict__.get("_corners_cache")
        if corners is None:
            corners = self._aabb_corners()
            object.__setattr__(self, "_corners_cache", corners)
        if len(corners) == 0:
            return []
        R, o = T_world_cam[:3, :3], T_world_cam[:3, 3]
        pc = (corners - o) @ R  # [P, 8, 3] camera frame
        near = 1e-2
        # clip the boxes by the plane z = near: add the points where their 12 edges cross it
        a, b = pc[:, _EDGES[:, 0]], pc[:, _EDGES[:, 1]]  # [P, 12, 3]
        za, zb = a[..., 2], b[..., 2]
        cross = (za - near) * (zb - near) < 0
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.where(cross, (near - za) / (zb - za), 0.0)
        xp = a + f[..., None] * (b - a)
        pts = np.concatenate([pc, xp], axis=1)  # [P, 20, 3]
        front = np.concatenate([pc[..., 2] > near, cross], axis=1)
        behind_all = ~np.any(front, axis=1)
        zs = np.where(front, np.maximum(pts[..., 2], near), 1.0)
        u = camera.fx_px * pts[..., 0] / zs + camera.cx_px
        v = camera.fy_px * pts[..., 1] / zs + camera.cy_px
        W, H = camera.width, camera.height
        big = 1e9
        u0 = np.floor(np.where(front, u, big).min(1)) - 1
        u1 = np.ceil(np.where(front, u, -big).max(1)) + 2
        v0 = np.floor(np.where(front, v, big).min(1)) - 1
        v1 = np.ceil(np.where(front, v, -big).max(1)) + 2
        u0, u1 = u0.clip(0, W).astype(int), u1.clip(0, W).astype(int)
        v0, v1 = v0.clip(0, H).astype(int), v1.clip(0, H).astype(int)
        ok = ~behind_all & (u1 > u0) & (v1 > v0)
        return [(int(i), u0[i], u1[i], v0[i], v1[i]) for i in np.nonzero(ok)[0]]

    def render(
        self, T_world_cam: np.ndarray, camera: PinholeCamera, *, stamp_ns: int = 0, index: int = -1
    ) -> SimFrame:
        """Ray-cast one view (see the module docstring) -> :class:`SimFrame`."""
        T = check_array("T_world_cam", T_world_cam, shape=(4, 4), finite=True).astype(np.float64)
        H, W = camera.height, camera.width
        R, o = T[:3, :3], T[:3, 3]
        d = camera.pixel_grid_rays(np.float64) @ R.T  # [H, W, 3], z-depth ray parameter
        depth = np.full((H, W), np.inf)
        ids = np.full((H, W), -1, dtype=np.int32)
        GROUND = -2
        if self.centerline is not None and o[2] > 0:
            dz = d[..., 2]
            with np.errstate(divide="ignore"):
                tg = np.where(dz < -1e-12, -o[2] / dz, np.inf)
            tg[tg > self.params.max_ground_depth_m] = np.inf
            hit = np.isfinite(tg)
            depth[hit] = tg[hit]
            ids[hit] = GROUND
        ng = self.n_ground
        for i, u0, u1, v0, v1 in self.visible_boxes(T, camera):
            sub_d = d[v0:v1, u0:u1].reshape(-1, 3)
            t = self.primitives[i].intersect(o, sub_d).reshape(v1 - v0, u1 - u0)
            zb = depth[v0:v1, u0:u1]
            closer = t < zb
            if closer.any():
                zb[closer] = t[closer]
                ids[v0:v1, u0:u1][closer] = ng + i
        rgb = np.empty((H, W, 3), dtype=np.float32)
        sky = ids == -1
        dn = d[sky] / np.linalg.norm(d[sky], axis=1, keepdims=True)
        elev = np.clip(dn[:, 2], 0.0, 1.0)[:, None].astype(np.float32)
        rgb[sky] = (
            np.array([0.82, 0.87, 0.93], np.float32) * (1 - elev)
            + np.array([0.45, 0.62, 0.88], np.float32) * elev
        )
        fpx = 0.5 * (camera.fx_px + camera.fy_px)
        flat_ids = ids.ravel()
        flat_d = d.reshape(-1, 3)
        flat_depth = depth.ravel()
        flat_rgb = rgb.reshape(-1, 3)
        order = np.argsort(flat_ids, kind="stable")
        sid = flat_ids[order]
        uniq, starts = np.unique(sid, return_index=True)
        ends = np.append(starts[1:], len(sid))
        for k, a, b in zip(uniq, starts, ends, strict=True):
            if k == -1:
                continue
            pix = order[a:b]
            dd = flat_d[pix]
            P = o + flat_depth[pix, None] * dd
            dnorm = np.linalg.norm(dd, axis=1)
            if k == GROUND:
                s, lat = self.centerline.station(P[:, :2])
                w = _footprint(flat_depth[pix], dnorm, np.abs(dd[:, 2]) / dnorm, fpx)
                alb = _ground_albedo(s, lat, P[:, 0], P[:, 1], w, self.params, self.seed)
                flat_rgb[pix] = _shade(alb, np.broadcast_to([0.0, 0.0, 1.0], P.shape), dd)
                p = self.params
                al = np.abs(lat)
                left = lat >= 0
                gid = np.where(
                    al < p.road_half_width_m,
                    GROUND_ROAD,
                    np.where(
                        al < p.sidewalk_outer_m,
                        np.where(left, GROUND_SIDEWALK_L, GROUND_SIDEWALK_R),
                        np.where(left, GROUND_TERRAIN_L, GROUND_TERRAIN_R),
                    ),
                )
                flat_ids[pix] = gid
                continue
            prim = self.primitives[k - ng]
            nrm = prim.normals(P)
            w = _footprint(
                flat_depth[pix], dnorm, np.abs(np.einsum("ij,ij->i", nrm, dd)) / dnorm, fpx
            )
            flat_rgb[pix] = _shade(prim.albedo(P, w), nrm, dd)
        rgb8 = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
        return SimFrame(
            int(index),
            int(stamp_ns),
            T.copy(),
            rgb8,
            depth.astype(np.float32),
            ids,
            self.instance_kind,
        )


# ------------------------------------------------------------------------------------ generation


_CAR_COLORS = (
    (0.7, 0.1, 0.1),
    (0.15, 0.2, 0.5),
    (0.85, 0.85, 0.85),
    (0.2, 0.2, 0.22),
    (0.5, 0.5, 0.55),
    (0.8, 0.6, 0.1),
)


@dataclass
class _Placer:
    """Places one kind of roadside object at a time along the centreline. Every draw comes from
    one generator in a fixed order (side, then kind), so a seed gives the same world."""

    cl: Centerline
    p: WorldParams
    rng: np.random.Generator
    last_id: int

    @property
    def length_m(self) -> float:
        return float(self.cl.s[-1])

    def next_id(self) -> int:
        self.last_id += 1
        return self.last_id

    def at(self, s: float, lat: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        c, t, n = self.cl.frame_at(s)
        return c + lat * n, t, n

    def stations(self, first_m: float, gap_m: tuple[float, float]) -> Iterator[float]:
        """Arc lengths of one kind's objects: the first in [0, ``first_m``), then gaps drawn in
        ``gap_m`` (shrunk by the density) after the caller has placed each object (so that the
        draws keep their order)."""
        s = self.rng.uniform(0, first_m)
        while s < self.length_m:
            yield s
            s += self.rng.uniform(*gap_m) / self.p.density

    def facades(self, side: float) -> list[Primitive]:
        rng, p, L, out = self.rng, self.p, self.length_m, []
        s = rng.uniform(0, 10)
        while s < L - 5:
            length = rng.uniform(8.0, 24.0)
            if s + length > L:
                break
            lat = side * rng.uniform(p.sidewalk_outer_m + 0.5, p.sidewalk_outer_m + 3.5)
            xy, t, _ = self.at(s + length / 2, lat)
            h = rng.uniform(6.0, 16.0)
            u = np.array([t[0], t[1], 0.0])
            centre = np.array([xy[0], xy[1], h / 2])
            up = np.array([0.0, 0.0, 1.0])
            out.append(PlaneRect(centre, u, up, length / 2, h / 2, "facade", self.next_id()))
            gap = rng.uniform(0.0, 4.0) if rng.random() < 0.6 else rng.uniform(8.0, 20.0)
            s += length + gap / p.density
        return out

    def poles(self, side: float) -> list[Primitive]:
        """Poles near the kerb."""
        rng, out = self.rng, []
        for s in self.stations(15.0, (18.0, 35.0)):
            xy, _, _ = self.at(s, side * (self.p.road_half_width_m + 0.4))
            r, h = float(rng.uniform(0.08, 0.14)), float(rng.uniform(5.0, 8.0))
            out.append(Cylinder(xy, r, 0.0, h, "pole", self.next_id()))
        return out

    def trees(self, side: float) -> list[Primitive]:
        """A trunk and an ellipsoid crown each."""
        rng, out = self.rng, []
        for s in self.stations(12.0, (10.0, 26.0)):
            xy, _, _ = self.at(s, side * rng.uniform(6.8, 7.6))
            h = float(rng.uniform(2.2, 3.2))
            out.append(
                Cylinder(xy, float(rng.uniform(0.14, 0.28)), 0.0, h, "trunk", self.next_id())
            )
            r = rng.uniform(1.3, 2.3, 3)
            r[2] = rng.uniform(1.4, 2.6)
            centre = np.array([xy[0], xy[1], h + 0.7 * r[2]])
            yaw = float(rng.uniform(0, np.pi))
            color = (0.24 + 0.1 * rng.random(), 0.42 + 0.1 * rng.random(), 0.15)
            out.append(Ellipsoid(centre, r, yaw, "crown", self.next_id(), color=color))
        return out

    def parked_cars(self, side: float) -> list[Primitive]:
        """Cars in the parking lane, either way round."""
        rng, out = self.rng, []
        for s in self.stations(20.0, (9.0, 35.0)):
            xy, t, _ = self.at(s, side * 4.5)
            yaw = float(np.arctan2(t[1], t[0]) + (np.pi if rng.random() < 0.5 else 0.0))
            color = _CAR_COLORS[int(rng.integers(len(_CAR_COLORS)))]
            centre, radii = np.array([xy[0], xy[1], 0.78]), np.array([2.1, 0.88, 0.74])
            out.append(Ellipsoid(centre, radii, yaw, "car", self.next_id(), color=color))
        return out

    def bushes_and_boxes(self, side: float) -> list[Primitive]:
        """Bushes (60 %) and boxes by the facades."""
        rng, out = self.rng, []
        for s in self.stations(20.0, (12.0, 30.0)):
            xy, t, _ = self.at(s, side * rng.uniform(8.0, 8.6))
            yaw = float(np.arctan2(t[1], t[0]))
            if rng.random() < 0.6:
                r = np.array([rng.uniform(0.7, 1.3), rng.uniform(0.5, 0.9), rng.uniform(0.4, 0.7)])
                centre = np.array([xy[0], xy[1], 0.8 * r[2]])
                color = (0.2, 0.34, 0.13)
                out.append(Ellipsoid(centre, r, yaw, "bush", self.next_id(), color=color))
            else:
                half = np.array(
                    [rng.uniform(0.3, 1.2), rng.uniform(0.25, 0.8), rng.uniform(0.5, 1.1)]
                )
                centre = np.array([xy[0], xy[1], half[2]])
                color = (0.45 + 0.3 * rng.random(), 0.45 + 0.2 * rng.random(), 0.4)
                out.append(Box(centre, half, yaw, "box", self.next_id(), color=color))
        return out


def generate_world(
    centerline_xy: np.ndarray, seed: int, params: WorldParams | None = None
) -> World:
    """Place facades, poles, trees, parked cars, bushes and boxes on both sides of a road.

    ``centerline_xy`` ``[K, 2]``: the road centreline (m, z = 0), already extended beyond the driven
    path. Deterministic for a given ``seed``.
    """
    p = params or WorldParams()
    if p.density <= 0:
        raise ConfigError(f"density: must be positive, got {p.density}")
    cl = Centerline.from_points(centerline_xy)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7]))
    placer = _Placer(cl, p, rng, last_id=int(rng.integers(1, 2**30)))
    prims: list[Primitive] = []
    for side in (1.0, -1.0):
        for kind in (
            placer.facades,
            placer.poles,
            placer.trees,
            placer.parked_cars,
            placer.bushes_and_boxes,
        ):
            prims.extend(kind(side))
    return World(tuple(prims), cl, p, seed)
