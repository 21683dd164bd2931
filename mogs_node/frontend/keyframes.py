"""Keyframe policy and landmark geometry (triangulation, covariance, the weight omega).

Keyframes are chosen by parallax and track count as in VINS-Mono. Each keyframe carries the metric
3D points of its tracked features in its camera frame together with a weight omega (paper section
III-B uses it to weigh the sparse points against the dense prior): omega grows with the track length
and falls with the reprojection error.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError
from mogs_node.geometry import PinholeCamera, check_array

__all__ = [
    "KeyframeParams",
    "StandstillKeyframes",
    "is_keyframe",
    "keeps_in_window",
    "landmark_covariance",
    "omega_weight",
    "triangulate_midpoint",
]


@dataclass(frozen=True)
class KeyframeParams:
    """Keyframe selection and omega parameters."""

    min_parallax_px: float = 10.0  # mean parallax to the last keyframe that makes a new keyframe
    min_tracked_ratio: float = 0.5  # fewer common features than this fraction -> new keyframe
    min_tracked: int = 20  # fewer common features than this -> new keyframe
    max_interval_s: float = 0.5  # at most this long between keyframes (bounds IMU-only spans)
    omega_track_len: float = 4.0  # track length at which omega's length factor reaches 1 - 1/e
    omega_reproj_px: float = 1.0  # reprojection error at which omega's error factor halves
    # standstill (docs/frontend.md, round 8): no keyframe while the vehicle stands still (nothing
    # new to map, no parallax for points); the first keyframe after a standstill (or a static
    # initialisation) waits until it carries this many triangulated points ...
    hold_at_standstill: bool = True  # False: keyframes at standstill too (before round 8)
    first_min_points: int = 100
    first_max_motion_m: float = 2.0  # ... or the camera moved this far since the standstill ...
    first_max_wait_s: float = 2.0  # ... or this long has passed since the standstill ended

    def __post_init__(self) -> None:
        if self.min_parallax_px < 0 or self.max_interval_s <= 0 or self.omega_reproj_px <= 0:
            raise ConfigError("keyframes: parallax >= 0, max_interval_s > 0, omega_reproj_px > 0")
        if self.first_min_points < 0 or self.first_max_motion_m < 0 or self.first_max_wait_s < 0:
            raise ConfigError(
                "keyframes: first_min_points, first_max_motion_m, first_max_wait_s >= 0"
            )


def is_keyframe(
    params: KeyframeParams,
    kf_ids: NDArray,
    kf_uv_px: NDArray,
    ids: NDArray,
    uv_px: NDArray,
    dt_s: float,
) -> tuple[bool, float]:
    """Decide whether the current frame becomes a keyframe; returns ``(decision, parallax_px)``.

    ``kf_ids`` [M] / ``kf_uv_px`` [M, 2]: the last keyframe's features; ``ids`` [N] / ``uv_px`` [N, 2]:
    the current frame's (undistorted pixels); ``dt_s``: time since the last keyframe.
    """
    kf_uv_px = check_array("kf_uv_px", kf_uv_px, shape=(len(kf_ids), 2))
    uv_px = check_array("uv_px", uv_px, shape=(len(ids), 2))
    _, ia, ib = np.intersect1d(kf_ids, ids, assume_unique=True, return_indices=True)
    parallax = float(np.mean(np.linalg.norm(kf_uv_px[ia] - uv_px[ib], axis=1))) if len(ia) else 0.0
    few = len(ia) < max(params.min_tracked, params.min_tracked_ratio * len(kf_ids))
    return bool(
        parallax >= params.min_parallax_px or few or dt_s >= params.max_interval_s
    ), parallax


def keeps_in_window(
    interval_s: float,
    parallax_px: float,
    tracked_ratio: float,
    last_ids: NDArray,
    last_uv_px: NDArray,
    ids: NDArray,
    uv_px: NDArray,
    dt_s: float,
) -> bool:
    """Whether a frame stays in the estimator's window beside the published keyframes
    (docs/frontend.md, round 9): VINS-Mono's keyframe rule with the window's own thresholds,
    against the last window frame (``last_*``, ``dt_s`` ago): ``interval_s`` passed, or the view
    moved (mean parallax >= ``parallax_px``, fewer than ``tracked_ratio`` of its tracks left).
    A head turn keeps frames close together, a slow walk spreads them in time."""
    rule = KeyframeParams(
        min_parallax_px=parallax_px,
        min_tracked_ratio=tracked_ratio,
        min_tracked=0,
        max_interval_s=max(interval_s - 1e-3, 1e-6),  # stamps jitter
    )
    return is_keyframe(rule, last_ids, last_uv_px, ids, uv_px, dt_s)[0]


class StandstillKeyframes:
    """Keyframe policy around standstill (docs/frontend.md, round 8).

    While the vehicle stands still a keyframe brings nothing new to map and, from one position,
    no parallax for its points: none is taken. The first keyframe after a standstill is held back
    until its tracks triangulate (``first_min_points`` points) from the motion since, or the
    camera moved ``first_max_motion_m``, or ``first_max_wait_s`` passed since the last still
    frame (a slow crawl or a turn on the spot still gets keyframes). The other keyframes are left
    as the parallax policy takes them.
    """

    def __init__(self, params: KeyframeParams) -> None:
        self.params = params
        self.holding = False  # the next keyframe waits for points
        self._still_t_ns = 0
        self._still_position_m = np.zeros(3)

    def reset(self) -> None:
        self.holding = False

    def parked(self, t_ns: int, position_m: NDArray) -> None:
        """A still frame (or a static initialisation) at ``t_ns``, camera at ``position_m``."""
        if self.params.hold_at_standstill:
            self.holding = True
            self._still_t_ns = int(t_ns)
            self._still_position_m = np.asarray(position_m, np.float64).copy()

    def decide(
        self,
        wanted: bool,
        still: bool,
        t_ns: int,
        position_m: NDArray,
        count_points: Callable[[], int],
    ) -> tuple[bool, str]:
        """Whether the frame the parallax policy ``wanted`` as a keyframe becomes one, and why
        not (``"standstill"``, ``"no_parallax"``; ``""`` when taken or not wanted).
        ``count_points()``: the points the keyframe would carry (called only when it decides)."""
        if not self.params.hold_at_standstill:
            return wanted, ""
        if still:
            self.parked(t_ns, position_m)
            return False, "standstill" if wanted else ""
        if not (wanted and self.holding):
            return wanted, ""
        p = self.params
        moved_m = float(np.linalg.norm(np.asarray(position_m) - self._still_position_m))
        waited_s = (t_ns - self._still_t_ns) * 1e-9
        if (
            moved_m >= p.first_max_motion_m
            or waited_s >= p.first_max_wait_s
            or count_points() >= p.first_min_points
        ):
            self.holding = False
            return True, ""
        return False, "no_parallax"


def triangulate_midpoint(
    origins_a: NDArray, dirs_a: NDArray, origins_b: NDArray, dirs_b: NDArray
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Midpoint of the closest approach of ray pairs, vectorised.

    ``origins_*`` / ``dirs_*`` [N, 3] in one frame (directions need not be unit). Returns the points
    [N, 3] and the parallax angle [N] (rad) between the rays; points of near-parallel rays are NaN.
    """
    oa, da = np.asarray(origins_a, float), np.asarray(dirs_a, float)
    ob, db = np.asarray(origins_b, float), np.asarray(dirs_b, float)
    da = da / np.linalg.norm(da, axis=1, keepdims=True)
    db = db / np.linalg.norm(db, axis=1, keepdims=True)
    w = oa - ob
    b = np.einsum("ij,ij->i", da, db)
    d = np.einsum("ij,ij->i", da, w)
    e = np.einsum("ij,ij->i", db, w)
    den = 1.0 - b * b
    ok = den > 1e-10
    den = np.where(ok, den, 1.0)
    sa = (b * e - d) / den
    sb = (e - b * d) / den
    p = 0.5 * (oa + sa[:, None] * da + ob + sb[:, None] * db)
    p[~ok | (sa <= 0) | (sb <= 0)] = np.nan
    angle = np.arccos(np.clip(b, -1.0, 1.0))
    return p, angle


