"""Views of the final map for the run report (pure: arrays in, arrays out; no bus, no files).

- :class:`MapReplica`: the mapper's map rebuilt from its incremental ``/mapper/gaussians`` updates
  (added or changed Gaussians by id, removed ids). Rows are kept in id order, which is the row
  order of the mapper's own map and of its ``map.ply``, so the replica renders exactly as the
  mapper's map does once every update has arrived.
- :class:`FrameStore`: a bounded, deterministic sample of the camera images of a drive (the
  ground truth of the held-out views), thinned by halving when it is full.
- :func:`choose_heldout`: which non-keyframe frames are scored, spread evenly over the drive.
- :func:`render_map_view`: the rasterizer (:func:`mogs_node.mapper.rasterizer.render`) behind a
  numpy interface: colour, expected depth and accumulated alpha of a map seen from one pose.
- :func:`score_view` (PSNR / SSIM of :mod:`mogs_node.mapper.image_metrics`) and
  :func:`side_by_side` (ground truth | render | depth picture).

The map is rendered without exposure compensation: the mapper's per-keyframe affine exposure is
not part of the map it publishes (nor of ``map.ply``), and a held-out frame has none; see
``docs/report.md``.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from mogs_node import msgs
from mogs_node.errors import ShapeError
from mogs_node.geometry import check_array, se3_inverse
from mogs_node.mapper.image_metrics import psnr_db, ssim
from mogs_node.mapper.rasterizer import GaussianTensors, RasterParams, render

__all__ = [
    "FrameStore",
    "MapReplica",
    "ViewScore",
    "choose_heldout",
    "depth_to_color",
    "image_to_rgb",
    "map_digest",
    "render_map_view",
    "score_view",
    "side_by_side",
]

#: the five parameter arrays of a Gaussian set and their widths (0: one value per Gaussian)
FIELDS = {"means": 3, "quats_wxyz": 4, "log_scales": 3, "opacity_logit": 0, "colors_rgb": 3}


def _empty(width: int) -> np.ndarray:
    return np.zeros((0, width) if width else (0,), np.float32)


@dataclass
class MapReplica:
    """A Gaussian map kept up to date from incremental updates (rows sorted by id)."""

    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    arrays: dict[str, np.ndarray] = field(
        default_factory=lambda: {k: _empty(w) for k, w in FIELDS.items()}
    )
    updates: int = 0

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def apply_update(self, msg: msgs.GaussianUpdate) -> None:
        """:meth:`apply` of one ``/mapper/gaussians`` message."""
        self.apply(msg.ids, msg.removed_ids, {name: getattr(msg, name) for name in FIELDS})

    def apply(
        self, ids: np.ndarray, removed_ids: np.ndarray, values: dict[str, np.ndarray]
    ) -> None:
        """Remove ``removed_ids``, then add or replace (by id) ``ids`` [N] with ``values[name]``
        ([N, width] float for every name of :data:`FIELDS`)."""
        ids = check_array("ids", ids, shape=(None,), dtype=np.integer).astype(np.int64)
        removed = check_array("removed_ids", removed_ids, shape=(None,), dtype=np.integer)
        n = len(ids)
        new = {}
        for name, w in FIELDS.items():
            if name not in values:
                raise ShapeError(f"values: missing {name!r}")
            shape = (n, w) if w else (n,)
            new[name] = check_array(name, values[name], shape=shape, dtype=np.floating)
        if len(np.unique(ids)) != n:
            raise ShapeError("ids: an update lists an id twice")
        keep = ~(np.isin(self.ids, removed) | np.isin(self.ids, ids))
        all_ids = np.concatenate([self.ids[keep], ids])
        order = np.argsort(all_ids, kind="stable")
        self.ids = all_ids[order]
        for name in FIELDS:
            merged = np.concatenate([self.arrays[name][keep], new[name].astype(np.float32)])
            self.arrays[name] = merged[order]
        self.updates += 1


def map_digest(means: np.ndarray) -> str:
    """SHA-1 of a map's Gaussian centres as float32 in row order (a replica's against a PLY's)."""
    m = check_array("means", means, shape=(None, 3), dtype=np.floating)
    return hashlib.sha1(np.ascontiguousarray(m, np.float32).tobytes()).hexdigest()


def image_to_rgb(data: np.ndarray, encoding: str = "rgb8") -> np.ndarray:
    """A camera image (``mono8`` [H, W], ``rgb8`` / ``bgr8`` [H, W, 3], uint8) as rgb [H, W, 3]."""
    a = np.asarray(data)
    if a.dtype != np.uint8:
        raise ShapeError(f"image: expected dtype uint8, got {a.dtype}")
    if a.ndim == 2:
        return np.repeat(a[..., None], 3, axis=2)
    a = check_array("image", a, shape=(None, None, 3))
    if encoding == "bgr8":
        return np.ascontiguousarray(a[..., ::-1])
    return a


