"""Weight-free default depth prior: two-view depth from dense optical flow (DESIGN.md section 3).

The paper's LFM slot (section III-A) wants a dense, scale-ambiguous but locally consistent depth per
keyframe. Without model weights we triangulate OpenCV DIS optical flow between the new keyframe and
an earlier one, using the relative pose carried by the keyframes. The result is partial: every pixel
carries a confidence in [0, 1], 0 where the two-view geometry gives no usable depth:

- parallax below ``min_parallax_deg`` (near the epipole, far away, standing still),
- forward-backward flow inconsistency above ``max_fb_error_px`` (occlusions, bad matches),
- distance of the match from its epipolar line above ``max_epipolar_px`` (moving objects off the
  epipolar line, bad matches),
- depth below the ground plane (a point cannot lie under the road; catches movers along the
  epipolar line), beyond ``max_depth_m``, behind a camera, or leaving the reference image,
- sky (bright, textureless region above the horizon connected to the top border).

The reference keyframe is chosen by distance, not frame count: the nearest earlier keyframe at least
``min_baseline_m`` back; optionally a second one near ``far_baseline_m`` back, which helps far
range. Where two pairs both give a depth they must agree within ``max_pair_disagreement``
(relative); they are then averaged by confidence, otherwise the pixel gets none (an independently
moving object is triangulated differently from two baselines). Elsewhere the one valid pair counts.
With ``far_field_baseline_m`` a reference farther back (:func:`choose_far_field_reference`) gives
depth only where the nearest pair measured the motion (forward-backward consistent) but its
parallax stayed below the gate and no pair gave depth: far objects near the focus of expansion,
whose parallax grows with the baseline.

Confidence models the relative depth error of a triangulation: a match error of ``sigma`` pixels on
a parallax of ``p`` pixels gives a relative depth error of about ``sigma / p``; we take
``sigma = max(fb_error, flow_noise_px)`` and ``conf = 1 / (1 + (sigma / p / rel_err_ref)^2)``.

Everything per pixel is float32 and vectorised (no Python loops over pixels).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError, ShapeError
from mogs_node.geometry import check_array, pixel_grid_xy, road_plane_depth, se3_inverse

__all__ = [
    "FlowPrior",
    "FlowPriorParams",
    "TwoViewDepth",
    "choose_far_field_reference",
    "choose_references",
    "compute_flow_prior",
    "detect_sky",
    "fit_scale_huber",
    "ground_depth_bound",
    "triangulate_matches",
    "two_view_depth",
]

log = logging.getLogger(__name__)

_DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


@dataclass(frozen=True)
class FlowPriorParams:
    """Parameters of the two-view flow depth prior."""

    dis_preset: str = "medium"  # OpenCV DIS preset: ultrafast | fast | medium (best coverage)
    min_baseline_m: float = 0.3  # first reference: nearest earlier keyframe at least this far
    far_baseline_m: float = 1.0  # second reference near this distance back (0 disables it)
    max_far_baseline_m: float = 2.0  # ... and never further back than this (see choose_references)
    min_parallax_deg: float = 0.5  # valid only where the two rays meet at a larger angle
    max_fb_error_px: float = 1.0  # valid only where forward-backward flow error is below this
    max_epipolar_px: float = 2.0  # valid only where the match lies this close to its epipolar line
    max_depth_m: float = 80.0  # valid only below this depth
    max_flow_gradient: float = 0.0  # motion boundaries: flow gradient above this (px/px) -> none
    boundary_px: int = 4  # width of the band rejected around motion boundaries
    camera_height_m: float = 1.65  # camera height above the ground plane (<= 0 disables the bound)
    ground_up_cam: tuple[float, float, float] = (0.0, -1.0, 0.0)  # unit "up" in the camera frame
    ground_margin: float = 1.15  # depth must be <= margin * depth where the ray meets the ground
    flow_noise_px: float = 0.3  # floor of the match error used in the confidence
    rel_err_ref: float = 0.05  # relative depth error at which confidence is 0.5
    sky_mask: bool = True  # mask sky (bright, flat, above the horizon, touching the top border)
    sky_min_brightness: int = 120  # sky: minimum grey level
    sky_max_gradient: float = 6.0  # sky: maximum smoothed gradient magnitude [grey levels / px]
    max_pair_disagreement: float = 0.1  # two pairs differing more (relative) -> no depth there
    history: int = 20  # keyframes kept by the node to choose references from
    # recent non-keyframe frames (image + tracked pose) kept as flow references too (0: none):
    # the first keyframe after a standstill has no earlier keyframe, but the frames in which the
    # car started moving have parallax; keyframes 3 m apart get a nearer reference
    frame_references: int = 0
    # far field (0: off): a reference about this far back, tried only where the nearest pair
    # measured the motion (forward-backward consistent) but its parallax was below the gate
    # (far objects near the focus of expansion): parallax grows with the baseline
    far_field_baseline_m: float = 0.0
    max_far_field_baseline_m: float = 8.0  # ... and never further back than this

    def __post_init__(self) -> None:
        if self.dis_preset not in _DIS_PRESETS:
            raise ConfigError(f"FlowPriorParams.dis_preset: expected one of {sorted(_DIS_PRESETS)}")
        if self.min_baseline_m <= 0 or self.far_baseline_m < 0:
            raise ConfigError("FlowPriorParams: need min_baseline_m > 0 and far_baseline_m >= 0")
        if self.max_far_baseline_m < self.far_baseline_m:
            raise ConfigError("FlowPriorParams: need max_far_baseline_m >= far_baseline_m")
        if min(self.min_parallax_deg, self.max_fb_error_px, self.max_epipolar_px) <= 0:
            raise ConfigError("FlowPriorParams: parallax, fb and epipolar thresholds must be > 0")
        if self.max_depth_m <= 0 or self.ground_margin < 1 or self.rel_err_ref <= 0:
            raise ConfigError(
                "FlowPriorParams: need max_depth_m > 0, ground_margin >= 1, rel_err_ref > 0"
            )
        if not (0 <= self.far_field_baseline_m <= self.max_far_field_baseline_m < float("inf")):
            raise ConfigError(
                "FlowPriorParams: need 0 <= far_field_baseline_m <= max_far_field_baseline_m < inf"
            )
        if self.frame_references < 0:
            raise ConfigError("FlowPriorParams.frame_references: must be >= 0")
        if np.linalg.norm(self.ground_up_cam) < 1e-6 or self.history < 2:
            raise ConfigError("FlowPriorParams: ground_up_cam must be non-zero and history >= 2")


@dataclass
class TwoViewDepth:
    """Per-pixel result of one keyframe pair (all ``[H, W]``)."""

    depth_m: NDArray[np.float32]  # z-depth in the new keyframe, 0 where not valid
    confidence: NDArray[np.float32]  # in [0, 1], 0 where not valid
    parallax_deg: NDArray[np.float32]  # triangulation angle (NaN where the flow check failed)
    fb_error_px: NDArray[np.float32]  # forward-backward flow error
    epipolar_px: NDArray[np.float32]  # distance from the epipolar line (NaN: flow check failed)
    baseline_m: float  # distance between the two camera centres
    flow_px: NDArray[np.float32] | None = None  # [H, W, 2] DIS flow k -> r (the road prior's test)

    @property
    def valid(self) -> NDArray[np.bool_]:
        return self.confidence > 0


@dataclass
class FlowPrior:
    """The fused prior of one keyframe."""

    depth_m: NDArray[np.float32]  # [H, W], 0 where there is no value
    confidence: NDArray[np.float32]  # [H, W] in [0, 1]
    sky: NDArray[np.bool_]  # [H, W] sky mask used
    pairs: list[TwoViewDepth] = field(default_factory=list)  # per reference, in order
    stats: dict[str, float] = field(default_factory=dict)


# ------------------------------------------------------------------------------------ helpers


def _grey(image: NDArray[np.uint8], name: str) -> NDArray[np.uint8]:
    img = np.asarray(image)
    if img.ndim == 3:
        img = check_array(name, img, shape=(None, None, 3), dtype=np.uint8)
        return cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(check_array(name, img, shape=(None, None), dtype=np.uint8))


def ground_depth_bound(
    K: NDArray[np.float64], H: int, W: int, params: FlowPriorParams
) -> NDArray[np.float32]:
    """Largest admissible z-depth per pixel ``[H, W]``: ``ground_margin`` times the depth where the
    pixel's ray meets the ground plane (``up . X = -camera_height``), capped at ``max_depth_m``."""
    K = check_array("K", K, shape=(3, 3), finite=True)
    return _ground_bound_cached(np.asarray(K, np.float64).tobytes(), H, W, params)


