"""Second merging scale of MSC (departure 11, docs/metrizer.md): groups without an accepted shape
join an adjacent group whose shape (Algorithm 1) explains their features, residual of eq. (2)
below ``T_s(z)``."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mogs_node.metrizer import shapes
from mogs_node.metrizer.alignment import depth_from_space
from mogs_node.metrizer.frame import Frame, model_agrees, model_depth
from mogs_node.metrizer.merging import absorb_into_models

__all__ = ["absorb_groups", "expand_rows"]

F64 = NDArray[np.float64]


def expand_rows(item_group, n_groups, pair_groups):
    """Rows ``(item, pair)`` for every item (feature / sample) of each pair's group, vectorised."""
    order = np.argsort(item_group, kind="stable")
    counts = np.bincount(item_group, minlength=n_groups)
    starts = np.concatenate([[0], np.cumsum(counts)])
    lens = counts[pair_groups]
    row_pair = np.repeat(np.arange(len(pair_groups)), lens)
    offs = np.arange(len(row_pair)) - np.repeat(np.cumsum(lens) - lens, lens)
    return order[starts[pair_groups][row_pair] + offs], row_pair


def absorb_groups(fr: Frame, group, adjacency, model, Xf, samples):
    """Second merging scale (departure, docs/metrizer.md): a group without an accepted shape joins
    an adjacent group whose shape explains it: at least ``tau`` of its features are inliers of that
    model (eq. 2 residual below ``T_s(z)``); a group with fewer than ``absorb_sample_below``
    features also counts its sample pixels, where the model depth must be within
    ``absorb_prior_gate`` of the globally aligned prior.
    ``adjacency`` = ``(adj_k, adj_l)`` object pairs, ``model`` = ``(kind, A, b, c, zlo, zhi)`` per
    group, ``samples`` = ``(grid, group of grid, globally aligned normaliser)`` of the CDR samples;
    features, groups, camera and parameters come from ``fr``.
    Returns ``(kept old ids [G'], old -> new id map [G])`` or None when nothing is absorbed."""
    adj_k, adj_l = adjacency
    kind_g, Am, bm, cm, zlo, zhi = model
    grid, gg_grid, norm_grid = samples
    p, G, W, K, prior_kind = fr.p, fr.G, fr.W, fr.K, fr.prior_kind
    z, feat_g, n_feat_g, sky = fr.z, fr.feat_g, fr.n_feat_g, fr.sky
    ga, gb = group[adj_k], group[adj_l]
    diff = ga != gb
    a = np.concatenate([ga[diff], gb[diff]])
    b = np.concatenate([gb[diff], ga[diff]])
    cand = (kind_g[a] == 0) & (kind_g[b] > 0) & ~sky[a]
    if not cand.any():
        return None
    key = np.unique(a[cand].astype(np.int64) * G + b[cand])
    pg, pu = (key // G).astype(np.intp), (key % G).astype(np.intp)
    # evidence 1: the features of g against u's model (eq. 2 residual below T_s)
    fi, frow = expand_rows(feat_g, G, pg)
    u = pu[frow]
    r = shapes.quadric_residual_rows(Am[u], bm[u], cm[u], Xf[fi])
    f_ok = r <= fr.t_abs_m + p.consensus.t_rel * z[fi]
    # evidence 2: g with few features: u's model depth at g's samples vs the global prior
    si, srow = expand_rows(gg_grid, G, pg)
    sel = n_feat_g[pg][srow] < p.absorb_sample_below
    si, srow = si[sel], srow[sel]
    us = pu[srow]
    dm = model_depth(grid[si], us, kind_g, Am, bm, cm, W, K)
    d_glob = depth_from_space(norm_grid[si], prior_kind, p.d_min_m, p.d_max_m)
    s_ok = model_agrees(dm, zlo[us], zhi[us], d_glob, p.absorb_prior_gate)
    evidence = (np.concatenate([frow, srow]), np.concatenate([f_ok, s_ok]))
    target = absorb_into_models((pg, pu), evidence, G, p.consensus.tau)
    if np.array_equal(target, np.arange(G)):
        return None
    keep_ids, remap = np.unique(target, return_inverse=True)
    return keep_ids, remap.astype(np.intp)