class FrameStore:
    """At most ``max_frames`` images, a deterministic, evenly spread sample of the drive.

    The i-th image added (0-based) is kept while ``i % stride == 0``; when more than
    ``max_frames`` are kept, ``stride`` doubles and the images that no longer qualify go. The
    result depends only on the order of arrival, and memory stays bounded on any drive length.
    """

    def __init__(self, max_frames: int) -> None:
        if max_frames < 1:
            raise ShapeError(f"max_frames: must be >= 1, got {max_frames}")
        self.max_frames = int(max_frames)
        self.stride = 1
        self.n_seen = 0
        self.images: dict[int, np.ndarray] = {}  # stamp_ns -> rgb
        self._index: dict[int, int] = {}  # stamp_ns -> arrival index

    def add(self, stamp_ns: int, rgb: np.ndarray) -> None:
        i = self.n_seen
        self.n_seen += 1
        if i % self.stride:
            return
        self.images[stamp_ns] = rgb
        self._index[stamp_ns] = i
        while len(self.images) > self.max_frames:
            self.stride *= 2
            for s in [s for s, k in self._index.items() if k % self.stride]:
                del self.images[s], self._index[s]


def choose_heldout(
    stamps_ns: np.ndarray | list[int],
    keyframe_stamps_ns: np.ndarray | list[int],
    n: int,
    *,
    positions_m: np.ndarray | None = None,
    within_keyframes: bool = True,
) -> np.ndarray:
    """Up to ``n`` held-out stamps spread evenly over the drive.

    Candidates are ``stamps_ns`` (frames with a pose and a ground-truth image) that are not
    keyframes and, with ``within_keyframes``, lie strictly between the first and the last keyframe
    (outside that span the map has not seen the scene). Without ``positions_m`` the choice is the
    sorted candidates at ``round(linspace(0, len - 1, n))``. With ``positions_m`` [len(stamps),
    3] (camera positions, aligned with ``stamps_ns``) it is even in distance travelled: for each
    of ``n`` equally spaced path lengths along the candidates, the first candidate at or after
    it; frames of a standing vehicle then count once, and the remaining places are filled in
    index order as without positions. Deterministic; the first candidate is included. Returns the chosen stamps (int64, sorted); all candidates when there are <= n.
    """
    if n < 0:
        raise ShapeError(f"n: must be >= 0, got {n}")
    stamps = np.asarray(stamps_ns, np.int64).reshape(-1)
    kf = np.unique(np.asarray(keyframe_stamps_ns, np.int64))
    order = np.argsort(stamps, kind="stable")
    stamps = stamps[order]
    keep = ~np.isin(stamps, kf) & np.concatenate([[True], np.diff(stamps) > 0])
    if within_keyframes:
        keep &= (stamps > kf[0]) & (stamps < kf[-1]) if len(kf) else False
    cand = stamps[keep]
    if len(cand) <= n:
        return cand
    if n == 0:
        return np.zeros(0, np.int64)
    by_index = np.round(np.linspace(0, len(cand) - 1, n)).astype(np.int64)
    if positions_m is None:
        return cand[by_index]
    pos = check_array("positions_m", positions_m, shape=(len(order), 3), finite=True)
    pos = np.asarray(pos, np.float64)[order][keep]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    targets = np.linspace(0.0, arc[-1], n)
    chosen = np.unique(np.minimum(np.searchsorted(arc, targets, side="left"), len(cand) - 1))
    fill = [i for i in by_index if i not in set(chosen.tolist())]
    chosen = np.sort(np.concatenate([chosen, fill[: n - len(chosen)]])).astype(np.int64)
    return cand[chosen]


