"""Mapper checkpoints: the whole state of a :class:`GaussianMapper` in one versioned file.

A checkpoint holds every Gaussian parameter with its id, birth keyframe, observation count and
per-row Adam state (moments and step counts), every keyframe the mapper keeps (image, pose, depth,
confidence, exposure parameters and their Adam state, pose-tangent Adam state, visible ids), the
window, the iteration counter, the pending change log and the random generator's state, plus the
:class:`MapperParams` it ran with. A mapper restored from it renders identically and its next
optimisation step equals that of the mapper that wrote it.

Long drives (:mod:`mogs_node.mapper.submaps`): the keyframes of offloaded regions are stored empty
(their data lives in the submap files, listed in the ``extra`` record the node passes in), and the
Gaussians in RAM are the checkpoint's; a restored mapper plus its submap files is the whole map.

Format (version :data:`CHECKPOINT_VERSION`): ``torch.save`` of a dict holding only tensors, a
JSON string (``meta``) and a SHA-256 digest of both (``sha256``), read back with
``torch.load(weights_only=True)``: no pickled Python objects are ever executed, and a flipped bit
anywhere in the data is detected. Writes go to a temporary file in the same directory, are fsynced and then
renamed over the target, so a crash mid-write leaves the previous checkpoint intact.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mogs_node.errors import ModelError
from mogs_node.mapper.gaussians import PARAM_NAMES, GaussianMap
from mogs_node.mapper.insertion import InsertionParams
from mogs_node.mapper.keyframe import KeyframeState, _SmallAdam
from mogs_node.mapper.mapper import GaussianMapper, MapperParams
from mogs_node.mapper.rasterizer import RasterParams

__all__ = [
    "CHECKPOINT_FORMAT",
    "CHECKPOINT_NAME",
    "CHECKPOINT_VERSION",
    "CheckpointError",
    "integrated_keyframe_ids",
    "latest_checkpoint",
    "load_checkpoint",
    "load_checkpoint_with_extra",
    "save_checkpoint",
]

CHECKPOINT_FORMAT = "mogs-mapper-checkpoint"
CHECKPOINT_VERSION = 2  # 2: keyframe images stored as uint8 (1: f32 in [0, 1], still read)
_READABLE_VERSIONS = (1, 2)
CHECKPOINT_NAME = "mapper.ckpt"  # file name inside a node's checkpoint_dir

_KF_TENSORS = ("image", "depth_m", "confidence", "T_cam_world", "exposure_ab")


class CheckpointError(ModelError):
    """A checkpoint is missing, truncated, corrupt or of another version; names the file."""


def _adam_state(a: _SmallAdam) -> dict[str, Any]:
    return {"m": a.m, "v": a.v}


def _params_to_dict(p: MapperParams) -> dict[str, Any]:
    return dataclasses.asdict(p)


def _params_from_dict(d: dict[str, Any]) -> MapperParams:
    d = dict(d)
    d["raster"] = RasterParams(**d["raster"])
    d["insertion"] = InsertionParams(**d["insertion"])
    return MapperParams(**d)


def _state(mapper: GaussianMapper, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    m = mapper.map
    tensors: dict[str, torch.Tensor] = {
        "map.ids": m.ids,
        "map.steps": m.steps,
        "map.birth_kf": m.birth_kf,
        "map.n_obs": m.n_obs,
        "map.changed": m.changed_ids,
        "map.removed": torch.tensor(sorted(m._removed), dtype=torch.long),
    }
    for k in PARAM_NAMES:
        tensors[f"map.params.{k}"] = m.params[k]
        tensors[f"map.adam_m.{k}"] = m.adam_m[k]
        tensors[f"map.adam_v.{k}"] = m.adam_v[k]
    kfs = []
    for i, kf in enumerate(mapper.keyframes):
        for name in _KF_TENSORS:
            tensors[f"kf{i}.{name}"] = getattr(kf, name)
        tensors[f"kf{i}.visible_ids"] = torch.as_tensor(kf.visible_ids, dtype=torch.long)
        tensors[f"kf{i}.visible_weights"] = torch.as_tensor(kf.visible_weights, dtype=torch.float32)
        for an in ("exposure_adam", "pose_adam"):
            a: _SmallAdam = getattr(kf, an)
            tensors[f"kf{i}.{an}.m"], tensors[f"kf{i}.{an}.v"] = a.m, a.v
        kfs.append(
            {
                "keyframe_id": kf.keyframe_id,
                "index": kf.index,
                "exposure_adam_t": kf.exposure_adam.t,
                "pose_adam_t": kf.pose_adam.t,
                "weights_next_id": kf.weights_next_id,
                "iterations": kf.iterations,
            }
        )
    meta = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "params": _params_to_dict(mapper.params),
        "K": list(mapper.K),
        "width": mapper.width,
        "height": mapper.height,
        "window": list(mapper.window),
        "iterations": mapper.iterations,
        "last_loss": mapper.last_loss,
        "last_psnr_db": mapper.last_psnr_db,
        "n_pruned": mapper.n_pruned,
        "n_densified": mapper.n_densified,
        "next_id": m._next_id,
        "n_gaussians": len(m),
        "keyframes": kfs,
        "integrated_keyframe_ids": sorted(kf.keyframe_id for kf in mapper.keyframes),
        "rng_state": mapper._rng.bit_generator.state,
        "offloaded_kfs": sorted(mapper.offloaded_kfs),
        "extra": extra or {},
    }
    tensors = {k: v.detach().cpu().contiguous().clone() for k, v in tensors.items()}
    meta_json = json.dumps(meta)
    return {"meta": meta_json, "tensors": tensors, "sha256": _digest(meta_json, tensors)}


def _digest(meta_json: str, tensors: dict[str, torch.Tensor]) -> str:
    """SHA-256 over the meta record and every tensor (name, dtype, shape, bytes): torch's zip
    reader does not verify CRCs, so flipped bits in tensor data would otherwise load silently."""
    h = hashlib.sha256(meta_json.encode())
    for k in sorted(tensors):
        t = tensors[k]
        h.update(f"{k}|{t.dtype}|{tuple(t.shape)}".encode())
        h.update(t.contiguous().numpy().tobytes())
    return h.hexdigest()


def save_checkpoint(
    mapper: GaussianMapper, path: str | os.PathLike[str], extra: dict[str, Any] | None = None
) -> Path:
    """Write ``mapper``'s state to ``path`` atomically (temp file, fsync, rename); returns it.
    ``extra``: a JSON record kept beside it (the node's submap store)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = _state(mapper, extra)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(state, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def latest_checkpoint(directory: str | os.PathLike[str]) -> Path | None:
    """The checkpoint a node keeps in ``directory`` (:data:`CHECKPOINT_NAME`), or None."""
    p = Path(directory) / CHECKPOINT_NAME
    return p if p.is_file() else None


def _tensor(t: dict[str, Any], key: str, path: Path, shape: tuple[int | None, ...]) -> torch.Tensor:
    v = t.get(key)
    if not isinstance(v, torch.Tensor):
        raise CheckpointError(f"checkpoint {path}: missing tensor {key!r}")
    if len(v.shape) != len(shape) or any(
        s is not None and s != int(d) for s, d in zip(shape, v.shape, strict=True)
    ):
        raise CheckpointError(
            f"checkpoint {path}: tensor {key!r} has shape {list(v.shape)}, expected {list(shape)}"
        )
    return v


def _keyframe_image(
    t: dict[str, Any], key: str, path: Path, hw: tuple[int, int], version: int
) -> torch.Tensor:
    """The [H, W, 3] uint8 image of a keyframe; version 1 stored u8 / 255 in f32 (exact back).
    An offloaded keyframe (``hw`` (0, 0)) has an empty [0, 0, 0] placeholder."""
    v = _tensor(t, key, path, (0, 0, 0) if hw == (0, 0) else (*hw, 3))
    if version == 1 and v.dtype == torch.float32:
        return (v * 255.0).round().clamp(0, 255).to(torch.uint8)
    if v.dtype != torch.uint8:
        raise CheckpointError(f"checkpoint {path}: tensor {key!r} is {v.dtype}, expected uint8")
    return v


def _read(path: Path) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path}: no such file")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # truncated zip, bad CRC, garbage bytes, forbidden globals
        raise CheckpointError(f"checkpoint {path}: unreadable or corrupt ({err})") from err
    if not isinstance(state, dict) or not isinstance(state.get("meta"), str):
        raise CheckpointError(f"checkpoint {path}: not a mapper checkpoint (no meta record)")
    try:
        meta = json.loads(state["meta"])
    except json.JSONDecodeError as err:
        raise CheckpointError(f"checkpoint {path}: corrupt meta record ({err})") from err
    if not isinstance(meta, dict) or meta.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"checkpoint {path}: not a mapper checkpoint")
    if meta.get("version") not in _READABLE_VERSIONS:
        raise CheckpointError(
            f"checkpoint {path}: version {meta.get('version')!r}, this code reads "
            f"versions {list(_READABLE_VERSIONS)}"
        )
    tensors = state.get("tensors")
    if not isinstance(tensors, dict) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in tensors.items()
    ):
        raise CheckpointError(f"checkpoint {path}: missing or malformed tensors record")
    if state.get("sha256") != _digest(state["meta"], tensors):
        raise CheckpointError(f"checkpoint {path}: corrupt (SHA-256 digest mismatch)")
    return meta, tensors


