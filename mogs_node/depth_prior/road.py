"""Road-plane depth prior: the ground at the calibrated camera height, verified against the images.

A camera at height ``h`` above a planar road sees the road at z-depth ``z = h / (-up . r)`` along
the pixel ray ``r = K^-1 [u, v, 1]`` (``up`` the unit "up" direction in the camera frame; pixels
with ``-up . r > 0`` lie below the horizon). This is what the system already knows: the height is
calibrated (the frontend's ``ground.camera_height_m`` on KITTI, the sim's 1.65 m on the demo) and
"up" comes from the keyframe's gravity-aligned pose (a visual-inertial world has ``z`` up) or, for
a camera-only world, from a fixed camera-frame direction.

Not every pixel below the horizon is road. With a reference keyframe (pose ``T_r_k``) the plane
hypothesis predicts where each pixel lands in the reference (the plane homography); it is
*verified* where

- the DIS flow, where forward-backward consistent, ends within ``max_flow_residual_px`` of the
  predicted point, and
- the reference image warped by the plane matches the keyframe (mean absolute grey difference in
  a window below ``max_photo_residual``) where the test is informative: textured, and the plane's
  prediction moves at least ``min_discrimination_px`` when the depth shrinks by 20 % (an object
  standing on the road would be seen there).

A pixel failing either test is *rejected*. Uninformative pixels (flat texture, near the horizon,
small baseline) count only when 4-connected to verified road through pixels not rejected, with a
larger error. Without any reference (standing still, first keyframe) the image alone decides: the
region below the horizon that is photometrically similar to the patch right in front of the car
(flood fill), with a larger error still.

Error model (relative depth error, :func:`plane_relative_error`): a normal known to ``sigma_n``
radians moves the depth by ``sigma_n / sin(alpha)`` (``alpha`` the ray's angle below the
horizon), the height by ``height_rel_err``; verified, connected and image-only pixels multiply this
by 1, ``unverified_factor`` and ``image_only_factor``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError
from mogs_node.geometry import check_array, road_plane_depth, up_in_camera

__all__ = [
    "RoadPlane",
    "RoadPriorParams",
    "plane_relative_error",
    "project_depth",
    "road_prior",
    "up_in_camera",
]


@dataclass(frozen=True)
class RoadPriorParams:
    """Parameters of the road-plane prior (the height is ``FlowPriorParams.camera_height_m``)."""

    enabled: bool = True  # False: no road prior
    up_world: tuple[float, float, float] | None = (0.0, 0.0, 1.0)  # world "up" (None: camera-fixed)
    max_depth_m: float = 40.0  # road farther than this gets no prior
    min_angle_deg: float = 0.5  # rays closer than this to the horizon get none
    normal_sigma_deg: float = 0.5  # uncertainty of the plane normal (pose gravity, road slope)
    height_rel_err: float = 0.02  # relative uncertainty of the camera height
    max_flow_residual_px: float = 1.5  # DIS end point vs the plane's prediction (fb-valid pixels)
    max_shift_px: float = 1.0  # photometric misalignment (window |I_k - warped I_r| / gradient)
    photo_window_px: int = 7  # window of the photometric test
    min_texture: float = 1.5  # grey levels / px (window mean gradient): below, test uninformative
    min_discrimination_px: float = 1.0  # the plane vs 0.8x its depth must differ this much
    unverified_factor: float = 2.0  # error factor of connected but unverified road pixels
    image_only_factor: float = 4.0  # error factor without a reference (flood fill from the car)
    flood_tolerance: float = 12.0  # grey levels: flood fill tolerance from the seed patch mean
    image_only: bool = False  # without a reference: flood fill from the car (unverifiable)
    extra_references: int = 1  # earlier keyframes besides the flow references to verify against
    fill_px: int = 3  # holes in the verified road up to about this radius are closed
    # no camera height given (flow.camera_height_m 0): measure it from the flow depth
    # (mogs_node/depth_prior/ground_height.py), the ground searched within this range of drops
    auto_height: bool = False
    auto_height_range_m: tuple[float, float] = (0.8, 3.5)

    def __post_init__(self) -> None:
        if self.up_world is not None and (
            len(self.up_world) != 3
            or not np.isfinite(self.up_world).all()
            or np.linalg.norm(self.up_world) < 1e-9
        ):
            raise ConfigError("road.up_world: expected a finite non-zero 3-vector or null")
        if self.max_depth_m <= 0 or not 0 <= self.min_angle_deg < 90:
            raise ConfigError("road: need max_depth_m > 0 and 0 <= min_angle_deg < 90")
        if min(self.normal_sigma_deg, self.height_rel_err) < 0:
            raise ConfigError("road: normal_sigma_deg and height_rel_err must be >= 0")
        if min(self.max_flow_residual_px, self.max_shift_px, self.min_texture) <= 0:
            raise ConfigError("road: flow/photometric thresholds and min_texture must be > 0")
        lo, hi = self.auto_height_range_m
        if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo < hi):
            raise ConfigError(
                f"road.auto_height_range_m: need 0 < low < high, got {self.auto_height_range_m}"
            )
        if self.photo_window_px < 1 or min(self.unverified_factor, self.image_only_factor) < 1:
            raise ConfigError("road: need photo_window_px >= 1 and error factors >= 1")


@dataclass
class RoadPlane:
    """Road prior of one keyframe (all ``[H, W]``)."""

    depth_m: NDArray[np.float32]  # plane depth on road pixels, 0 elsewhere
    rel_err: NDArray[np.float32]  # predicted relative depth error, inf where no road
    verified: NDArray[np.bool_]  # plane confirmed by flow / photometry
    rejected: NDArray[np.bool_]  # below the horizon but inconsistent with the plane
    up_cam: NDArray[np.float64]  # [3] unit up direction used, camera frame


def plane_relative_error(
    sin_below: NDArray[np.float32], params: RoadPriorParams
) -> NDArray[np.float32]:
    """Predicted relative depth error of the plane depth: ``sqrt(e_h^2 + (sigma_n / sin a)^2)``."""
    s_n = np.radians(params.normal_sigma_deg)
    with np.errstate(divide="ignore"):
        e_n = np.float32(s_n) / np.maximum(sin_below, 1e-9)
    return np.sqrt(np.float32(params.height_rel_err) ** 2 + e_n * e_n).astype(np.float32)


def project_depth(
    z: NDArray[np.float32], rays_xy: NDArray[np.float32], K: NDArray, T_r_k: NDArray
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.bool_]]:
    """Pixel in the reference of the point at depth ``z`` on each ray; ``ok`` where in front."""
    x, y = rays_xy
    R, t = T_r_k[:3, :3].astype(np.float32), T_r_k[:3, 3].astype(np.float32)
    Xr = [z * (R[i, 0] * x + R[i, 1] * y + R[i, 2]) + t[i] for i in range(3)]
    ok = np.isfinite(Xr[2]) & (Xr[2] > 1e-3)
    zr = np.where(ok, Xr[2], 1.0)
    u = K[0, 0] * Xr[0] / zr + K[0, 1] * Xr[1] / zr + K[0, 2]
    v = K[1, 1] * Xr[1] / zr + K[1, 2]
    return u.astype(np.float32), v.astype(np.float32), ok


def _box(a: NDArray[np.float32], k: int) -> NDArray[np.float32]:
    return cv2.blur(a.astype(np.float32), (k, k), borderType=cv2.BORDER_REFLECT)


def _image_only(grey: NDArray[np.uint8], below: NDArray[np.bool_], tol: float) -> NDArray:
    """Pixels below the horizon flood-filled from the bottom-centre patch (the road ahead)."""
    H, W = grey.shape
    g = cv2.GaussianBlur(grey, (0, 0), 2.0)
    seed_v, seed_u = H - 1 - max(1, H // 20), W // 2
    if not below[seed_v, seed_u]:
        return np.zeros((H, W), bool)
    lo = max(0, seed_v - H // 20)
    seed_val = float(np.median(g[lo : seed_v + 1, seed_u - W // 20 : seed_u + W // 20 + 1]))
    img = np.where(below, g, 0).astype(np.uint8)  # above the horizon: never within tolerance
    img[seed_v, seed_u] = np.uint8(np.clip(round(seed_val), 0, 255))
    mask = np.zeros((H + 2, W + 2), np.uint8)
    flags = 4 | cv2.FLOODFILL_FIXED_RANGE | cv2.FLOODFILL_MASK_ONLY | (1 << 8)
    cv2.floodFill(img, mask, (seed_u, seed_v), 0, (tol,), (tol,), flags)
    return mask[1:-1, 1:-1].astype(bool) & below


def road_prior(
    grey_k: NDArray[np.uint8],
    K: NDArray[np.float64],
    rays_xy: NDArray[np.float32],
    up_cam: NDArray[np.float64],
    height_m: float,
    params: RoadPriorParams,
    reference: tuple[
        NDArray[np.uint8],
        NDArray[np.float64],
        NDArray[np.float32] | None,
        NDArray[np.float32] | None,
    ]
    | None = None,
) -> RoadPlane:
    """Road-plane depth of keyframe ``k`` verified against one reference (module docstring).

    Args:
        grey_k: ``[H, W]`` uint8 keyframe.
        K: ``[3, 3]`` intrinsics; rays_xy: ``[2, H, W]`` normalised rays of the pixels.
        up_cam: ``[3]`` unit up direction in the camera frame; height_m: camera height (> 0).
        params: see :class:`RoadPriorParams`.
        reference: ``(grey_r, T_r_k, flow_px, fb_error_px)``: the reference image, the pose of
            ``k`` in ``r``, and optionally the DIS flow ``k -> r`` ``[H, W, 2]`` with its
            forward-backward error ``[H, W]``; None: image-only (no motion).
    """
    H, W = grey_k.shape
    if not (np.isfinite(height_m) and height_m > 0):
        raise ConfigError(f"camera_height_m: the road prior needs a height > 0, got {height_m}")
    z, sin_a = road_plane_depth(rays_xy, up_cam, height_m)
    below = (sin_a > np.sin(np.radians(params.min_angle_deg))) & (z <= params.max_depth_m)
    err = plane_relative_error(sin_a, params)
    verified = np.zeros((H, W), bool)
    rejected = np.zeros((H, W), bool)
    if reference is None:
        road = (
            _image_only(grey_k, below, params.flood_tolerance)
            if params.image_only
            else below & False
        )
        err = err * np.float32(params.image_only_factor)
    else:
        grey_r, T_r_k, flow, fb = reference
        T = check_array("T_r_k", T_r_k, shape=(4, 4), finite=True)
        zc = np.where(below, z, 1.0).astype(np.float32)
        u_p, v_p, ok = project_depth(zc, rays_xy, K, T)
        u_n, v_n, ok_n = project_depth(0.8 * zc, rays_xy, K, T)
        inside = ok & (u_p >= 0) & (u_p <= W - 1) & (v_p >= 0) & (v_p <= H - 1)
        disc_px = np.hypot(u_n - u_p, v_n - v_p)
        disc = disc_px >= params.min_discrimination_px
        k = params.photo_window_px
        gk = cv2.GaussianBlur(grey_k, (0, 0), 1.0).astype(np.float32)
        gr = cv2.GaussianBlur(grey_r, (0, 0), 1.0).astype(np.float32)
        warped = cv2.remap(gr, u_p, v_p, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        photo = _box(np.abs(gk - warped), k)
        grad = cv2.magnitude(cv2.Sobel(gk, cv2.CV_32F, 1, 0), cv2.Sobel(gk, cv2.CV_32F, 0, 1))
        texture = _box(grad / 8.0, k)
        informative = below & inside & ok_n & disc & (texture >= params.min_texture)
        # |I_k - warped I_r| ~ |gradient| x misalignment: their window ratio estimates the
        # misalignment in pixels; the plane must explain the image better than a 0.8x depth
        shift_px = photo / np.maximum(texture, 1e-3)
        photo_ok = informative & (shift_px <= np.minimum(params.max_shift_px, 0.5 * disc_px))
        photo_bad = informative & ~photo_ok
        flow_bad = np.zeros((H, W), bool)
        flow_ok = np.zeros((H, W), bool)
        if flow is not None and fb is not None:
            u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
            res = np.hypot(u + flow[..., 0] - u_p, v + flow[..., 1] - v_p)
            good_flow = below & inside & (fb < 1.0)
            # the flow must be nearer the plane's prediction than the 0.8x-depth one's
            tol = np.minimum(params.max_flow_residual_px, 0.5 * disc_px)
            flow_bad = good_flow & (res > tol)
            flow_ok = good_flow & disc & ~flow_bad
        rejected = below & (photo_bad | flow_bad)
        verified = (flow_ok | photo_ok) & ~rejected
        # small holes inside verified road (flat texture, a bad match): closed, larger error
        r = params.fill_px
        if r > 0:
            kern = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
            closed = cv2.morphologyEx(verified.astype(np.uint8), cv2.MORPH_CLOSE, kern)
            road = closed.astype(bool) & below & ~rejected
        else:
            road = verified
        err = np.where(verified, err, err * np.float32(params.unverified_factor))
    depth = np.where(road, z, 0.0).astype(np.float32)
    rel = np.where(road, err, np.inf).astype(np.float32)
    return RoadPlane(depth, rel, verified & road, rejected, np.asarray(up_cam, np.float64))