@functools.lru_cache(maxsize=4)
def _ground_bound_cached(K_bytes: bytes, H: int, W: int, params: FlowPriorParams) -> NDArray:
    K = np.frombuffer(K_bytes, np.float64).reshape(3, 3)
    bound = np.full((H, W), params.max_depth_m, np.float32)
    if params.camera_height_m <= 0:
        bound.setflags(write=False)
        return bound
    up = np.asarray(params.ground_up_cam, np.float64)
    t, _ = road_plane_depth(
        pixel_grid_xy(K, H, W)[2], up / np.linalg.norm(up), params.camera_height_m
    )
    out = np.minimum(bound, (params.ground_margin * t).astype(np.float32))
    out.setflags(write=False)
    return out


def detect_sky(
    image: NDArray[np.uint8], K: NDArray[np.float64], params: FlowPriorParams
) -> NDArray[np.bool_]:
    """Sky mask ``[H, W]``: bright, flat pixels above the horizon connected to the top border.

    ``image`` is ``[H, W, 3]`` RGB or ``[H, W]`` grey uint8; the horizon comes from
    ``params.ground_up_cam``.
    """
    grey = _grey(image, "image")
    H, W = grey.shape
    K = check_array("K", K, shape=(3, 3), finite=True)
    _, _, (x, y) = pixel_grid_xy(K, H, W)
    up = np.asarray(params.ground_up_cam, np.float64)
    above = (up[0] * x + up[1] * y + up[2]) > 0.0
    g = cv2.GaussianBlur(grey, (0, 0), 1.5).astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    grad = cv2.magnitude(gx, cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3))
    grad = cv2.blur(grad, (5, 5)) / 8.0  # Sobel gain 8 -> grey levels per pixel
    cand = above & (grey >= params.sky_min_brightness) & (grad <= params.sky_max_gradient)
    n, comp = cv2.connectedComponents(cand.astype(np.uint8), connectivity=4)
    if n <= 1:
        return np.zeros((H, W), bool)
    top = np.unique(comp[0][cand[0]])
    keep = np.zeros(n, bool)
    keep[top] = True
    keep[0] = False
    return keep[comp]


