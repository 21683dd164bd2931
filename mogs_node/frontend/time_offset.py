"""Camera-IMU time offset from rotation rates: the camera's (from tracked features) against the
gyro's, searched over a grid of offsets (pure; no I/O).

Convention as everywhere in the frontend: ``t_imu = t_cam + offset``. For a pair of consecutive
frames ``(t0, t1)`` (camera clock) the features give the camera rotation ``R_c1_c0`` (essential
matrix, RANSAC); in the IMU frame its rotation vector is ``r_k = R_ic log(R_c1_c0^T)``. The gyro
predicts ``g_k(d) = int_{t0 + d}^{t1 + d} omega dt - b (t1 - t0)`` for an offset ``d`` and a
constant bias ``b``. The estimate minimises ``sum_k |r_k - g_k(d)|^2`` over ``d`` (bias solved in
closed form for each ``d``, pairs with gross residuals dropped), refined to a fraction of the grid
step by the parabola through the best three grid points; its standard error follows from that
parabola's curvature and the residual variance, so a motion without rotation changes (a straight
drive) gives a large error and the estimate is not used. This is the correlation of gyro and
visual rotation rates that Kalibr's and OpenVINS' initial time-offset guesses use; it keeps
running over every frame pair as they arrive (the online refinement), see ``docs/frontend.md``
("Time offset").
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError
from mogs_node.frontend.preintegration import ImuSamples
from mogs_node.geometry import check_array, so3_log

__all__ = [
    "OffsetEstimate",
    "gyro_variation",
    "TimeOffsetEstimator",
    "TimeOffsetParams",
    "estimate_time_offset",
    "gyro_integral",
    "rotation_from_tracks",
]


@dataclass(frozen=True)
class TimeOffsetParams:
    """Parameters of the camera-IMU time-offset estimation."""

    enabled: bool = True  # estimate the offset (False: the launch value is used as it is)
    search_ms: float = 150.0  # offsets searched within +-this of the launch value (the prior)
    step_ms: float = 1.0  # grid step of the search (refined below it by a parabola)
    max_sigma_ms: float = 1.0  # an estimate is used once its standard error is below this
    min_pairs: int = 40  # frame pairs needed before a first estimate
    max_pairs: int = 3000  # frame pairs kept (the oldest are dropped beyond)
    min_flow_px: float = 1.0  # a pair whose median feature motion is below this is skipped
    min_features: int = 15  # common features a pair needs
    ransac_px: float = 1.0  # RANSAC threshold of the essential matrix (undistorted px)
    solve_every: int = 10  # frames between two solves
    init_wait_s: float = 15.0  # the dynamic initialisation waits at most this long (camera
    # time since the first frame) for a first estimate, then goes on with the launch value ...
    init_wait_gyro_std_rad_s: float = 0.1  # ... and only while the gyro over the last 2 s varies
    # more than this (rotation changes: the offset matters and will be estimated; a car driving
    # straight initialises at once, the offset being neither observable nor harmful then)
    reinit_ms: float = 5.0  # a usable estimate this far from the value the running window was
    # initialised with re-initialises it once (counted as resets_time_offset)

    def __post_init__(self) -> None:
        if self.search_ms <= 0 or not 0 < self.step_ms <= self.search_ms:
            raise ConfigError("time_offset: search_ms > 0 and 0 < step_ms <= search_ms")
        if self.max_sigma_ms <= 0 or self.min_pairs < 5 or self.solve_every < 1:
            raise ConfigError("time_offset: max_sigma_ms > 0, min_pairs >= 5, solve_every >= 1")


@dataclass(frozen=True)
class OffsetEstimate:
    """An estimate of the offset with its standard error and what it rests on."""

    offset_ns: int
    sigma_ns: float
    pairs: int  # frame pairs used (after dropping gross residuals)
    gyro_bias_rad_s: NDArray[np.float64]  # [3] bias solved with it


def rotation_from_tracks(
    uv0_px: NDArray, uv1_px: NDArray, K: NDArray, ransac_px: float = 1.0
) -> NDArray[np.float64] | None:
    """``R_c1_c0`` [3, 3] between two views from matched undistorted pixels ``uv0_px`` /
    ``uv1_px`` [N, 2] (essential matrix, RANSAC); None when too few inliers support it."""
    uv0 = check_array("uv0_px", uv0_px, shape=(None, 2), finite=True).astype(np.float64)
    uv1 = check_array("uv1_px", uv1_px, shape=(len(uv0), 2), finite=True).astype(np.float64)
    if len(uv0) < 8:
        return None
    E, mask = cv2.findEssentialMat(uv0, uv1, K, cv2.RANSAC, 0.999, ransac_px)
    if E is None or E.shape != (3, 3) or mask is None or int(mask.sum()) < max(8, len(uv0) // 2):
        return None
    # of the two rotations an essential matrix allows, the other one is the first turned by
    # 180 deg about the baseline: between consecutive frames the smaller one is the motion
    # (cheirality counting fails here: far points over a short baseline look behind)
    R1, R2, _ = cv2.decomposeEssentialMat(E)
    a1, a2 = (float(np.linalg.norm(so3_log(np.asarray(R, np.float64)))) for R in (R1, R2))
    R = np.asarray(R1 if a1 <= a2 else R2, np.float64)
    return R if min(a1, a2) < np.pi / 2 else None


def gyro_integral(imu: ImuSamples, t_ns: NDArray) -> NDArray[np.float64]:
    """``int_{t_first}^{t} omega dt`` [..., 3] (rad) at the times ``t_ns`` [...] (trapezoid,
    linear interpolation between samples); NaN outside the samples' span."""
    ts = imu.stamps_ns
    g = imu.gyro_rad_s
    cum = np.zeros((len(ts), 3))
    if len(ts) > 1:
        dt = np.diff(ts) * 1e-9
        cum[1:] = np.cumsum(0.5 * (g[1:] + g[:-1]) * dt[:, None], axis=0)
    q = np.asarray(t_ns, np.int64)
    flat = q.reshape(-1)
    i = np.clip(np.searchsorted(ts, flat, side="right") - 1, 0, max(len(ts) - 2, 0))
    out = np.full((len(flat), 3), np.nan)
    if len(ts) > 1:
        inside = (flat >= ts[0]) & (flat <= ts[-1])
        i = i[inside]
        f = (flat[inside] - ts[i]) * 1e-9
        # integral up to the sample before plus the trapezoid of the linearly interpolated rate
        span = (ts[i + 1] - ts[i]) * 1e-9
        w = g[i] + (g[i + 1] - g[i]) * (f / span)[:, None]
        out[inside] = cum[i] + 0.5 * (g[i] + w) * f[:, None]
    return out.reshape(*q.shape, 3)


