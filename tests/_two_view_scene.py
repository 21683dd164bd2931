"""A small ray-cast street scene with world-anchored texture, for depth-prior tests.

Ground plane (y = +1.65 m, camera frame y down), two facades (x = -6 m, x = +7 m) and an end wall
(z = 45 m). Images are supersampled 2x2 to limit texture aliasing. Ground-truth z-depth per pixel.
"""

from __future__ import annotations

import numpy as np

from mogs_node.geometry import PinholeCamera, intersect_rays_plane

CAM = PinholeCamera(300.0, 300.0, 239.5, 79.5, 480, 160)
# (normal, offset, two in-plane texture axes): plane n . x + offset = 0 in world.
PLANES = [
    (np.array([0.0, 1.0, 0.0]), -1.65, (0, 2)),  # ground y = 1.65
    (np.array([1.0, 0.0, 0.0]), 6.0, (1, 2)),  # left facade x = -6
    (np.array([1.0, 0.0, 0.0]), -7.0, (1, 2)),  # right facade x = 7
    (np.array([0.0, 0.0, 1.0]), -45.0, (0, 1)),  # end wall z = 45
]


def _texture(a: np.ndarray, b: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = np.zeros_like(a)
    for _ in range(24):
        ang = rng.uniform(0, np.pi)
        freq = rng.uniform(0.4, 3.0)
        ph = rng.uniform(0, 2 * np.pi)
        out += np.sin(2 * np.pi * freq * (np.cos(ang) * a + np.sin(ang) * b) + ph)
    return out / np.sqrt(12.0)


def render(T_world_cam: np.ndarray, cam: PinholeCamera = CAM, ss: int = 2):
    """Grey image ``[H, W]`` uint8 and ground-truth z-depth ``[H, W]`` float64."""
    W, H = cam.width * ss, cam.height * ss
    cam_ss = cam.scaled(W, H)
    rays = cam_ss.pixel_grid_rays().reshape(-1, 3)
    R, o = T_world_cam[:3, :3], T_world_cam[:3, 3]
    dirs = rays @ R.T
    ts = np.stack([intersect_rays_plane(o, dirs, n, off) for n, off, _ in PLANES], -1)
    idx = np.argmin(ts, -1)
    t = ts[np.arange(len(ts)), idx]
    X = o + dirs * t[:, None]
    val = np.zeros(len(X))
    for k, (_, _, (i, j)) in enumerate(PLANES):
        m = idx == k
        val[m] = _texture(X[m, i], X[m, j], seed=k)
    img = (128 + 45 * val).reshape(H, W)
    img = img.reshape(cam.height, ss, cam.width, ss).mean(axis=(1, 3))
    depth = t.reshape(H, W)[ss // 2 :: ss, ss // 2 :: ss]  # z-depth (rays have z = 1)
    return np.clip(img, 0, 255).astype(np.uint8), depth
