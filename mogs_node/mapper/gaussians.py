"""The Gaussian map: parameters of every Gaussian, stable ids, per-Gaussian Adam state, change log.

The map is a struct of tensors, one row per Gaussian, kept apart from any optimiser object so that
rows can be appended and removed at any time (insertion and pruning happen between optimisation
rounds). Optimisation touches only a subset of rows (the Gaussians the keyframe window sees);
:meth:`GaussianMap.adam_step` is Adam (Kingma & Ba 2015) applied to those rows only, with a
per-row step count, so an unseen Gaussian neither moves nor ages.

Every change is logged by id (``changed`` / ``removed``) so that map updates leave as increments
(:meth:`GaussianMap.drain_changes`), never as whole-map copies.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from mogs_node.errors import ShapeError
from mogs_node.mapper.rasterizer import GaussianTensors

__all__ = ["PARAM_NAMES", "GaussianMap", "MapChanges"]

PARAM_NAMES = ("means", "quats_wxyz", "log_scales", "opacity_logit", "colors")
_WIDTH = {"means": 3, "quats_wxyz": 4, "log_scales": 3, "opacity_logit": 0, "colors": 3}


@dataclass
class MapChanges:
    """Gaussians added or changed since the last drain (with their values) and removed ids."""

    ids: np.ndarray  # [N] int64
    means: np.ndarray  # [N, 3] f32
    log_scales: np.ndarray  # [N, 3] f32
    quats_wxyz: np.ndarray  # [N, 4] f32
    opacity_logit: np.ndarray  # [N] f32
    colors: np.ndarray  # [N, 3] f32
    removed_ids: np.ndarray  # [M] int64


class GaussianMap:
    """Mutable map state: float32 tensors (and the per-row bookkeeping) on ``device``."""

    def __init__(self, device: torch.device | str = "cpu") -> None:
        self.device = torch.device(device)
        dev = self.device
        self.ids = torch.zeros(0, dtype=torch.long, device=dev)
        self.params: dict[str, torch.Tensor] = {
            k: torch.zeros((0, w) if w else (0,), device=dev) for k, w in _WIDTH.items()
        }
        self.adam_m = {k: torch.zeros_like(v) for k, v in self.params.items()}
        self.adam_v = {k: torch.zeros_like(v) for k, v in self.params.items()}
        self.steps = torch.zeros(0, dtype=torch.long, device=dev)
        self.birth_kf = torch.zeros(0, dtype=torch.long, device=dev)  # keyframe index at insertion
        self.n_obs = torch.zeros(0, dtype=torch.long, device=dev)  # keyframes that saw it
        self._next_id = 0
        self._dirty = torch.zeros(0, dtype=torch.bool, device=dev)  # row changed since drain
        self._removed: set[int] = set()

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    @property
    def next_id(self) -> int:
        """The id the next added Gaussian gets (ids only grow: every id below it was issued)."""
        return self._next_id

    def to(self, device: torch.device | str) -> GaussianMap:
        """Move every tensor to ``device`` (in place; returns self)."""
        self.device = dev = torch.device(device)
        self.ids, self.steps = self.ids.to(dev), self.steps.to(dev)
        self.birth_kf, self.n_obs = self.birth_kf.to(dev), self.n_obs.to(dev)
        self._dirty = self._dirty.to(dev)
        for d in (self.params, self.adam_m, self.adam_v):
            for k in d:
                d[k] = d[k].to(dev)
        return self

    def tensors(self) -> GaussianTensors:
        """The whole map as :class:`GaussianTensors` (views, no copy)."""
        return GaussianTensors(**{k: self.params[k] for k in PARAM_NAMES})

    def add(self, values: dict[str, torch.Tensor], birth_kf: int) -> torch.Tensor:
        """Append Gaussians; ``values`` holds every name of ``PARAM_NAMES``. Returns new ids [n]."""
        n = int(values["means"].shape[0])
        for k, w in _WIDTH.items():
            want = (n, w) if w else (n,)
            if tuple(values[k].shape) != want:
                raise ShapeError(
                    f"values[{k!r}]: expected shape {list(want)}, got {list(values[k].shape)}"
                )
        dev = self.device
        new_ids = torch.arange(self._next_id, self._next_id + n, dtype=torch.long, device=dev)
        self._next_id += n
        self.ids = torch.cat([self.ids, new_ids])
        for k in PARAM_NAMES:
            v = values[k].detach().to(device=dev, dtype=torch.float32)
            self.params[k] = torch.cat([self.params[k], v])
            self.adam_m[k] = torch.cat([self.adam_m[k], torch.zeros_like(v)])
            self.adam_v[k] = torch.cat([self.adam_v[k], torch.zeros_like(v)])
        self.steps = torch.cat([self.steps, torch.zeros(n, dtype=torch.long, device=dev)])
        self.birth_kf = torch.cat(
            [self.birth_kf, torch.full((n,), birth_kf, dtype=torch.long, device=dev)]
        )
        self.n_obs = torch.cat([self.n_obs, torch.zeros(n, dtype=torch.long, device=dev)])
        self._dirty = torch.cat([self._dirty, torch.ones(n, dtype=torch.bool, device=dev)])
        return new_ids

    def remove(self, mask: torch.Tensor) -> int:
        """Remove the rows where ``mask`` [N] bool is True; returns how many were removed."""
        mask = mask.to(self.device)
        if mask.shape != self.ids.shape:
            raise ShapeError(f"mask: expected shape [{len(self)}], got {list(mask.shape)}")
        n = int(mask.sum())
        if n == 0:
            return 0
        self._removed.update(self.ids[mask].tolist())
        keep = ~mask
        self.ids = self.ids[keep]
        self._dirty = self._dirty[keep]
        for k in PARAM_NAMES:
            self.params[k] = self.params[k][keep]
            self.adam_m[k] = self.adam_m[k][keep]
            self.adam_v[k] = self.adam_v[k][keep]
        self.steps, self.birth_kf, self.n_obs = (
            self.steps[keep],
            self.birth_kf[keep],
            self.n_obs[keep],
        )
        return n

    def adam_step(
        self,
        rows: torch.Tensor,
        grads: dict[str, torch.Tensor],
        lrs: dict[str, float],
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-15,
    ) -> None:
        """One Adam update of the rows ``rows`` [R] with gradients ``grads[name]`` [R, ...]."""
        b1, b2 = betas
        self.steps[rows] += 1
        t = self.steps[rows].to(torch.float32)
        c1 = 1 - b1**t
        c2 = 1 - b2**t
        for k, g in grads.items():
            if g is None:
                continue
            g = torch.nan_to_num(g, nan=0.0, posinf=0.0, neginf=0.0)
            m = self.adam_m[k][rows] * b1 + (1 - b1) * g
            v = self.adam_v[k][rows] * b2 + (1 - b2) * g * g
            self.adam_m[k][rows] = m
            self.adam_v[k][rows] = v
            shape = (-1,) + (1,) * (g.ndim - 1)
            step = lrs[k] * (m / c1.reshape(shape)) / ((v / c2.reshape(shape)).sqrt() + eps)
            self.params[k][rows] -= step
        self._dirty[rows] = True

    def mark_changed(self, rows: torch.Tensor) -> None:
        self._dirty[rows] = True

    @property
    def changed_ids(self) -> torch.Tensor:
        """Ids [M] (ascending) of the rows added or changed since the last drain."""
        return self.ids[self._dirty]

    def set_changed_ids(self, ids: torch.Tensor) -> None:
        """Mark exactly the rows with ``ids`` as changed (restoring a checkpoint)."""
        self._dirty = torch.isin(self.ids, ids.to(self.device))

    def drain_changes(self) -> MapChanges:
        """Rows changed since the last call (by id) and ids removed since then; resets the log."""
        rows = torch.nonzero(self._dirty).flatten()
        changed = self.ids[rows]
        p = {k: self.params[k][rows].cpu().numpy().astype(np.float32) for k in PARAM_NAMES}
        out = MapChanges(
            ids=changed.cpu().numpy().astype(np.int64),
            means=p["means"],
            log_scales=p["log_scales"],
            quats_wxyz=p["quats_wxyz"],
            opacity_logit=p["opacity_logit"],
            colors=p["colors"],
            removed_ids=np.array(sorted(self._removed), dtype=np.int64),
        )
        self._dirty[:] = False
        self._removed.clear()
        return out
