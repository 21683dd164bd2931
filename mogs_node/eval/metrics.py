"""Depth metrics of the paper's Table I (AbsRel, RMSE, delta1), computed on valid pixels only."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["depth_metrics", "depth_metrics_by_range"]


def depth_metrics(
    pred_m: NDArray[np.floating], gt_m: NDArray[np.floating], valid: NDArray[np.bool_] | None = None
) -> dict[str, float]:
    """AbsRel, RMSE [m] and delta1 (< 1.25) over pixels with finite, positive ``gt_m`` and ``pred_m``.

    ``pred_m`` and ``gt_m`` have the same shape; ``valid`` (same shape) further restricts the pixels.
    Returns NaN metrics and ``count = 0`` when no pixel is valid.
    """
    pred = np.asarray(pred_m, dtype=np.float64)
    gt = np.asarray(gt_m, dtype=np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"pred_m shape {pred.shape} != gt_m shape {gt.shape}")
    m = np.isfinite(gt) & (gt > 0) & np.isfinite(pred) & (pred > 0)
    if valid is not None:
        m &= np.asarray(valid, dtype=bool)
    n = int(m.sum())
    if n == 0:
        return {"absrel": float("nan"), "rmse": float("nan"), "delta1": float("nan"), "count": 0}
    p, g = pred[m], gt[m]
    ratio = np.maximum(p / g, g / p)
    return {
        "absrel": float(np.mean(np.abs(p - g) / g)),
        "rmse": float(np.sqrt(np.mean((p - g) ** 2))),
        "delta1": float(np.mean(ratio < 1.25)),
        "count": n,
    }


def depth_metrics_by_range(
    pred_m: NDArray[np.floating],
    gt_m: NDArray[np.floating],
    valid: NDArray[np.bool_] | None = None,
    edges_m: tuple[float, ...] = (0.0, 20.0, 40.0, 80.0),
) -> dict[str, dict[str, float]]:
    """:func:`depth_metrics` per ground-truth depth range, keyed ``"0-20"``, ``"20-40"``, ..."""
    gt = np.asarray(gt_m, dtype=np.float64)
    base = np.ones(gt.shape, bool) if valid is None else np.asarray(valid, dtype=bool)
    out = {}
    for lo, hi in zip(edges_m[:-1], edges_m[1:]):
        out[f"{lo:g}-{hi:g}"] = depth_metrics(pred_m, gt, base & (gt >= lo) & (gt < hi))
    return out
