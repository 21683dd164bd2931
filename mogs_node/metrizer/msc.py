"""Stages 5-6 of the metrizer: Algorithm 1 (III-B) for every group of the frame, the absorption of
groups without a shape (departure 11) and the model depth at the CDR samples."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from mogs_node.geometry import pixel_to_normalized
from mogs_node.metrizer import shapes
from mogs_node.metrizer.absorption import absorb_groups
from mogs_node.metrizer.alignment import depth_from_space
from mogs_node.metrizer.cdr_rows import SampleRows
from mogs_node.metrizer.consensus import fit_objects
from mogs_node.metrizer.frame import Frame, ShapeModels, model_agrees, model_depth, object_map
from mogs_node.metrizer.grouping import Merged

__all__ = ["absorb", "fit_shapes", "propagate"]

F64 = NDArray[np.float64]


def fit_shapes(
    fr: Frame, uv: F64, w: F64, mode: str
) -> tuple[ShapeModels, F64 | None, dict[str, int]]:
    """Stage 5, Algorithm 1 (III-B) for every object of ``fr`` (mode ``full`` only): plane,
    cylinder, ellipsoid by RANSAC with the residual of eq. (2), best by eq. (5), accepted with at
    least ``tau |F_k|`` inliers (consensus.py). Sets ``fr.t_abs_m``.

    Returns the accepted models, the features' 3D points ``[N, 3]`` (None when not fitted) and
    the counts ``tried`` / ``skipped`` (costly models skipped) / ``degenerate``.
    """
    p, z, G, K = fr.p, fr.z, fr.G, fr.K
    models = ShapeModels.none(G)
    counts = {"tried": 0, "skipped": 0, "degenerate": 0}
    # T_s(z) = t_abs + t_rel z: the absolute term (set for street scenes) shrinks with the scene:
    # at most t_abs_m * median feature depth / t_abs_ref_depth_m (departure 14)
    cons = p.consensus
    if len(z):
        t_abs = cons.t_abs_m * min(1.0, float(np.median(z)) / p.t_abs_ref_depth_m)
        if t_abs < cons.t_abs_m:
            cons = replace(cons, t_abs_m=t_abs)
    fr.t_abs_m = cons.t_abs_m
    if mode != "full" or not len(z):
        return models, None, counts
    rng = np.random.default_rng(p.seed)
    x_n, y_n = pixel_to_normalized(K, uv[:, 0], uv[:, 1])
    Xf = np.stack([x_n * z, y_n * z, z], 1)
    order = np.argsort(fr.feat_g, kind="stable")
    starts = np.concatenate([[0], np.cumsum(fr.n_feat_g)])
    fits = fit_objects(Xf, w, fr.feat_g, G, rng, cons)
    for g, fit in fits.items():
        counts["tried"] += 1
        counts["skipped"] += int(fit.skipped_costly)
        counts["degenerate"] += int(fit.degenerate)
        if fit.kind == shapes.KIND_NONE:
            continue
        models.kind[g], models.conf[g] = fit.kind, fit.confidence
        models.A[g], models.b[g], models.c[g] = fit.A, fit.b, fit.c
        zi = z[order[starts[g] : starts[g + 1]]][fit.inliers]
        models.zlo[g] = max(zi.min() / p.model_extrapolation, p.d_min_m)
        models.zhi[g] = min(zi.max() * p.model_extrapolation, p.d_max_m)
    return models, Xf, counts


def absorb(
    fr: Frame, ms: Merged, models: ShapeModels, Xf: F64, mode: str
) -> tuple[ShapeModels, NDArray[np.intp], int]:
    """Stage 5b (mode full): groups without a shape join an adjacent shape that explains them;
    updates ``fr`` (groups, features, sky, object map). Returns the models, the samples' groups
    and the number of absorbed groups."""
    p = fr.p
    gg_grid, n_absorbed, obj_to_g = ms.gg_grid, 0, ms.group
    if mode == "full" and p.absorb and (models.kind > 0).any():
        remap = absorb_groups(
            fr,
            ms.group,
            ms.adjacency,
            (models.kind, models.A, models.b, models.c, models.zlo, models.zhi),
            Xf,
            (ms.grid, ms.gg_grid, ms.norm_grid),
        )
        if remap is not None:
            keep_ids, remap = remap
            n_absorbed = fr.G - len(keep_ids)
            obj_to_g = remap[ms.group]
            gg_grid, feat_g = remap[ms.gg_grid], remap[fr.feat_g]
            fr.G = len(keep_ids)
            fr.feat_g, fr.n_feat_g = feat_g, np.bincount(feat_g, minlength=fr.G)
            fr.sky, models = fr.sky[keep_ids], models.take(keep_ids)
    if fr.gobj is None:
        fr.gobj = object_map(obj_to_g, ms.obj_i)
    return models, gg_grid, n_absorbed


def propagate(
    fr: Frame,
    models: ShapeModels,
    grid: NDArray[np.intp],
    gg_grid: NDArray[np.intp],
    norm_grid: F64,
) -> tuple[SampleRows, F64, F64]:
    """Stage 6: model depth by ray-shape intersection at the CDR samples (sky excluded) and
    whether it agrees with the globally aligned prior there."""
    p = fr.p
    keep = ~fr.sky[gg_grid]
    sidx, sg, snorm = grid[keep], gg_grid[keep], norm_grid[keep]
    sx, sc = fr.prior[sidx].astype(np.float64), fr.conf[sidx].astype(np.float64)
    mdepth = np.full(len(sidx), np.inf)
    mi = np.flatnonzero(models.kind[sg] > 0)
    if len(mi):
        mdepth[mi] = model_depth(
            sidx[mi], sg[mi], models.kind, models.A, models.b, models.c, fr.W, fr.K
        )
    d_glob = depth_from_space(snorm, fr.prior_kind, p.d_min_m, p.d_max_m)
    mok = model_agrees(mdepth, models.zlo[sg], models.zhi[sg], d_glob, p.model_prior_gate)
    return SampleRows(sidx, sg, sx, sc, mdepth, mok), snorm, d_glob
