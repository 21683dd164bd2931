"""Camera-only frontend: a drive without an IMU (KITTI odometry, a dashcam), or with poses the user
already has (``player.poses``). docs/bridges.md, "No IMU: camera only; your own poses".

The pose of a frame relative to the last keyframe comes from the essential matrix of the dense
KLT tracks (rotation and translation direction, five-point RANSAC) and the metric length of the
translation from the road at the calibrated camera height (:func:`~mogs_node.frontend.ground.
estimate_ground_translation`: the plane homography of the road between the two images; the
visual-inertial frontend uses the same measurement for its scale). Each keyframe's own road
points check that scale (:func:`~mogs_node.frontend.ground.road_height_of_points`); where they
find the road grossly off (under a vehicle ahead on KITTI: 3x low), the keyframe's points carry
the scale from then on (:func:`~mogs_node.frontend.point_scale.distance_from_points`) until the
road agrees again (docs/frontend.md, round 12). A frame whose tracks stand still does not move.
A frame with too little parallax for the essential matrix keeps the previous rotation and
direction. With given poses (``add_image(..., T_world_cam=...)``) nothing is estimated. Either way the keyframes' sparse
points are the dense tracks triangulated over the last frames with those poses (DLT + Gauss-Newton
and the gates of :func:`~mogs_node.frontend.track_points.keyframe_points`, paper IV-A).

World frame (estimated poses): road-aligned, z up (away from the road), x along the first camera's
view, the first camera ``camera_height_m`` above the origin: what the depth prior's road model and
the mapper expect of the visual-inertial world. The same interface as
:class:`~mogs_node.frontend.frontend.Frontend` (``add_image``, ``add_imu``, ``counters``), so the
node shell drives either.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError
from mogs_node.frontend.camera import CameraModel
from mogs_node.frontend.frontend import FrameOutput, KeyframeOutput
from mogs_node.frontend.ground import (
    GroundParams,
    estimate_ground_translation,
    road_height_of_points,
    road_normal_from_mount,
)
from mogs_node.frontend.keyframes import KeyframeParams, StandstillKeyframes, is_keyframe
from mogs_node.frontend.point_scale import distance_from_points
from mogs_node.frontend.speed_memory import SpeedMemory
from mogs_node.frontend.track_points import (
    KeyframePoints,
    TrackHistory,
    TrackPointsParams,
    keyframe_points,
)
from mogs_node.frontend.tracker import FeatureTracker
from mogs_node.geometry import check_array, make_T, se3_inverse

__all__ = ["MonocularFrontend", "MonocularParams", "road_aligned_start"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MonocularParams:
    """Parameters of the camera-only frontend."""

    min_parallax_px: float = 20.0  # keyframe: median track motion since the last keyframe
    max_interval_s: float = 1.0  # ... or this long since it (with min_pose_parallax_px)
    min_pose_parallax_px: float = 4.0  # below: too little baseline for the essential matrix
    # (the frame keeps the previous frame's rotation)
    min_tracks: int = 40  # tracks shared with the keyframe to estimate a pose
    ransac_px: float = 1.0  # five-point RANSAC threshold (undistorted px)
    min_inlier_share: float = 0.5  # of the shared tracks, for a pose to be kept
    max_turn_deg: float = 45.0  # a motion direction this far from the last one is not kept (a
    # near-stop's essential matrix flipped it on KITTI: a 2 m jump; round 12)
    first_speed_m_s: float = 5.0  # scale search of the first pair: around this speed ...
    first_search_span: float = 8.0  # ... within this factor either way
    max_speed_m_s: float = 60.0  # a road measurement implying more is rejected
    gate_rel: float = 0.3  # a road speed this far from the median of the recent ones is gated
    gate_window: int = 9  # recent accepted road speeds kept
    relock_after: int = 5  # this many gated road speeds in a row, all on one side of the median:
    # the speed has changed (the car sped up or braked), not an outlier: they replace the recent
    # ones (without it one early median held the speed for the rest of the drive: issue 18)
    still_flow_px: float = 0.5  # median track motion since the previous frame below this: parked,
    # no step (a failed road measurement while parked kept the last speed: 0.56 m/s on KITTI)
    road_points_min: int = 5  # a keyframe's own road points (at least this many; 0: off) check
    # the scale: the calibrated camera height over their height below the camera corrects the
    # road measurement's gain, the recent frames and the keyframe's points (round 12)
    road_points_window: float = 0.1  # the road: the densest of the points' heights within +-this
    road_points_max_correction: float = 4.0  # one check corrects by at most this factor ...
    road_points_min_correction: float = 1.25  # ... and at least this one (a gross error only)
    scale_points_min: int = 10  # the keyframe's points seen in a frame (at least this many; 0:
    # off) give its distance from the keyframe (the points' scale carried on) where the road
    # fails, and instead of the road once a road points' check found it grossly off ...
    road_agree_rel: float = 0.15  # ... until the road's distance over a keyframe interval
    # agrees with theirs this well (the chain drifts a few % per keyframe; a biased road is off
    # by far more: 3x under a vehicle ahead on KITTI)
    road_normal_cam: tuple[float, float, float] | None = None  # road normal (towards the road) in
    # the camera; None: from T_imu_cam (IMU mounted level) or +y (a level rectified camera)
    ground_max_residual: float = 20.0  # the road measurement's residual bound (grey levels):
    # looser than the visual-inertial frontend's 12, which has the IMU to fall back on; the
    # speed gate (gate_rel) stands between a bad measurement and the poses
    points: TrackPointsParams = field(
        default_factory=lambda: TrackPointsParams(max_reproj_px=1.5)
    )  # each frame's pose has its own essential matrix: a looser reprojection gate than the
    # window-optimised poses of the visual-inertial frontend (0.6 px)
    ground: GroundParams = field(default_factory=GroundParams)
    # with given poses nothing is estimated from the keyframes' spacing: they are taken as the
    # visual-inertial frontend takes them (frontend.keyframes: parallax, tracks kept, interval,
    # none while parked), so a run with the user's poses maps the same keyframes as one with the IMU
    keyframes: KeyframeParams = field(default_factory=KeyframeParams)
    still_step_m: float = 0.01  # given poses: a frame that moved less is parked

    def __post_init__(self) -> None:
        if self.min_parallax_px <= self.min_pose_parallax_px or self.min_pose_parallax_px <= 0:
            raise ConfigError("camera-only: 0 < min_pose_parallax_px < min_parallax_px")
        if self.min_tracks < 8 or not 0 < self.min_inlier_share <= 1:
            raise ConfigError("camera-only: min_tracks >= 8, 0 < min_inlier_share <= 1")
        if self.relock_after < 2:
            raise ConfigError(f"camera-only: relock_after >= 2, got {self.relock_after}")
        if self.still_flow_px < 0 or self.road_points_min < 0:
            raise ConfigError("camera-only: still_flow_px >= 0, road_points_min >= 0")
        if not 0 < self.road_points_window < 1 or not (
            1 <= self.road_points_min_correction <= self.road_points_max_correction
        ):
            raise ConfigError(
                "camera-only: 0 < road_points_window < 1, "
                "1 <= road_points_min_correction <= road_points_max_correction"
            )


def road_aligned_start(normal_cam: NDArray, height_m: float) -> NDArray[np.float64]:
    """``T_world_cam`` [4, 4] of the first camera: world z up (against the road normal
    ``normal_cam`` [3], which points from the camera to the road), x along the camera's view
    projected onto the road, the camera ``height_m`` above the origin."""
    n = check_array("normal_cam", normal_cam, shape=(3,), finite=True)
    z = -n / np.linalg.norm(n)
    x = np.array([0.0, 0.0, 1.0]) - z * z[2]
    if np.linalg.norm(x) < 1e-6:
        raise ConfigError("road normal along the optical axis: the camera looks at the road")
    x /= np.linalg.norm(x)
    R_world_cam = np.stack([x, np.cross(z, x), z])  # rows: world axes in the camera frame
    return make_T(R_world_cam, [0.0, 0.0, height_m])


@dataclass
class _Keyframe:
    t_ns: int
    gray: NDArray[np.uint8]
    uv: dict[int, NDArray]  # track id -> undistorted pixel
    T_world_cam: NDArray[np.float64]
    points: KeyframePoints  # its sparse points (PnP of the next frames)


class MonocularFrontend:
    """Camera-only (or given-pose) frontend; see the module docstring."""

    def __init__(
        self,
        params: MonocularParams,
        camera: CameraModel,
        T_imu_cam: NDArray | None = None,
        *,
        given_poses: bool = False,
    ) -> None:
        if not given_poses and not params.ground.enabled:
            raise ConfigError(
                "camera-only: the metric scale comes from the road: needs the camera height "
                "(player.camera_height_m, or frontend.ground.camera_height_m > 0)"
            )
        if camera.model != "none":
            raise ConfigError(
                f"camera-only: needs rectified images (camera model 'none', got {camera.model!r})"
            )
        self.params = replace(
            params, ground=replace(params.ground, max_residual=params.ground_max_residual)
        )
        self.given_poses = given_poses
        self.camera = camera
        self.T_imu_cam = None if T_imu_cam is None else np.asarray(T_imu_cam, np.float64)
        if params.road_normal_cam is not None:
            n = np.asarray(params.road_normal_cam, np.float64)
        elif self.T_imu_cam is not None:
            n = road_normal_from_mount(self.T_imu_cam)
        else:
            n = np.array([0.0, 1.0, 0.0])
        self.normal_cam = n / np.linalg.norm(n)
        self.tracker = FeatureTracker(params.points.tracker(), camera)
        self.history = TrackHistory(params.points.history_frames)
        self.kf: _Keyframe | None = None
        self._keyframe_id = 0
        self._frame_index = 0
        self._last_ns: int | None = None
        self._last_pose: tuple[int, NDArray] | None = None  # (t_ns, T_world_cam)
        self.speed = SpeedMemory(params.gate_rel, params.gate_window, params.relock_after)
        self.points_mode = False  # the keyframe's points carry the scale, not the road
        self._standstill = StandstillKeyframes(params.keyframes)  # given poses: none while parked
        self._prev_uv: dict[int, NDArray] = {}  # the previous frame's tracks (standstill test)
        # the previous frame with a pose: (t_ns, grey, R_cam_kf, T_world_cam)
        self._prev: tuple[int, NDArray, NDArray, NDArray] | None = None
        self._prev_R_kf = np.eye(3)
        self._dist_since_kf = 0.0  # road distance travelled since the keyframe
        fwd = np.array([0.0, 0.0, 1.0]) - self.normal_cam * self.normal_cam[2]
        self._dir_kf = fwd / np.linalg.norm(fwd)  # a car moves along the road, ahead
        self.counters: dict[str, float] = {
            "frames": 0,
            "keyframes": 0,
            "imu_samples_ignored": 0,
            "image_time_backwards": 0,
            "image_wrong_size": 0,
            "poses_essential": 0,
            "poses_given": 0,
            "frames_without_pose": 0,
            "ground_measurements": 0,
            "ground_failed": 0,
            "ground_gated": 0,
            "ground_relocked": 0,
            "standstill_frames": 0,
            "scale_from_points": 0,
            "ground_agreed": 0,
            "road_points_checks": 0,
            "road_points_unchecked": 0,
            "road_points_corrections": 0,
            "road_trusted_again": 0,
        }

    @property
    def pending_stamps_ns(self) -> list[int]:
        return []  # nothing waits: there is no IMU to wait for

    def add_imu(self, t_ns: int, gyro_rad_s: object, accel_m_s2: object) -> list[FrameOutput]:
        """Ignored (camera-only), counted."""
        self.counters["imu_samples_ignored"] += 1
        return []

    # ----------------------------------------------------------------------------------- frames

    def add_image(
        self, stamp_ns: int, image: NDArray, T_world_cam: NDArray | None = None
    ) -> list[FrameOutput]:
        """One frame; ``T_world_cam`` [4, 4]: the pose the user has (nothing is estimated)."""
        if self._last_ns is not None and stamp_ns <= self._last_ns:
            self.counters["image_time_backwards"] += 1
            return []
        pin = self.camera.pinhole
        if image.ndim not in (2, 3) or image.shape[:2] != (pin.height, pin.width):
            self.counters["image_wrong_size"] += 1
            return []
        self._last_ns = int(stamp_ns)
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        tr = self.tracker.track(image)
        self.history.add(stamp_ns, tr.ids, tr.uv_px, gray)
        self.counters["frames"] += 1
        idx = self._frame_index
        self._frame_index += 1
        uv = dict(zip(tr.ids.tolist(), tr.uv_px))
        flow_px, self._prev_uv = _median_motion(self._prev_uv, uv), uv
        if self.given_poses and T_world_cam is None:
            self.counters["frames_without_pose"] += 1  # no pose of the user's for this frame
            return [self._output(stamp_ns, idx, None, "no_pose")]
        if self.kf is None:  # the first frame: the first keyframe (no points yet)
            T0 = (
                np.asarray(T_world_cam, np.float64)
                if T_world_cam is not None
                else road_aligned_start(self.normal_cam, self.params.ground.camera_height_m)
            )
            self.kf = _Keyframe(int(stamp_ns), gray, uv, T0, KeyframePoints.empty())
            self.history.set_pose(stamp_ns, T0)
            self._prev = (int(stamp_ns), gray, np.eye(3), T0)
            return [self._output(stamp_ns, idx, T0, "tracking")]
        parallax, shared = self._parallax(uv)
        prev_position_m = self._prev[3][:3, 3] if self._prev is not None else None
        if T_world_cam is not None:
            T = np.asarray(T_world_cam, np.float64)
            self.counters["poses_given"] += 1
            self._prev_R_kf = T[:3, :3].T @ self.kf.T_world_cam[:3, :3]
        else:
            T = self._estimate(stamp_ns, gray, uv, parallax, shared, flow_px)
        if T is None:
            self.counters["frames_without_pose"] += 1
            return [self._output(stamp_ns, idx, None, "initializing")]
        self.history.set_pose(stamp_ns, T)
        self._prev = (int(stamp_ns), gray, self._prev_R_kf, T)
        out = self._output(stamp_ns, idx, T, "tracking")
        p = self.params
        interval = (stamp_ns - self.kf.t_ns) * 1e-9
        if self.given_poses:
            take = self._given_pose_keyframe(stamp_ns, uv, T, prev_position_m, interval)
        else:
            take = parallax >= p.min_parallax_px or (
                interval >= p.max_interval_s and parallax >= p.min_pose_parallax_px
            )
        if take:
            out.keyframe = self._make_keyframe(stamp_ns, image, gray, uv, T)
        return [out]

    def _given_pose_keyframe(
        self,
        stamp_ns: int,
        uv: dict[int, NDArray],
        T: NDArray,
        prev_position_m: NDArray | None,
        interval_s: float,
    ) -> bool:
        """With given poses: the visual-inertial frontend's keyframe policy (``keyframes``)."""
        assert self.kf is not None
        kf_ids = np.fromiter(self.kf.uv, np.int64, len(self.kf.uv))
        ids = np.fromiter(uv, np.int64, len(uv))
        wanted, _ = is_keyframe(
            self.params.keyframes,
            kf_ids,
            np.array([self.kf.uv[i] for i in kf_ids.tolist()], np.float64).reshape(-1, 2),
            ids,
            np.array([uv[i] for i in ids.tolist()], np.float64).reshape(-1, 2),
            interval_s,
        )
        step = np.inf if prev_position_m is None else np.linalg.norm(T[:3, 3] - prev_position_m)
        take, _ = self._standstill.decide(
            wanted,
            bool(step < self.params.still_step_m),
            stamp_ns,
            T[:3, 3],
            lambda: len(keyframe_points(self.history, self.camera.pinhole, self.params.points).ids),
        )
        return take

    def _parallax(self, uv: dict[int, NDArray]) -> tuple[float, list[int]]:
        assert self.kf is not None
        shared = [i for i in uv if i in self.kf.uv]
        if not shared:
            return 0.0, shared
        d = np.linalg.norm(np.array([uv[i] - self.kf.uv[i] for i in shared]), axis=1)
        return float(np.median(d)), shared

    def _relative_to_keyframe(
        self, uv: dict[int, NDArray], parallax: float, shared: list[int]
    ) -> tuple[NDArray, NDArray] | None:
        """``R_cur_kf`` [3, 3] and the motion direction in the keyframe's camera [3] from the
        essential matrix of the tracks shared with the keyframe (None: too few or too little
        parallax)."""
        assert self.kf is not None
        p = self.params
        if len(shared) < p.min_tracks or parallax < p.min_pose_parallax_px:
            return None
        uv0 = np.array([self.kf.uv[i] for i in shared], np.float64)
        uv1 = np.array([uv[i] for i in shared], np.float64)
        K = self.camera.K
        E, mask = cv2.findEssentialMat(uv0, uv1, K, cv2.RANSAC, 0.999, p.ransac_px)
        if E is None or E.shape != (3, 3) or mask is None:
            return None
        n_in, R, t, _ = cv2.recoverPose(E, uv0, uv1, K, mask=mask)
        if n_in < p.min_inlier_share * mask.sum() or n_in < p.min_tracks // 2:
            return None
        t = t.reshape(3) / max(float(np.linalg.norm(t)), 1e-12)
        d = -R.T @ t  # X_cur = R X_kf + t: the camera moved along -R^T t
        if d @ self._dir_kf < np.cos(np.radians(p.max_turn_deg)):
            return None  # a car does not turn back: a degenerate essential matrix (round 12)
        return R, d

    def _estimate(
        self,
        stamp_ns: int,
        gray: NDArray,
        uv: dict[int, NDArray],
        parallax: float,
        shared: list[int],
        flow_px: float,
    ) -> NDArray | None:
        """``T_world_cam`` of this frame (None: no scale yet): the rotation from the essential
        matrix against the keyframe (or the previous frame's, when there is too little parallax),
        the step from the previous frame measured on the road along the motion direction (none
        when the tracks stood still: ``flow_px`` below ``still_flow_px``)."""
        assert self.kf is not None and self._prev is not None
        p = self.params
        rel = self._relative_to_keyframe(uv, parallax, shared)
        if rel is not None:
            R_cur_kf, self._dir_kf = rel
            self.counters["poses_essential"] += 1
        else:
            R_cur_kf = self._prev_R_kf  # too little parallax: no rotation since the last frame
        t_prev, gray_prev, R_prev_kf, T_world_prev = self._prev
        dt = (stamp_ns - t_prev) * 1e-9
        d_prev = R_prev_kf @ self._dir_kf  # motion direction in the previous camera
        R_cur_prev = R_cur_kf @ R_prev_kf.T
        step = None
        still = flow_px < p.still_flow_px and self.speed.speed_m_s is not None
        step = None
        if still:
            self.counters["standstill_frames"] += 1
            step = 0.0
        elif dt > 0:
            step = self._step(gray_prev, gray, R_cur_prev, d_prev, R_cur_kf, uv, dt)
        if step is None:
            self.counters["ground_failed"] += 1
            if self.speed.speed_m_s is None:
                return None
            step = self.speed.speed_m_s * dt  # constant speed over a gap of the road
        self._dist_since_kf += step
        self._prev_R_kf = R_cur_kf
        if rel is not None:  # along the essential matrix's direction: consistent with the tracks
            t_cur_kf = -R_cur_kf @ self._dir_kf * self._dist_since_kf
            return self.kf.T_world_cam @ se3_inverse(make_T(R_cur_kf, t_cur_kf))
        T = np.eye(4)
        T[:3, :3] = self.kf.T_world_cam[:3, :3] @ R_cur_kf.T
        T[:3, 3] = T_world_prev[:3, 3] + step * (T_world_prev[:3, :3] @ d_prev)
        return T

    def _step(
        self,
        gray_prev: NDArray,
        gray: NDArray,
        R_cur_prev: NDArray,
        d_prev: NDArray,
        R_cur_kf: NDArray,
        uv: dict[int, NDArray],
        dt: float,
    ) -> float | None:
        """The step [m] since the previous frame (None: no measurement). The road's through
        the speed gate, until a keyframe's road points find it grossly off (3x low under a
        vehicle ahead on KITTI: round 12); from then on (``points_mode``) the distance from the
        keyframe that its points seen here give (the scale they carry), until the road agrees
        again with that chain over a keyframe interval. Either falls back on the other."""
        from_pts = self._distance_from_points(uv, R_cur_kf)
        pts_step = None if from_pts is None else from_pts - self._dist_since_kf
        guess = pts_step if self.points_mode and pts_step is not None and pts_step > 0 else None
        road = self._road_step(gray_prev, gray, R_cur_prev, d_prev, dt, guess)
        if pts_step is not None and (self.points_mode or road is None):
            self.counters["scale_from_points"] += 1
            self.speed.note(road, pts_step)
            self.speed.remember(max(pts_step, 0.0) / dt)
            return pts_step
        if self.points_mode or road is None:
            return None  # not measured or not trusted: the recent speed (the caller's fallback)
        v = self._gate(road / dt)
        if self.kf is not None and not len(self.kf.points.ids) and self.speed.speed_m_s:
            # no points to carry the scale yet: the recent median, a smooth chain (per frame
            # the road jumps by 2x on KITTI) triangulates the first points, whose road check
            # then corrects its scale
            v = self.speed.speed_m_s
        return v * dt

    def _road_step(
        self,
        gray_prev: NDArray,
        gray: NDArray,
        R_cur_prev: NDArray,
        d_prev: NDArray,
        dt: float,
        guess_m: float | None,
    ) -> float | None:
        """The road's step [m] (its gain applied) around ``guess_m`` (None: the recent speed's,
        or the first search's); None where the road gives none."""
        p = self.params
        if self.speed.speed_m_s is None and guess_m is None:
            guess, g = p.first_speed_m_s * dt, replace(p.ground, search_span=p.first_search_span)
        else:
            guess = guess_m if guess_m is not None else max(self.speed.speed_m_s or 0.0, 0.3) * dt
            guess, g = guess / self.speed.road_gain, p.ground
        m = estimate_ground_translation(
            gray_prev,
            gray,
            self.camera.K,
            R_cur_prev,
            -R_cur_prev @ d_prev,
            self.normal_cam,
            guess / p.ground.camera_height_m,
            g,
            search=True,
        )
        dist = None if m is None else m.distance_m * self.speed.road_gain
        return dist if dist is not None and dist <= p.max_speed_m_s * dt else None

    def _gate(self, speed_m_s: float) -> float:
        """The road speed through the speed gate (:class:`SpeedMemory`), counted."""
        v, event = self.speed.gate(speed_m_s)
        self.counters[event] += 1
        if event == "ground_relocked":
            self.counters["ground_measurements"] += 1
        return v

    def _make_keyframe(
        self, stamp_ns: int, image: NDArray, gray: NDArray, uv: dict, T: NDArray
    ) -> KeyframeOutput:
        pts = keyframe_points(self.history, self.camera.pinhole, self.params.points)
        if not self.given_poses:
            pts = self._scale_checks(pts, T)
        self.kf = _Keyframe(int(stamp_ns), gray, uv, T, pts)
        self._dir_kf = self._prev_R_kf @ self._dir_kf  # into the new keyframe's camera
        self._prev_R_kf = np.eye(3)
        self._dist_since_kf = 0.0
        assert self._prev is not None
        self._prev = (self._prev[0], gray, np.eye(3), T)
        self.counters["keyframes"] += 1
        kf = KeyframeOutput(
            keyframe_id=self._keyframe_id,
            stamp_ns=int(stamp_ns),
            image=np.asarray(image),
            K=self.camera.K.copy(),
            T_world_cam=T.copy(),
            feature_ids=pts.ids.astype(np.int64),
            feature_uv_px=pts.uv_px.astype(np.float32),
            feature_xyz_cam_m=pts.xyz_cam_m.astype(np.float32),
            feature_cov_cam_m2=pts.cov_cam_m2.astype(np.float32),
            feature_weight=pts.weight.astype(np.float32),
        )
        self._keyframe_id += 1
        return kf

    def _distance_from_points(self, uv: dict[int, NDArray], R_cur_kf: NDArray) -> float | None:
        """Distance from the keyframe along its motion direction, from its points seen here."""
        assert self.kf is not None
        p, pts = self.params, self.kf.points
        if p.scale_points_min <= 0 or len(pts.ids) < p.scale_points_min:
            return None
        seen = [(k, i) for k, i in enumerate(pts.ids.tolist()) if i in uv]
        if len(seen) < p.scale_points_min:
            return None
        K = self.camera.K
        uv_cur = np.array([uv[i] for _, i in seen], np.float64)
        xy = (uv_cur - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
        X = pts.xyz_cam_m[[k for k, _ in seen]].astype(np.float64)
        est = distance_from_points(X, xy, R_cur_kf, self._dir_kf, min_points=p.scale_points_min)
        return None if est is None or est[0] < 0 else est[0]

    def _scale_checks(self, pts: KeyframePoints, T: NDArray) -> KeyframePoints:
        """At a keyframe: the road points' check (a gross error of the road's scale: the road is
        not to be trusted, the points carry the scale from here), and in ``points_mode`` the road's
        distance over the interval against the chain's: within ``road_agree_rel`` the road is
        trusted again (and corrects the chain's drift)."""
        p = self.params
        q = self.speed.interval_ratio()
        # in points_mode the chain is continuous (it drifts by a few % per keyframe): a gross
        # error there is more likely the check's (the road under a vehicle close ahead holds
        # no road points: x1.3-1.8 "corrections" at KITTI frames 41-50 with a frame dropped)
        use_check = p.road_points_min > 0 and not self.points_mode
        checked = self._road_points_check(pts, T) if use_check else None
        if checked is not None:
            if p.scale_points_min > 0:
                self.points_mode = True
            return checked
        if not self.points_mode or q is None or abs(np.log(q)) > np.log1p(p.road_agree_rel):
            return pts
        self.points_mode = False
        self.counters["road_trusted_again"] += 1
        return self._rescale(pts, T, q, gain=False)

    def _rescale(self, pts: KeyframePoints, T: NDArray, r: float, *, gain: bool) -> KeyframePoints:
        """The scale corrected by ``r`` about the keyframe at ``T``: the speeds (and the road's
        gain), the frames kept for the next keyframe's points, and these points."""
        self.speed.rescale(r, gain=gain)
        self.history.rescale(T[:3, 3], r)
        return replace(pts, xyz_cam_m=pts.xyz_cam_m * r, cov_cam_m2=pts.cov_cam_m2 * r**2)

    def _road_points_check(self, pts: KeyframePoints, T: NDArray) -> KeyframePoints | None:
        """The keyframe's points in the lane below the camera are road: the calibrated height
        over theirs is the error of the scale they (and the recent poses) were built with. It
        corrects the road measurement's gain (the road under a vehicle ahead reads low: round
        12), the recent speeds, the frames kept for the next keyframe's points and these points."""
        p = self.params
        est = road_height_of_points(
            pts.xyz_cam_m,
            self.normal_cam,
            window=p.road_points_window,
            min_points=p.road_points_min,
        )
        if est is None:
            self.counters["road_points_unchecked"] += 1
            return None
        self.counters["road_points_checks"] += 1
        c = p.road_points_max_correction
        r = float(np.clip(p.ground.camera_height_m / est[0], 1 / c, c))
        if abs(np.log(r)) < np.log(p.road_points_min_correction):
            return None  # within the check's own noise (~10 % with 10-20 road points)
        self.counters["road_points_corrections"] += 1
        return self._rescale(pts, T, r, gain=True)

    def _output(self, stamp_ns: int, idx: int, T: NDArray | None, status: str) -> FrameOutput:
        v = None
        if T is not None:
            if self._last_pose is not None and stamp_ns > self._last_pose[0]:
                dt = (stamp_ns - self._last_pose[0]) * 1e-9
                v = (T[:3, 3] - self._last_pose[1][:3, 3]) / dt
            else:
                v = np.zeros(3)
            self._last_pose = (int(stamp_ns), T)
        return FrameOutput(int(stamp_ns), idx, status, T, v)


def _median_motion(prev: dict[int, NDArray], cur: dict[int, NDArray]) -> float:
    """Median pixel motion of the tracks seen in both frames (inf: none shared)."""
    shared = [i for i in cur if i in prev]
    if not shared:
        return float("inf")
    return float(np.median(np.linalg.norm(np.array([cur[i] - prev[i] for i in shared]), axis=1)))
