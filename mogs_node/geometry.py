"""Geometry in one place: SO(3)/SE(3), quaternions, the pinhole camera, projection and ray casting.

Conventions (see docs/architecture.md):

- Poses are 4x4 float64 homogeneous matrices named ``T_dst_src``: ``T_world_cam`` maps points in
  the camera frame into the world, so ``T_a_b @ T_b_c == T_a_c``.
- Camera frame: x right, y down, z forward (OpenCV). Depth ``depth_m`` is the z coordinate.
- Quaternions are ``quat_wxyz`` (scalar first), unit norm.
- Tangent vectors of SE(3) are ``xi = [rho (translation part), phi (rotation part)]``.
- Every function is vectorised over a leading batch of points / rays; no Python loops over points.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mogs_node.errors import ConfigError, GeometryError, ShapeError

__all__ = [
    "PinholeCamera",
    "check_array",
    "hat",
    "intersect_rays_plane",
    "intersect_rays_quadric",
    "make_T",
    "nearest_rotation",
    "pixel_grid_xy",
    "pixel_to_normalized",
    "road_plane_depth",
    "rigid_transform",
    "rotation_defect",
    "quat_wxyz_from_rotmat",
    "quat_wxyz_to_rotmat",
    "rotmat_from_rpy",
    "se3_exp",
    "se3_inverse",
    "tf_lookup",
    "se3_log",
    "so3_exp",
    "so3_log",
    "transform_points",
    "up_in_camera",
    "view_tan_limits",
]

FloatArray = NDArray[np.floating]
_EPS = 1e-12


def check_array(
    name: str,
    arr: object,
    *,
    shape: tuple[int | None, ...] | None = None,
    dtype: type | tuple[type, ...] | None = None,
    finite: bool = False,
) -> np.ndarray:
    """Return ``arr`` as an ndarray after checking shape (``None`` = any size) and dtype kind.

    Raises :class:`ShapeError` naming ``name`` on any mismatch.
    """
    a = np.asarray(arr)
    if shape is not None and (
        a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape))
    ):
        want = "x".join("N" if s is None else str(s) for s in shape)
        raise ShapeError(f"{name}: expected shape [{want}], got {list(a.shape)}")
    if dtype is not None:
        kinds = dtype if isinstance(dtype, tuple) else (dtype,)
        if not any(np.issubdtype(a.dtype, k) for k in kinds):
            raise ShapeError(f"{name}: expected dtype {[k.__name__ for k in kinds]}, got {a.dtype}")
    if finite and a.size and not np.all(np.isfinite(a)):
        raise ShapeError(f"{name}: contains NaN or inf")
    return a


# ----------------------------------------------------------------------------------------- SO(3)


def hat(v: FloatArray) -> FloatArray:
    """Skew-symmetric matrix of ``v`` ([..., 3] -> [..., 3, 3])."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def so3_exp(phi: FloatArray) -> FloatArray:
    """Rodrigues' formula, ``[..., 3] -> [..., 3, 3]``, exact to first order near zero."""
    phi = np.asarray(phi, dtype=np.float64)
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = hat(phi)
    small = theta < 1e-8
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    return np.eye(3) + a * K + b * (K @ K)


def so3_log(R: FloatArray) -> FloatArray:
    """Inverse of :func:`so3_exp` (``[..., 3, 3] -> [..., 3]``), stable near 0 and near pi."""
    R = np.asarray(R, dtype=np.float64)
    q = quat_wxyz_from_rotmat(R)
    w = np.clip(q[..., 0], -1.0, 1.0)
    v = q[..., 1:]
    sin_half = np.linalg.norm(v, axis=-1)
    theta = 2.0 * np.arctan2(sin_half, w)
    scale = np.where(
        sin_half < 1e-10,
        2.0 / np.where(np.abs(w) < _EPS, 1.0, w),
        theta / np.maximum(sin_half, 1e-300),
    )
    return v * scale[..., None]