def gyro_variation(imu: ImuSamples, t_ns: int, span_s: float = 2.0) -> float:
    """Norm of the per-axis standard deviation of the gyro over ``[t - span, t]`` (rad/s): how
    much the rotation rate changes, what makes the offset observable (0 without samples)."""
    m = (imu.stamps_ns <= t_ns) & (imu.stamps_ns >= t_ns - int(span_s * 1e9))
    if m.sum() < 2:
        return 0.0
    return float(np.linalg.norm(np.std(imu.gyro_rad_s[m], axis=0)))


def estimate_time_offset(
    dt_s: NDArray, rotvec_imu: NDArray, gyro_rotvec: NDArray, offsets_ns: NDArray
) -> OffsetEstimate | None:
    """Least-squares offset over a grid (module docstring).

    ``dt_s`` [P]: each pair's duration; ``rotvec_imu`` [P, 3]: the visual rotation vectors in the
    IMU frame; ``gyro_rotvec`` [P, D, 3]: the gyro integral over each pair shifted by each
    candidate of ``offsets_ns`` [D] (evenly spaced). None when fewer than 5 pairs remain."""
    dt = check_array("dt_s", dt_s, shape=(None,), finite=True)
    r = check_array("rotvec_imu", rotvec_imu, shape=(len(dt), 3), finite=True)
    offs = check_array("offsets_ns", offsets_ns, shape=(None,))
    G = check_array("gyro_rotvec", gyro_rotvec, shape=(len(dt), len(offs), 3), finite=True)
    keep = np.ones(len(dt), bool)
    for _ in range(3):  # drop gross residuals (a bad essential matrix), then re-solve
        if keep.sum() < 5:
            return None
        d, Gk, rk = dt[keep], G[keep], r[keep]
        # bias per candidate: min_b sum |G - b dt - r|^2 -> b = sum dt (G - r) / sum dt^2
        b = np.einsum("p,pdi->di", d, Gk - rk[:, None]) / float(d @ d)
        res = Gk - rk[:, None] - d[:, None, None] * b[None]
        cost = np.einsum("pdi,pdi->d", res, res)
        j = int(np.argmin(cost))
        e = np.linalg.norm(res[:, j], axis=1)
        bad = e > 5.0 * max(float(np.median(e)), 1e-6)
        if not bad.any():
            break
        idx = np.flatnonzero(keep)
        keep[idx[bad]] = False
    n = int(keep.sum())
    step = float(offs[1] - offs[0]) if len(offs) > 1 else 1.0
    j = int(np.clip(j, 1, len(offs) - 2)) if len(offs) >= 3 else j
    if len(offs) < 3:
        return OffsetEstimate(int(offs[j]), np.inf, n, b[j])
    c0, c1, c2 = cost[j - 1], cost[j], cost[j + 1]
    a = 0.5 * (c0 - 2 * c1 + c2) / step**2  # cost ~ c + a (x - x*)^2
    if a <= 0:
        return OffsetEstimate(int(offs[j]), np.inf, n, b[j])
    x = float(np.clip(0.5 * (c0 - c2) / (c0 - 2 * c1 + c2), -1.0, 1.0)) * step
    c_min = c1 - a * x**2
    var_r = max(c_min, 0.0) / max(3 * n - 4, 1)
    sigma = float(np.sqrt(var_r / a))
    bias = b[j] + (b[j + 1] - b[j - 1]) * 0.5 * x / step
    return OffsetEstimate(int(round(offs[j] + x)), sigma, n, bias)


