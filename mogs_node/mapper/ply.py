"""Standard 3D Gaussian splatting PLY (the layout of Kerbl et al.'s reference code and its viewers).

One binary little-endian ``vertex`` element with float32 properties, in this order:
``x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3``.
Colours are degree-0 spherical-harmonic coefficients (``f_dc = (rgb - 0.5) / C0``,
``C0 = 0.28209479177387814``), ``opacity`` is the logit, ``scale_*`` are log standard deviations,
``rot_*`` is the quaternion w, x, y, z (unnormalised is allowed), normals are zero.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from mogs_node.errors import DatasetError
from mogs_node.geometry import check_array

__all__ = ["PLY_PROPERTIES", "SH_C0", "read_gaussian_ply", "write_gaussian_ply"]

SH_C0 = 0.28209479177387814
PLY_PROPERTIES = (
    "x",
    "y",
    "z",
    "nx",
    "ny",
    "nz",
    "f_dc_0",
    "f_dc_1",
    "f_dc_2",
    "opacity",
    "scale_0",
    "scale_1",
    "scale_2",
    "rot_0",
    "rot_1",
    "rot_2",
    "rot_3",
)


def write_gaussian_ply(
    path: str | Path,
    means: np.ndarray,
    quats_wxyz: np.ndarray,
    log_scales: np.ndarray,
    opacity_logit: np.ndarray,
    colors_rgb: np.ndarray,
) -> Path:
    """Write N Gaussians: ``means`` [N, 3], ``quats_wxyz`` [N, 4], ``log_scales`` [N, 3],
    ``opacity_logit`` [N], ``colors_rgb`` [N, 3] in [0, 1]. Returns the path."""
    m = check_array("means", means, shape=(None, 3), dtype=np.floating)
    n = len(m)
    q = check_array("quats_wxyz", quats_wxyz, shape=(n, 4), dtype=np.floating)
    s = check_array("log_scales", log_scales, shape=(n, 3), dtype=np.floating)
    o = check_array("opacity_logit", opacity_logit, shape=(n,), dtype=np.floating)
    c = check_array("colors_rgb", colors_rgb, shape=(n, 3), dtype=np.floating)
    data = np.zeros(n, dtype=[(name, "<f4") for name in PLY_PROPERTIES])
    for i, k in enumerate("xyz"):
        data[k] = m[:, i]
        data[f"scale_{i}"] = s[:, i]
        data[f"f_dc_{i}"] = (c[:, i] - 0.5) / SH_C0
    data["opacity"] = o
    for i in range(4):
        data[f"rot_{i}"] = q[:, i]
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(data, "vertex")], text=False).write(str(p))
    return p


def read_gaussian_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Read a 3DGS PLY: ``{"means", "quats_wxyz", "log_scales", "opacity_logit", "colors_rgb"}``."""
    try:
        v = PlyData.read(str(path))["vertex"].data
    except (OSError, KeyError, ValueError) as err:
        raise DatasetError(f"{path}: not a readable Gaussian PLY ({err})") from err
    missing = [k for k in PLY_PROPERTIES if k not in v.dtype.names]
    if missing:
        raise DatasetError(f"{path}: missing properties {missing}")

    def cols(names: list[str]) -> np.ndarray:
        return np.stack([np.asarray(v[k], np.float32) for k in names], -1)

    return {
        "means": cols(["x", "y", "z"]),
        "quats_wxyz": cols([f"rot_{i}" for i in range(4)]),
        "log_scales": cols([f"scale_{i}" for i in range(3)]),
        "opacity_logit": np.asarray(v["opacity"], np.float32),
        "colors_rgb": cols([f"f_dc_{i}" for i in range(3)]) * SH_C0 + 0.5,
    }
