"""Baseline registry for evaluation: every entry takes the inputs of :func:`metrize_depth`.

- ``no_msc_cdr``: one global robust affine alignment of the prior (Table IV, w/o MSC and CDR);
- ``no_msc``: per-mask CDR from the sparse features alone (Table IV, w/o MSC);
- ``interp_nearest``: sparse points only, depth of the nearest feature pixel;
- ``interp_edge_aware``: sparse points only, edge-aware normalised-convolution fill guided by the
  image (fill.py).

Usage: ``BASELINES[name](K=..., labels=..., feature_uv_px=..., ..., params=MetrizerParams())``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from mogs_node.metrizer.fill import edge_aware_fill, nearest_fill
from mogs_node.metrizer.inputs import MetrizerInputs
from mogs_node.metrizer.pipeline import MetrizedDepth, MetrizerParams, metrize_depth

__all__ = ["BASELINES", "interp_edge_aware", "interp_nearest"]


def _sparse(kw: dict[str, Any]):
    p: MetrizerParams = kw.get("params") or MetrizerParams()
    fields_ = {k: v for k, v in kw.items() if k not in ("params", "mode")}
    c = MetrizerInputs(**fields_).checked()
    labels = c.labels
    H, W = labels.shape
    uv, z, w, _, _ = c.sanitised(p.d_min_m, p.d_max_m)
    image = c.image_rgb
    u = np.clip(np.round(uv[:, 0]).astype(np.intp), 0, W - 1)
    v = np.clip(np.round(uv[:, 1]).astype(np.intp), 0, H - 1)
    return p, labels, u, v, z, image


def _wrap(depth: np.ndarray, labels: np.ndarray, p: MetrizerParams, conf: float, t0: float):
    d = np.where(np.isfinite(depth) & (depth > 0), np.clip(depth, p.d_min_m, p.d_max_m), 0.0)
    d = d.astype(np.float32)
    return MetrizedDepth(
        depth_m=d,
        confidence=np.where(d > 0, conf, 0.0).astype(np.float32),
        object_labels=np.zeros(labels.shape, np.int32),
        object_model=np.zeros(1, np.int8),
        stats={"ms": {"total": (time.perf_counter() - t0) * 1e3}},
    )


def interp_nearest(**kw: Any) -> MetrizedDepth:
    """Nearest-feature depth everywhere (sparse points only; the prior is ignored)."""
    t0 = time.perf_counter()
    p, labels, u, v, z, _ = _sparse(kw)
    return _wrap(nearest_fill(labels.shape, u, v, z.astype(np.float32)), labels, p, 0.1, t0)


def interp_edge_aware(**kw: Any) -> MetrizedDepth:
    """Edge-aware (image-guided) fill of the sparse points (the prior is ignored)."""
    t0 = time.perf_counter()
    p, labels, u, v, z, image = _sparse(kw)
    seed = np.zeros(labels.shape, np.float32)
    wt = np.zeros(labels.shape, np.float32)
    seed[v, u] = z
    wt[v, u] = 1.0
    f = edge_aware_fill(seed, wt, image, p.fill_scale, p.fill_lambda, p.fill_sigma_color)
    return _wrap(f, labels, p, 0.1, t0)


def _mode(mode: str) -> Callable[..., MetrizedDepth]:
    def run(**kw: Any) -> MetrizedDepth:
        return metrize_depth(**kw, mode=mode)

    run.__name__ = f"metrize_{mode}"
    run.__doc__ = f"metrize_depth(mode={mode!r})"
    return run


BASELINES: dict[str, Callable[..., MetrizedDepth]] = {
    "full": _mode("full"),
    "no_msc": _mode("no_msc"),
    "no_msc_cdr": _mode("no_msc_cdr"),
    "interp_nearest": interp_nearest,
    "interp_edge_aware": interp_edge_aware,
}
