"""Stage 4 of the metrizer: the groups after multi-scale merging (III-B), the CDR sample pixels
and the sky groups; the sky's prior value that pins the global shift (departure "The sky pins the
shift", docs/metrizer.md)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mogs_node.depth_kind import DepthKind
from mogs_node.group_stats import group_medians
from mogs_node.metrizer.association import boundary_pairs, region_adjacency
from mogs_node.metrizer.frame import far_and_norm
from mogs_node.metrizer.global_fit import GlobalFit
from mogs_node.metrizer.merging import merge_undersupported
from mogs_node.metrizer.params import MetrizerParams

__all__ = ["Merged", "merge_and_sample", "sky_value"]

F64 = NDArray[np.float64]


@dataclass
class Merged:
    """Stage 4: groups after multi-scale merging, the CDR sample grid and the sky groups."""

    group: NDArray[np.intp]  # [n_obj] object -> group
    obj_i: NDArray[np.intp]  # [HW] object of each pixel
    G: int  # number of groups
    n_merges: int
    pairs: Any  # boundary pixel pairs (None in mode no_msc_cdr)
    adjacency: tuple | None  # (adj_k, adj_l) region adjacency, mode full
    feat_g: NDArray[np.intp]  # [N] group of each feature
    n_feat_g: NDArray[np.int64]  # [G]
    grid: NDArray[np.intp]  # [S] CDR sample pixels (with a prior)
    gg_grid: NDArray[np.intp]  # [S] their group
    norm_grid: F64  # [S] globally aligned prior at them, normalised space
    sky: NDArray[np.bool_]  # [G]


def merge_and_sample(
    p: MetrizerParams,
    mode: str,
    obj2d: NDArray,
    n_obj: int,
    feat_obj: NDArray[np.intp],
    z: F64,
    prior: NDArray,
    conf: NDArray,
    ga: GlobalFit,
    prior_kind: str,
) -> Merged:
    """Multi-scale merging (III-B, mode full), the CDR sample pixels (a strided grid plus every
    pixel of objects the grid misses) and sky: featureless groups whose prior is mostly far."""
    H, W = obj2d.shape
    pairs = boundary_pairs(obj2d) if mode != "no_msc_cdr" else None
    adjacency = None
    if mode == "full":
        adj_k, adj_l, _ = region_adjacency(obj2d, n_obj, pairs)
        adjacency = (adj_k, adj_l)
        group, n_merges = merge_undersupported(
            n_obj, adjacency, feat_obj, z, p.n_min, p.rho_contiguity
        )
    else:
        group, n_merges = np.arange(n_obj), 0
    G = int(group.max()) + 1 if n_obj else 0
    # intp indices: np.take with int32 indices is several times slower (index conversion); the
    # full-resolution object map is built once, after the last merge (absorption in mode full)
    obj_i = obj2d.ravel().astype(np.intp)
    group = group.astype(np.intp, copy=False)
    feat_g = group[feat_obj]
    n_feat_g = np.bincount(feat_g, minlength=G)
    s = p.sample_stride
    grid = (np.arange(0, H, s)[:, None] * W + np.arange(0, W, s)[None, :]).ravel()
    missing = np.bincount(group[obj_i[grid]], minlength=G) == 0
    if missing.any():
        grid = np.concatenate([grid, np.flatnonzero(np.take(missing[group], obj_i))])
    grid = grid[conf[grid] > 0]
    gg_grid = group[obj_i[grid]]
    theta0 = ga.theta0
    y_grid = theta0[0] * prior[grid].astype(np.float64) + theta0[1]
    far_grid, norm_grid = far_and_norm(y_grid, prior_kind, p)
    n_prior_g = np.bincount(gg_grid, minlength=G)
    n_far_g = np.bincount(gg_grid[far_grid], minlength=G)
    # sky needs the metric global alignment (no feature with a prior: "far" means nothing)
    sky = (n_feat_g == 0) & (n_prior_g > 0) & (n_far_g >= p.sky_far_fraction * n_prior_g)
    sky &= ga.n_global > 0
    return Merged(
        group,
        obj_i,
        G,
        int(n_merges),
        pairs,
        adjacency,
        feat_g,
        n_feat_g,
        grid,
        gg_grid,
        norm_grid,
        sky,
    )


def sky_value(
    p: MetrizerParams, ms: Merged, prior: NDArray, prior_kind: str, ga: GlobalFit
) -> float | None:
    """The prior's value on the sky when it should pin the global shift (``sky_anchor`` > 0, a
    relative inverse-depth prior, sky found), else None: the lowest median prior of the sky
    groups with at least 5 sample pixels (a featureless far object counts as sky too; the sky
    itself is the farthest, its inverse depth the lowest). An affine-invariant inverse-depth
    model gives the sky its shift: inverse depth 0."""
    if not (p.sky_anchor > 0 and prior_kind == DepthKind.RELATIVE_INVERSE_DEPTH and ms.sky.any()):
        return None
    if ga.n_global < p.min_anchor_features:
        return None
    on_sky = ms.sky[ms.gg_grid]
    g, x = ms.gg_grid[on_sky], prior[ms.grid[on_sky]].astype(np.float64)
    n_g = np.bincount(g, minlength=ms.G)
    keep = n_g[g] >= 5
    if not keep.any():
        return None
    cnt, med = group_medians(g[keep], x[keep], ms.G)
    return float(med[cnt > 0].min())
