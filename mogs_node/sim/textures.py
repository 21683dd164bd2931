"""World-anchored procedural textures: integer hashing, value noise and cell patterns.

Every function is a pure, vectorised function of world (or primitive-local) coordinates, so the
colour of a surface point is the same from every view (photometric consistency), and the hashed
cells give sharp, trackable corners.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "band_coverage",
    "cell_hash2",
    "cell_hash3",
    "filtered_cell_hash2",
    "filtered_cell_hash3",
    "hash_u01",
    "periodic_band_coverage",
    "value_noise2",
    "value_noise3",
]

_M1 = np.uint32(0x7FEB352D)
_M2 = np.uint32(0x846CA68B)


def _mix(h: np.ndarray) -> np.ndarray:
    h = h ^ (h >> np.uint32(16))
    h = h * _M1
    h = h ^ (h >> np.uint32(15))
    h = h * _M2
    return h ^ (h >> np.uint32(16))


def hash_u01(*ints: np.ndarray, seed: int = 0) -> np.ndarray:
    """Uniform values in ``[0, 1)`` from integer lattice coordinates (same shapes), float32."""
    h = np.full(np.shape(ints[0]), np.uint32(seed * 2654435761 % 2**32), dtype=np.uint32)
    for k, a in enumerate(ints):
        ai = np.asarray(a).astype(np.int64).astype(np.uint32)
        h = _mix(h ^ (ai * np.uint32((0x9E3779B1 + 0x632BE5AB * k) % 2**32)))
    return (h >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))


def cell_hash2(u: np.ndarray, v: np.ndarray, size: float, seed: int = 0) -> np.ndarray:
    """Piecewise-constant hash over square cells of ``size`` (sharp edges and corners)."""
    return hash_u01(np.floor(u / size), np.floor(v / size), seed=seed)


def cell_hash3(
    x: np.ndarray, y: np.ndarray, z: np.ndarray, size: float, seed: int = 0
) -> np.ndarray:
    """Piecewise-constant hash over cubic cells of ``size``."""
    return hash_u01(np.floor(x / size), np.floor(y / size), np.floor(z / size), seed=seed)


def _fade(t: np.ndarray) -> np.ndarray:
    return t * t * (3.0 - 2.0 * t)


def value_noise2(u: np.ndarray, v: np.ndarray, size: float, seed: int = 0) -> np.ndarray:
    """Smooth value noise in ``[0, 1)`` with features of about ``size`` (bilinear, smoothstep)."""
    x, y = np.asarray(u) / size, np.asarray(v) / size
    ix, iy = np.floor(x), np.floor(y)
    fx, fy = _fade((x - ix).astype(np.float32)), _fade((y - iy).astype(np.float32))
    a = hash_u01(ix, iy, seed=seed)
    b = hash_u01(ix + 1, iy, seed=seed)
    c = hash_u01(ix, iy + 1, seed=seed)
    d = hash_u01(ix + 1, iy + 1, seed=seed)
    return (a + (b - a) * fx) * (1 - fy) + (c + (d - c) * fx) * fy


def value_noise3(
    x: np.ndarray, y: np.ndarray, z: np.ndarray, size: float, seed: int = 0
) -> np.ndarray:
    """Smooth 3D value noise in ``[0, 1)`` (trilinear, smoothstep)."""
    p = [np.asarray(a) / size for a in (x, y, z)]
    i = [np.floor(a) for a in p]
    f = [_fade((a - b).astype(np.float32)) for a, b in zip(p, i, strict=True)]
    out = np.zeros(np.shape(p[0]), dtype=np.float32)
    for dx in (0, 1):
        wx = f[0] if dx else 1 - f[0]
        for dy in (0, 1):
            wy = f[1] if dy else 1 - f[1]
            for dz in (0, 1):
                wz = f[2] if dz else 1 - f[2]
                out += wx * wy * wz * hash_u01(i[0] + dx, i[1] + dy, i[2] + dz, seed=seed)
    return out


# ------------------------------------------------------------------------- box-filtered patterns
# A camera pixel integrates light over its footprint; point-sampling sharp patterns would alias
# (staircase edges, corners that jump by whole pixels). These functions return the pattern
# averaged over a box of width ``w`` (the pixel footprint on the surface, same units as the
# coordinates), so edges and corners move smoothly with sub-pixel accuracy across views.


def band_coverage(x: np.ndarray, a: float, b: float, w: np.ndarray) -> np.ndarray:
    """Fraction of ``[x - w/2, x + w/2]`` inside the band ``[a, b]`` (float32)."""
    lo = np.maximum(x - 0.5 * w, a)
    hi = np.minimum(x + 0.5 * w, b)
    return (np.maximum(hi - lo, 0.0) / w).astype(np.float32)


def periodic_band_coverage(
    x: np.ndarray, a: float, b: float, period: float, w: np.ndarray
) -> np.ndarray:
    """Fraction of ``[x - w/2, x + w/2]`` inside the bands ``[a + k period, b + k period]``."""
    width = b - a

    def F(y: np.ndarray) -> np.ndarray:  # integral of the band indicator from a to y
        z = y - a
        k = np.floor(z / period)
        return k * width + np.minimum(z - k * period, width)

    return ((F(x + 0.5 * w) - F(x - 0.5 * w)) / w).astype(np.float32)


def _axis_blend(x: np.ndarray, wn: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cell index, the nearer neighbour's offset (-1/+1) and its box-filter weight on one axis."""
    i = np.floor(x)
    f = x - i
    side = np.where(f < 0.5, -1.0, 1.0)
    dist = np.where(f < 0.5, f, 1.0 - f)
    wgt = np.clip(0.5 - dist / wn, 0.0, 0.5).astype(np.float32)
    return i, side, wgt


