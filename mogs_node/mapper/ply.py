"""Standard 3D Gaussian splatting PLY (the layout of Kerbl et al.'s reference code and its viewers).

One binary little-endian ``vertex`` element with float32 properties, in this order:
``x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3``.
Colours are degree-0 spherical-harmonic coefficients (``f_dc = (rgb - 0.5) / C0``,
``C0 = 0.28209479177387814``), ``opacity`` is the logit, ``scale_*`` are log standard deviations,
``rot_*`` is the quaternion w, x, y, z (unnormalised is allowed), normals are zero.

:func:`write_gaussian_ply_stream` writes a map chunk by chunk (the offloaded submaps of a long
drive, :mod:`mogs_node.mapper.submaps`) without holding it in memory; the file is written to a
temporary name and renamed, so a reader never sees half a map.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from plyfile import PlyData

from mogs_node.errors import DatasetError
from mogs_node.geometry import check_array

__all__ = [
    "export_ply",
    "PLY_PROPERTIES",
    "SH_C0",
    "read_gaussian_ply",
    "write_gaussian_ply",
    "write_gaussian_ply_stream",
]

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
    chunk = {
        "means": means,
        "quats_wxyz": quats_wxyz,
        "log_scales": log_scales,
        "opacity_logit": opacity_logit,
        "colors": colors_rgb,
    }
    return write_gaussian_ply_stream(path, len(np.asarray(means)), [chunk])


def _vertex_records(chunk: Mapping[str, np.ndarray]) -> np.ndarray:
    """One chunk (``means`` [n, 3], ``quats_wxyz`` [n, 4], ``log_scales`` [n, 3],
    ``opacity_logit`` [n], ``colors`` [n, 3] in [0, 1]) as PLY vertex records."""
    m = check_array("means", chunk["means"], shape=(None, 3), dtype=np.floating)
    n = len(m)
    q = check_array("quats_wxyz", chunk["quats_wxyz"], shape=(n, 4), dtype=np.floating)
    s = check_array("log_scales", chunk["log_scales"], shape=(n, 3), dtype=np.floating)
    o = check_array("opacity_logit", chunk["opacity_logit"], shape=(n,), dtype=np.floating)
    c = check_array("colors_rgb", chunk["colors"], shape=(n, 3), dtype=np.floating)
    data = np.zeros(n, dtype=[(name, "<f4") for name in PLY_PROPERTIES])
    for i, k in enumerate("xyz"):
        data[k] = m[:, i]
        data[f"scale_{i}"] = s[:, i]
        data[f"f_dc_{i}"] = (c[:, i] - 0.5) / SH_C0
    data["opacity"] = o
    for i in range(4):
        data[f"rot_{i}"] = q[:, i]
    return data


def write_gaussian_ply_stream(
    path: str | Path, n: int, chunks: Iterable[Mapping[str, np.ndarray]]
) -> Path:
    """Write ``n`` Gaussians given as ``chunks`` (each as :func:`_vertex_records` takes it),
    one chunk in memory at a time; the chunks must hold exactly ``n`` rows. Returns the path."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {int(n)}\n"
    header += "".join(f"property float {name}\n" for name in PLY_PROPERTIES) + "end_header\n"
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    written = 0
    try:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            for chunk in chunks:
                data = _vertex_records(chunk)
                written += len(data)
                if written > n:
                    break
                f.write(data.tobytes())
        if written != n:
            raise DatasetError(f"{p}: {written} Gaussians in the chunks, the header says {n}")
        os.replace(tmp, p)
    finally:
        tmp.unlink(missing_ok=True)
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


def export_ply(mapper: Any, path: str) -> None:
    """Write a :class:`~mogs_node.mapper.mapper.GaussianMapper`'s map as a standard 3DGS PLY."""
    prm = {k: v.detach().cpu().numpy() for k, v in mapper.map.params.items()}
    write_gaussian_ply(
        path,
        prm["means"],
        prm["quats_wxyz"],
        prm["log_scales"],
        prm["opacity_logit"],
        prm["colors"],
    )
