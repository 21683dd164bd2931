"""Large scenes at flat cost: regions the vehicle has left leave RAM for disk (issue 17, item 3).

The map is cut into submaps by distance travelled: keyframe ``i`` belongs to submap
``floor(path_m[i] / length_m)`` and every Gaussian to the submap of the keyframe it was born at
(``GaussianMap.birth_kf``). After each keyframe, a closed submap (the vehicle is in a later one)
that no window keyframe belongs to and whose keyframes are all farther than
``offload_distance_m`` from the camera is *offloaded*: its Gaussians (every per-row tensor of the
map: parameters, Adam moments, step counts, bookkeeping) and its keyframes' images, depth,
confidence and visibility records are written to one file and dropped from RAM. Before a new
keyframe is inserted, any offloaded submap with a keyframe nearer than ``reload_distance_m``
(< ``offload_distance_m``: hysteresis) comes back, so that a vehicle that returns finds its map
(no duplicate Gaussians inserted over it). RAM therefore holds the neighbourhood of the vehicle,
not the drive, and every window iteration, pruning pass and insertion render touches only that:
the per-iteration frustum cull (:meth:`GaussianMapper._visible_rows`) runs over a bounded set.

Offloading is exact: a submap written and read back gives the same rows (bit for bit) in the same
id order; rows leave without being logged as removed, so the incremental map updates of
``/mapper/gaussians`` (which already carried them) stay valid. The final PLY streams every
offloaded submap, then the rows in RAM (:func:`write_map_ply`).

Files are never overwritten: each offload writes a new generation, and an older one is deleted
only when no saved checkpoint refers to it (:meth:`SubmapStore.pin`), so a checkpoint and its
submap files always belong together (``--resume`` after an offload, tests).

No bus and no node state: functions over the mapper's tensors, plus a small store of file names.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import math
import os
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mogs_node.errors import ConfigError, ModelError
from mogs_node.mapper.gaussians import PARAM_NAMES, GaussianMap
from mogs_node.mapper.mapper import GaussianMapper
from mogs_node.mapper.ply import write_gaussian_ply_stream

__all__ = [
    "SubmapParams",
    "SubmapStore",
    "put_rows",
    "take_rows",
    "write_map_ply",
]

log = logging.getLogger(__name__)

#: per-row tensors of a :class:`GaussianMap` (attribute names; dicts hold one per parameter)
_ROW_TENSORS = ("ids", "steps", "birth_kf", "n_obs", "_dirty")
_ROW_DICTS = ("params", "adam_m", "adam_v")
#: what an offloaded keyframe leaves on disk (its pose and exposure stay in RAM: a few bytes)
_KF_TENSORS = ("image", "depth_m", "confidence")
_KF_ARRAYS = ("visible_ids", "visible_weights")
SUBMAP_FORMAT = "mogs-submap"


class SubmapError(ModelError):
    """A submap file is missing or does not hold what its store says; names the file."""


@dataclass(frozen=True)
class SubmapParams:
    """When regions leave RAM and come back (metres of camera position / distance travelled)."""

    length_m: float = 50.0  # distance travelled per submap
    offload_distance_m: float = 150.0  # a closed submap farther than this leaves RAM (0: never)
    reload_distance_m: float = 100.0  # an offloaded one nearer than this comes back
    # Gaussians kept in RAM at most (0: no bound): beyond it, closed submaps farther than
    # reload_distance_m leave too, the farthest first (a dense stretch of road would otherwise
    # hold several times a sparse one's Gaussians within offload_distance_m)
    max_gaussians_in_ram: int = 0

    def __post_init__(self) -> None:
        if not (self.length_m > 0 and math.isfinite(self.length_m)):
            raise ConfigError(f"submaps.length_m: must be > 0, got {self.length_m}")
        if self.offload_distance_m < 0 or not math.isfinite(self.offload_distance_m):
            raise ConfigError("submaps.offload_distance_m: must be >= 0 (0: never offload)")
        if self.max_gaussians_in_ram < 0:
            raise ConfigError(
                f"submaps.max_gaussians_in_ram: must be >= 0 (0: no bound), got "
                f"{self.max_gaussians_in_ram}"
            )
        if self.offload_distance_m and not (0 <= self.reload_distance_m < self.offload_distance_m):
            raise ConfigError(
                "submaps: need 0 <= reload_distance_m < offload_distance_m (hysteresis), got "
                f"{self.reload_distance_m} and {self.offload_distance_m}"
            )

    @property
    def enabled(self) -> bool:
        return self.offload_distance_m > 0


# ---------------------------------------------------------------------------------- map rows


def _check_known_fields(gm: GaussianMap) -> None:
    """Every per-row tensor of the map must be one this module moves: a new field would otherwise
    be silently cut out of step with the others."""
    n = len(gm)
    for name, value in vars(gm).items():
        row_like = isinstance(value, torch.Tensor) and value.ndim and value.shape[0] == n
        if row_like and n > 0 and name not in _ROW_TENSORS:
            raise SubmapError(f"GaussianMap.{name}: a per-row tensor submaps.py does not move")


def take_rows(gm: GaussianMap, mask: torch.Tensor) -> dict[str, torch.Tensor]:
    """Remove the rows where ``mask`` [N] bool is True from ``gm`` *without* logging them as
    removed; returns them (CPU copies) by name (``ids``, ``params.means``, ``adam_m.colors``...)."""
    _check_known_fields(gm)
    mask = mask.to(gm.device)
    if mask.shape != gm.ids.shape or mask.dtype != torch.bool:
        raise SubmapError(f"mask: expected bool [{len(gm)}], got {mask.dtype} {list(mask.shape)}")
    keep = ~mask
    out: dict[str, torch.Tensor] = {}
    for name in _ROW_TENSORS:
        t = getattr(gm, name)
        out[name] = t[mask].cpu().clone()
        setattr(gm, name, t[keep])
    for dname in _ROW_DICTS:
        d = getattr(gm, dname)
        for k in PARAM_NAMES:
            out[f"{dname}.{k}"] = d[k][mask].cpu().clone()
            d[k] = d[k][keep]
    return out


def put_rows(gm: GaussianMap, rows: dict[str, torch.Tensor]) -> int:
    """Insert rows taken by :func:`take_rows` back into ``gm``, keeping ids ascending (the map's
    invariant: rows are looked up by ``searchsorted``); returns how many. Ids already in the map
    raise :class:`SubmapError` (a submap loaded twice)."""
    n = int(rows["ids"].shape[0])
    if n == 0:
        return 0
    new_ids = rows["ids"].to(gm.device)
    if len(gm) and bool(torch.isin(new_ids, gm.ids).any()):
        raise SubmapError("put_rows: some ids are already in the map")
    order = torch.argsort(torch.cat([gm.ids, new_ids]), stable=True)
    for name in _ROW_TENSORS:
        t = getattr(gm, name)
        setattr(gm, name, torch.cat([t, rows[name].to(device=gm.device, dtype=t.dtype)])[order])
    for dname in _ROW_DICTS:
        d = getattr(gm, dname)
        for k in PARAM_NAMES:
            v = rows[f"{dname}.{k}"].to(device=gm.device, dtype=d[k].dtype)
            d[k] = torch.cat([d[k], v])[order]
    return n


def _trim_heap() -> None:
    """Give freed heap pages back to the system (glibc keeps them otherwise; RSS would not drop)."""
    with contextlib.suppress(OSError, AttributeError):  # not glibc
        ctypes.CDLL("libc.so.6").malloc_trim(0)


# ---------------------------------------------------------------------------------- the store


class SubmapStore:
    """Which keyframe belongs to which submap, which submaps are on disk, and their files.

    ``directory``: where submap files go (a node's ``checkpoint_dir/submaps`` so that a resumed
    run finds them; None: a temporary folder removed by :meth:`close`).
    """

    def __init__(self, params: SubmapParams, directory: str | os.PathLike[str] | None) -> None:
        self.params = params
        self._own_dir = directory is None
        self.directory = Path(directory or tempfile.mkdtemp(prefix="mogs-submaps-"))
        self.directory.mkdir(parents=True, exist_ok=True)
        self.path_m: list[float] = []  # distance travelled at each keyframe index
        self.centres: list[np.ndarray] = []  # camera centre [3] of each keyframe index
        self.offloaded: dict[int, str] = {}  # submap -> file name (in directory)
        self.counts: dict[int, int] = {}  # submap -> Gaussians in its file
        self._generation = 0
        self._pinned: set[str] = set()  # files the latest checkpoint refers to
        self.counters = {
            "offloads": 0,
            "offloads_for_count": 0,
            "reloads": 0,
            "gaussians_offloaded": 0,
        }

    # -------------------------------------------------------------------- bookkeeping
    def submap_of(self, index: int) -> int:
        return int(self.path_m[index] // self.params.length_m)

    def add_keyframe(self, index: int, T_world_cam: np.ndarray) -> None:
        """Record keyframe ``index`` (in insertion order) at pose ``T_world_cam`` [4, 4]."""
        if index != len(self.path_m):
            raise SubmapError(f"keyframe index {index}: expected {len(self.path_m)} (in order)")
        c = np.asarray(T_world_cam, np.float64)[:3, 3].copy()
        step = float(np.linalg.norm(c - self.centres[-1])) if self.centres else 0.0
        self.path_m.append((self.path_m[-1] if self.path_m else 0.0) + step)
        self.centres.append(c)

    def _members(self) -> dict[int, list[int]]:
        out: dict[int, list[int]] = {}
        for i in range(len(self.path_m)):
            out.setdefault(self.submap_of(i), []).append(i)
        return out

    def _distance(self, kfs: list[int], position: np.ndarray) -> float:
        c = np.stack([self.centres[i] for i in kfs])
        return float(np.min(np.linalg.norm(c - position[None], axis=1)))

    @property
    def gaussians_on_disk(self) -> int:
        return int(sum(self.counts.values()))

    # -------------------------------------------------------------------- offload / reload
    def offload_far(self, mapper: GaussianMapper, position: np.ndarray) -> list[int]:
        """Offload every closed submap far from ``position`` [3] (see the module doc), then, while
        the map holds more than ``max_gaussians_in_ram``, the farthest closed ones beyond
        ``reload_distance_m`` (nearer ones would come back at the next keyframe); returns the
        submaps offloaded. Call between keyframes, after the map changes were drained."""
        p = self.params
        if not p.enabled or not self.path_m:
            return []
        current = self.submap_of(len(self.path_m) - 1)
        in_window = {self.submap_of(i) for i in mapper.window}
        closed = [
            (self._distance(kfs, position), s, kfs)
            for s, kfs in sorted(self._members().items())
            if s < current and s not in in_window and s not in self.offloaded
        ]
        done = []
        for d, s, kfs in closed:
            if d > p.offload_distance_m:
                self._offload(mapper, s, kfs)
                done.append(s)
        if p.max_gaussians_in_ram:
            for d, s, kfs in sorted(closed, key=lambda c: -c[0]):
                if len(mapper.map) <= p.max_gaussians_in_ram or d <= p.reload_distance_m:
                    break
                if s not in self.offloaded:
                    self._offload(mapper, s, kfs)
                    self.counters["offloads_for_count"] += 1
                    done.append(s)
        if done:
            _trim_heap()
        return done

    def reload_near(self, mapper: GaussianMapper, position: np.ndarray) -> list[int]:
        """Bring back every offloaded submap with a keyframe within ``reload_distance_m`` of
        ``position`` [3]; returns them. Call before inserting a keyframe taken there."""
        if not self.offloaded:
            return []
        members = self._members()
        back = [
            s
            for s in sorted(self.offloaded)
            if self._distance(members[s], position) < self.params.reload_distance_m
        ]
        for s in back:
            self._reload(mapper, s, members[s])
        return back

    def reload_all(self, mapper: GaussianMapper) -> None:
        """Every submap back in RAM (tests; a final pass over the whole map)."""
        members = self._members()
        for s in sorted(self.offloaded):
            self._reload(mapper, s, members[s])

    def _offload(self, mapper: GaussianMapper, s: int, kfs: list[int]) -> None:
        gm = mapper.map
        birth = gm.birth_kf
        mask = torch.isin(birth, torch.as_tensor(kfs, dtype=birth.dtype, device=birth.device))
        rows = take_rows(gm, mask)
        kf_data: dict[str, Any] = {}
        for i in kfs:
            kf = mapper.keyframes[i]
            for name in _KF_TENSORS:
                t = getattr(kf, name)
                kf_data[f"kf{i}.{name}"] = t.cpu().clone()
                setattr(kf, name, t.new_zeros((0,) * t.ndim))
            for name in _KF_ARRAYS:
                a = getattr(kf, name)
                kf_data[f"kf{i}.{name}"] = torch.as_tensor(np.array(a, copy=True))
                setattr(kf, name, a[:0].copy())
            kf.train_targets = None  # derived: rebuilt on use
        self._generation += 1
        name = f"submap_{s:05d}_{self._generation:06d}.pt"
        payload = {"format": SUBMAP_FORMAT, "submap": s, "keyframes": list(kfs)}
        payload["tensors"] = {**rows, **kf_data}
        tmp = self.directory / f".{name}.tmp"
        torch.save(payload, tmp)
        os.replace(tmp, self.directory / name)
        self.offloaded[s] = name
        self.counts[s] = int(rows["ids"].shape[0])
        mapper.offloaded_kfs.update(kfs)
        self.counters["offloads"] += 1
        self.counters["gaussians_offloaded"] += self.counts[s]
        log.debug("submap %d offloaded: %d Gaussians, %d keyframes", s, self.counts[s], len(kfs))

    def _read(self, s: int) -> dict[str, Any]:
        path = self.directory / self.offloaded[s]
        try:
            payload = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as err:
            raise SubmapError(f"submap file {path}: unreadable ({err})") from err
        if not isinstance(payload, dict) or payload.get("format") != SUBMAP_FORMAT:
            raise SubmapError(f"submap file {path}: not a submap")
        if int(payload["submap"]) != s:
            raise SubmapError(f"submap file {path}: holds submap {payload['submap']}, not {s}")
        return payload

    def _reload(self, mapper: GaussianMapper, s: int, kfs: list[int]) -> None:
        payload = self._read(s)
        t = payload["tensors"]
        rows = {k: v for k, v in t.items() if not k.startswith("kf")}
        put_rows(mapper.map, rows)
        dev = mapper.device
        for i in payload["keyframes"]:
            kf = mapper.keyframes[int(i)]
            for name in _KF_TENSORS:
                setattr(kf, name, t[f"kf{i}.{name}"].to(dev))
            for name in _KF_ARRAYS:
                setattr(kf, name, t[f"kf{i}.{name}"].numpy().copy())
        mapper.offloaded_kfs.difference_update(int(i) for i in payload["keyframes"])
        stale = self.offloaded.pop(s)
        self.counts.pop(s)
        self._drop_unpinned(stale)
        self.counters["reloads"] += 1
        log.debug("submap %d reloaded (%d keyframes)", s, len(kfs))

    def _drop_unpinned(self, name: str) -> None:
        if name not in self._pinned:
            (self.directory / name).unlink(missing_ok=True)

    # -------------------------------------------------------------------- the whole map
    def iter_offloaded(self) -> Iterator[dict[str, np.ndarray]]:
        """The parameters (``PARAM_NAMES`` -> numpy) of each offloaded submap, one at a time."""
        for s in sorted(self.offloaded):
            t = self._read(s)["tensors"]
            yield {k: t[f"params.{k}"].numpy() for k in PARAM_NAMES}

    # -------------------------------------------------------------------- checkpoints
    def state(self) -> dict[str, Any]:
        """What a checkpoint records (JSON); :meth:`pin` once it is written."""
        return {
            "params": {
                "length_m": self.params.length_m,
                "offload_distance_m": self.params.offload_distance_m,
                "reload_distance_m": self.params.reload_distance_m,
                "max_gaussians_in_ram": self.params.max_gaussians_in_ram,
            },
            "path_m": list(self.path_m),
            "centres": [c.tolist() for c in self.centres],
            "offloaded": {str(k): v for k, v in self.offloaded.items()},
            "counts": {str(k): v for k, v in self.counts.items()},
            "generation": self._generation,
        }

    def pin(self) -> None:
        """A checkpoint referring to the current files was written: older ones can go."""
        self._pinned = set(self.offloaded.values())
        for f in self.directory.glob("submap_*.pt"):
            if f.name not in self._pinned:
                f.unlink(missing_ok=True)

    def restore(self, state: dict[str, Any], mapper: GaussianMapper) -> None:
        """Take over a checkpoint's record (after :func:`load_checkpoint`); its files must be in
        ``directory``. Files no checkpoint refers to (written after it) are deleted."""
        try:
            self.path_m = [float(x) for x in state["path_m"]]
            self.centres = [np.asarray(c, np.float64) for c in state["centres"]]
            self.offloaded = {int(k): str(v) for k, v in state["offloaded"].items()}
            self.counts = {int(k): int(v) for k, v in state["counts"].items()}
            self._generation = int(state["generation"])
        except (KeyError, TypeError, ValueError) as err:
            raise SubmapError(f"checkpoint: malformed submap record ({err!r})") from err
        if len(self.path_m) != len(mapper.keyframes):
            raise SubmapError(
                f"checkpoint: submap record has {len(self.path_m)} keyframes, "
                f"the map {len(mapper.keyframes)}"
            )
        for name in self.offloaded.values():
            if not (self.directory / name).is_file():
                raise SubmapError(f"checkpoint: submap file {self.directory / name} is missing")
        self.pin()

    def close(self) -> None:
        """Remove a temporary folder (a user's ``submap_dir`` is left alone)."""
        if self._own_dir:
            for f in self.directory.glob("*"):
                f.unlink(missing_ok=True)
            with contextlib.suppress(OSError):
                self.directory.rmdir()


def write_map_ply(mapper: GaussianMapper, store: SubmapStore | None, path: str | Path) -> int:
    """Write the whole map as one 3DGS PLY, streaming each offloaded submap from disk (never all
    of it in RAM at once), then the rows in RAM; returns the number of Gaussians written."""
    prm = {k: v.detach().cpu().numpy() for k, v in mapper.map.params.items()}
    chunks: list[Any] = []
    n = len(mapper.map)
    if store is not None:
        n += store.gaussians_on_disk
        chunks.append(store.iter_offloaded())
    chunks.append(iter([prm]))

    def all_chunks() -> Iterator[dict[str, np.ndarray]]:
        for it in chunks:
            yield from it

    write_gaussian_ply_stream(path, n, all_chunks())
    return n
