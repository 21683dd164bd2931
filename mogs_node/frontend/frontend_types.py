"""The frontend core's parameters and outputs (:class:`~mogs_node.frontend.frontend.Frontend`)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError
from mogs_node.frontend.estimator import EstimatorParams
from mogs_node.frontend.ground import (
    GroundParams,
)
from mogs_node.frontend.initialization import (
    InitParams,
)
from mogs_node.frontend.keyframes import (
    KeyframeParams,
)
from mogs_node.frontend.platform import (
    PlatformBounds,
    PlatformProfile,
)
from mogs_node.frontend.preintegration import ImuNoise
from mogs_node.frontend.time_offset import (
    TimeOffsetParams,
)
from mogs_node.frontend.track_points import (
    TrackPointsParams,
)
from mogs_node.frontend.tracker import TrackerParams

__all__ = ["INIT_MODES", "FrameOutput", "FrontendParams", "KeyframeOutput"]

INIT_MODES = ("auto", "static", "dynamic")


@dataclass(frozen=True)
class FrontendParams:
    """Parameters of the whole frontend (one group per component)."""

    tracker: TrackerParams = field(default_factory=TrackerParams)  # feature tracking
    estimator: EstimatorParams = field(default_factory=EstimatorParams)  # sliding window
    keyframes: KeyframeParams = field(default_factory=KeyframeParams)  # keyframe policy, omega
    points: TrackPointsParams = field(default_factory=TrackPointsParams)  # keyframes' sparse
    # points from a second, denser tracker (the estimator's tracks are unchanged)
    init: InitParams = field(default_factory=InitParams)  # static / dynamic initialisation
    imu: ImuNoise = field(default_factory=ImuNoise)  # IMU noise densities and gravity
    ground: GroundParams = field(default_factory=GroundParams)  # road-plane distance (off unless
    # the camera height above the road is given: a vehicle calibration, docs/frontend.md round 5)
    init_mode: str = "auto"  # 'auto' (static when still, else dynamic), 'static' or 'dynamic'
    window_every_frame: bool = True  # every frame enters the estimator's window (not only the
    # published keyframes): shorter window span, more IMU-vision coupling, better accuracy
    window_interval_s: float | None = None  # with window_every_frame: a frame that is no
    # published keyframe stays in the window only when this long after the previous window frame,
    # or when its view moved (the two thresholds below; the newest frame is always on top): a
    # longer window span for the same window_size, which a slow walk's metric scale needs
    # (docs/frontend.md, round 9). 0: every frame stays; None: the platform profile's value
    window_parallax_px: float = 10.0  # ... mean parallax to the previous window frame
    window_tracked_ratio: float = 0.7  # ... fewer of its tracks than this fraction
    time_offset_ns: int = 0  # t_imu = t_cam + time_offset_ns (camera-IMU time offset): the
    # prior of the estimate (time_offset.enabled), the value used as it is otherwise
    time_offset: TimeOffsetParams = field(default_factory=TimeOffsetParams)  # its estimation
    platform: str = "car"  # 'car', 'handheld' or 'drone': bounds on plausible motion and the
    # keyframe rate cap (frontend/platform.py, docs/frontend.md "Platform profiles"); 'auto':
    # platform_default until the IMU shows a walk's step cadence, then 'handheld'
    platform_default: str = "car"
    bounds: PlatformBounds = field(default_factory=PlatformBounds)  # overrides of its bounds
    max_imu_gap_s: float = 0.05  # a larger hole in the IMU stream between frames resets the window
    max_pending_frames: int = 5  # frames waiting for their IMU; older ones are dropped (counted)
    imu_history_s: float = 30.0  # IMU kept in memory

    def __post_init__(self) -> None:
        if self.init_mode not in INIT_MODES:
            raise ConfigError(f"frontend.init_mode: {self.init_mode!r} not in {INIT_MODES}")
        if self.window_interval_s is not None and self.window_interval_s < 0:
            raise ConfigError(f"frontend.window_interval_s: {self.window_interval_s} < 0")
        if self.max_imu_gap_s <= 0 or self.max_pending_frames < 1:
            raise ConfigError("frontend: max_imu_gap_s > 0 and max_pending_frames >= 1")

    def estimator_for(self, profile: PlatformProfile) -> EstimatorParams:
        """The estimator's parameters, with the platform profile's defaults for those left
        unset (None)."""
        est = self.estimator
        if est.keep_visual_prior is None:
            est = replace(est, keep_visual_prior=profile.keep_visual_prior)
        if est.outlier_reproj_rel is None:
            est = replace(est, outlier_reproj_rel=profile.outlier_reproj_rel)
        return est


@dataclass
class KeyframeOutput:
    """A keyframe with the metric sparse points of its tracked features (camera frame)."""

    keyframe_id: int
    stamp_ns: int  # camera time
    image: NDArray[np.uint8]  # [H, W, 3] or [H, W], undistorted
    K: NDArray[np.float64]  # [3, 3] of the undistorted image
    T_world_cam: NDArray[np.float64]  # [4, 4]
    feature_ids: NDArray[np.int64]  # [N]
    feature_uv_px: NDArray[np.float32]  # [N, 2]
    feature_xyz_cam_m: NDArray[np.float32]  # [N, 3]
    feature_cov_cam_m2: NDArray[np.float32]  # [N, 3, 3]
    feature_weight: NDArray[np.float32]  # [N] omega


@dataclass
class FrameOutput:
    """Result of one processed camera frame."""

    stamp_ns: int  # camera time
    frame_index: int
    status: str  # 'initializing', 'tracking', 'reset'
    T_world_cam: NDArray[np.float64] | None  # [4, 4], None while initialising
    velocity_world_m_s: NDArray[np.float64] | None  # [3]
    keyframe: KeyframeOutput | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    stats: dict[str, float] = field(default_factory=dict)