def fit_scale_huber(
    depth_m: NDArray[np.floating],
    target_m: NDArray[np.floating],
    weight: NDArray[np.floating] | None = None,
    *,
    delta_rel: float = 0.05,
    iterations: int = 20,
) -> float:
    """Robust scale ``s`` minimising ``sum w * huber(log(s * d / t))`` over pairs ``[N]``.

    A Huber M-estimate (threshold ``delta_rel``, about a relative error) of the log depth ratio,
    solved by IRLS from the weighted median. The log residual treats over- and under-estimates
    alike (a relative residual would let far outliers drag the scale down). Never plain least
    squares. Returns NaN when no pair is usable.
    """
    d = np.asarray(depth_m, np.float64).ravel()
    t = np.asarray(target_m, np.float64).ravel()
    if d.shape != t.shape:
        raise ShapeError(f"target_m: expected {d.shape[0]} values, got {t.shape[0]}")
    w = np.ones_like(d) if weight is None else np.asarray(weight, np.float64).ravel()
    if w.shape != d.shape:
        raise ShapeError(f"weight: expected {d.shape[0]} values, got {w.shape[0]}")
    ok = np.isfinite(d) & np.isfinite(t) & np.isfinite(w) & (d > 0) & (t > 0) & (w > 0)
    if not np.any(ok):
        return float("nan")
    y = np.log(t[ok]) - np.log(d[ok])
    w = w[ok]
    order = np.argsort(y)
    cw = np.cumsum(w[order])
    m = float(y[order][np.searchsorted(cw, 0.5 * cw[-1])])  # weighted median start
    for _ in range(iterations):
        r = np.abs(y - m)
        hw = w * np.where(r <= delta_rel, 1.0, delta_rel / np.maximum(r, 1e-12))
        m_new = float(np.sum(hw * y) / np.sum(hw))
        if abs(m_new - m) < 1e-10:
            m = m_new
            break
        m = m_new
    return float(np.exp(m))


