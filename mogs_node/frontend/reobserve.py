"""The previous keyframes' sparse points in a new keyframe (pure; rounds 7, 8, 13 and 14).

- :func:`carry_forward`: a keyframe with too few fresh points (standstill) takes the previous
  keyframe's points moved into its camera frame.
- :func:`reobserved_points`: while moving, the last keyframes' points that the new keyframe still
  sees (their patch, moved by the relative pose and scaled by the depth ratio, still matches: not
  occluded, not out of view; optionally it keeps its contrast: a flat occluder, round 14) join
  the fresh ones (map points re-observed, as a keyframe-based SLAM tracks its local map), in
  one pass; :func:`reproject_points` + :func:`merge_points` are the
  same for one keyframe at a time.

Split from :mod:`mogs_node.frontend.track_points` (round 13). No I/O, no bus.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from mogs_node.frontend.track_points import (
    KeyframePoints,
    TrackPointsParams,
    edge_flags,
    patch_match,
)
from mogs_node.geometry import PinholeCamera, check_array, se3_inverse, transform_points

__all__ = ["carry_forward", "merge_points", "reobserved_points", "reproject_points"]


def _moved(
    prev: KeyframePoints, T_cur_prev: NDArray, camera: PinholeCamera
) -> tuple[NDArray[np.bool_], KeyframePoints]:
    """Every point of ``prev`` moved by ``T_cur_prev`` [4, 4] (covariances rotated), and which
    of them [N] land in the image in front of the camera."""
    T = check_array("T_cur_prev", T_cur_prev, shape=(4, 4), finite=True).astype(np.float64)
    xyz = transform_points(T, prev.xyz_cam_m.astype(np.float64))
    uv, front = camera.project(xyz)
    R = T[:3, :3]
    cov = R[None] @ prev.cov_cam_m2.astype(np.float64) @ R.T[None]
    moved = KeyframePoints(
        ids=prev.ids,
        uv_px=uv.astype(np.float32),
        xyz_cam_m=xyz.astype(np.float32),
        cov_cam_m2=cov.astype(np.float32),
        weight=prev.weight,
    )
    return front & camera.in_image(uv), moved


def reproject_points(
    prev: KeyframePoints,
    T_cur_prev: NDArray,
    camera: PinholeCamera,
    image_prev: NDArray,
    image_cur: NDArray,
    *,
    radius_px: int,
    min_zncc: float,
) -> KeyframePoints:
    """The previous keyframe's points that the current keyframe still sees, in its camera.

    ``T_cur_prev`` [4, 4] as in :func:`carry_forward`; ``image_prev``, ``image_cur`` [H, W] the
    two keyframes' undistorted grey images. A point is kept when it lands in the image in front
    of the camera and the patch around its new pixel matches the patch around its old one
    (:func:`patch_match`, scaled by the depth ratio) with a ZNCC of at least ``min_zncc``: an
    occluder that moved over it, or a point on a moving object, fails.
    """
    keep, moved = _moved(prev, T_cur_prev, camera)
    idx = np.flatnonzero(keep)
    z_prev = np.maximum(prev.xyz_cam_m[idx, 2].astype(np.float64), 1e-9)
    scale = moved.xyz_cam_m[idx, 2] / z_prev
    zncc, _ = patch_match(
        image_cur, moved.uv_px[idx], image_prev, prev.uv_px[idx], scale, radius_px
    )
    keep[idx] = zncc >= min_zncc
    return moved.subset(keep)


def merge_points(
    fresh: KeyframePoints, old: KeyframePoints, *, min_distance_px: float, params: TrackPointsParams
) -> KeyframePoints:
    """``fresh`` with those of ``old`` (re-observed points) that add to it: not the same track,
    not within ``min_distance_px`` of a fresh point, and not across a depth edge from their
    neighbours in the union (:func:`depth_edge_flags`; fresh points are kept as they are)."""
    if len(old) == 0:
        return fresh
    add = ~np.isin(old.ids, fresh.ids)
    if len(fresh):
        d, _ = cKDTree(fresh.uv_px).query(old.uv_px, k=1)
        add &= d >= min_distance_px
    uv = np.concatenate([fresh.uv_px, old.uv_px[add]])
    z = np.concatenate([fresh.xyz_cam_m[:, 2], old.xyz_cam_m[add, 2]])
    edge = edge_flags(params)(
        uv, z, radius_px=params.edge_radius_px, rel_jump=params.edge_rel_jump
    )[len(fresh) :]
    add[np.flatnonzero(add)[edge]] = False
    new = old.subset(add)
    return KeyframePoints(
        *(
            np.concatenate([getattr(fresh, k), getattr(new, k)])
            for k in ("ids", "uv_px", "xyz_cam_m", "cov_cam_m2", "weight")
        ),
        carried=fresh.carried,
    )


def reobserved_points(
    fresh: KeyframePoints,
    recent: Iterable[tuple[NDArray, KeyframePoints, NDArray]],
    T_world_cam: NDArray,
    camera: PinholeCamera,
    image: NDArray,
    params: TrackPointsParams,
) -> KeyframePoints:
    """``fresh`` with the points of the ``recent`` keyframes (``(T_world_cam, points, grey
    image)``, oldest first) that the keyframe still sees, in one pass (round 13; before it,
    :func:`reproject_points` then :func:`merge_points` for each keyframe in turn, ~3x the CPU).

    A recent point joins when it lands in the image in front of the camera, is no fresh track
    (its id) and no newer keyframe's point (only the newest keyframe's copy of a track is
    tested: one patch test per track, where merging keyframe by keyframe tested every copy), lies at
    least ``params.min_distance_px`` from every fresh point and from every joining point of a
    newer keyframe, its patch still matches (:func:`patch_match` against its own keyframe's
    image: a ZNCC of at least ``params.reproject_min_zncc``, and at least
    ``params.reproject_min_contrast`` of the grey-level spread it had there, since a flat
    occluder hides it; round 14), and no close neighbour in the union contradicts its depth (the
    edge rule of ``params``; fresh points are kept as they are)."""
    T_cam_world = se3_inverse(check_array("T_world_cam", T_world_cam, shape=(4, 4), finite=True))
    image = np.asarray(image, np.float32)  # converted once, not per patch test
    groups = []  # newest keyframe first: (points, T_cur_prev, image, index of kept, pixels, z)
    for T_world_prev, prev, image_prev in reversed(list(recent)):
        if len(prev) == 0:
            continue
        T = (T_cam_world @ T_world_prev).astype(np.float64)
        xyz = transform_points(T, prev.xyz_cam_m.astype(np.float64))
        uv, front = camera.project(xyz)
        idx = np.flatnonzero(front & camera.in_image(uv) & ~np.isin(prev.ids, fresh.ids))
        groups.append((prev, T, np.asarray(image_prev, np.float32), idx, uv[idx], xyz[idx]))
    if not groups:
        return fresh
    ids = np.concatenate([g[0].ids[g[3]] for g in groups])
    uv = np.concatenate([g[4] for g in groups])
    offset = np.cumsum([0] + [len(g[3]) for g in groups])
    # the newest copy of each track (a track occluded there is taken as occluded), away from
    # the fresh points
    ok = np.zeros(len(ids), bool)
    ok[np.unique(ids, return_index=True)[1]] = True
    if len(fresh) and ok.any():
        d, _ = cKDTree(fresh.uv_px).query(uv[ok], k=1)
        ok[np.flatnonzero(ok)] = d >= params.min_distance_px
    for k, (prev, _, image_prev, idx, g_uv, g_xyz) in enumerate(groups):  # per keyframe image
        loc = np.flatnonzero(ok[offset[k] : offset[k + 1]])
        z_prev = np.maximum(prev.xyz_cam_m[idx[loc], 2].astype(np.float64), 1e-9)
        zncc, contrast = patch_match(
            image,
            g_uv[loc],
            image_prev,
            prev.uv_px[idx[loc]],
            g_xyz[loc, 2] / z_prev,
            params.patch_radius_px,
        )
        ok[offset[k] + loc] = (zncc >= params.reproject_min_zncc) & (
            contrast >= params.reproject_min_contrast
        )
    # a joining point close to one of a newer keyframe's (earlier in the order) gives way
    cand = np.flatnonzero(ok)
    if len(cand) > 1:
        pairs = cKDTree(uv[cand]).query_pairs(
            max(params.min_distance_px, 1e-9) * (1 - 1e-9), output_type="ndarray"
        )
        # greedy in priority order, as merging keyframe by keyframe would (few pairs)
        for i, j in sorted(map(tuple, np.sort(pairs, axis=1).tolist())):
            if ok[cand[i]]:
                ok[cand[j]] = False
    cand = np.flatnonzero(ok)
    z_all = np.concatenate([g[5][:, 2] for g in groups])
    edge = edge_flags(params)(
        np.concatenate([fresh.uv_px, uv[cand]]),
        np.concatenate([fresh.xyz_cam_m[:, 2], z_all[cand]]),
        radius_px=params.edge_radius_px,
        rel_jump=params.edge_rel_jump,
    )[len(fresh) :]
    ok[cand[edge]] = False
    parts = [fresh]
    start = 0
    for prev, T, _, idx, g_uv, g_xyz in groups:
        sel = np.flatnonzero(ok[start : start + len(idx)])
        start += len(idx)
        if len(sel) == 0:
            continue
        R = T[:3, :3]
        cov = R[None] @ prev.cov_cam_m2[idx[sel]].astype(np.float64) @ R.T[None]
        parts.append(
            KeyframePoints(
                ids=prev.ids[idx[sel]],
                uv_px=g_uv[sel].astype(np.float32),
                xyz_cam_m=g_xyz[sel].astype(np.float32),
                cov_cam_m2=cov.astype(np.float32),
                weight=prev.weight[idx[sel]],
            )
        )
    return KeyframePoints(
        *(
            np.concatenate([getattr(p, k) for p in parts])
            for k in ("ids", "uv_px", "xyz_cam_m", "cov_cam_m2", "weight")
        ),
        carried=fresh.carried,
    )


def carry_forward(
    prev: KeyframePoints, T_cur_prev: NDArray, camera: PinholeCamera
) -> KeyframePoints:
    """The previous keyframe's points moved into the current camera (standstill keyframes).

    ``T_cur_prev`` [4, 4]: the previous camera's pose in the current camera frame. Points that
    leave the image or fall behind the camera are dropped; covariances are rotated.
    """
    keep, moved = _moved(prev, T_cur_prev, camera)
    return dataclasses.replace(moved.subset(keep), carried=True)
