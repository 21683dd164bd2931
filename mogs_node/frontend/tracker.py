"""Sparse feature tracking, VINS-Mono style (paper's frontend, DESIGN section 2).

Shi-Tomasi corners kept at a minimum distance, pyramidal Lucas-Kanade (OpenCV) with initial guesses
predicted from the IMU rotation, a forward-backward consistency check and fundamental-matrix RANSAC
on undistorted points; optional CLAHE contrast equalisation. Pure: images in, tracks out.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError, ShapeError
from mogs_node.frontend.camera import CameraModel
from mogs_node.geometry import check_array

__all__ = ["FeatureTracker", "TrackerParams", "TrackResult"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrackerParams:
    """Parameters of :class:`FeatureTracker`."""

    max_features: int = 150  # corners kept per frame
    min_distance_px: int = 20  # minimum distance between corners (also between new and old)
    quality_level: float = 0.01  # Shi-Tomasi quality relative to the best corner
    win_size_px: int = 21  # KLT window side
    pyr_levels: int = 3  # KLT pyramid levels above the base image
    fb_max_err_px: float = 0.5  # forward-backward round trip error bound
    fb_check: bool = True  # track back and check the round trip (False: half the KLT cost)
    klt_max_iter: int = 30  # KLT iterations per pyramid level (also stops at 0.01 px steps)
    top_up_below: float = 1.0  # new corners only when fewer than this share of max_features
    top_up_every: int = 1  # look for new corners every this many frames
    square_spacing: bool = False  # keep new corners out of squares (not discs) around tracks:
    # one dilation instead of a disc per track (for many tracks)
    ransac_thresh_px: float = 1.0  # fundamental-matrix RANSAC threshold (undistorted px)
    ransac_min_flow_px: float = 0.5  # skip F-RANSAC when the median flow is below this (standstill)
    clahe: bool = False  # equalise contrast with CLAHE before tracking
    clahe_clip: float = 3.0  # CLAHE clip limit
    border_px: int = 2  # tracks closer than this to the border are dropped
    bucket_cols: int = 0  # bucketing grid for new corners (0: none): a cell takes new corners
    bucket_rows: int = 0  # only while it holds fewer than bucket_cap tracks, so that corners
    bucket_cap: int = 0  # spread over the image instead of piling up on the strongest texture

    def __post_init__(self) -> None:
        if self.max_features < 8:
            raise ConfigError("tracker.max_features: must be >= 8")
        if self.min_distance_px < 1 or self.win_size_px < 5 or self.pyr_levels < 0:
            raise ConfigError("tracker: min_distance_px >= 1, win_size_px >= 5, pyr_levels >= 0")
        if self.klt_max_iter < 1 or not 0 < self.top_up_below <= 1 or self.top_up_every < 1:
            raise ConfigError(
                "tracker: klt_max_iter >= 1, 0 < top_up_below <= 1, top_up_every >= 1"
            )
        if min(self.bucket_cols, self.bucket_rows, self.bucket_cap) < 0:
            raise ConfigError("tracker: bucket_cols, bucket_rows, bucket_cap >= 0")


@dataclass
class TrackResult:
    """Features of one frame after tracking. All arrays have the same length ``N``."""

    ids: NDArray[np.int64]  # [N] track ids (stable across frames)
    uv_raw_px: NDArray[np.float32]  # [N, 2] pixel in the raw image
    uv_px: NDArray[np.float64]  # [N, 2] undistorted pinhole pixel
    track_len: NDArray[np.int32]  # [N] frames this track has been seen in (>= 1)
    n_prev: int = 0  # features in the previous frame
    n_tracked: int = 0  # of those, tracked into this frame and kept
    stats: dict[str, float] = field(default_factory=dict)

    @property
    def kept_ratio(self) -> float:
        return self.n_tracked / self.n_prev if self.n_prev else 1.0


class FeatureTracker:
    """Stateful tracker: call :meth:`track` once per frame in time order."""

    def __init__(self, params: TrackerParams, camera: CameraModel) -> None:
        self.params = params
        self.camera = camera
        self._clahe = cv2.createCLAHE(clipLimit=params.clahe_clip, tileGridSize=(8, 8))
        self._prev_img: NDArray[np.uint8] | None = None
        self._prev_pyr: tuple | None = None
        self._ids = np.zeros(0, np.int64)
        self._uv = np.zeros((0, 2), np.float32)
        self._len = np.zeros(0, np.int32)
        self._next_id = 0
        self._frames = 0
        w = params.win_size_px
        self._lk = dict(
            winSize=(w, w),
            maxLevel=params.pyr_levels,
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, params.klt_max_iter, 0.01),
        )

    def reset(self) -> None:
        """Forget every track (the next frame starts fresh ids)."""
        self._prev_img = None
        self._ids = np.zeros(0, np.int64)
        self._uv = np.zeros((0, 2), np.float32)
        self._len = np.zeros(0, np.int32)

    def _prepare(self, image: NDArray) -> NDArray[np.uint8]:
        img = check_array("image", image, dtype=np.uint8)
        if img.ndim == 3 and img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        elif img.ndim != 2:
            raise ShapeError(f"image: expected [H,W] or [H,W,3] uint8, got {list(img.shape)}")
        if img.shape != (self.camera.pinhole.height, self.camera.pinhole.width):
            raise ShapeError(
                f"image: size {img.shape[::-1]} != camera "
                f"{(self.camera.pinhole.width, self.camera.pinhole.height)}"
            )
        return self._clahe.apply(img) if self.params.clahe else np.ascontiguousarray(img)

    def predict_px(self, uv_raw_px: NDArray, R_cur_prev_cam: NDArray | None) -> NDArray[np.float32]:
        """Initial KLT guesses: pixels moved by the infinite homography ``K R K^-1`` of the
        IMU-predicted camera rotation ``R_cur_prev_cam`` [3, 3] (None: no motion)."""
        if R_cur_prev_cam is None or len(uv_raw_px) == 0:
            return uv_raw_px.astype(np.float32).copy()
        R = check_array("R_cur_prev_cam", R_cur_prev_cam, shape=(3, 3), finite=True)
        und = self.camera.undistort_px(uv_raw_px)
        rays = self.camera.pinhole.rays(und) @ R.T
        ok = rays[:, 2] > 1e-3
        z = np.where(ok, rays[:, 2], 1.0)
        K = self.camera.K
        pred = np.stack(
            [K[0, 0] * rays[:, 0] / z + K[0, 2], K[1, 1] * rays[:, 1] / z + K[1, 2]], -1
        )
        pred = np.where(ok[:, None], pred, und)
        return self.camera.distort_px(pred).astype(np.float32)

    def track(
        self,
        image: NDArray,
        R_cur_prev_cam: NDArray | None = None,
        cell_caps: NDArray | None = None,
    ) -> TrackResult:
        """Track the previous frame's features into ``image`` ([H, W] or [H, W, 3] uint8) and top up
        with new Shi-Tomasi corners. ``R_cur_prev_cam`` [3, 3]: predicted rotation (IMU) or None.
        ``cell_caps`` [bucket_rows, bucket_cols]: per-cell caps for this frame instead of
        ``bucket_cap`` (bucketing only); a cell above its cap keeps its longest tracks."""
        p = self.params
        if cell_caps is not None:
            cell_caps = check_array(
                "cell_caps", cell_caps, shape=(p.bucket_rows, p.bucket_cols), dtype=np.number
            ).astype(np.int64)
        img = self._prepare(image)
        H, W = img.shape
        n_prev = len(self._ids)
        stats: dict[str, float] = {}
        if self._prev_img is not None and n_prev > 0:
            p0 = self._uv.reshape(-1, 1, 2)
            guess = self.predict_px(self._uv, R_cur_prev_cam).reshape(-1, 1, 2)
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(
                self._prev_img,
                img,
                p0,
                guess.copy(),
                flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                **self._lk,
            )
            p1 = p1.reshape(-1, 2)
            if p.fb_check:
                p0b, st2, _ = cv2.calcOpticalFlowPyrLK(
                    img,
                    self._prev_img,
                    p1,
                    p0.copy(),
                    flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                    **self._lk,
                )
                fb = np.linalg.norm(p0b.reshape(-1, 2) - self._uv, axis=1)
            else:
                st2, fb = st1, np.zeros(len(p1))
            b = p.border_px
            inside = (p1[:, 0] >= b) & (p1[:, 0] < W - b) & (p1[:, 1] >= b) & (p1[:, 1] < H - b)
            keep = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < p.fb_max_err_px) & inside
            keep &= np.all(np.isfinite(p1), axis=1)
            stats["fb_rejected"] = float(np.count_nonzero(~keep))
            if np.count_nonzero(keep) >= 8:
                u0 = self.camera.undistort_px(self._uv[keep])
                u1 = self.camera.undistort_px(p1[keep])
                flow = np.median(np.linalg.norm(u1 - u0, axis=1))
                stats["median_flow_px"] = float(flow)
                if flow >= p.ransac_min_flow_px:
                    _, inl = cv2.findFundamentalMat(u0, u1, cv2.FM_RANSAC, p.ransac_thresh_px, 0.99)
                    if inl is not None:
                        idx = np.flatnonzero(keep)
                        keep[idx[inl.ravel() == 0]] = False
                        stats["ransac_rejected"] = float(np.count_nonzero(inl.ravel() == 0))
            ids, uv, tl = self._ids[keep], p1[keep].astype(np.float32), self._len[keep] + 1
        else:
            ids, uv, tl = np.zeros(0, np.int64), np.zeros((0, 2), np.float32), np.zeros(0, np.int32)
        if cell_caps is not None and len(ids):
            ids, uv, tl = self._prune(ids, uv, tl, cell_caps.ravel(), (H, W))
        n_tracked = len(ids)
        ids, uv, tl = self._top_up(img, ids, uv, tl, cell_caps)
        self._prev_img, self._ids, self._uv, self._len = img, ids, uv, tl
        return TrackResult(
            ids=ids.copy(),
            uv_raw_px=uv.copy(),
            uv_px=self.camera.undistort_px(uv),
            track_len=tl.copy(),
            n_prev=n_prev,
            n_tracked=n_tracked,
            stats=stats,
        )

    def _top_up(
        self,
        img: NDArray[np.uint8],
        ids: NDArray,
        uv: NDArray,
        tl: NDArray,
        cell_caps: NDArray | None = None,
    ) -> tuple[NDArray, NDArray, NDArray]:
        p = self.params
        H, W = img.shape
        d = p.min_distance_px
        # Enforce the minimum distance among tracked features, longest tracks first (VINS-Mono).
        if len(ids):
            order = np.argsort(-tl, kind="stable")
            ids, uv, tl = ids[order], uv[order], tl[order]
            cell = np.floor(uv / (0.5 * d)).astype(np.int64)
            key = cell[:, 0] * 100003 + cell[:, 1]
            _, first = np.unique(key, return_index=True)
            sel = np.sort(first)
            ids, uv, tl = ids[sel], uv[sel], tl[sel]
        need = p.max_features - len(ids)
        self._frames += 1
        if (
            need <= 0
            or len(ids) >= p.top_up_below * p.max_features
            or (self._frames - 1) % p.top_up_every
        ):
            return ids, uv, tl
        mask = np.full((H, W), 255, np.uint8)
        xy = np.clip(np.round(uv).astype(np.int64), 0, [W - 1, H - 1])
        if p.square_spacing:
            mask[xy[:, 1], xy[:, 0]] = 0
            mask = cv2.erode(mask, np.ones((2 * d + 1, 2 * d + 1), np.uint8))
        else:
            # Discs of radius d around the kept features (a few hundred small fills: much
            # cheaper than dilating a full-size occupancy image with a (2d+1)^2 disc kernel).
            for x, y in xy.tolist():
                cv2.circle(mask, (x, y), d, 0, -1)
        b = max(p.border_px, 1)
        mask[:b], mask[-b:], mask[:, :b], mask[:, -b:] = 0, 0, 0, 0
        bucketed = p.bucket_cols > 0 and p.bucket_rows > 0 and p.bucket_cap > 0
        pts = cv2.goodFeaturesToTrack(
            img,
            maxCorners=3 * need if bucketed else need,
            qualityLevel=p.quality_level,
            minDistance=d,
            mask=mask,
            blockSize=3,
        )
        if pts is None:
            return ids, uv, tl
        pts = pts.reshape(-1, 2).astype(np.float32)
        if bucketed:
            pts = self._bucket(pts, uv, (H, W), cell_caps)[:need]
        new_ids = np.arange(self._next_id, self._next_id + len(pts), dtype=np.int64)
        self._next_id += len(pts)
        return (
            np.concatenate([ids, new_ids]),
            np.concatenate([uv, pts]),
            np.concatenate([tl, np.ones(len(pts), np.int32)]),
        )

    def _cell(self, uv: NDArray, shape: tuple[int, int]) -> NDArray[np.int64]:
        """Bucketing cell index [N] (row-major) of pixels ``uv`` [N, 2]."""
        p = self.params
        H, W = shape
        cx = np.clip((uv[:, 0] * p.bucket_cols / W).astype(np.int64), 0, p.bucket_cols - 1)
        cy = np.clip((uv[:, 1] * p.bucket_rows / H).astype(np.int64), 0, p.bucket_rows - 1)
        return cy * p.bucket_cols + cx

    @staticmethod
    def _rank_in_cell(c: NDArray[np.int64]) -> NDArray[np.int64]:
        """Each element's rank [N] among the elements of its cell ``c`` [N], in their order."""
        order = np.argsort(c, kind="stable")
        first = np.searchsorted(c[order], c[order])  # start of each element's cell group
        rank = np.empty(len(c), np.int64)
        rank[order] = np.arange(len(c)) - first
        return rank

    def _prune(
        self, ids: NDArray, uv: NDArray, tl: NDArray, caps: NDArray, shape: tuple[int, int]
    ) -> tuple[NDArray, NDArray, NDArray]:
        """The tracks within their cell's cap ``caps`` [cells], the longest kept."""
        order = np.argsort(-tl, kind="stable")
        c = self._cell(uv[order], shape)
        keep = np.sort(order[self._rank_in_cell(c) < caps[c]])
        return ids[keep], uv[keep], tl[keep]

    def _bucket(
        self,
        cand_px: NDArray,
        tracked_px: NDArray,
        shape: tuple[int, int],
        cell_caps: NDArray | None = None,
    ) -> NDArray[np.float32]:
        """New corners ``cand_px`` [M, 2] (strongest first) that a grid cell accepts while it
        holds fewer than its cap (``bucket_cap``, or ``cell_caps``) tracks (``tracked_px`` [K, 2]
        counted), in their order."""
        p = self.params
        n_cells = p.bucket_cols * p.bucket_rows
        caps = np.full(n_cells, p.bucket_cap) if cell_caps is None else cell_caps.ravel()
        held = np.bincount(self._cell(tracked_px, shape), minlength=n_cells)
        c = self._cell(cand_px, shape)
        return cand_px[self._rank_in_cell(c) + held[c] < caps[c]]