def render_map_view(
    arrays: dict[str, np.ndarray],
    T_world_cam: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    *,
    background_rgb: tuple[float, float, float] = (0.0, 0.0, 0.0),
    raster: RasterParams = RasterParams(),  # noqa: B008 - frozen dataclass
    alpha_min: float = 1e-3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render a Gaussian map (arrays of :data:`FIELDS`, world frame) at ``T_world_cam`` [4, 4].

    ``K`` [3, 3] pinhole intrinsics of a ``width x height`` image. Returns ``rgb`` [H, W, 3]
    float32 in [0, 1], ``depth_m`` [H, W] float32 (expected z-depth of the covered part, 0 where
    the accumulated alpha is below ``alpha_min``) and ``alpha`` [H, W] float32. No gradients, no
    exposure compensation; the rasterizer's CPU backend unless ``raster`` says otherwise.
    """
    T = check_array("T_world_cam", T_world_cam, shape=(4, 4), finite=True)
    Km = check_array("K", K, shape=(3, 3), finite=True)
    if Km[0, 0] <= 0 or Km[1, 1] <= 0:
        raise ShapeError(f"K: focal lengths must be > 0, got fx={Km[0, 0]}, fy={Km[1, 1]}")
    if width <= 0 or height <= 0:
        raise ShapeError(f"width/height: must be positive, got {width}x{height}")
    n = len(np.asarray(arrays["means"]))
    tens = {}
    for name, w in FIELDS.items():
        a = check_array(name, arrays[name], shape=(n, w) if w else (n,), dtype=np.floating)
        tens[name] = torch.as_tensor(np.ascontiguousarray(a, np.float32))
    g = GaussianTensors(
        tens["means"],
        tens["quats_wxyz"],
        tens["log_scales"],
        tens["opacity_logit"],
        tens["colors_rgb"],
    )
    bg = torch.tensor(background_rgb, dtype=torch.float32)
    K4 = (float(Km[0, 0]), float(Km[1, 1]), float(Km[0, 2]), float(Km[1, 2]))
    with torch.no_grad():
        out = render(
            g,
            torch.as_tensor(se3_inverse(T)),
            K4,
            int(width),
            int(height),
            background=bg,
            params=raster,
        )
    alpha = out.alpha.numpy().astype(np.float32)
    covered = alpha >= alpha_min
    depth = np.where(covered, out.depth.numpy() / np.maximum(alpha, alpha_min), 0.0)
    rgb = np.clip(out.color.numpy(), 0.0, 1.0).astype(np.float32)
    return rgb, np.nan_to_num(depth).astype(np.float32), alpha


@dataclass(frozen=True)
class ViewScore:
    """Scores of one rendered view (``kind`` ``heldout`` or ``keyframe``)."""

    kind: str
    stamp_ns: int
    keyframe_id: int  # -1 for a held-out frame
    psnr_db: float
    ssim: float
    coverage: float  # share of pixels with accumulated alpha >= 0.5
    png: str  # picture file, relative to the run folder ("" if none)


def score_view(gt_rgb: np.ndarray, render_rgb: np.ndarray) -> tuple[float, float]:
    """PSNR [dB] and SSIM of a render against its ground-truth image (same size, [H, W, 3])."""
    gt = check_array("gt_rgb", gt_rgb, shape=(None, None, 3))
    r = check_array("render_rgb", render_rgb, shape=gt.shape)
    return psnr_db(r, gt), ssim(r, gt)


def depth_to_color(depth_m: np.ndarray, near_m: float | None = None, far_m: float | None = None):
    """Colour picture [H, W, 3] uint8 rgb of a depth map: inverse depth on the turbo colour map
    (near = red, far = blue) between ``near_m`` and ``far_m`` (default: the 2nd / 98th
    percentiles of the valid depths); pixels without a depth (<= 0 or not finite) are black."""
    d = check_array("depth_m", depth_m, shape=(None, None)).astype(np.float64)
    valid = np.isfinite(d) & (d > 0)
    out = np.zeros((*d.shape, 3), np.uint8)
    if not valid.any():
        return out
    lo = near_m if near_m is not None else float(np.percentile(d[valid], 2))
    hi = far_m if far_m is not None else float(np.percentile(d[valid], 98))
    lo, hi = max(lo, 1e-6), max(hi, lo * (1 + 1e-6))
    d = np.clip(np.where(valid, d, hi), lo, hi)
    inv = np.clip((1.0 / d - 1.0 / hi) / (1.0 / lo - 1.0 / hi), 0.0, 1.0)
    colored = cv2.applyColorMap((inv * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    out[valid] = colored[valid]
    return out


def side_by_side(
    gt_rgb: np.ndarray,
    render_rgb: np.ndarray,
    depth_m: np.ndarray,
    captions: tuple[str, str, str] = ("ground truth", "render", "rendered depth"),
    band_px: int = 18,
    gap_px: int = 4,
) -> np.ndarray:
    """One rgb uint8 picture: ground truth | render | depth, each under a caption band.

    ``gt_rgb`` uint8 or float [H, W, 3], ``render_rgb`` float in [0, 1] or uint8, ``depth_m``
    [H, W]. The panels start at columns 0, W + gap, 2 (W + gap) below ``band_px`` rows of captions.
    """
    gt = check_array("gt_rgb", gt_rgb, shape=(None, None, 3))
    H, W = gt.shape[:2]
    r = check_array("render_rgb", render_rgb, shape=(H, W, 3))
    check_array("depth_m", depth_m, shape=(H, W))

    def u8(a: np.ndarray) -> np.ndarray:
        return a if a.dtype == np.uint8 else (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)

    panels = (u8(gt), u8(r), depth_to_color(depth_m))
    out = np.full((band_px + H, 3 * W + 2 * gap_px, 3), 255, np.uint8)
    for k, (panel, text) in enumerate(zip(panels, captions)):
        x0 = k * (W + gap_px)
        out[band_px:, x0 : x0 + W] = panel
        cv2.putText(
            out,
            text,
            (x0 + 3, band_px - 5),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.42,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
    return out