class TimeOffsetEstimator:
    """Streaming use of :func:`estimate_time_offset`: one call of :meth:`add_frame` per frame.

    Each consecutive pair of frames gives a visual rotation; its gyro integrals over the whole
    offset grid are computed once the IMU covers the grid's latest shift, then kept (so the IMU
    need not be). Every ``solve_every`` frames the offset is re-solved over all pairs kept.
    """

    def __init__(self, params: TimeOffsetParams, prior_ns: int, K: NDArray, R_imu_cam: NDArray):
        self.params = params
        self.prior_ns = int(prior_ns)
        self.K = check_array("K", K, shape=(3, 3), finite=True)
        self.R_imu_cam = check_array("R_imu_cam", R_imu_cam, shape=(3, 3), finite=True)
        half = int(round(params.search_ms / params.step_ms))
        self.offsets_ns = self.prior_ns + np.arange(-half, half + 1) * int(params.step_ms * 1e6)
        self._last: tuple[int, NDArray, NDArray] | None = None
        self._waiting: list[tuple[int, int, NDArray]] = []  # (t0, t1, rotvec) without gyro yet
        self._dt: list[float] = []
        self._r: list[NDArray] = []
        self._G: list[NDArray] = []
        self._frames = 0
        self.estimate: OffsetEstimate | None = None  # the latest usable one
        self.last_solve: OffsetEstimate | None = None  # the latest, usable or not
        self.pairs_skipped = 0

    @property
    def pairs(self) -> int:
        return len(self._dt)

    def add_frame(
        self, t_cam_ns: int, ids: NDArray, uv_px: NDArray, imu: ImuSamples
    ) -> OffsetEstimate | None:
        """One frame's tracks (camera time, undistorted px); returns a new usable estimate when
        this frame's solve gave one (else None)."""
        p = self.params
        last, self._last = self._last, (int(t_cam_ns), np.asarray(ids), np.asarray(uv_px))
        if last is not None:
            _, ia, ib = np.intersect1d(last[1], ids, assume_unique=True, return_indices=True)
            uv0, uv1 = last[2][ia], np.asarray(uv_px)[ib]
            flow = float(np.median(np.linalg.norm(uv1 - uv0, axis=1))) if len(ia) else 0.0
            R = None
            if len(ia) >= p.min_features and flow >= p.min_flow_px:
                R = rotation_from_tracks(uv0, uv1, self.K, p.ransac_px)
            if R is None:
                self.pairs_skipped += 1
            else:
                rv = self.R_imu_cam @ so3_log(R.T)
                self._waiting.append((last[0], int(t_cam_ns), rv))
        self._integrate_waiting(imu)
        self._frames += 1
        if self._frames % p.solve_every or len(self._dt) < p.min_pairs:
            return None
        est = estimate_time_offset(
            np.asarray(self._dt), np.stack(self._r), np.stack(self._G), self.offsets_ns
        )
        self.last_solve = est
        if est is None or est.sigma_ns > p.max_sigma_ms * 1e6:
            return None
        self.estimate = est
        return est

    def _integrate_waiting(self, imu: ImuSamples) -> None:
        if not self._waiting or len(imu.stamps_ns) < 2:
            return
        hi, lo = int(self.offsets_ns[-1]), int(self.offsets_ns[0])
        ready = [w for w in self._waiting if w[1] + hi <= imu.stamps_ns[-1]]
        self._waiting = [w for w in self._waiting if w[1] + hi > imu.stamps_ns[-1]]
        for t0, t1, rv in ready:
            if t0 + lo < imu.stamps_ns[0]:
                continue  # the IMU before this pair is gone (not kept that long)
            G = gyro_integral(imu, np.stack([t1 + self.offsets_ns, t0 + self.offsets_ns]))
            self._dt.append((t1 - t0) * 1e-9)
            self._r.append(rv)
            self._G.append(G[0] - G[1])
        over = len(self._dt) - self.params.max_pairs
        if over > 0:
            del self._dt[:over], self._r[:over], self._G[:over]