def filtered_cell_hash2(
    u: np.ndarray, v: np.ndarray, size: float, w: np.ndarray, seed: int = 0
) -> np.ndarray:
    """:func:`cell_hash2` averaged over a box of width ``w``; tends to 0.5 for tiny cells."""
    wn = np.maximum(np.asarray(w) / size, 1e-6)
    iu, su, au = _axis_blend(np.asarray(u) / size, wn)
    iv, sv, av = _axis_blend(np.asarray(v) / size, wn)
    out = (
        (1 - au) * (1 - av) * hash_u01(iu, iv, seed=seed)
        + au * (1 - av) * hash_u01(iu + su, iv, seed=seed)
        + (1 - au) * av * hash_u01(iu, iv + sv, seed=seed)
        + au * av * hash_u01(iu + su, iv + sv, seed=seed)
    )
    fade = np.clip(wn - 1.0, 0.0, 1.0).astype(np.float32)
    return out * (1 - fade) + 0.5 * fade


def filtered_cell_hash3(
    x: np.ndarray, y: np.ndarray, z: np.ndarray, size: float, w: np.ndarray, seed: int = 0
) -> np.ndarray:
    """:func:`cell_hash3` averaged over a box of width ``w`` (nearest neighbour cell per axis)."""
    wn = np.maximum(np.asarray(w) / size, 1e-6)
    ax = [_axis_blend(np.asarray(c) / size, wn) for c in (x, y, z)]
    out = np.zeros(np.shape(x), dtype=np.float32)
    for bx in (0, 1):
        for by in (0, 1):
            for bz in (0, 1):
                wt = (
                    (ax[0][2] if bx else 1 - ax[0][2])
                    * (ax[1][2] if by else 1 - ax[1][2])
                    * (ax[2][2] if bz else 1 - ax[2][2])
                )
                out += wt * hash_u01(
                    ax[0][0] + bx * ax[0][1],
                    ax[1][0] + by * ax[1][1],
                    ax[2][0] + bz * ax[2][1],
                    seed=seed,
                )
    fade = np.clip(wn - 1.0, 0.0, 1.0).astype(np.float32)
    return out * (1 - fade) + 0.5 * fade
