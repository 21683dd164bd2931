"""Sliding-window visual-inertial estimator on GTSAM (VINS-Mono style backend, paper's frontend).

State per window frame k: IMU pose ``X(k)`` (``T_world_imu``), world velocity ``V(k)`` and IMU biases
``B(k)``. Factors: ``CombinedImuFactor`` between consecutive frames, ``GenericProjectionFactor`` with
the camera-IMU extrinsics and a Huber loss for every observation of a triangulated landmark ``L(i)``,
zero-motion factors when the platform stands still, and the marginalisation prior.

The window holds the last ``window_size`` keyframes plus the newest frame; a newest frame that is not
a keyframe is dropped when the next frame arrives (its IMU span is re-preintegrated from the last
keyframe). When the window is full, the oldest keyframe (pose, velocity, biases) is marginalised by
Schur complement on the linearised factors touching it (GTSAM partial elimination); the result
stays in the graph as ``LinearContainerFactor``s. Its visual observations are dropped (default) or,
with ``marginalize_landmarks``, every landmark it observes is marginalised with it: the landmark
keeps its track id and its later observations start a new landmark, so no measurement is used
twice; or, with ``keep_visual_prior``, its observations of mature landmarks enter the
marginalisation with those landmarks kept as variables of the prior (exact, OKVIS-style; a landmark
leaving the window is then Schur-complemented out of the prior). Each update is a windowed
Levenberg-Marquardt solve; each frame's projection factors are built once and reused.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError
from mogs_node.frontend.estimator_types import (
    B,
    EstimatorDivergedError,
    EstimatorParams,
    EstimatorState,
    L,
    LandmarkView,
    V,
    WindowFrame,
    X,
    depth_in_range,
    lookup,
    outlier_gate_px,
    sorted_map,
)
from mogs_node.frontend.keyframes import landmark_covariance, triangulate_midpoint
from mogs_node.frontend.preintegration import ImuNoise, ImuSamples, make_params, preintegrate
from mogs_node.frontend.schur import regularize_points, schur_complement
from mogs_node.geometry import PinholeCamera, check_array, se3_inverse

__all__ = [
    "EstimatorDivergedError",
    "EstimatorParams",
    "EstimatorState",
    "LandmarkView",
    "VioEstimator",
]

log = logging.getLogger(__name__)


class VioEstimator:
    """Windowed VI estimator. Call :meth:`initialize` once, then :meth:`add_frame` per frame."""

    def __init__(
        self, params: EstimatorParams, camera: PinholeCamera, T_imu_cam: NDArray, noise: ImuNoise
    ) -> None:
        self.params = params
        self.camera = camera
        T_ic = check_array("T_imu_cam", T_imu_cam, shape=(4, 4), finite=True)
        self.T_imu_cam = T_ic.astype(float)
        self.noise = noise
        self._pim_params = make_params(noise)
        self._cal = gtsam.Cal3_S2(camera.fx_px, camera.fy_px, 0.0, camera.cx_px, camera.cy_px)
        self._body_P_cam = gtsam.Pose3(self.T_imu_cam)
        self._proj_noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(params.huber_k),
            gtsam.noiseModel.Isotropic.Sigma(2, params.pixel_sigma_px),
        )
        self._prior_proj_noise = gtsam.noiseModel.Robust.Create(  # keep_visual_prior's weight
            gtsam.noiseModel.mEstimator.Huber.Create(params.huber_k),
            gtsam.noiseModel.Isotropic.Sigma(2, params.pixel_sigma_px * params.visual_prior_sigma),
        )
        zs = np.r_[[params.zero_motion_sigma_rad] * 3, [params.zero_motion_sigma_m] * 3]
        self._zero_noise = gtsam.noiseModel.Diagonal.Sigmas(zs)
        self._zero_vel_noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.01)
        self.reset()

    # ------------------------------------------------------------------------------------ state

    def reset(self) -> None:
        self.frames: list[WindowFrame] = []
        self.values = gtsam.Values()
        self._priors: list[gtsam.NonlinearFactor] = []
        self._imu: dict[int, gtsam.CombinedImuFactor] = {}  # keyed by the later frame's seq
        self._zero: dict[int, list[gtsam.NonlinearFactor]] = {}
        self._lid_of_track: dict[int, int] = {}
        self._min_seq_of_track: dict[int, int] = {}
        self._next_lid = 0
        self._touch()
        self._factor_cache: dict[int, tuple] = {}
        self._seq = 0
        self.initialized = False
        self.last_error = 0.0  # graph error after the last solve
        self.last_n_factors = 0
        self.last_imu_error = 0.0  # error of the IMU factors alone after the last solve

    @property
    def newest_seq(self) -> int:
        return self.frames[-1].seq

    def initialize(
        self,
        t_ns: int,
        T_world_imu: NDArray,
        velocity_world_m_s: NDArray,
        gyro_bias_rad_s: NDArray,
        accel_bias_m_s2: NDArray,
        ids: NDArray,
        uv_px: NDArray,
        track_len: NDArray | None = None,
        vel_sigma_m_s: float | None = None,
        tilt_sigma_rad: float | None = None,
    ) -> None:
        """Start the window at one frame with a prior from an initialiser (static or dynamic);
        ``vel_sigma_m_s`` / ``tilt_sigma_rad`` override the velocity / roll-pitch prior sigmas."""
        self.reset()
        p = self.params
        T = check_array("T_world_imu", T_world_imu, shape=(4, 4), finite=True)
        v = check_array("velocity_world_m_s", velocity_world_m_s, shape=(3,), finite=True)
        bias = gtsam.imuBias.ConstantBias(
            np.asarray(accel_bias_m_s2, float), np.asarray(gyro_bias_rad_s, float)
        )
        f = self._new_frame(t_ns, ids, uv_px, track_len, True, False)
        k = f.seq
        self.values.insert(X(k), gtsam.Pose3(T))
        self.values.insert(V(k), np.asarray(v, float))
        self.values.insert(B(k), bias)
        sig = np.r_[[tilt_sigma_rad or p.init_rot_sigma_rad] * 2, 1e-3, [p.init_pos_sigma_m] * 3]
        self._priors = [
            gtsam.PriorFactorPose3(X(k), gtsam.Pose3(T), gtsam.noiseModel.Diagonal.Sigmas(sig)),
            gtsam.PriorFactorVector(
                V(k),
                np.asarray(v, float),
                gtsam.noiseModel.Isotropic.Sigma(3, vel_sigma_m_s or p.init_vel_sigma_m_s),
            ),
            gtsam.PriorFactorConstantBias(
                B(k),
                bias,
                gtsam.noiseModel.Diagonal.Sigmas(
                    np.r_[[p.init_accel_bias_sigma_m_s2] * 3, [p.init_gyro_bias_sigma_rad_s] * 3]
                ),
            ),
        ]
        self.initialized = True

    def _new_frame(
        self,
        t_ns: int,
        ids: NDArray,
        uv_px: NDArray,
        track_len: NDArray | None,
        is_keyframe: bool,
        stationary: bool,
    ) -> WindowFrame:
        ids = check_array("ids", ids, shape=(None,), dtype=np.integer).astype(np.int64)
        uv = check_array("uv_px", uv_px, shape=(len(ids), 2), finite=True).astype(np.float64)
        tl = (
            np.ones(len(ids), np.int32)
            if track_len is None
            else check_array("track_len", track_len, shape=(len(ids),)).astype(np.int32)
        )
        f = WindowFrame(self._seq, int(t_ns), ids, uv, tl, is_keyframe, stationary)
        self._seq += 1
        self.frames.append(f)
        return f

    def _bias(self, k: int) -> gtsam.imuBias.ConstantBias:
        return self.values.atConstantBias(B(k))

    def gyro_bias(self) -> NDArray[np.float64]:
        """Gyroscope bias [3] of the newest frame (zero before initialisation)."""
        if not self.frames:
            return np.zeros(3)
        return np.asarray(self._bias(self.newest_seq).gyroscope(), float)

    def state(self) -> EstimatorState:
        """Estimate at the newest frame."""
        return self._state(0)

    def pose(self, k: int) -> NDArray[np.float64]:
        return self.values.atPose3(X(k)).matrix()

    # ------------------------------------------------------------------------------------ update

    def add_frame(
        self,
        t_ns: int,
        ids: NDArray,
        uv_px: NDArray,
        imu: ImuSamples,
        *,
        is_keyframe: bool,
        stationary: bool = False,
        track_len: NDArray | None = None,
    ) -> EstimatorState:
        """Add the newest frame (undistorted pixels ``uv_px`` [N, 2] of tracks ``ids`` [N]), with the
        IMU samples covering the span since the previous frame, and solve the window."""
        if not self.initialized:
            raise EstimatorDivergedError("add_frame before initialize")
        if t_ns <= self.frames[-1].t_ns:
            raise ConfigError(f"t_ns: {t_ns} not after the previous frame {self.frames[-1].t_ns}")
        if len(self.frames) > 1 and not self.frames[-1].is_keyframe:
            self._drop_newest()
        while sum(f.is_keyframe for f in self.frames) > self.params.window_size:
            self._marginalize_oldest()
        prev = self.frames[-1]
        pim = preintegrate(imu, prev.t_ns, t_ns, self._pim_params, self._bias(prev.seq))
        f = self._new_frame(t_ns, ids, uv_px, track_len, is_keyframe, stationary)
        k, j = f.seq, prev.seq
        nav = pim.predict(
            gtsam.NavState(self.values.atPose3(X(j)), self.values.atVector(V(j))), self._bias(j)
        )
        self.values.insert(X(k), nav.pose())
        self.values.insert(V(k), nav.velocity())
        self.values.insert(B(k), self._bias(j))
        self._imu[k] = gtsam.CombinedImuFactor(X(j), V(j), X(k), V(k), B(j), B(k), pim)
        if stationary:
            self._zero[k] = [
                gtsam.BetweenFactorPose3(X(j), X(k), gtsam.Pose3(), self._zero_noise),
                gtsam.PriorFactorVector(V(k), np.zeros(3), self._zero_vel_noise),
            ]
        self._triangulate_new(f)
        self._solve()
        n_removed = self._reject_outliers()
        return self._state(n_removed)

    def add_ground_distance(
        self, seq_prev: int, seq_cur: int, distance_cam_m: float, sigma_m: float
    ) -> bool:
        """A measured distance between the camera centres of two consecutive window frames (the
        road-plane measurement, :mod:`~mogs_node.frontend.ground`); it enters from the next solve
        and is marginalised with the older frame. False when a frame is not in the window."""
        if not (np.isfinite(distance_cam_m) and distance_cam_m > 0 and sigma_m > 0):
            raise ConfigError(f"ground distance: {distance_cam_m} m, sigma {sigma_m} m")
        seqs = [f.seq for f in self.frames]
        if (
            seq_cur not in seqs
            or seq_prev not in seqs
            or seqs.index(seq_cur) != seqs.index(seq_prev) + 1
        ):
            return False
        Tp, Tc = self.pose(seq_prev), self.pose(seq_cur)
        d_imu = float(np.linalg.norm(Tc[:3, 3] - Tp[:3, 3]))
        t_ic = self.T_imu_cam[:3, 3]
        d_cam = float(np.linalg.norm(Tc[:3, :3] @ t_ic + Tc[:3, 3] - Tp[:3, :3] @ t_ic - Tp[:3, 3]))
        # the lever arm changes the IMU's distance by < 0.2 % per frame on a car: the measured
        # camera distance is carried over to the IMU centres by the current ratio
        r_imu = distance_cam_m * (d_imu / d_cam if d_cam > 1e-6 else 1.0)
        noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(self.params.huber_k),
            gtsam.noiseModel.Isotropic.Sigma(1, sigma_m),
        )
        self._zero.setdefault(seq_cur, []).append(
            gtsam.RangeFactorPose3(X(seq_prev), X(seq_cur), r_imu, noise)
        )
        return True

    def _drop_newest(self) -> None:
        f = self.frames.pop()
        self._factor_cache.pop(f.seq, None)
        for key in (X(f.seq), V(f.seq), B(f.seq)):
            self.values.erase(key)
        self._imu.pop(f.seq, None)
        self._zero.pop(f.seq, None)

    def _obs(
        self, f: WindowFrame
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
        """Valid landmark observations of frame ``f``: (track ids, landmark ids, uv). Cached until
        the landmark bookkeeping changes (:meth:`_touch`)."""
        hit = self._obs_cache.get(f.seq)
        if hit is not None:
            return hit
        if not self._lid_of_track:
            out = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))
        else:
            (kl, vl), (km, vm) = self._lookup_tables()
            lid = lookup(kl, vl, f.ids, -1)
            mins = lookup(km, vm, f.ids, 0)
            ok = (lid >= 0) & (f.seq >= mins)
            out = (f.ids[ok], lid[ok], f.uv_px[ok])
        self._obs_cache[f.seq] = out
        return out

    def _lookup_tables(self) -> tuple:
        if self._lut is None:
            self._lut = (sorted_map(self._lid_of_track), sorted_map(self._min_seq_of_track))
        return self._lut

    def _touch(self) -> None:
        self._obs_cache: dict[int, tuple] = {}
        self._lut: tuple | None = None  # sorted (track -> landmark, track -> min seq) arrays

    def _cam_poses(self) -> NDArray[np.float64]:
        return np.stack([self.pose(f.seq) @ self.T_imu_cam for f in self.frames])

    def _triangulate_new(self, newest: WindowFrame) -> None:
        """Triangulate tracks of the newest frame that have no landmark yet (two-ray midpoint
        between their earliest valid observation in the window and the newest one)."""
        p = self.params
        (kl, vl), (km, vm) = self._lookup_tables()
        cand = newest.ids[lookup(kl, vl, newest.ids, -1) < 0]
        if len(cand) == 0 or len(self.frames) < 2:
            return
        Tc = self._cam_poses()
        first_uv = np.full((len(cand), 2), np.nan)
        first_f = np.full(len(cand), -1, np.int64)
        for fi, f in enumerate(self.frames[:-1]):
            _, ia, ib = np.intersect1d(cand, f.ids, assume_unique=True, return_indices=True)
            mins = lookup(km, vm, cand[ia], 0)
            new = (first_f[ia] < 0) & (f.seq >= mins)
            first_uv[ia[new]] = f.uv_px[ib[new]]
            first_f[ia[new]] = fi
        has = first_f >= 0
        if not np.any(has):
            return
        cand, first_uv, first_f = cand[has], first_uv[has], first_f[has]
        _, ia, ib = np.intersect1d(cand, newest.ids, assume_unique=True, return_indices=True)
        cand, first_uv, first_f = cand[ia], first_uv[ia], first_f[ia]
        last_uv = newest.uv_px[ib]
        Ta, Tb = Tc[first_f], Tc[-1]
        ra = self.camera.rays(first_uv)
        rb = self.camera.rays(last_uv)
        da = np.einsum("nij,nj->ni", Ta[:, :3, :3], ra)
        db = rb @ Tb[:3, :3].T
        pts, ang = triangulate_midpoint(Ta[:, :3, 3], da, np.broadcast_to(Tb[:3, 3], da.shape), db)
        ok = np.all(np.isfinite(pts), axis=1) & (np.degrees(ang) >= p.min_parallax_deg)
        for T in (Tb[None], Ta):
            ok &= depth_in_range(T, pts, p.min_depth_m, p.max_depth_m)
        if np.any(ok):  # else the bookkeeping is unchanged: the cached observations stay valid
            self._touch()
        for t, x in zip(cand[ok].tolist(), pts[ok], strict=True):
            lid = self._next_lid
            self._next_lid += 1
            self._lid_of_track[t] = lid
            self.values.insert(L(lid), gtsam.Point3(*x))

    def _graph(self) -> gtsam.NonlinearFactorGraph:
        g = gtsam.NonlinearFactorGraph()
        for fac in self._priors:
            g.add(fac)
        for fac in self._imu.values():
            g.add(fac)
        for facs in self._zero.values():
            for fac in facs:
                g.add(fac)
        for f in self.frames:
            g.push_back(self._frame_factors(f))
        return g

    def _frame_factors(self, f: WindowFrame) -> gtsam.NonlinearFactorGraph:
        """Projection factors of frame ``f``, built once and reused while its valid landmark
        observations stay the same (factor construction dominated the per-frame Python time)."""
        _, lids, uv = self._obs(f)
        hit = self._factor_cache.get(f.seq)
        if hit is not None and len(hit[0]) == len(lids) and np.array_equal(hit[0], lids):
            return hit[1]
        if hit is not None and np.all(np.isin(hit[0], lids)):  # only new landmarks: append
            g, new = hit[1], ~np.isin(lids, hit[0])
        else:
            g, new = gtsam.NonlinearFactorGraph(), np.ones(len(lids), bool)
        x = X(f.seq)
        for lid, m in zip(lids[new].tolist(), uv[new], strict=True):
            g.add(
                gtsam.GenericProjectionFactorCal3_S2(
                    m, self._proj_noise, x, L(lid), self._cal, self._body_P_cam
                )
            )
        self._factor_cache[f.seq] = (lids, g)
        return g

    def _solve(self) -> None:
        lm = gtsam.LevenbergMarquardtParams()
        lm.setMaxIterations(self.params.lm_iterations)
        lm.setRelativeErrorTol(1e-4)
        lm.setlambdaInitial(self.params.lm_lambda_initial)
        try:
            graph = self._graph()
            opt = gtsam.LevenbergMarquardtOptimizer(graph, self.values, lm)
            self.values = opt.optimize()
            self.last_error = float(opt.error())
            self.last_n_factors = int(graph.size())
            self.last_imu_error = float(sum(f.error(self.values) for f in self._imu.values()))
        except RuntimeError as err:
            raise EstimatorDivergedError(f"window solve failed: {err}", "solve_failed") from err
        p = self.params
        k = self.newest_seq
        b = self._bias(k)
        speed = float(np.linalg.norm(self.values.atVector(V(k))))
        reason = None
        if not np.all(np.isfinite(self.pose(k))) or not np.isfinite(speed):
            reason = "not_finite"
        elif speed > p.max_speed_m_s:
            reason = "speed"
        elif np.linalg.norm(b.gyroscope()) > p.max_gyro_bias_rad_s:
            reason = "gyro_bias"
        elif np.linalg.norm(b.accelerometer()) > p.max_accel_bias_m_s2:
            reason = "accel_bias"
        if reason is not None:
            raise EstimatorDivergedError(
                f"state out of bounds ({reason}): speed {speed:.1f} m/s, bias "
                f"gyro {b.gyroscope()}, accel {b.accelerometer()}",
                reason,
            )

    def _reproj(self) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """All valid observations: (frame index, landmark id, track id, error px)."""
        obs = [self._obs(f) for f in self.frames]
        n = [len(o[1]) for o in obs]
        if sum(n) == 0:
            z = np.zeros(0, np.int64)
            return z, z, z, np.zeros(0)
        fi = np.repeat(np.arange(len(obs)), n)
        lid = np.concatenate([o[1] for o in obs])
        tid = np.concatenate([o[0] for o in obs])
        uv = np.concatenate([o[2] for o in obs])
        uniq, inv = np.unique(lid, return_inverse=True)
        P = np.array([self.values.atPoint3(L(i)) for i in uniq.tolist()])[inv]
        T_cw = np.stack([se3_inverse(T) for T in self._cam_poses()])[fi]
        Pc = np.einsum("nij,nj->ni", T_cw[:, :3, :3], P) + T_cw[:, :3, 3]
        pix, front = self.camera.project(Pc)
        err = np.where(front, np.linalg.norm(pix - uv, axis=1), np.inf)
        return fi, lid, tid, err

    def _reject_outliers(self) -> int:
        _, lids, tids, err = self._reproj()
        bad = np.unique(tids[err > outlier_gate_px(err, self.params)])
        if len(bad):
            self._touch()
        gone = []
        for t in bad.tolist():
            gone.append(self._lid_of_track.pop(t))
            self._min_seq_of_track[t] = self._seq  # never reuse this track's past observations
        self._forget_landmarks(gone)
        return len(bad)

    def _forget_landmarks(self, lids: list[int]) -> None:
        """Remove landmarks from the window. Those the marginalisation prior involves are
        Schur-complemented out of it (their information on the poses stays), the rest erased."""
        if not lids:
            return
        keys = {L(i) for i in lids}
        touched = [f for f in self._priors if set(f.keys()) & keys]
        if touched:
            lin = gtsam.GaussianFactorGraph()
            for fac in touched:
                lin.push_back(fac.linearize(self.values))
            elim = sorted(keys & set().union(*(set(f.keys()) for f in touched)))
            regularize_points(lin, elim)
            keep = [f for f in self._priors if not set(f.keys()) & keys]
            try:
                self._priors = keep + schur_complement(lin, elim, self.values)
            except RuntimeError as err:
                log.warning("landmark marginalisation failed (%s); dropping its prior", err)
                self._priors = keep
        for key in keys:
            self.values.erase(key)

    def _marginalize_oldest(self) -> None:
        """Schur-complement the oldest keyframe and its landmarks into a linear prior."""
        f0 = self.frames[0]
        _, lids0, _ = self._obs(f0)
        lid_set = set(lids0.tolist()) if self.params.marginalize_landmarks else set()
        elim = {X(f0.seq), V(f0.seq), B(f0.seq)} | {L(i) for i in lid_set}
        g = gtsam.NonlinearFactorGraph()
        keep_priors = []
        for fac in self._priors:
            if set(fac.keys()) & elim:
                g.add(fac)
            else:
                keep_priors.append(fac)
        f1 = self.frames[1]
        g.add(self._imu.pop(f1.seq))
        for fac in self._zero.pop(f1.seq, []):
            g.add(fac)
        keep_visual = self.params.keep_visual_prior and not lid_set
        if keep_visual:
            n_obs = np.bincount(
                np.concatenate([self._obs(f)[1] for f in self.frames]), minlength=self._next_lid + 1
            )
            mature = set(lids0[n_obs[lids0] >= self.params.visual_prior_min_obs].tolist())
        for f in self.frames:
            if keep_visual and f is not f0:
                break
            _, lids, uv = self._obs(f)
            for lid, m in zip(lids.tolist(), uv, strict=True):
                if lid in lid_set or (keep_visual and lid in mature):
                    g.add(
                        gtsam.GenericProjectionFactorCal3_S2(
                            m, self._prior_proj_noise, X(f.seq), L(lid), self._cal, self._body_P_cam
                        )
                    )
        lin = g.linearize(self.values)
        regularize_points(lin, [L(lid) for lid in lid_set])
        try:
            new_priors = schur_complement(lin, sorted(elim), self.values)
        except RuntimeError as err:
            log.warning(
                "marginalisation failed (%s); dropping the oldest keyframe's information", err
            )
            new_priors = [
                gtsam.PriorFactorPose3(
                    X(f1.seq),
                    self.values.atPose3(X(f1.seq)),
                    gtsam.noiseModel.Isotropic.Sigma(6, 0.01),
                )
            ]
        self._priors = keep_priors + new_priors
        self.frames.pop(0)
        self._factor_cache.pop(f0.seq, None)
        self._touch()
        for key in elim:
            self.values.erase(key)
        # Landmarks left without observations in the window are forgotten.
        seen = set()
        for f in self.frames:
            seen.update(self._obs(f)[1].tolist())
        gone = []
        for t, lid in list(self._lid_of_track.items()):
            if lid in lid_set or lid not in seen:
                del self._lid_of_track[t]
                self._min_seq_of_track[t] = self._seq
                if lid not in lid_set:
                    gone.append(lid)
        self._forget_landmarks(gone)
        # A track in no window frame never comes back (the tracker only continues the newest
        # frame's tracks or starts new ids): its entry would only grow the lookup.
        k, v = sorted_map(self._min_seq_of_track)
        keep = np.isin(k, np.concatenate([f.ids for f in self.frames]))
        self._min_seq_of_track = dict(zip(k[keep].tolist(), v[keep].tolist(), strict=True))
        self._touch()  # tracks whose landmark was never triangulated keep their observations

    # ------------------------------------------------------------------------------------ output

    def _state(self, n_removed: int) -> EstimatorState:
        k = self.newest_seq
        b = self._bias(k)
        return EstimatorState(
            t_ns=self.frames[-1].t_ns,
            T_world_imu=self.pose(k),
            velocity_world_m_s=np.asarray(self.values.atVector(V(k)), float),
            gyro_bias_rad_s=np.asarray(b.gyroscope(), float),
            accel_bias_m_s2=np.asarray(b.accelerometer(), float),
            n_landmarks=len(self._lid_of_track),
            stats={
                "outliers_removed": float(n_removed),
                "window_frames": float(len(self.frames)),
                "priors": float(len(self._priors)),
            },
        )

    def window_states(self) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """Stamps [F] (IMU time), ``T_world_imu`` [F, 4, 4] and velocities [F, 3] of the window."""
        stamps = np.array([f.t_ns for f in self.frames], np.int64)
        T = np.stack([self.pose(f.seq) for f in self.frames])
        v = np.stack([np.asarray(self.values.atVector(V(f.seq)), float) for f in self.frames])
        return stamps, T, v

    def newest_landmarks(self) -> LandmarkView:
        """Triangulated landmarks seen in the newest frame, in its camera frame."""
        f = self.frames[-1]
        tids, lids, uv = self._obs(f)
        fi, all_lids, _, err = self._reproj()
        mx = np.zeros(self._next_lid + 1)
        np.maximum.at(mx, all_lids, np.where(np.isfinite(err), err, 1e3))
        worst = mx[lids]
        P = np.array([self.values.atPoint3(L(i)) for i in lids.tolist()]).reshape(-1, 3)
        Tc = self._cam_poses()
        obs = np.zeros((len(lids), len(self.frames)), bool)
        lid_index = {lid: n for n, lid in enumerate(lids.tolist())}
        for a, b in zip(fi.tolist(), all_lids.tolist(), strict=True):
            n = lid_index.get(b)
            if n is not None:
                obs[n, a] = True
        cov_w = landmark_covariance(P, Tc, obs, self.camera, self.params.pixel_sigma_px)
        T_cam_world = se3_inverse(Tc[-1])
        Rcw = T_cam_world[:3, :3]
        xyz = P @ Rcw.T + T_cam_world[:3, 3]
        cov_c = Rcw[None] @ cov_w @ Rcw.T[None]
        tl_of = dict(zip(f.ids.tolist(), f.track_len.tolist(), strict=True))
        tl = np.array([tl_of[t] for t in tids.tolist()], np.int32)
        return LandmarkView(
            track_ids=tids.astype(np.int64),
            uv_px=uv.astype(np.float32),
            xyz_cam_m=xyz.astype(np.float32),
            cov_cam_m2=cov_c.astype(np.float32),
            reproj_err_px=worst.astype(np.float32),
            track_len=np.asarray(tl, np.int32),
        )
