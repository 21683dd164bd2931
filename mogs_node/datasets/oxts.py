"""KITTI OXTS (GPS/INS) packets and time stamps, converted to poses as the KITTI devkit does.

The devkit (``convertOxtsToPose.m``, also ``pykitti.utils``) maps latitude/longitude to metric
coordinates with a Mercator projection whose scale ``cos(lat0)`` is taken from the first packet, and
the attitude to ``R = Rz(yaw) Ry(pitch) Rx(roll)``. The OXTS body frame is x forward, y left, z up.
"""

from __future__ import annotations

import calendar
import datetime as _dt
from pathlib import Path

import numpy as np

from mogs_node.datasets.base import text_lines
from mogs_node.errors import DatasetError
from mogs_node.geometry import make_T, rotmat_from_rpy

__all__ = [
    "EARTH_RADIUS_M",
    "OXTS_FIELDS",
    "format_kitti_timestamps",
    "oxts_to_poses",
    "parse_kitti_timestamp",
    "read_kitti_timestamps",
    "read_oxts",
]

EARTH_RADIUS_M = 6378137.0

#: the 30 fields of one OXTS packet, in file order (``oxts/dataformat.txt``)
OXTS_FIELDS = (
    "lat",
    "lon",
    "alt",
    "roll",
    "pitch",
    "yaw",
    "vn",
    "ve",
    "vf",
    "vl",
    "vu",
    "ax",
    "ay",
    "az",
    "af",
    "al",
    "au",
    "wx",
    "wy",
    "wz",
    "wf",
    "wl",
    "wu",
    "pos_accuracy",
    "vel_accuracy",
    "navstat",
    "numsats",
    "posmode",
    "velmode",
    "orimode",
)


def parse_kitti_timestamp(text: str) -> int:
    """``'2011-09-26 13:02:25.964389445'`` (UTC) -> int nanoseconds since the Unix epoch."""
    text = text.strip()
    date_part, _, frac = text.partition(".")
    when = _dt.datetime.strptime(date_part, "%Y-%m-%d %H:%M:%S")
    frac_ns = int((frac + "000000000")[:9]) if frac else 0
    if frac and not frac.isdigit():
        raise ValueError(f"bad fractional seconds {frac!r}")
    return calendar.timegm(when.timetuple()) * 1_000_000_000 + frac_ns


def format_kitti_timestamp(t_ns: int) -> str:
    """Inverse of :func:`parse_kitti_timestamp` (nanosecond precision kept)."""
    sec, ns = divmod(int(t_ns), 1_000_000_000)
    when = _dt.datetime.fromtimestamp(sec, tz=_dt.UTC)
    return f"{when:%Y-%m-%d %H:%M:%S}.{ns:09d}"


def format_kitti_timestamps(stamps_ns: np.ndarray) -> str:
    """KITTI ``timestamps.txt`` text for int64 stamps ``[N]``."""
    return "".join(format_kitti_timestamp(int(t)) + "\n" for t in np.asarray(stamps_ns))


def read_kitti_timestamps(path: str | Path) -> np.ndarray:
    """Read a KITTI ``timestamps.txt`` -> int64 ``[N]`` ns; errors name the file and line."""
    p = Path(path)
    out = []
    for i, line in text_lines(p, "timestamps"):
        try:
            out.append(parse_kitti_timestamp(line))
        except ValueError as err:
            raise DatasetError(f"{p}:{i}: bad timestamp {line!r} ({err})") from err
    if not out:
        raise DatasetError(f"{p}: no timestamps")
    return np.asarray(out, dtype=np.int64)


def read_oxts(oxts_dir: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read ``oxts/timestamps.txt`` and ``oxts/data/*.txt``.

    Returns (stamps_ns int64 [N], packets f64 [N, 30]).

    ``oxts_dir`` is the ``oxts`` folder itself or a drive folder that contains it.
    """
    d = Path(oxts_dir)
    if not (d / "timestamps.txt").exists() and (d / "oxts" / "timestamps.txt").exists():
        d = d / "oxts"
    stamps_ns = read_kitti_timestamps(d / "timestamps.txt")
    files = sorted((d / "data").glob("*.txt"))
    if not files:
        raise DatasetError(f"{d / 'data'}: no OXTS packet files")
    if len(files) != len(stamps_ns):
        raise DatasetError(
            f"{d / 'timestamps.txt'}: {len(stamps_ns)} stamps but {len(files)} packets "
            f"in {d / 'data'}"
        )
    packets = np.empty((len(files), len(OXTS_FIELDS)))
    for i, f in enumerate(files):
        vals = f.read_text().split()
        if len(vals) != len(OXTS_FIELDS):
            raise DatasetError(f"{f}:1: expected {len(OXTS_FIELDS)} values, got {len(vals)}")
        try:
            packets[i] = [float(v) for v in vals]
        except ValueError as err:
            raise DatasetError(f"{f}:1: non-numeric value ({err})") from err
    if not np.all(np.isfinite(packets[:, :6])):
        raise DatasetError(f"{d / 'data'}: non-finite lat/lon/alt/roll/pitch/yaw")
    return stamps_ns, packets


def oxts_to_poses(packets: np.ndarray, *, relative: bool = True) -> np.ndarray:
    """OXTS packets ``[N, >=6]`` -> ``T_world_imu`` ``[N, 4, 4]`` exactly as the KITTI devkit does.

    Mercator scale from the first packet's latitude; with ``relative`` (the devkit's default) the
    poses are expressed in the first packet's frame, so ``T[0] = I``.
    """
    P = np.asarray(packets, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] < 6 or len(P) == 0:
        raise DatasetError(f"packets: expected [N, >=6], got {list(P.shape)}")
    lat, lon, alt = P[:, 0], P[:, 1], P[:, 2]
    scale = np.cos(np.deg2rad(lat[0]))
    tx = scale * np.deg2rad(lon) * EARTH_RADIUS_M
    ty = scale * EARTH_RADIUS_M * np.log(np.tan(np.deg2rad(90.0 + lat) / 2.0))
    T = make_T(rotmat_from_rpy(P[:, 3], P[:, 4], P[:, 5]), np.stack([tx, ty, alt], -1))
    if relative:
        T = np.linalg.inv(T[0]) @ T
    return T