# ------------------------------------------------------------------------------------ core


def _dis(preset: str) -> cv2.DISOpticalFlow:
    return cv2.DISOpticalFlow_create(_DIS_PRESETS[preset])


def two_view_depth(
    image_k: NDArray[np.uint8],
    image_r: NDArray[np.uint8],
    K: NDArray[np.float64],
    T_r_k: NDArray[np.float64],
    params: FlowPriorParams = FlowPriorParams(),
    *,
    depth_bound_m: NDArray[np.float32] | None = None,
) -> TwoViewDepth:
    """Triangulate dense DIS flow from keyframe ``k`` to reference ``r``.

    Args:
        image_k: ``[H, W, 3]`` RGB or ``[H, W]`` grey uint8, the keyframe that gets the depth.
        image_r: same shape, the reference keyframe.
        K: ``[3, 3]`` intrinsics shared by both images.
        T_r_k: ``[4, 4]`` pose of camera ``k`` in camera ``r`` (maps k-frame points into r-frame).
        params: thresholds (see module docstring).
        depth_bound_m: optional ``[H, W]`` largest admissible depth (default
            :func:`ground_depth_bound`).

    Returns:
        :class:`TwoViewDepth` with depth and confidence, both 0 where not valid.
    """
    gk, gr = _grey(image_k, "image_k"), _grey(image_r, "image_r")
    if gk.shape != gr.shape:
        raise ShapeError(f"image_r: expected shape {list(gk.shape)}, got {list(gr.shape)}")
    K = check_array("K", K, shape=(3, 3), finite=True)
    T = check_array("T_r_k", T_r_k, shape=(4, 4), finite=True)
    H, W = gk.shape
    bound = ground_depth_bound(K, H, W, params) if depth_bound_m is None else depth_bound_m
    bound = check_array("depth_bound_m", bound, shape=(H, W))

    dis = _dis(params.dis_preset)
    flow_f = dis.calc(gk, gr, None)  # k -> r
    flow_b = dis.calc(gr, gk, None)  # r -> k
    u, v, _ = pixel_grid_xy(K, H, W)
    u_r = u + flow_f[..., 0]
    v_r = v + flow_f[..., 1]
    back = cv2.remap(
        flow_b, u_r, v_r, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=(1e4, 1e4)
    )
    fb = np.sqrt((flow_f[..., 0] + back[..., 0]) ** 2 + (flow_f[..., 1] + back[..., 1]) ** 2)
    cand = (fb < params.max_fb_error_px) & (u_r >= 0) & (u_r <= W - 1) & (v_r >= 0) & (v_r <= H - 1)
    if params.max_flow_gradient > 0:
        # DIS smooths across occlusion boundaries: near a jump of the flow both sides are unsure.
        grad = np.zeros((H, W), np.float32)
        for c in (0, 1):
            grad += np.abs(cv2.Sobel(flow_f[..., c], cv2.CV_32F, 1, 0, ksize=3)) / 8.0
            grad += np.abs(cv2.Sobel(flow_f[..., c], cv2.CV_32F, 0, 1, ksize=3)) / 8.0
        jump = (grad > params.max_flow_gradient).astype(np.uint8)
        k = 2 * params.boundary_px + 1
        cand &= ~cv2.dilate(jump, np.ones((k, k), np.uint8)).astype(bool)
    # Everything below runs on the flow-consistent candidates only (1-D float32 arrays).
    idx = np.flatnonzero(cand)
    uk, vk = u.ravel()[idx], v.ravel()[idx]
    ur, vr = u_r.ravel()[idx], v_r.ravel()[idx]

    baseline = float(np.linalg.norm(T[:3, 3]))
    depth, z_r, parallax, epi = triangulate_matches(uk, vk, ur, vr, K, T)
    ok = (
        np.isfinite(depth)
        & (depth > 0)
        & (z_r > 0)
        & (depth <= bound.ravel()[idx])
        & (parallax > params.min_parallax_deg)
        & (epi < params.max_epipolar_px)
    )
    parallax_px = np.radians(parallax) * np.float32(0.5 * (K[0, 0] + K[1, 1]))
    sigma = np.maximum(np.maximum(fb.ravel()[idx], epi), np.float32(params.flow_noise_px))
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = sigma / parallax_px / np.float32(params.rel_err_ref)
    good = idx[ok]
    depth_out = np.zeros(H * W, np.float32)
    conf_out = np.zeros(H * W, np.float32)
    depth_out[good] = depth[ok]
    conf_out[good] = 1.0 / (1.0 + rel[ok] * rel[ok])
    par_out = np.full(H * W, np.nan, np.float32)
    par_out[idx] = parallax
    epi_out = np.full(H * W, np.nan, np.float32)
    epi_out[idx] = epi
    return TwoViewDepth(
        depth_m=depth_out.reshape(H, W),
        confidence=conf_out.reshape(H, W),
        parallax_deg=par_out.reshape(H, W),
        fb_error_px=np.where(np.isfinite(fb), fb, np.inf).astype(np.float32),
        epipolar_px=epi_out.reshape(H, W),
        baseline_m=baseline,
        flow_px=flow_f,
    )


