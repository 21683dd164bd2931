"""The map: point clouds of Gaussian centres and map statistics as diagnostics."""

from __future__ import annotations

from typing import Any

import numpy as np

from bridges.ros_convert.base import (
    _T,
    Distro,
    header,
    ros_stamp_ns,
)
from mogs_node import msgs
from mogs_node.errors import MessageError

# ------------------------------------------------------------------------------ point clouds

#: sensor_msgs/PointField datatypes -> numpy
_PF_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def pointcloud_to_ros(
    xyz_world_m: np.ndarray,
    rgb: np.ndarray | None,
    *,
    stamp_ns: int,
    frame_id: str = "world",
    distro: Distro = Distro.ROS2,
) -> Any:
    """Points ``xyz_world_m`` [N, 3] with colours ``rgb`` [N, 3] (float in [0, 1] or uint8) ->
    unorganised ``sensor_msgs/PointCloud2``: fields x, y, z (float32, offsets 0, 4, 8) and rgb
    (offset 12: uint32 0x00RRGGBB stored as FLOAT32, as PCL and RViz read it), point_step 16."""
    xyz = np.asarray(xyz_world_m)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not np.isfinite(xyz).all():
        raise MessageError(f"expected finite [N, 3] points, got {xyz.shape}", field="xyz_world_m")
    n = len(xyz)
    rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    fields = ["x", "y", "z"]
    if rgb is not None:
        c = np.asarray(rgb)
        if c.shape != (n, 3):
            raise MessageError(f"expected [{n}, 3] colours, got {c.shape}", field="rgb")
        if c.dtype != np.uint8:
            c = np.round(np.clip(np.nan_to_num(c.astype(np.float64)), 0.0, 1.0) * 255)
        c = c.astype(np.uint32)
        rec["rgb"] = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
        fields.append("rgb")
    PF = _T(distro, "sensor_msgs/msg/PointField")
    pfields = [PF(name=f, offset=4 * i, datatype=PF.FLOAT32, count=1) for i, f in enumerate(fields)]
    return _T(distro, "sensor_msgs/msg/PointCloud2")(
        header=header(stamp_ns, frame_id, distro),
        height=1,
        width=n,
        fields=pfields,
        is_bigendian=False,
        point_step=16,
        row_step=16 * n,
        data=rec.view(np.uint8).reshape(-1),
        is_dense=True,
    )


def pointcloud_from_ros(ros: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """``sensor_msgs/PointCloud2`` -> (``xyz`` float32 [N, 3], ``rgb`` uint8 [N, 3] or None).

    Reads any layout: field offsets and datatypes as declared, ``point_step`` / ``row_step``
    padding, organised clouds (N = height * width), big-endian data; ``rgb`` or ``rgba`` packed
    in 4 bytes (FLOAT32 or UINT32). Points with a non-finite coordinate are dropped."""
    h, w = int(ros.height), int(ros.width)
    pstep, rstep = int(ros.point_step), int(ros.row_step)
    fields = {f.name: f for f in ros.fields}
    missing = [f for f in ("x", "y", "z") if f not in fields]
    if missing:
        raise MessageError(f"no field(s) {missing} (fields: {sorted(fields)})", field="fields")
    order = ">" if ros.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for name in ("x", "y", "z", "rgb" if "rgb" in fields else "rgba"):
        f = fields.get(name)
        if f is None:
            continue
        if int(f.datatype) not in _PF_DTYPES:
            raise MessageError(f"unknown datatype {f.datatype}", field=f"fields.{name}")
        dt = np.dtype(order + _PF_DTYPES[int(f.datatype)])
        if name in ("rgb", "rgba"):
            dt = np.dtype(order + "u4")
            if int(f.datatype) not in (6, 7):
                raise MessageError("packed colour must be 4 bytes", field=f"fields.{name}")
        if int(f.offset) < 0 or int(f.offset) + dt.itemsize > pstep:
            raise MessageError(
                f"offset {f.offset} + {dt.itemsize} bytes exceeds point_step {pstep}",
                field=f"fields.{name}",
            )
        names.append(name)
        formats.append(dt)
        offsets.append(int(f.offset))
    data = np.asarray(ros.data, dtype=np.uint8).reshape(-1)
    if h < 0 or w < 0 or pstep <= 0 or (h * w and rstep < w * pstep) or data.size < h * rstep:
        raise MessageError(
            f"{data.size} bytes do not hold {h}x{w} points of {pstep} bytes, row_step {rstep}",
            field="data",
        )
    rows = data[: h * rstep].reshape(h, rstep)[:, : w * pstep]
    rec_dt = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": pstep})
    rec = np.ascontiguousarray(rows).view(rec_dt).reshape(-1)
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float32)
    keep = np.isfinite(xyz).all(axis=1)
    rgb = None
    if len(names) == 4:
        packed = rec[names[3]].astype(np.uint32)[keep]
        rgb = np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], 1)
        rgb = rgb.astype(np.uint8)
    return xyz[keep], rgb


# --------------------------------------------------------------------------------- map stats

_STATS_FIELDS = ("keyframe_id", "n_gaussians", "n_keyframes", "iterations", "loss", "psnr_db")


def mapstats_to_ros(
    msg: msgs.MapStats, *, name: str = "mogs/mapper", distro: Distro = Distro.ROS2
) -> Any:
    """``MapStats`` -> ``diagnostic_msgs/DiagnosticArray``: one status ``name`` whose values are
    the fields and ``extra`` entries (``repr`` of each number, so floats round-trip)."""
    msg.validate()
    KV = _T(distro, "diagnostic_msgs/msg/KeyValue")
    values = [KV(key=k, value=repr(getattr(msg, k))) for k in _STATS_FIELDS]
    values += [KV(key=f"extra.{k}", value=repr(v)) for k, v in sorted(msg.extra.items())]
    Status = _T(distro, "diagnostic_msgs/msg/DiagnosticStatus")
    status = Status(
        level=Status.OK,
        name=name,
        message=f"keyframe {msg.keyframe_id}",
        hardware_id="",
        values=values,
    )
    return _T(distro, "diagnostic_msgs/msg/DiagnosticArray")(
        header=header(msg.stamp_ns, msg.frame_id, distro), status=[status]
    )


def _number(text: str, key: str) -> int | float:
    try:
        return int(text)
    except ValueError:
        try:
            return float(text)
        except ValueError as err:
            raise MessageError(f"value {text!r} is not a number", field=key) from err


def mapstats_from_ros(ros: Any) -> msgs.MapStats:
    """Inverse of :func:`mapstats_to_ros` (first status of the array)."""
    if not ros.status:
        raise MessageError("DiagnosticArray without a status", field="status")
    vals = {kv.key: kv.value for kv in ros.status[0].values}
    missing = [k for k in _STATS_FIELDS if k not in vals]
    if missing:
        raise MessageError(f"missing key(s) {missing}", field="values")
    f = {k: _number(vals[k], k) for k in _STATS_FIELDS}
    extra = {k[6:]: _number(v, k) for k, v in vals.items() if k.startswith("extra.")}
    out = msgs.MapStats(
        stamp_ns=ros_stamp_ns(ros.header),
        frame_id=ros.header.frame_id,
        keyframe_id=int(f["keyframe_id"]),
        n_gaussians=int(f["n_gaussians"]),
        n_keyframes=int(f["n_keyframes"]),
        iterations=int(f["iterations"]),
        loss=float(f["loss"]),
        psnr_db=float(f["psnr_db"]),
        extra=extra,
    )
    out.validate()
    return out
