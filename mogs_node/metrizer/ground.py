"""The road plane in the metrizer: whole road objects, and objects standing on the road.

Departure from the paper (issue 16, docs/metrizer.md "The road plane: road objects and ground
contact"). A car's camera at a calibrated height ``h`` above a planar road, with "up" from the
keyframe's gravity-aligned pose, sees the road at ``z = h / (-up . r)`` along the ray
``r = (x, y, 1)`` (:func:`mogs_node.geometry.road_plane_depth`, the one plane of the prior's
road source and of these passes). Two passes use it where the prior leaves an object's pixels empty:

- :func:`fill_road_objects`: an object (after merging) whose pixels with a depth agree with the
  plane, that lies below the horizon and has enough of them, is road: its empty pixels get the
  plane's depth. The plane is known, not fitted, so nothing is extrapolated from the pixels.
- :func:`fill_ground_contact`: an object whose bottom edge rests on road pixels stands on the road
  there; a vertical plane through that contact line gives depth to its empty pixels above it,
  when the object's confident pixels agree with that plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError

__all__ = ["GroundParams", "fill_ground_contact", "fill_road_objects", "snap_road_objects"]

F32 = NDArray[np.float32]


@dataclass(frozen=True)
class GroundParams:
    """Thresholds of the two passes (``MetrizerParams.road_*`` / ``ground_contact_*``)."""

    agree_rel: float = 0.05  # a pixel agrees with the road plane within this relative depth
    min_pixels: int = 20  # an object needs this many agreeing pixels
    min_agree_share: float = 0.7  # ... making this share of its pixels with a depth
    min_depth_share: float = 0.1  # ... and this share of the whole object
    below_share: float = 0.9  # ... of which this share lies below the horizon (plane < 1.5 max)
    max_depth_m: float = 40.0  # road farther than this gets no depth
    contact_min_px: int = 5  # ground contact: at least this many bottom pixels on road
    contact_min_share: float = 0.3  # ... making this share of the object's bottom edge
    contact_check_conf: float = 0.4  # ... pixels of prior confidence >= this check the plane:
    contact_min_check: int = 20  # at least this many, their median relative
    contact_check_rel: float = 0.1  # disagreement with the vertical plane at most this

    def __post_init__(self) -> None:
        rels = (self.agree_rel, self.contact_check_rel, self.max_depth_m)
        if not all(r > 0 and np.isfinite(r) for r in rels):
            raise ConfigError("ground: agree_rel, contact_check_rel, max_depth_m must be > 0")
        shares = (self.min_agree_share, self.min_depth_share, self.below_share)
        if not all(0 <= s <= 1 for s in (*shares, self.contact_min_share)):
            raise ConfigError("ground: shares must be in [0, 1]")


def _bincount(idx: NDArray[np.intp], G: int, w: NDArray | None = None) -> NDArray:
    return np.bincount(idx, w, minlength=G)[:G]


def fill_road_objects(
    depth: F32,
    conf: F32,
    obj: NDArray[np.intp],
    G: int,
    z_road: F32,
    p: GroundParams,
) -> int:
    """Give the empty pixels of road objects the road plane's depth (flat arrays, in place).

    An object is road when at least ``min_pixels`` of its pixels with a depth agree with the plane
    (within ``agree_rel``), making ``min_agree_share`` of those and ``min_depth_share`` of the
    object, and ``below_share`` of the object lies below the horizon: an under-segmented object
    (road and a car, road and a pole) fails one of these. Filled pixels (plane depth <=
    ``max_depth_m``) get the mean confidence of the agreeing pixels times the agreeing share.
    Returns the number of pixels filled.
    """
    hole = depth <= 0
    if not hole.any():  # a fully covered frame costs nothing
        return 0
    has_hole = _bincount(obj[hole], G) > 0
    idx = np.flatnonzero(has_hole[obj])  # only objects with empty pixels
    o, d, zr = obj[idx], depth[idx], z_road[idx]
    good, agree, nd = _road_objects(o, d, zr, G, p, p.agree_rel)
    if good is None:
        return 0
    sel = good[o] & (d <= 0) & (zr <= p.max_depth_m)
    fill = idx[sel]
    if len(fill) == 0:
        return 0
    c_g = _bincount(o[agree], G, conf[idx[agree]].astype(np.float64)) / np.maximum(nd, 1)
    depth[fill] = zr[sel]
    conf[fill] = c_g[o[sel]].astype(np.float32)
    return len(fill)


def _road_objects(
    o: NDArray[np.intp], d: F32, zr: F32, G: int, p: GroundParams, agree_rel: float
) -> tuple[NDArray[np.bool_] | None, NDArray[np.bool_], NDArray]:
    """Of pixels (object ``o``, depth ``d``, road-plane depth ``zr``): which objects ``[G]`` are
    road (None: none), which pixels agree with the plane within ``agree_rel``, and the pixels
    with a depth below the horizon per object ``[G]`` (the tests of :func:`fill_road_objects`)."""
    below = zr <= 1.5 * p.max_depth_m
    hasd = (d > 0) & below
    agree = hasd & (np.abs(d - zr) <= agree_rel * zr)
    na = _bincount(o[agree], G)
    nd = _bincount(o[hasd], G)
    if not (na >= p.min_pixels).any():
        return None, agree, nd
    ns = _bincount(o, G)
    nb = _bincount(o[below], G)
    good = (na >= p.min_pixels) & (na >= p.min_agree_share * nd)
    good &= (na >= p.min_depth_share * ns) & (nb >= p.below_share * ns)
    return good, agree, nd


def snap_road_objects(
    depth: F32, obj: NDArray[np.intp], G: int, z_road: F32, p: GroundParams, agree_rel: float
) -> int:
    """Give the pixels of road objects that agree with the road plane within ``agree_rel`` the
    plane's depth (flat arrays, in place): the plane is known, a learned prior's road is warped
    (departure, docs/metrizer.md "The road plane over a learned prior's road"). Road objects as
    in :func:`fill_road_objects`, with ``agree_rel`` as the agreement. Returns the pixels set."""
    good, agree, _ = _road_objects(obj, depth, z_road, G, p, agree_rel)
    if good is None:
        return 0
    sel = np.flatnonzero(good[obj] & agree & (z_road <= p.max_depth_m))
    depth[sel] = z_road[sel]
    return len(sel)


def _ground_basis(up: NDArray) -> tuple[NDArray, NDArray]:
    """Two unit vectors spanning the ground plane (orthogonal to ``up``)."""
    a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    e1 = np.cross(up, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def _vertical_plane(P: NDArray, up: NDArray) -> tuple[NDArray, float]:
    """Vertical plane ``n . X = d0`` through road contact points ``P`` ``[N, 3]``: the line that
    the points spread along on the ground (principal axis); a contact shorter than 0.2 m faces
    the camera."""
    e1, e2 = _ground_basis(up)
    q = np.stack([P @ e1, P @ e2], 1)
    c = np.median(q, 0)
    evals, evecs = np.linalg.eigh(np.cov((q - c).T))
    n2 = evecs[:, 0] if np.sqrt(max(evals[1], 0.0)) >= 0.2 else c / np.linalg.norm(c)
    n = n2[0] * e1 + n2[1] * e2
    d0 = float(n @ (c[0] * e1 + c[1] * e2))
    return (n, d0) if d0 >= 0 else (-n, -d0)  # the camera on the plane's negative side


def fill_ground_contact(
    depth: F32,
    conf: F32,
    prior_conf: F32,
    obj: NDArray[np.intp],
    G: int,
    rays: tuple[NDArray, NDArray],
    z_road: F32,
    up_cam: NDArray,
    height_m: float,
    p: GroundParams,
    hw: tuple[int, int],
) -> int:
    """Give the empty pixels of objects standing on the road the depth of a vertical plane
    through their contact line (flat arrays, in place). ``rays`` the flat ``x, y`` of each pixel.

    A bottom pixel of an object (the pixel below belongs to another object) is a contact when the
    pixel below has a depth on the road plane (within ``agree_rel``). An object with at least
    ``contact_min_px`` contacts making ``contact_min_share`` of its bottom pixels gets the
    vertical plane through the contact points (on the road, half a pixel below the object); it
    is used when at least ``contact_min_check`` of the object's pixels of prior confidence >=
    ``contact_check_conf`` agree with it (median relative difference <= ``contact_check_rel``),
    for the object's empty pixels whose plane depth lies within a factor 2 of the contacts'.
    Their confidence: a quarter of the checking pixels' mean output confidence.
    """
    H, W = hw
    roadlike = (depth > 0) & (np.abs(depth - z_road) <= p.agree_rel * z_road)
    roadlike &= z_road <= p.max_depth_m
    o2 = obj.reshape(H, W)
    bottom = np.zeros((H, W), bool)
    bottom[:-1] = o2[:-1] != o2[1:]
    contact = bottom.copy()
    contact[:-1] &= roadlike.reshape(H, W)[1:]
    bottom, contact = bottom.ravel(), contact.ravel()
    n_c = _bincount(obj[contact], G)
    n_b = _bincount(obj[bottom], G)
    check = (depth > 0) & (prior_conf >= p.contact_check_conf)
    n_chk = _bincount(obj[check], G)
    hole = depth <= 0
    cand = (n_c >= p.contact_min_px) & (n_c >= p.contact_min_share * n_b)
    cand &= (n_chk >= p.contact_min_check) & (_bincount(obj[hole], G) > 0)
    if not cand.any():
        return 0
    x, y = rays
    ci = np.flatnonzero(contact & cand[obj])
    ki = np.flatnonzero(check & cand[obj])
    hi = np.flatnonzero(hole & cand[obj])
    order = [i[np.argsort(obj[i], kind="stable")] for i in (ci, ki, hi)]
    parts = [np.split(i, np.cumsum(_bincount(obj[i], G)[cand])[:-1]) for i in order]
    dy = 0.5 * (y[W] - y[0]) if H > 1 else 0.0  # half a pixel down, in ray units
    n_filled = 0
    for c_idx, k_idx, h_idx in zip(*parts, strict=True):
        r = np.stack([x[c_idx], y[c_idx] + dy, np.ones(len(c_idx))], 1)
        down = -(r @ up_cam)
        r, down = r[down > 1e-9], down[down > 1e-9]
        if len(down) < p.contact_min_px:
            continue
        P = r * (height_m / down)[:, None]
        n, d0 = _vertical_plane(P, up_cam)
        if d0 <= 1e-6:  # a plane through the camera
            continue

        def plane_z(idx: NDArray[np.intp], n=n, d0=d0) -> NDArray:
            den = n[0] * x[idx] + n[1] * y[idx] + n[2]
            with np.errstate(divide="ignore", invalid="ignore"):
                return np.where(den > 1e-9, d0 / den, 0.0)

        zk = plane_z(k_idx)
        if np.median(np.abs(zk / depth[k_idx] - 1.0)) > p.contact_check_rel:
            continue
        zh = plane_z(h_idx)
        keep = (zh >= 0.5 * P[:, 2].min()) & (zh <= 2.0 * P[:, 2].max())
        depth[h_idx[keep]] = zh[keep].astype(np.float32)
        conf[h_idx[keep]] = np.float32(0.25 * conf[k_idx].mean())
        n_filled += int(keep.sum())
    return n_filled
