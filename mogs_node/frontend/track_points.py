"""Sparse metric points of a keyframe from the frontend's dense feature tracks (pure).

Paper section IV-A: the sparse points are triangulated from several views by the linear (SVD)
method and then refined by nonlinear least squares. Here every track of the dense tracker that is
alive in the keyframe is triangulated from the frames it was seen in, with the frontend's own
poses:

1. :func:`triangulate_on_ray` (round 13): the linear (DLT) equations of all views solved for the
   depth along the keyframe's ray, in closed form (:func:`triangulate_dlt`: all three unknowns,
   by SVD, before).
2. :func:`refine_points`: Gauss-Newton on the reprojection error, in the keyframe's camera frame,
   parametrised by inverse depth along the keyframe ray (well conditioned for far points),
   vectorised over points. It returns the covariance from the Jacobian (poses held fixed).
3. :func:`gate_points`: parallax angle, reprojection error, depth range, relative depth sigma;
   the weight omega from the relative depth sigma.
4. :func:`unsupported_depth_flags` (round 9; :func:`depth_edge_flags` before): points that no
   image-space neighbour agrees with in depth are dropped: a track straddling a depth edge
   triangulates between the two sides; a silhouette corner whose own side agrees is kept.
5. :func:`epipole_cell_caps` (round 13, opt-in): fewer dense tracks around the focus of
   expansion, where they seldom triangulate.

The previous keyframes' points (carried at standstill, re-observed while moving) are in
:mod:`mogs_node.frontend.reobserve`; :func:`patch_match` (ZNCC and contrast ratio of two
patches) serves both. :class:`TrackHistory` keeps the observations and poses of the last frames.
No I/O, no bus.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from mogs_node.errors import ConfigError
from mogs_node.frontend.tracker import TrackerParams
from mogs_node.frontend.triangulation import (
    RefinedPoints,
    RefineParams,
    refine_points,
    triangulate_dlt,
    triangulate_on_ray,
)
from mogs_node.geometry import PinholeCamera, check_array, se3_inverse, transform_points

__all__ = [
    "KeyframePoints",
    "RefinedPoints",
    "TrackHistory",
    "TrackPointsParams",
    "TrackViews",
    "depth_edge_flags",
    "edge_flags",
    "epipole_cell_caps",
    "unsupported_depth_flags",
    "gate_points",
    "keyframe_points",
    "patch_match",
    "refine_points",
    "triangulate_dlt",
    "triangulate_on_ray",
]


@dataclass(frozen=True)
class TrackPointsParams:
    """Dense tracks and the sparse points triangulated from them (docs/frontend.md, rounds 6-9)."""

    enabled: bool = True  # publish the dense tracks' points (False: the estimator's landmarks)
    max_tracks: int = 900  # dense tracks kept per frame (the estimator's tracker is separate)
    min_distance_px: int = 5  # minimum distance between dense tracks (a square, not a disc)
    quality_level: float = 0.001  # Shi-Tomasi quality relative to the best corner
    win_size_px: int = 9  # KLT window of the dense tracker (small: cheap, local motion)
    pyr_levels: int = 3  # KLT pyramid levels
    fb_check: bool = False  # forward-backward check (True: twice the KLT cost; the multi-view
    # reprojection gate catches the same drifting tracks)
    klt_max_iter: int = 10  # KLT iterations per pyramid level
    top_up_every: int = 2  # new corners every this many frames (2: ~40 % less tracker time,
    # ~7 % fewer points on the demo drive, whose tracks die in bursts; round 9)
    ransac_thresh_px: float = 1.0  # F-RANSAC threshold of the dense tracker (undistorted px)
    bucket_cols: int = 16  # bucketing grid: at most ~2x the even share of tracks per cell
    bucket_rows: int = 5
    epipole_radius_deg: float = 0.0  # cells whose centre ray is within this angle of the
    # direction of motion (the focus of expansion) hold at most epipole_cap_share of the cap:
    # tracks there rarely get the parallax for a point (round 13; 0: off; the visual-inertial
    # frontend only: the camera-only one's poses come from these tracks)
    epipole_cap_share: float = 0.25
    history_frames: int = 10  # frames of observations (and poses) a track is triangulated from
    min_views: int = 3  # observations needed (the keyframe's included)
    min_parallax_deg: float = 1.0  # largest ray angle between the keyframe and another view
    # (0.3: the same points on the demo drive, a worse metrized depth on KITTI; round 9)
    max_reproj_px: float = 0.6  # largest reprojection error over the views after refinement
    min_depth_m: float = 0.5  # depth range in the keyframe
    max_depth_m: float = 100.0
    pixel_sigma_px: float = 0.5  # KLT noise assumed for the covariance (at least the residual)
    max_depth_rel_sigma: float = 0.05  # 1-sigma depth / depth above this: dropped
    omega_rel_sigma: float = 0.02  # omega = 1 / (1 + (sigma_z / z / this)^2)
    view_stride: int = 1  # frames older than the last 3 are used every this many frames
    # (triangulation cost is linear in the frames; round 9)
    gn_iterations: int = 2  # Gauss-Newton iterations of the refinement (from the DLT start, 1,
    # 2 and 4 give the same points on the demo drive; round 9)
    edge_radius_px: float = 8.0  # neighbours this close in the image are compared ...
    edge_rel_jump: float = 0.1  # ... and a relative depth jump larger than this marks an edge
    edge_rule: str = "both_sides"  # "both_sides": drop both sides of every jump
    # (depth_edge_flags); "unsupported": drop points no close neighbour agrees with
    # (unsupported_depth_flags; round 9)
    patch_radius_px: int = 3  # photometric check: (2r+1)^2 patch around the point in the
    min_patch_zncc: float = 0.8  # keyframe against its oldest view, moved by the point's own
    # depth: a patch straddling a depth edge does not match (ZNCC below this: dropped)
    two_view_min_zncc: float = 0.9  # with min_views 2: a point seen in 2 views only needs at
    # least this ZNCC (one residual degree of freedom: the reprojection gate sees little)
    suspect_zncc: float = 0.95  # a point with a lower ZNCC ...
    suspect_reproj_px: float = 0.3  # ... or a larger reprojection error ...
    suspect_weight: float = 0.25  # ... keeps this share of its omega
    reproject_keyframes: int = 3  # the last keyframes whose points join a new keyframe's fresh
    # ones where they still match (0: none)
    reproject_min_zncc: float = 0.9  # their patch against the previous keyframe's, at least this
    reproject_min_contrast: float = 0.0  # ... and at least this share of its grey-level spread
    # there (a textured point behind a flat occluder leaves a flat patch; round 14; 0: off)
    carry_min_points: int = 30  # fewer fresh points: the previous keyframe's are carried forward,
    carry_max_motion_m: float = 0.25  # if the camera moved less than this since (standstill:
    # moving on, occluders move over the old points and they no longer hold)

    def __post_init__(self) -> None:
        if (
            self.max_tracks < 8
            or self.history_frames < 2
            or self.min_views < 2
            or self.view_stride < 1
        ):
            raise ConfigError(
                "points: max_tracks >= 8, history_frames >= 2, min_views >= 2, view_stride >= 1"
            )
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise ConfigError("points: 0 < min_depth_m < max_depth_m")
        if min(self.max_reproj_px, self.pixel_sigma_px, self.omega_rel_sigma) <= 0:
            raise ConfigError("points: max_reproj_px, pixel_sigma_px, omega_rel_sigma > 0")
        if self.edge_rule not in ("both_sides", "unsupported"):
            raise ConfigError(
                f"points.edge_rule: 'both_sides' or 'unsupported', got {self.edge_rule!r}"
            )
        if self.epipole_radius_deg < 0 or not 0 <= self.epipole_cap_share <= 1:
            raise ConfigError("points: epipole_radius_deg >= 0, 0 <= epipole_cap_share <= 1")
        if not 0 < self.suspect_weight <= 1:
            raise ConfigError("points: 0 < suspect_weight <= 1")
        if not self.reproject_min_contrast >= 0:
            raise ConfigError(
                f"points.reproject_min_contrast: >= 0, got {self.reproject_min_contrast!r}"
            )
        if (
            min(self.bucket_cols, self.bucket_rows, self.gn_iterations, self.reproject_keyframes)
            < 0
        ):
            raise ConfigError(
                "points: bucket_cols, bucket_rows, gn_iterations, reproject_keyframes >= 0"
            )

    def bucket_cap(self) -> int:
        """Tracks a bucketing cell may hold (~2x its even share)."""
        return int(np.ceil(2.0 * self.max_tracks / max(self.bucket_cols * self.bucket_rows, 1)))

    def refine(self) -> RefineParams:
        """Settings of the Gauss-Newton refinement (:func:`refine_points`)."""
        return RefineParams(iterations=self.gn_iterations, pixel_sigma_px=self.pixel_sigma_px)

    def tracker(self) -> TrackerParams:
        """Parameters of the dense :class:`~mogs_node.frontend.tracker.FeatureTracker`."""
        return TrackerParams(
            max_features=self.max_tracks,
            min_distance_px=self.min_distance_px,
            quality_level=self.quality_level,
            win_size_px=self.win_size_px,
            pyr_levels=self.pyr_levels,
            fb_check=self.fb_check,
            klt_max_iter=self.klt_max_iter,
            top_up_every=self.top_up_every,
            ransac_thresh_px=self.ransac_thresh_px,
            square_spacing=True,
            bucket_cols=self.bucket_cols,
            bucket_rows=self.bucket_rows,
            bucket_cap=self.bucket_cap(),
        )


def epipole_cell_caps(
    camera: PinholeCamera, v_cam: NDArray, params: TrackPointsParams
) -> NDArray[np.int64] | None:
    """Per-cell track caps [bucket_rows, bucket_cols] for the dense tracker: the cells whose
    centre ray is within ``params.epipole_radius_deg`` of the direction of motion ``v_cam`` [3]
    (camera frame, any scale) get ``epipole_cap_share`` of the cap. A track's parallax grows with
    its angle from that direction, so near the focus of expansion tracks seldom pass the parallax
    and depth-sigma gates (on the demo drive 0-1 % of them give a point, against 16 % overall):
    their KLT and triangulation cost goes to tracks elsewhere. None: off, or no forward motion
    (standing, reversing, or the direction not finite)."""
    v = np.asarray(v_cam, np.float64).reshape(3)
    p = params
    if p.epipole_radius_deg <= 0 or p.bucket_cols <= 0 or p.bucket_rows <= 0:
        return None
    n = float(np.linalg.norm(v))
    if not np.isfinite(n) or n < 1e-9 or v[2] <= 0.5 * n:  # mostly forward, or nothing
        return None
    u = (np.arange(p.bucket_cols) + 0.5) * camera.width / p.bucket_cols
    w = (np.arange(p.bucket_rows) + 0.5) * camera.height / p.bucket_rows
    uu, ww = np.meshgrid(u, w)
    rays = camera.rays(np.stack([uu.ravel(), ww.ravel()], 1))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    near = rays @ (v / n) >= np.cos(np.radians(p.epipole_radius_deg))
    cap = p.bucket_cap()
    caps = np.where(near, int(np.ceil(p.epipole_cap_share * cap)), cap)
    return caps.reshape(p.bucket_rows, p.bucket_cols).astype(np.int64)


@dataclass
class KeyframePoints:
    """Sparse points of one keyframe in its camera frame; arrays share length ``N``."""

    ids: NDArray[np.int64]  # [N] dense track ids
    uv_px: NDArray[np.float32]  # [N, 2] undistorted pixel in the keyframe
    xyz_cam_m: NDArray[np.float32]  # [N, 3]
    cov_cam_m2: NDArray[np.float32]  # [N, 3, 3]
    weight: NDArray[np.float32]  # [N] omega in (0, 1]
    carried: bool = False  # True: moved over from the previous keyframe (standstill)

    @classmethod
    def empty(cls) -> KeyframePoints:
        return cls(
            np.zeros(0, np.int64),
            np.zeros((0, 2), np.float32),
            np.zeros((0, 3), np.float32),
            np.zeros((0, 3, 3), np.float32),
            np.zeros(0, np.float32),
        )

    def __len__(self) -> int:
        return len(self.ids)

    def subset(self, mask: NDArray) -> KeyframePoints:
        """The points selected by ``mask`` [N] (bool) or an index array."""
        return KeyframePoints(
            self.ids[mask],
            self.uv_px[mask],
            self.xyz_cam_m[mask],
            self.cov_cam_m2[mask],
            self.weight[mask],
            self.carried,
        )


def gate_points(
    pts: RefinedPoints, params: TrackPointsParams
) -> tuple[NDArray[np.bool_], NDArray[np.float32]]:
    """Well-triangulated points: enough views, parallax, reprojection error, depth range, relative
    depth sigma. Returns the mask [N] and omega [N] ``= 1 / (1 + (sigma_z / z / s0)^2)``."""
    z = pts.xyz_ref_m[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = pts.depth_sigma_m / z
        keep = (
            pts.in_front
            & (pts.n_views >= params.min_views)
            & (pts.parallax_deg >= params.min_parallax_deg)
            & (pts.reproj_max_px <= params.max_reproj_px)
            & (z >= params.min_depth_m)
            & (z <= params.max_depth_m)
            & (rel <= params.max_depth_rel_sigma)
        )
        omega = 1.0 / (1.0 + (rel / params.omega_rel_sigma) ** 2)
    keep &= np.isfinite(omega)
    return keep, np.where(keep, omega, 0.0).astype(np.float32)


def depth_edge_flags(
    uv_px: NDArray, depth_m: NDArray, *, radius_px: float, rel_jump: float
) -> NDArray[np.bool_]:
    """Points [N] with an image-space neighbour within ``radius_px`` whose depth differs by more
    than ``rel_jump`` (relative): the two sides of a depth edge, where a corner's depth is
    ambiguous. ``uv_px`` [N, 2], ``depth_m`` [N] (> 0)."""
    uv = check_array("uv_px", uv_px, shape=(None, 2), dtype=np.number)
    z = check_array("depth_m", depth_m, shape=(len(uv),), dtype=np.number)
    flags = np.zeros(len(uv), bool)
    if len(uv) < 2:
        return flags
    pairs = cKDTree(uv).query_pairs(radius_px, output_type="ndarray")
    if len(pairs) == 0:
        return flags
    za, zb = z[pairs[:, 0]], z[pairs[:, 1]]
    jump = np.abs(np.log(za / zb)) > np.log1p(rel_jump)
    flags[pairs[jump, 0]] = True
    flags[pairs[jump, 1]] = True
    return flags


def unsupported_depth_flags(
    uv_px: NDArray, depth_m: NDArray, *, radius_px: float, rel_jump: float
) -> NDArray[np.bool_]:
    """Points [N] that have image-space neighbours within ``radius_px`` but none whose depth is
    within ``rel_jump`` (relative) of theirs: a depth no close surface agrees with, as a track
    straddling a depth edge gets (its corner slides along the occluding contour and triangulates
    between the two sides). A point by a silhouette whose neighbours on its own side agree is
    kept, unlike :func:`depth_edge_flags`, which drops both sides of every jump. Isolated points
    (no neighbour) are kept. ``uv_px`` [N, 2], ``depth_m`` [N] (> 0)."""
    uv = check_array("uv_px", uv_px, shape=(None, 2), dtype=np.number)
    z = check_array("depth_m", depth_m, shape=(len(uv),), dtype=np.number)
    if len(uv) < 2:
        return np.zeros(len(uv), bool)
    pairs = cKDTree(uv).query_pairs(radius_px, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros(len(uv), bool)
    agree = np.abs(np.log(z[pairs[:, 0]] / z[pairs[:, 1]])) <= np.log1p(rel_jump)
    near = np.bincount(pairs.ravel(), minlength=len(uv))
    agreeing = np.bincount(pairs[agree].ravel(), minlength=len(uv))
    return (near > 0) & (agreeing == 0)


def edge_flags(params: TrackPointsParams) -> Callable[..., NDArray[np.bool_]]:
    """The depth-edge test that ``params.edge_rule`` names."""
    return unsupported_depth_flags if params.edge_rule == "unsupported" else depth_edge_flags


def patch_match(
    image_ref: NDArray,
    uv_ref_px: NDArray,
    image_view: NDArray,
    uv_view_px: NDArray,
    scale: NDArray,
    radius_px: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Zero-mean normalised cross-correlation [N] of a ``(2r+1)^2`` patch around each point in
    the reference image with the patch around its observation in another view, sampled at
    ``scale`` [N] times the offsets (a fronto-parallel patch at the point's depth: ``z_ref /
    z_view``), and the contrast ratio [N] (the reference patch's grey-level standard deviation
    over the view's; inf where the view's patch is flat). Images are [H, W] grey (float32 ones
    are sampled without a copy); pixels [N, 2]. A patch with no texture gives a ZNCC of 0.

    Why the contrast: a textured point hidden behind a flat occluder leaves a near-flat patch
    whose few grey levels of shading can still correlate with the old texture (round 14: the
    demo's re-observed points behind the gate's columns, 4-8x their true depth, at ZNCC
    0.70-0.96 and a contrast ratio of 0.03-0.35)."""
    uv_r = check_array("uv_ref_px", uv_ref_px, shape=(None, 2)).astype(np.float32)
    uv_v = check_array("uv_view_px", uv_view_px, shape=(len(uv_r), 2)).astype(np.float32)
    s = check_array("scale", scale, shape=(len(uv_r),)).astype(np.float32)
    if len(uv_r) == 0:
        return np.zeros(0), np.zeros(0)
    o = np.arange(-radius_px, radius_px + 1, dtype=np.float32)
    ox, oy = np.meshgrid(o, o)
    ox, oy = ox.ravel()[None], oy.ravel()[None]  # [1, P]

    def sample(img: NDArray, uv: NDArray, k: NDArray) -> NDArray:
        mx = (uv[:, :1] + k[:, None] * ox).astype(np.float32)
        my = (uv[:, 1:] + k[:, None] * oy).astype(np.float32)
        return cv2.remap(
            np.asarray(img, np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        ).astype(np.float64)

    a = sample(image_ref, uv_r, np.ones_like(s))
    b = sample(image_view, uv_v, np.where(np.isfinite(s), s, 1.0))
    a -= a.mean(axis=1, keepdims=True)
    b -= b.mean(axis=1, keepdims=True)
    aa, bb = (a * a).sum(axis=1), (b * b).sum(axis=1)
    den = np.sqrt(aa * bb)
    zncc = np.where(den > 1e-6, (a * b).sum(axis=1) / np.maximum(den, 1e-6), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        contrast = np.where(bb > 0, np.sqrt(aa / np.where(bb > 0, bb, 1.0)), np.inf)
    return zncc, contrast


@dataclass
class TrackViews:
    """The newest frame's tracks over the kept frames with a pose (the newest frame last)."""

    ids: NDArray[np.int64]  # [N] track ids
    uv_px: NDArray[np.float64]  # [N, F, 2] undistorted pixels, NaN where not seen
    T_world_cams: NDArray[np.float64]  # [F, 4, 4]
    images: list[NDArray[np.uint8] | None]  # [F] grey images ([H, W]) where kept
    t_ns: int  # stamp of the newest frame


class TrackHistory:
    """Dense-track observations, grey images and camera poses of the last ``max_frames`` frames."""

    def __init__(self, max_frames: int) -> None:
        self._frames: deque[tuple[int, NDArray, NDArray, NDArray | None]] = deque(maxlen=max_frames)
        self._poses: dict[int, NDArray] = {}

    def reset(self) -> None:
        self._frames.clear()
        self._poses.clear()

    def add(
        self, t_ns: int, ids: NDArray, uv_px: NDArray, image: NDArray[np.uint8] | None = None
    ) -> None:
        """Observations of frame ``t_ns``: track ids [M], undistorted pixels [M, 2] and the
        (undistorted) grey image [H, W] for the photometric check (None: no check)."""
        order = np.argsort(ids, kind="stable")
        self._frames.append((int(t_ns), np.asarray(ids)[order], np.asarray(uv_px)[order], image))
        kept = {fr[0] for fr in self._frames}
        self._poses = {t: T for t, T in self._poses.items() if t in kept}

    def newest_image(self) -> NDArray[np.uint8] | None:
        """The newest frame's grey image [H, W] (None: none kept)."""
        return self._frames[-1][3] if self._frames else None

    def set_pose(self, t_ns: int, T_world_cam: NDArray) -> None:
        """Latest estimate of the camera pose [4, 4] of frame ``t_ns`` (ignored if not kept)."""
        if any(fr[0] == t_ns for fr in self._frames):
            self._poses[int(t_ns)] = np.array(T_world_cam, np.float64)

    def rescale(self, center: NDArray, ratio: float) -> None:
        """Scale the kept poses' positions about ``center`` [3] by ``ratio`` (a corrected metric
        scale: the next keyframe's points are triangulated over frames of one scale)."""
        c = np.asarray(center, np.float64)
        for T in self._poses.values():
            T[:3, 3] = c + ratio * (T[:3, 3] - c)

    def views(self) -> TrackViews | None:
        """The newest frame's tracks in every kept frame with a pose (None: the newest frame
        has no pose yet)."""
        if not self._frames or self._frames[-1][0] not in self._poses:
            return None
        frames = [fr for fr in self._frames if fr[0] in self._poses]
        ids = frames[-1][1]
        uv = np.full((len(ids), len(frames), 2), np.nan)
        for f, (_, fids, fuv, _) in enumerate(frames):  # over <= max_frames frames
            if len(fids) == 0:
                continue
            pos = np.clip(np.searchsorted(fids, ids), 0, len(fids) - 1)
            hit = fids[pos] == ids
            uv[hit, f] = fuv[pos[hit]]
        T = np.stack([self._poses[fr[0]] for fr in frames])
        return TrackViews(ids, uv, T, [fr[3] for fr in frames], frames[-1][0])


def _thinned(views: TrackViews, stride: int, recent: int = 3) -> TrackViews:
    """``views`` with the frames older than the last ``recent`` taken every ``stride`` frames
    (the oldest kept): the cost of the triangulation is linear in the frames, its accuracy
    depends mostly on the baseline, and young tracks keep all their views."""
    n_f = views.uv_px.shape[1]
    if stride <= 1 or n_f <= recent:
        return views
    cols = sorted(set(range(n_f - 1, n_f - 1 - recent, -1)) | set(range(0, n_f - recent, stride)))
    return TrackViews(
        views.ids,
        views.uv_px[:, cols],
        views.T_world_cams[cols],
        [views.images[c] for c in cols],
        views.t_ns,
    )


def _patch_scores(
    views: TrackViews,
    uv: NDArray,
    xyz_ref_m: NDArray,
    T_ref_cams: NDArray,
    params: TrackPointsParams,
) -> NDArray[np.float64]:
    """ZNCC [N] of each point's keyframe patch with its oldest view's (:func:`patch_match`);
    1 where there is no image to compare."""
    score = np.ones(len(uv))
    img_ref = views.images[-1]
    if img_ref is None:
        return score
    img_ref = np.asarray(img_ref, np.float32)  # converted once, not per view
    oldest = np.argmax(np.isfinite(uv[..., 0]), axis=1)  # first view that saw each point
    T_cam_ref = se3_inverse(T_ref_cams)
    for f in np.unique(oldest).tolist():  # over <= history_frames views
        img = views.images[f]
        sel = np.flatnonzero(oldest == f)
        if img is None or f == len(views.images) - 1:
            continue
        z_view = transform_points(T_cam_ref[f], xyz_ref_m[sel])[:, 2]
        scale = xyz_ref_m[sel, 2] / np.maximum(z_view, 1e-9)
        score[sel] = patch_match(
            img_ref, uv[sel, -1], img, uv[sel, f], scale, params.patch_radius_px
        )[0]
    return score


def keyframe_points(
    history: TrackHistory, camera: PinholeCamera, params: TrackPointsParams
) -> KeyframePoints:
    """Every well-triangulated dense track of the newest frame (the keyframe), in its camera:
    DLT + Gauss-Newton (paper IV-A), the gates of :func:`gate_points`, then the depth-edge tests
    (photometric patch check, neighbour depth jumps)."""
    views = history.views()
    if views is None or views.uv_px.shape[1] < 2:
        return KeyframePoints.empty()
    views = _thinned(views, params.view_stride)
    T_ref_cams = se3_inverse(views.T_world_cams[-1])[None] @ views.T_world_cams  # [F, 4, 4]
    enough = np.isfinite(views.uv_px[..., 0]).sum(axis=1) >= params.min_views
    ids, uv = views.ids[enough], views.uv_px[enough]
    X0 = triangulate_on_ray(uv, T_ref_cams, camera)  # the DLT's points at ~1/10 of its cost
    pts = refine_points(uv, T_ref_cams, camera, X0, params.refine())
    keep, omega = gate_points(pts, params)
    idx = np.flatnonzero(keep)
    zncc = np.ones(len(ids))
    zncc[idx] = _patch_scores(views, uv[idx], pts.xyz_ref_m[idx], T_ref_cams, params)
    keep &= zncc >= params.min_patch_zncc
    # a track seen twice has one residual degree of freedom: it must match closely
    keep &= (pts.n_views > 2) | (zncc >= params.two_view_min_zncc)
    # close to the gates: kept, but weighed down (a point by a depth edge often lands here)
    suspect = (zncc < params.suspect_zncc) | (pts.reproj_max_px > params.suspect_reproj_px)
    omega = np.where(suspect, params.suspect_weight * omega, omega).astype(np.float32)
    idx = np.flatnonzero(keep)
    uv_k, z_k = uv[idx, -1], pts.xyz_ref_m[idx, 2]
    edge = edge_flags(params)(
        uv_k, z_k, radius_px=params.edge_radius_px, rel_jump=params.edge_rel_jump
    )
    keep[idx] = ~edge
    return KeyframePoints(
        ids=ids[keep].astype(np.int64),
        uv_px=uv[keep, -1].astype(np.float32),
        xyz_cam_m=pts.xyz_ref_m[keep].astype(np.float32),
        cov_cam_m2=pts.cov_ref_m2[keep].astype(np.float32),
        weight=omega[keep],
    )