def load_checkpoint(
    path: str | os.PathLike[str], params: MapperParams | None = None
) -> GaussianMapper:
    """Restore the mapper saved in ``path``.

    ``params``: run on with these settings instead of the saved ones (e.g. another rasterizer
    backend); None keeps the saved ones. Raises :class:`CheckpointError` for a missing, truncated,
    corrupt or wrong-version file.
    """
    return load_checkpoint_with_extra(path, params)[0]


def load_checkpoint_with_extra(
    path: str | os.PathLike[str], params: MapperParams | None = None
) -> tuple[GaussianMapper, dict[str, Any]]:
    """:func:`load_checkpoint`, and the ``extra`` record saved with it (``{}`` if none)."""
    path = Path(path)
    meta, t = _read(path)
    try:
        offloaded = {int(i) for i in meta.get("offloaded_kfs", [])}
        saved_params = _params_from_dict(meta["params"])
        fx, fy, cx, cy = (float(x) for x in meta["K"])
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        W, H, n = int(meta["width"]), int(meta["height"]), int(meta["n_gaussians"])
        mapper = GaussianMapper(params or saved_params, K, W, H)
        gm = GaussianMap()
        gm.ids = _tensor(t, "map.ids", path, (n,))
        for k in PARAM_NAMES:
            shape = tuple(gm.params[k].shape[1:])
            gm.params[k] = _tensor(t, f"map.params.{k}", path, (n, *shape))
            gm.adam_m[k] = _tensor(t, f"map.adam_m.{k}", path, (n, *shape))
            gm.adam_v[k] = _tensor(t, f"map.adam_v.{k}", path, (n, *shape))
        gm.steps = _tensor(t, "map.steps", path, (n,))
        gm.birth_kf = _tensor(t, "map.birth_kf", path, (n,))
        gm.n_obs = _tensor(t, "map.n_obs", path, (n,))
        gm._next_id = int(meta["next_id"])
        gm.set_changed_ids(_tensor(t, "map.changed", path, (None,)))
        gm._removed = set(_tensor(t, "map.removed", path, (None,)).tolist())
        if n and (bool((gm.ids[1:] <= gm.ids[:-1]).any()) or int(gm.ids[-1]) >= gm._next_id):
            raise CheckpointError(f"checkpoint {path}: Gaussian ids are not increasing")
        mapper.map = gm
        for i, rec in enumerate(meta["keyframes"]):
            hw = (0, 0) if i in offloaded else (H, W)  # offloaded: data in its submap file
            kf = KeyframeState(
                keyframe_id=int(rec["keyframe_id"]),
                index=int(rec["index"]),
                image=_keyframe_image(t, f"kf{i}.image", path, hw, int(meta["version"])),
                depth_m=_tensor(t, f"kf{i}.depth_m", path, hw),
                confidence=_tensor(t, f"kf{i}.confidence", path, hw),
                T_cam_world=_tensor(t, f"kf{i}.T_cam_world", path, (4, 4)),
                exposure_ab=_tensor(t, f"kf{i}.exposure_ab", path, (2,)),
                visible_ids=_tensor(t, f"kf{i}.visible_ids", path, (None,)).numpy().copy(),
            )
            # blending-weight records (older files have none: unknown until re-rendered)
            if f"kf{i}.visible_weights" in t:
                kf.visible_weights = (
                    _tensor(t, f"kf{i}.visible_weights", path, (len(kf.visible_ids),))
                    .numpy()
                    .copy()
                )
                kf.weights_next_id = int(rec.get("weights_next_id", 0))
            kf.iterations = int(rec.get("iterations", 0))  # older files: none recorded
            for an, size in (("exposure_adam", 2), ("pose_adam", 6)):
                a = _SmallAdam(size)
                a.m = _tensor(t, f"kf{i}.{an}.m", path, (size,))
                a.v = _tensor(t, f"kf{i}.{an}.v", path, (size,))
                a.t = int(rec[f"{an}_t"])
                setattr(kf, an, a)
            if kf.index != i:
                raise CheckpointError(f"checkpoint {path}: keyframe {i} has index {kf.index}")
            mapper.keyframes.append(kf)
        if mapper.device.type != "cpu":
            gm.to(mapper.device)
            for kf in mapper.keyframes:
                kf.image = kf.image.to(mapper.device)
                kf.depth_m = kf.depth_m.to(mapper.device)
                kf.confidence = kf.confidence.to(mapper.device)
        mapper.window = [int(i) for i in meta["window"]]
        if any(not 0 <= i < len(mapper.keyframes) for i in mapper.window):
            raise CheckpointError(f"checkpoint {path}: window {mapper.window} out of range")
        mapper.iterations = int(meta["iterations"])
        mapper.last_loss = float(meta["last_loss"])
        mapper.last_psnr_db = float(meta["last_psnr_db"])
        mapper.n_pruned = int(meta["n_pruned"])
        mapper.n_densified = int(meta["n_densified"])
        mapper._rng.bit_generator.state = meta["rng_state"]
        mapper.offloaded_kfs = offloaded
        extra = meta.get("extra") or {}
        if not isinstance(extra, dict):
            raise CheckpointError(f"checkpoint {path}: malformed extra record")
    except CheckpointError:
        raise
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f"checkpoint {path}: malformed record ({err!r})") from err
    return mapper, extra


def integrated_keyframe_ids(mapper: GaussianMapper) -> set[int]:
    """Ids of the keyframes ``mapper`` has integrated (after a restore: those in the file)."""
    return {kf.keyframe_id for kf in mapper.keyframes}