def triangulate_matches(
    u_k: NDArray[np.floating],
    v_k: NDArray[np.floating],
    u_r: NDArray[np.floating],
    v_r: NDArray[np.floating],
    K: NDArray[np.float64],
    T_r_k: NDArray[np.float64],
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
    """Vectorised float32 two-view triangulation of matches ``(u_k, v_k) -> (u_r, v_r)`` ``[N]``.

    The point is ``X_k = d [x, y, 1]`` (``x, y`` the normalised ray of the k pixel); ``d`` solves
    the two linear projection equations of ``X_r = d R [x, y, 1] + t`` onto ``(u_r, v_r)`` in least
    squares (exact for a noise-free match). Returns ``(depth_k, depth_r, parallax_deg,
    epipolar_px)``, each ``[N]`` float32: z-depth in k and in r (NaN/inf where degenerate), the
    angle between the two rays, and the distance of ``(u_r, v_r)`` from the epipolar line of the
    k pixel in r.
    """
    K = np.asarray(K, np.float64)
    T = np.asarray(T_r_k, np.float64)
    f32 = np.float32
    u_k, v_k, u_r, v_r = (np.asarray(a, f32) for a in (u_k, v_k, u_r, v_r))
    Kinv = np.linalg.inv(K).astype(f32)
    x = Kinv[0, 0] * u_k + Kinv[0, 1] * v_k + Kinv[0, 2]
    y = Kinv[1, 1] * v_k + Kinv[1, 2]
    R = T[:3, :3].astype(f32)
    t = T[:3, 3].astype(f32)
    # Ray of the k pixel rotated into r: a = R [x, y, 1].
    ax = R[0, 0] * x + R[0, 1] * y + R[0, 2]
    ay = R[1, 0] * x + R[1, 1] * y + R[1, 2]
    az = R[2, 0] * x + R[2, 1] * y + R[2, 2]
    xr = Kinv[0, 0] * u_r + Kinv[0, 1] * v_r + Kinv[0, 2]
    yr = Kinv[1, 1] * v_r + Kinv[1, 2]
    A1, B1 = xr * az - ax, t[0] - xr * t[2]
    A2, B2 = yr * az - ay, t[1] - yr * t[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = (A1 * B1 + A2 * B2) / (A1 * A1 + A2 * A2)
    z_r = depth * az + t[2]
    cos_p = (ax * xr + ay * yr + az) / np.sqrt(
        (ax * ax + ay * ay + az * az) * (xr * xr + yr * yr + 1.0)
    )
    parallax = np.degrees(np.arccos(np.clip(cos_p, -1.0, 1.0)))
    # Epipolar line in r pixels: l = F [u, v, 1], F = K^-T [t]x R K^-1.
    tx = np.array([[0, -T[2, 3], T[1, 3]], [T[2, 3], 0, -T[0, 3]], [-T[1, 3], T[0, 3], 0]])
    Kinv64 = np.linalg.inv(K)
    F = (Kinv64.T @ tx @ T[:3, :3] @ Kinv64).astype(f32)
    l0 = F[0, 0] * u_k + F[0, 1] * v_k + F[0, 2]
    l1 = F[1, 0] * u_k + F[1, 1] * v_k + F[1, 2]
    l2 = F[2, 0] * u_k + F[2, 1] * v_k + F[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        epi = np.abs(l0 * u_r + l1 * v_r + l2) / np.sqrt(l0 * l0 + l1 * l1)
    epi = np.where(np.isfinite(epi), epi, np.inf).astype(f32)
    return depth.astype(f32), z_r.astype(f32), parallax.astype(f32), epi


def choose_references(
    T_world_cam_k: NDArray[np.float64],
    T_world_cam_history: NDArray[np.float64],
    params: FlowPriorParams = FlowPriorParams(),
) -> list[int]:
    """Indices into ``T_world_cam_history`` ``[N, 4, 4]`` (earlier keyframes) of the references.

    First: among earlier keyframes at least ``min_baseline_m`` away, the nearest one. Second
    (if ``far_baseline_m > 0``): the one whose distance is closest to ``far_baseline_m``, if that
    distance exceeds 1.5x the first's and is at most ``max_far_baseline_m``. Returns ``[]`` when
    none is far enough (standing still).

    The upper bound matters when keyframes are sparse (the demo's are 1-3 m apart): without it the
    "far" reference was the next keyframe back, 4-5 m away, where DIS fails on the large
    displacement; its wrong depths then either filled pixels or, disagreeing with the good near
    pair, erased them (prior AbsRel 0.138 -> 0.094 without such pairs,
    docs/benchmarks.md "pipeline-depth-stages").
    """
    Tk = check_array("T_world_cam_k", T_world_cam_k, shape=(4, 4), finite=True)
    Th = np.asarray(T_world_cam_history, np.float64)
    if Th.size == 0:
        return []
    Th = check_array("T_world_cam_history", Th, shape=(None, 4, 4), finite=True)
    dist = np.linalg.norm(Th[:, :3, 3] - Tk[:3, 3], axis=1)
    far = np.flatnonzero(dist >= params.min_baseline_m)
    if far.size == 0:
        return []
    first = int(far[np.argmin(dist[far])])
    refs = [first]
    if params.far_baseline_m > 0:
        cand = far[(dist[far] >= 1.5 * dist[first]) & (dist[far] <= params.max_far_baseline_m)]
        if cand.size:
            second = int(cand[np.argmin(np.abs(dist[cand] - params.far_baseline_m))])
            refs.append(second)
    return refs


def choose_far_field_reference(
    T_world_cam_k: NDArray[np.float64],
    T_world_cam_history: NDArray[np.float64],
    references: Sequence[int],
    params: FlowPriorParams = FlowPriorParams(),
) -> int | None:
    """Index into ``T_world_cam_history`` ``[N, 4, 4]`` of the far-field reference, or None.

    The entry whose distance is closest to ``far_field_baseline_m``, farther than 1.5x every
    chosen reference (``references``, from :func:`choose_references`) and at most
    ``max_far_field_baseline_m`` back. None when off (``far_field_baseline_m`` 0), without
    references or without such an entry.
    """
    if params.far_field_baseline_m <= 0 or not references:
        return None
    Tk = check_array("T_world_cam_k", T_world_cam_k, shape=(4, 4), finite=True)
    Th = check_array("T_world_cam_history", T_world_cam_history, shape=(None, 4, 4), finite=True)
    dist = np.linalg.norm(Th[:, :3, 3] - Tk[:3, 3], axis=1)
    lo = 1.5 * float(dist[list(references)].max())
    cand = np.flatnonzero((dist >= lo) & (dist <= params.max_far_field_baseline_m))
    if cand.size == 0:
        return None
    return int(cand[np.argmin(np.abs(dist[cand] - params.far_field_baseline_m))])


def _far_field_pair(
    grey: NDArray[np.uint8],
    K: NDArray[np.float64],
    T_world_cam_k: NDArray[np.float64],
    far_field: tuple[NDArray[np.uint8], NDArray[np.float64]],
    nearest: TwoViewDepth,
    params: FlowPriorParams,
    bound: NDArray[np.float32],
) -> tuple[TwoViewDepth, NDArray[np.bool_]]:
    """The far-field pair and where it may give depth: pixels whose nearest pair was
    forward-backward consistent (the motion was measured) but below the parallax gate."""
    image_r, T_world_cam_r = far_field
    Tr = check_array("far_field.T_world_cam", T_world_cam_r, shape=(4, 4), finite=True)
    pair = two_view_depth(
        grey,
        _grey(image_r, "far_field.image"),
        K,
        se3_inverse(Tr) @ T_world_cam_k,
        params,
        depth_bound_m=bound,
    )
    slow = np.isfinite(nearest.parallax_deg) & (nearest.parallax_deg <= params.min_parallax_deg)
    return pair, slow & (pair.confidence > 0)


def compute_flow_prior(
    image_k: NDArray[np.uint8],
    K: NDArray[np.float64],
    T_world_cam_k: NDArray[np.float64],
    references: Sequence[tuple[NDArray[np.uint8], NDArray[np.float64]]],
    params: FlowPriorParams = FlowPriorParams(),
    *,
    far_field: tuple[NDArray[np.uint8], NDArray[np.float64]] | None = None,
) -> FlowPrior:
    """Depth prior of keyframe ``k`` from one or more reference keyframes.

    Args:
        image_k: ``[H, W, 3]`` RGB or ``[H, W]`` uint8 image of the keyframe.
        K: ``[3, 3]`` intrinsics.
        T_world_cam_k: ``[4, 4]`` pose of the keyframe.
        references: ``(image, T_world_cam)`` of earlier keyframes (see :func:`choose_references`);
            may be empty (the prior is then all zero).
        params: see :class:`FlowPriorParams`.

    Returns:
        :class:`FlowPrior`: per pixel the fused depth of the pairs (module docstring), sky zeroed.
    """
    grey = _grey(image_k, "image_k")
    H, W = grey.shape
    K = check_array("K", K, shape=(3, 3), finite=True)
    Tk = check_array("T_world_cam_k", T_world_cam_k, shape=(4, 4), finite=True)
    bound = ground_depth_bound(K, H, W, params)
    sky = detect_sky(grey, K, params) if params.sky_mask else np.zeros((H, W), bool)
    depth = np.zeros((H, W), np.float32)
    conf = np.zeros((H, W), np.float32)
    pairs = []
    rejected = np.zeros((H, W), bool)
    for i, (image_r, T_world_cam_r) in enumerate(references):
        Tr = check_array(f"references[{i}].T_world_cam", T_world_cam_r, shape=(4, 4), finite=True)
        pair = two_view_depth(
            grey,
            _grey(image_r, f"references[{i}].image"),
            K,
            se3_inverse(Tr) @ Tk,
            params,
            depth_bound_m=bound,
        )
        pc = pair.confidence
        both = (conf > 0) & (pc > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            gap = np.abs(pair.depth_m - depth) / np.minimum(pair.depth_m, depth)
        agree = both & (gap <= params.max_pair_disagreement)
        clash = both & ~agree  # a moving object is triangulated differently by each pair
        fused = (conf * depth + pc * pair.depth_m) / np.maximum(conf + pc, 1e-12)
        depth = np.where(agree, fused, np.where((conf == 0) & (pc > 0), pair.depth_m, depth))
        conf = np.where(agree, np.maximum(conf, pc), np.where(conf == 0, pc, conf))
        rejected |= clash
        depth = np.where(rejected, 0.0, depth).astype(np.float32)
        conf = np.where(rejected, 0.0, conf).astype(np.float32)
        pairs.append(pair)
    n_far = 0
    if far_field is not None and pairs:
        far, take = _far_field_pair(grey, K, Tk, far_field, pairs[0], params, bound)
        take &= (conf == 0) & ~rejected
        depth[take] = far.depth_m[take]
        conf[take] = far.confidence[take]
        n_far = int(take.sum())
    depth[sky] = 0.0
    conf[sky] = 0.0
    stats = {
        "coverage": float(np.mean(conf > 0)),
        "sky_fraction": float(np.mean(sky)),
        "n_references": float(len(pairs)),
        "pair_disagreement_fraction": float(np.mean(rejected)),
        "far_field_fraction": n_far / float(H * W),
    }
    for i, p in enumerate(pairs):
        stats[f"baseline_m_{i}"] = p.baseline_m
    log.debug("flow prior: %s", stats)
    return FlowPrior(depth_m=depth, confidence=conf, sky=sky, pairs=pairs, stats=stats)
