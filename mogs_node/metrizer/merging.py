"""Multi-scale merging of under-supported masks (paper III-B).

A mask with fewer than ``n_min`` features cannot support a shape fit on its own. Repeatedly, every
under-supported group that has at least one feature merges into the adjacent group (region
adjacency of the label image) that has features, is depth-contiguous (``|z_i - z_u| <= rho z_i``
with ``z`` the median feature depth of a group) and has the smallest median-depth gap, until every
group is supported or no candidate is left. Merges of one round are applied together (union-find),
so the number of rounds is small; the loop is over rounds and merge pairs, never over pixels.

Groups with no feature at all are not merged (their depth cannot be tested for contiguity); the
refinement (CDR) calibrates them through prior anchoring and smoothness with their neighbours.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mogs_node.group_stats import group_medians

__all__ = ["absorb_into_models", "merge_undersupported"]

Idx = NDArray[np.intp]
Pairs = tuple[Idx, Idx]  # two aligned index arrays: edges (k, l) or candidate pairs (g, u)
MAX_ROUNDS = 100  # merge rounds at most (each round merges every candidate at once)


def _find_all(parent: NDArray[np.intp]) -> NDArray[np.intp]:
    while True:
        nxt = parent[parent]
        if np.array_equal(nxt, parent):
            return parent
        parent = nxt


def merge_undersupported(
    n_obj: int, adjacency: Pairs, feat_obj: Idx, feat_z: NDArray[np.float64], n_min: int, rho: float
) -> tuple[Idx, int]:
    """Group id per object ``[M]`` (compact, ``0..G-1``) and the number of merges performed.

    ``adjacency = (adj_k, adj_l)`` ``[E]``: adjacent object pairs; ``feat_obj`` ``[N]`` object per
    feature (all ``>= 0``), ``feat_z`` ``[N]`` metric depths.
    """
    adj_k, adj_l = adjacency
    parent = np.arange(n_obj)
    merges = 0
    for _ in range(MAX_ROUNDS):
        root = _find_all(parent)
        counts, med = group_medians(root[feat_obj], feat_z, n_obj)
        gk, gl = root[adj_k], root[adj_l]
        keep = gk != gl
        a = np.concatenate([gk[keep], gl[keep]])  # directed edges a -> b
        b = np.concatenate([gl[keep], gk[keep]])
        under = (counts[a] > 0) & (counts[a] < n_min) & (counts[b] > 0)
        gap = np.abs(med[a] - med[b])
        ok = under & (gap <= rho * med[a])
        if not ok.any():
            break
        a, b, gap = a[ok], b[ok], gap[ok]
        order = np.lexsort((gap, a))
        a, b = a[order], b[order]
        first = np.concatenate([[True], a[1:] != a[:-1]])
        for i, u in zip(a[first].tolist(), b[first].tolist(), strict=False):
            ri, ru = i, u
            while parent[ri] != ri:
                ri = parent[ri]
            while parent[ru] != ru:
                ru = parent[ru]
            if ri != ru:
                parent[ri] = ru
                merges += 1
    root = _find_all(parent)
    _, group = np.unique(root, return_inverse=True)
    return group.astype(np.intp), merges


def absorb_into_models(
    candidates: Pairs, evidence: tuple[Idx, NDArray[np.bool_]], n_groups: int, min_fraction: float
) -> Idx:
    """Second, shape-driven merging scale: absorb groups into an adjacent group's accepted shape.

    ``candidates = (pair_g, pair_u)`` ``[P]``: candidate pairs (group ``g`` without an accepted
    model, adjacent group ``u`` with one); ``evidence = (row_pair, row_ok)`` ``[R]``: the pair of
    each evidence row (a feature of ``g``, or a sample pixel of a featureless ``g``) and whether
    ``u``'s model explains it.
    ``g`` is absorbed into the ``u`` that explains the largest fraction of its rows, if that
    fraction is at least ``min_fraction``. Returns the new group of every group ``[G]`` (not
    compacted; absorbed groups point at their host, hosts never move).
    """
    (pair_g, pair_u), (row_pair, row_ok) = candidates, evidence
    target = np.arange(n_groups)
    if len(pair_g) == 0:
        return target
    n_rows = np.bincount(row_pair, minlength=len(pair_g))
    n_ok = np.bincount(row_pair, row_ok.astype(np.float64), minlength=len(pair_g))
    frac = np.where(n_rows > 0, n_ok / np.maximum(n_rows, 1), 0.0)
    good = frac >= min_fraction
    if not good.any():
        return target
    g, u, f = pair_g[good], pair_u[good], frac[good]
    order = np.lexsort((-f, g))
    g, u = g[order], u[order]
    first = np.concatenate([[True], g[1:] != g[:-1]])
    target[g[first]] = u[first]
    return target
