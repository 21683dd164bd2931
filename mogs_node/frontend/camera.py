"""Camera model of the frontend: pinhole intrinsics plus an optional lens distortion.

Feature pixels are tracked in the raw (distorted) image and converted to the undistorted pinhole
image with :meth:`CameraModel.undistort_px`; everything downstream (estimator, keyframes) works on
undistorted pixels of :attr:`CameraModel.pinhole`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError
from mogs_node.geometry import PinholeCamera, check_array

__all__ = ["DISTORTION_MODELS", "CameraModel"]

DISTORTION_MODELS = ("none", "radtan", "equidistant")


@dataclass(frozen=True)
class CameraModel:
    """Pinhole intrinsics + distortion ``model`` ('none', 'radtan' [k1,k2,p1,p2(,k3)],
    'equidistant' [k1,k2,k3,k4], the Kalibr / EuRoC conventions)."""

    pinhole: PinholeCamera
    model: str = "none"
    coeffs: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.model not in DISTORTION_MODELS:
            raise ConfigError(f"camera.model: {self.model!r} not in {DISTORTION_MODELS}")
        need = {"none": (0,), "radtan": (4, 5), "equidistant": (4,)}[self.model]
        if len(self.coeffs) not in need:
            raise ConfigError(
                f"camera.coeffs: {self.model} needs {need} values, got {len(self.coeffs)}"
            )

    @property
    def K(self) -> NDArray[np.float64]:
        return self.pinhole.K

    def _dist(self) -> NDArray[np.float64]:
        return np.asarray(self.coeffs, dtype=np.float64)

    def undistort_maps(self) -> tuple[NDArray[np.float32], NDArray[np.float32]] | None:
        """``cv2.remap`` maps from the distorted image to the undistorted pinhole one (same K and
        size); None for a camera without distortion."""
        if self.model == "none":
            return None
        K, D = self.K, np.asarray(self.coeffs, float)
        size = (self.pinhole.width, self.pinhole.height)
        if self.model == "radtan":
            return cv2.initUndistortRectifyMap(K, D, None, K, size, cv2.CV_32FC1)
        return cv2.fisheye.initUndistortRectifyMap(K, D, np.eye(3), K, size, cv2.CV_32FC1)

    def undistort_px(self, uv_px: NDArray) -> NDArray[np.float64]:
        """Raw pixels ``[N, 2]`` -> undistorted pinhole pixels ``[N, 2]`` (float64)."""
        uv = check_array("uv_px", uv_px, shape=(None, 2)).astype(np.float64)
        if self.model == "none" or len(uv) == 0:
            return uv.copy()
        pts = uv.reshape(-1, 1, 2)
        if self.model == "radtan":
            out = cv2.undistortPoints(pts, self.K, self._dist(), P=self.K)
        else:
            out = cv2.fisheye.undistortPoints(pts, self.K, self._dist(), P=self.K)
        return out.reshape(-1, 2).astype(np.float64)

    def distort_px(self, uv_px: NDArray) -> NDArray[np.float64]:
        """Undistorted pinhole pixels ``[N, 2]`` -> raw pixels ``[N, 2]`` (inverse of undistort)."""
        uv = check_array("uv_px", uv_px, shape=(None, 2)).astype(np.float64)
        if self.model == "none" or len(uv) == 0:
            return uv.copy()
        rays = self.pinhole.rays(uv)
        if self.model == "radtan":
            out, _ = cv2.projectPoints(
                rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K, self._dist()
            )
        else:
            out = cv2.fisheye.distortPoints(rays[:, None, :2].copy(), self.K, self._dist())
        return out.reshape(-1, 2).astype(np.float64)