def quat_wxyz_to_rotmat(q: FloatArray) -> FloatArray:
    """Unit quaternion(s) ``[..., 4]`` (w, x, y, z) to rotation matrices ``[..., 3, 3]``."""
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < _EPS) or not np.all(np.isfinite(q)):
        raise GeometryError("quat_wxyz: zero-norm or non-finite quaternion")
    w, x, y, z = np.moveaxis(q / n, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def quat_wxyz_from_rotmat(R: FloatArray) -> FloatArray:
    """Rotation matrices ``[..., 3, 3]`` to unit quaternions ``[..., 4]`` with ``w >= 0``.

    Uses the numerically stable branch (largest diagonal element) per matrix, vectorised.
    """
    R = np.asarray(R, dtype=np.float64)
    m = R
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cand = np.stack(
        [
            np.stack(
                [
                    1 + tr,
                    m[..., 2, 1] - m[..., 1, 2],
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 1, 0] - m[..., 0, 1],
                ],
                -1,
            ),
            np.stack(
                [
                    m[..., 2, 1] - m[..., 1, 2],
                    1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
                    m[..., 0, 1] + m[..., 1, 0],
                    m[..., 0, 2] + m[..., 2, 0],
                ],
                -1,
            ),
            np.stack(
                [
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 0, 1] + m[..., 1, 0],
                    1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
                    m[..., 1, 2] + m[..., 2, 1],
                ],
                -1,
            ),
            np.stack(
                [
                    m[..., 1, 0] - m[..., 0, 1],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 1, 2] + m[..., 2, 1],
                    1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
                ],
                -1,
            ),
        ],
        -2,
    )  # [..., 4 (branch), 4 (q)]
    diag = np.stack([tr, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1)
    best = np.argmax(diag, axis=-1)
    q = np.take_along_axis(cand, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return q * np.where(q[..., :1] < 0, -1.0, 1.0)


def rotmat_from_rpy(roll: FloatArray, pitch: FloatArray, yaw: FloatArray) -> FloatArray:
    """``R = Rz(yaw) Ry(pitch) Rx(roll)`` as used by the KITTI OXTS devkit."""
    roll, pitch, yaw = (np.asarray(a, dtype=np.float64) for a in (roll, pitch, yaw))
    cr, sr, cp, sp, cy, sy = (
        np.cos(roll),
        np.sin(roll),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(yaw),
        np.sin(yaw),
    )
    return np.stack(
        [
            np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
            np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
            np.stack([-sp, cp * sr, cp * cr], -1),
        ],
        -2,
    )


# ----------------------------------------------------------------------------------------- SE(3)


def make_T(R: FloatArray, t: FloatArray) -> FloatArray:
    """Homogeneous matrices ``[..., 4, 4]`` from rotations ``[..., 3, 3]`` and translations ``[..., 3]``."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T = np.zeros(np.broadcast_shapes(R.shape[:-2], t.shape[:-1]) + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


#: a typed rotation this close to orthonormal (max |R R^T - I|) is projected without complaint
ROTATION_TOLERANCE = 1e-4


def nearest_rotation(R: FloatArray) -> FloatArray:
    """The rotation ``[..., 3, 3]`` nearest to ``R`` in the Frobenius norm (SVD, det +1).

    Six-decimal calibrations and text files are orthonormal only to ~1e-6; chained into relative
    poses they fail strict SO(3) checks (evo's 1e-6), so typed rotations go through this once.
    """
    R = np.asarray(R, dtype=np.float64)
    U, _, Vt = np.linalg.svd(R)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.zeros(R.shape[:-2] + (3, 3))
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    return U @ D @ Vt


def rotation_defect(R: FloatArray) -> FloatArray:
    """How far rotations ``[..., 3, 3]`` are from SO(3): max |R R^T - I| per matrix (``[...]``),
    inf where det <= 0 or a value is not finite."""
    R = np.asarray(R, dtype=np.float64)
    ok = np.isfinite(R).all(axis=(-1, -2))
    Rs = np.where(ok[..., None, None], R, np.eye(3))
    d = np.abs(Rs @ np.swapaxes(Rs, -1, -2) - np.eye(3)).max(axis=(-1, -2))
    return np.where(ok & (np.linalg.det(Rs) > 0), d, np.inf)


def rigid_transform(
    values: object, name: str, *, tolerance: float = ROTATION_TOLERANCE
) -> tuple[FloatArray, float]:
    """A typed rigid transform (16 numbers row-major, or ``[4, 4]``) -> ``(T [4, 4], defect)``.

    A rotation orthonormal to within ``tolerance`` (max |R R^T - I|) is replaced by the nearest
    rotation (:func:`nearest_rotation`) and its defect returned, for the caller to note once;
    beyond that, or a last row other than ``[0, 0, 0, 1]``, it is a :class:`GeometryError` naming
    ``name`` and the size of the defect.
    """
    try:
        T = np.asarray(values, dtype=np.float64).reshape(4, 4)
    except (TypeError, ValueError) as err:
        raise GeometryError(f"{name}: expected 16 numbers (a 4x4 matrix), got {values!r}") from err
    if not np.isfinite(T).all():
        raise GeometryError(f"{name}: contains NaN or inf")
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > tolerance:
        raise GeometryError(f"{name}: last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    defect = float(rotation_defect(T[:3, :3]))
    if not defect <= tolerance:
        raise GeometryError(
            f"{name}: the rotation is not orthonormal (max |R R^T - I| = {defect:.3g}, "
            f"tolerance {tolerance:g}; det {np.linalg.det(T[:3, :3]):.6g}): check the typed values"
        )
    return make_T(nearest_rotation(T[:3, :3]), T[:3, 3]), defect


def tf_lookup(
    edges: dict[tuple[str, str], FloatArray], parent: str, child: str
) -> FloatArray | None:
    """``T_parent_child`` [4, 4] through a tree of static transforms, or None if unconnected.

    ``edges`` maps ``(parent, child)`` to ``T_parent_child`` (ROS ``TransformStamped``: header
    frame -> child frame); edges are walked both ways (breadth first), so IMU and camera may hang
    off a common base frame.
    """
    if parent == child:
        return np.eye(4)
    nbrs: dict[str, list[tuple[str, FloatArray]]] = {}
    for (a, b), T in edges.items():
        T = np.asarray(T, dtype=np.float64)
        nbrs.setdefault(a, []).append((b, T))
        nbrs.setdefault(b, []).append((a, se3_inverse(T)))
    seen = {parent: np.eye(4)}
    todo = [parent]
    while todo:
        frame = todo.pop(0)
        for nxt, T in nbrs.get(frame, ()):
            if nxt not in seen:
                seen[nxt] = seen[frame] @ T
                if nxt == child:
                    return seen[nxt]
                todo.append(nxt)
    return None


def se3_inverse(T: FloatArray) -> FloatArray:
    """Closed-form inverse of rigid transforms ``[..., 4, 4]``."""
    T = np.asarray(T, dtype=np.float64)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_T(Rt, -(Rt @ T[..., :3, 3:])[..., 0])


def _left_jacobian(phi: FloatArray) -> FloatArray:
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = hat(phi)
    small = theta < 1e-6
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    b = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (t - np.sin(t)) / t**3)
    return np.eye(3) + a * K + b * (K @ K)


def se3_exp(xi: FloatArray) -> FloatArray:
    """Exponential map ``[..., 6] (rho, phi) -> [..., 4, 4]``."""
    xi = np.asarray(xi, dtype=np.float64)
    rho, phi = xi[..., :3], xi[..., 3:]
    return make_T(so3_exp(phi), (_left_jacobian(phi) @ rho[..., None])[..., 0])


def se3_log(T: FloatArray) -> FloatArray:
    """Logarithm ``[..., 4, 4] -> [..., 6]``, inverse of :func:`se3_exp`."""
    T = np.asarray(T, dtype=np.float64)
    phi = so3_log(T[..., :3, :3])
    rho = np.linalg.solve(_left_jacobian(phi), T[..., :3, 3:])[..., 0]
    return np.concatenate([rho, phi], -1)


def transform_points(T_dst_src: FloatArray, points_src: FloatArray) -> FloatArray:
    """Apply ``T_dst_src`` ``[4, 4]`` to ``points_src`` ``[N, 3]`` -> ``[N, 3]``."""
    T = check_array("T_dst_src", T_dst_src, shape=(4, 4))
    P = check_array("points_src", points_src, shape=(None, 3))
    return P @ T[:3, :3].T + T[:3, 3]


# ----------------------------------------------------------------------------------------- camera


def pixel_to_normalized(K: FloatArray, u: ArrayLike, v: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Normalised image coordinates ``x, y`` (the ray ``(x, y, 1)``) of pixels ``u, v`` (any
    shapes that broadcast) for a ``[3, 3]`` intrinsic matrix without skew; times a z-depth they
    give the camera-frame point. The one back-projection formula for callers that hold ``K``."""
    return (np.asarray(u) - K[0, 2]) / K[0, 0], (np.asarray(v) - K[1, 2]) / K[1, 1]


def view_tan_limits(
    fx: float, fy: float, cx: float, cy: float, width: int, height: int, scale: float = 1.0
) -> tuple[float, float]:
    """``scale`` times the largest ``|x / z|`` and ``|y / z|`` of a ray through the image (to its
    farther pixel edge): the view-direction clamp of the 3DGS projection Jacobian."""
    return (
        scale * max(cx + 0.5, width - 0.5 - cx) / fx,
        scale * max(cy + 0.5, height - 0.5 - cy) / fy,
    )


@dataclass(frozen=True)
class PinholeCamera:
    """Undistorted pinhole camera; pixel centres are at integer coordinates (OpenCV convention)."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    width: int
    height: int

    def __post_init__(self) -> None:
        vals = (self.fx_px, self.fy_px, self.cx_px, self.cy_px)
        if not all(np.isfinite(v) for v in vals) or self.fx_px <= 0 or self.fy_px <= 0:
            raise GeometryError(f"PinholeCamera: invalid intrinsics {vals}")
        if self.width <= 0 or self.height <= 0:
            raise GeometryError(f"PinholeCamera: invalid size {self.width}x{self.height}")

    @property
    def K(self) -> FloatArray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx_px, 0, self.cx_px], [0, self.fy_px, self.cy_px], [0, 0, 1.0]])

    @classmethod
    def from_K(cls, K: FloatArray, width: int, height: int) -> PinholeCamera:
        K = check_array("K", K, shape=(3, 3), finite=True)
        return cls(
            float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height)
        )

    def scaled(self, width: int, height: int) -> PinholeCamera:
        """The same camera resampled to ``width x height`` (pixel-centre convention kept)."""
        sx, sy = width / self.width, height / self.height
        return PinholeCamera(
            self.fx_px * sx,
            self.fy_px * sy,
            (self.cx_px + 0.5) * sx - 0.5,
            (self.cy_px + 0.5) * sy - 0.5,
            width,
            height,
        )

    def project(self, points_cam: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        """Project camera-frame points ``[N, 3]`` to pixels ``[N, 2]``; also ``z > 0`` mask ``[N]``."""
        P = check_array("points_cam", points_cam, shape=(None, 3))
        z = P[:, 2]
        in_front = z > 1e-9
        zs = np.where(in_front, z, 1.0)
        uv = np.stack(
            [self.fx_px * P[:, 0] / zs + self.cx_px, self.fy_px * P[:, 1] / zs + self.cy_px], -1
        )
        return uv, in_front

    def in_image(self, uv: FloatArray) -> NDArray[np.bool_]:
        """Pixels ``[N, 2]`` whose rounded position lies inside the image."""
        u, v = np.round(uv[:, 0]), np.round(uv[:, 1])
        return (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)

    def rays(self, uv: FloatArray) -> FloatArray:
        """Rays ``[N, 3]`` with ``z = 1`` through pixels ``uv`` ``[N, 2]`` (camera frame)."""
        uv = check_array("uv", uv, shape=(None, 2))
        return np.stack(
            [
                (uv[:, 0] - self.cx_px) / self.fx_px,
                (uv[:, 1] - self.cy_px) / self.fy_px,
                np.ones(len(uv)),
            ],
            -1,
        )

    def pixel_grid_rays(self, dtype: type = np.float64) -> NDArray:
        """Rays with ``z = 1`` for every pixel, ``[H, W, 3]``."""
        u = (np.arange(self.width, dtype=dtype) - self.cx_px) / self.fx_px
        v = (np.arange(self.height, dtype=dtype) - self.cy_px) / self.fy_px
        out = np.empty((self.height, self.width, 3), dtype=dtype)
        out[..., 0] = u[None, :]
        out[..., 1] = v[:, None]
        out[..., 2] = 1.0
        return out

    def backproject(self, uv: FloatArray, depth_m: FloatArray) -> FloatArray:
        """Camera-frame points ``[N, 3]`` at pixels ``uv`` ``[N, 2]`` with z-depth ``depth_m`` ``[N]``."""
        return self.rays(uv) * np.asarray(depth_m, dtype=np.float64)[:, None]

    def backproject_depth(self, depth_m: FloatArray) -> FloatArray:
        """Point map ``[H, W, 3]`` from a z-depth image ``[H, W]``."""
        d = check_array("depth_m", depth_m, shape=(self.height, self.width))
        return (
            self.pixel_grid_rays(np.float64 if d.dtype == np.float64 else np.float32) * d[..., None]
        )


# ----------------------------------------------------------------------------------------- rays


def intersect_rays_plane(
    origins: FloatArray, dirs: FloatArray, normal: FloatArray, offset: float
) -> FloatArray:
    """Ray parameter ``t > 0`` where rays hit the plane ``n . x + offset = 0``; ``inf`` on a miss.

    ``origins`` ``[N, 3]`` or ``[3]``, ``dirs`` ``[N, 3]``. With ``dirs`` of unit z this ``t`` is the
    z-depth of the hit in the ray's frame.
    """
    n = np.asarray(normal, dtype=np.float64)
    denom = dirs @ n
    num = -(np.asarray(origins) @ n + offset)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num / denom
    ok = np.isfinite(t) & (t > 0) & (np.abs(denom) > 1e-12)
    return np.where(ok, t, np.inf)


def pixel_grid_xy(K: NDArray[np.float64], H: int, W: int) -> tuple[NDArray, NDArray, NDArray]:
    """Pixel grid ``u, v`` ``[H, W]`` and the rays with ``z = 1`` as ``x, y`` ``[2, H, W]``
    (float32, skew included).

    Cached per camera (read-only arrays): the keyframes of one camera share them.
    """
    return _pixel_grid_xy_cached(np.asarray(K, np.float64).tobytes(), int(H), int(W))


@functools.lru_cache(maxsize=4)
def _pixel_grid_xy_cached(K_bytes: bytes, H: int, W: int) -> tuple[NDArray, NDArray, NDArray]:
    K = np.frombuffer(K_bytes, np.float64).reshape(3, 3)
    u = np.arange(W, dtype=np.float32)[None, :].repeat(H, 0)
    v = np.arange(H, dtype=np.float32)[:, None].repeat(W, 1)
    Kinv = np.linalg.inv(K)
    x = (Kinv[0, 0] * u + Kinv[0, 1] * v + Kinv[0, 2]).astype(np.float32)
    y = (Kinv[1, 1] * v + Kinv[1, 2]).astype(np.float32)
    rays = np.stack([x, y])
    for a in (u, v, rays):
        a.setflags(write=False)
    return u, v, rays


def road_plane_depth(
    rays_xy: NDArray[np.float32], up_cam: NDArray[np.float64], height_m: float
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Z-depth where each ray ``[x, y, 1]`` (``rays_xy`` ``[2, H, W]``, :func:`pixel_grid_xy`)
    meets the road plane ``up . X = -height_m``, and the sine of the ray's angle below the
    horizon; depth is ``inf`` at or above the horizon.

    The one road plane of the prior's road source and the metrizer's road pass.
    """
    x, y = rays_xy
    down = -(up_cam[0] * x + up_cam[1] * y + up_cam[2])  # -up . r with r = [x, y, 1]
    norm = np.sqrt(x * x + y * y + 1.0)
    meets = down > 1e-9  # a ray within 1e-9 of the horizon counts as on it (sine 0, depth inf)
    sin_a = np.where(meets, down / norm, np.minimum(down / norm, 0.0)).astype(np.float32)
    with np.errstate(divide="ignore"):
        z = np.where(meets, np.float32(height_m) / np.maximum(down, 1e-9), np.inf)
    return z.astype(np.float32), sin_a


def up_in_camera(
    T_world_cam: NDArray[np.float64],
    up_world: tuple[float, float, float] | None,
    up_cam_fixed: tuple[float, float, float],
) -> NDArray[np.float64]:
    """Unit "up" in the camera frame: ``R_world_cam^T up_world``, or ``up_cam_fixed`` if None.

    The road plane's orientation, shared by the prior's road source and the metrizer's road pass.
    """
    if up_world is None:
        u = np.asarray(up_cam_fixed, np.float64)
    else:
        T = check_array("T_world_cam", T_world_cam, shape=(4, 4), finite=True)
        u = T[:3, :3].T @ np.asarray(up_world, np.float64)
    n = np.linalg.norm(u)
    if not np.isfinite(n) or n < 1e-9:
        raise ConfigError("up direction: must be finite and non-zero")
    return u / n


def intersect_rays_quadric(
    origins: FloatArray, dirs: FloatArray, A: FloatArray, b: FloatArray, c: float
) -> FloatArray:
    """Nearest ray parameter ``t > 0`` where rays hit ``x^T A x + b^T x + c = 0``; ``inf`` on a miss.

    Covers ellipsoids, spheres and infinite cylinders (A of rank 2). ``A`` is symmetric ``[3, 3]``.
    Solves the quadratic in ``t`` with the cancellation-free formula.
    """
    A = np.asarray(A, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    o = np.broadcast_to(np.asarray(origins, dtype=np.float64), np.shape(dirs))
    d = np.asarray(dirs, dtype=np.float64)
    Ad = d @ A
    qa = np.einsum("ij,ij->i", Ad, d)
    qb = 2.0 * np.einsum("ij,ij->i", Ad, o) + d @ b
    qc = np.einsum("ij,ij->i", o @ A, o) + o @ b + c
    disc = qb * qb - 4.0 * qa * qc
    with np.errstate(divide="ignore", invalid="ignore"):
        sq = np.sqrt(np.maximum(disc, 0.0))
        qq = -0.5 * (qb + np.copysign(sq, qb))
        t1 = qq / qa
        t2 = qc / qq
        lin = np.abs(qa) < 1e-14  # degenerate: ray parallel to the cylinder axis, linear equation
        t_lin = -qc / qb
    t1 = np.where(lin, t_lin, t1)
    t2 = np.where(lin, t_lin, t2)
    t1 = np.where(np.isfinite(t1) & (t1 > 1e-9), t1, np.inf)
    t2 = np.where(np.isfinite(t2) & (t2 > 1e-9), t2, np.inf)
    t = np.minimum(t1, t2)
    return np.where(disc >= 0, t, np.inf)