def landmark_covariance(
    points_world: NDArray,
    T_world_cams: NDArray,
    obs_mask: NDArray,
    camera: PinholeCamera,
    pixel_sigma: float,
) -> NDArray[np.float64]:
    """Covariance [N, 3, 3] of each landmark with the poses held fixed (Gauss-Newton, first order).

    ``points_world`` [N, 3], ``T_world_cams`` [F, 4, 4], ``obs_mask`` [N, F] bool (which frames see
    which point). Information ``sum_f J_f^T J_f / sigma^2`` with ``J_f`` the projection Jacobian.
    """
    P = check_array("points_world", points_world, shape=(None, 3))
    T = check_array("T_world_cams", T_world_cams, shape=(None, 4, 4))
    M = check_array("obs_mask", obs_mask, shape=(len(P), len(T)))
    R_cw = np.swapaxes(T[:, :3, :3], 1, 2)  # [F, 3, 3]
    t_cw = -(R_cw @ T[:, :3, 3:])[..., 0]  # [F, 3]
    Pc = np.einsum("fij,nj->nfi", R_cw, P) + t_cw[None]  # [N, F, 3]
    z = np.maximum(Pc[..., 2], 1e-6)
    x, y = Pc[..., 0], Pc[..., 1]
    J = np.zeros(Pc.shape[:2] + (2, 3))  # d(uv)/d(P_cam)
    J[..., 0, 0] = camera.fx_px / z
    J[..., 0, 2] = -camera.fx_px * x / z**2
    J[..., 1, 1] = camera.fy_px / z
    J[..., 1, 2] = -camera.fy_px * y / z**2
    Jw = J @ R_cw[None]  # [N, F, 2, 3]
    info = np.einsum("nfki,nfkj,nf->nij", Jw, Jw, M.astype(float)) / pixel_sigma**2
    info += np.eye(3) * 1e-9
    return np.linalg.inv(info)


def omega_weight(
    track_len: NDArray, reproj_err_px: NDArray, params: KeyframeParams
) -> NDArray[np.float32]:
    """Weight omega in [0, 1] per feature: ``(1 - exp(-len / L0)) / (1 + (err / e0)^2)``."""
    n = np.asarray(track_len, dtype=np.float64)
    e = np.asarray(reproj_err_px, dtype=np.float64)
    w = (1.0 - np.exp(-n / params.omega_track_len)) / (1.0 + (e / params.omega_reproj_px) ** 2)
    return np.clip(np.nan_to_num(w, nan=0.0), 0.0, 1.0).astype(np.float32)
