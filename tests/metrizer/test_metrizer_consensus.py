"""Algorithm 1 (paper III-B): model selection by eq. (5), outliers, the skip rule; merging."""

from __future__ import annotations

import numpy as np
import pytest

from mogs_node.group_stats import group_medians
from mogs_node.metrizer import shapes
from mogs_node.metrizer.association import (
    associate_features,
    prepare_labels,
    region_adjacency,
)
from mogs_node.metrizer.consensus import ConsensusParams, fit_object
from mogs_node.metrizer.merging import merge_undersupported

PARAMS = ConsensusParams(t_rel=0.01, tau=0.6)  # 0.3% noise in these scenes


def _plane(rng, n):
    x, z = rng.uniform(-3, 3, n), rng.uniform(8, 15, n)
    return np.c_[x, 1.5 + 0.05 * x + 0.02 * z, z]


def _cylinder(rng, n):  # a 2 m radius tank / trunk, seen from the camera side
    th, y = rng.uniform(0.6 * np.pi, 1.4 * np.pi, n), rng.uniform(-3, 1.5, n)
    return np.c_[1 + 2.0 * np.sin(th), y, 10 + 2.0 * np.cos(th)]


def _ellipsoid(rng, n):  # the visible half of a 4 x 1.6 x 3 m ellipsoid
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u[:, 2] = -np.abs(u[:, 2])
    return u * [2, 0.8, 1.5] + [0, 0, 12]


def _corrupt(rng, X, frac, noise=0.003):
    X = X * (1 + noise * rng.normal(size=(len(X), 1)))
    n_out = int(round(frac * len(X)))
    f = np.where(
        rng.random((n_out, 1)) < 0.5,
        rng.uniform(0.5, 0.8, (n_out, 1)),
        rng.uniform(1.25, 2.0, (n_out, 1)),
    )
    X[:n_out] *= f  # outliers slide along their rays (wrong depth), as triangulation errors do
    return X


@pytest.mark.parametrize(
    "kind,make",
    [
        (shapes.KIND_PLANE, _plane),
        (shapes.KIND_CYLINDER, _cylinder),
        (shapes.KIND_ELLIPSOID, _ellipsoid),
    ],
)
@pytest.mark.parametrize("seed", range(3))
def test_model_selection_under_30_percent_outliers(kind, make, seed):
    rng = np.random.default_rng(seed)
    X = _corrupt(rng, make(rng, 60), 0.3)
    fit = fit_object(X, np.ones(60), rng, PARAMS)
    assert fit.kind == kind
    assert fit.inliers[18:].mean() > 0.95  # the true points are inliers
    assert fit.inliers[:18].mean() < 0.3  # most outliers are not
    r = shapes.quadric_residual(fit.A[None], fit.b[None], np.array([fit.c]), X[18:])[0]
    assert np.median(r / X[18:, 2]) < 0.006  # the true surface, within twice the 0.3% noise


def test_clean_plane_skips_costly_models():
    rng = np.random.default_rng(0)
    X = _plane(rng, 40)
    fit = fit_object(X, np.ones(40), rng, PARAMS)
    assert fit.kind == shapes.KIND_PLANE and fit.skipped_costly
    assert set(fit.confidences) == {shapes.KIND_PLANE}
    assert fit.confidence > 0.99  # eq. (5): gamma = 1, sigma = 0


def test_confidence_eq5():
    from mogs_node.metrizer.consensus import score_hypotheses

    X = np.array([[0, 0, 1.0], [1, 0, 1.0], [0, 1, 1.0], [1, 1, 1.5]])  # last point 0.5 off z=1
    b = np.array([[0, 0, 1.0]])
    ts = np.full(4, 0.25)
    conf, inl = score_hypotheses(
        np.zeros((1, 3, 3)), b, np.array([-1.0]), np.array([True]), X, ts, beta=1.0
    )
    assert inl[0].tolist() == [True, True, True, False]
    assert conf[0] == pytest.approx(0.75)  # gamma = 3/4, sigma = 0
    X[0, 2] = 1.1  # residual 0.1 = 0.4 T_s
    conf, _ = score_hypotheses(
        np.zeros((1, 3, 3)), b, np.array([-1.0]), np.array([True]), X, ts, beta=2.0
    )
    assert conf[0] == pytest.approx(0.75 * np.exp(-(0.4**2 / 3) / 2.0))


def test_acceptance_threshold_tau():
    rng = np.random.default_rng(1)
    X = _corrupt(rng, _plane(rng, 40), 0.3)
    assert fit_object(X, np.ones(40), rng, ConsensusParams(t_rel=0.01, tau=0.9)).kind == 0
    assert fit_object(X, np.ones(40), rng, ConsensusParams(t_rel=0.01, tau=0.6)).kind == 1


def test_collinear_and_tiny_sets_are_rejected():
    rng = np.random.default_rng(2)
    line = np.array([0, 1.5, 8.0]) + rng.uniform(0, 6, (20, 1)) * np.array([0.0, 0.02, 1.0])
    assert fit_object(line, np.ones(20), rng, PARAMS).kind == 0  # exactly collinear
    near = line + np.c_[rng.normal(0, 0.01, 20), np.zeros(20), np.zeros(20)]  # a lane marking
    fit = fit_object(near, np.ones(20), rng, PARAMS)
    assert fit.kind == 0 and fit.degenerate
    assert fit_object(_plane(rng, 3), np.ones(3), rng, PARAMS).kind == 0
    assert fit_object(np.zeros((0, 3)), np.zeros(0), rng, PARAMS).kind == 0
    same = np.repeat([[0.0, 1.0, 5.0]], 12, axis=0)
    assert fit_object(same, np.ones(12), rng, PARAMS).kind == 0


# ------------------------------------------------------------------------------ association


def test_prepare_labels_compacts_and_splits_unmasked():
    lab = np.array([[5, 5, -1, 9], [5, -1, -1, 9], [-1, 9, 9, 9]], np.int32)
    obj, n, unmasked = prepare_labels(lab)
    assert n == 4 and unmasked.tolist() == [False, False, True, True]
    assert obj[0, 0] == 0 and obj[0, 3] == 1
    assert obj[0, 2] == obj[1, 1] == obj[1, 2] and obj[2, 0] != obj[0, 2]
    obj2, n2, _ = prepare_labels(np.array([[3, 3], [7, 7]], np.int64))
    assert n2 == 2 and obj2.tolist() == [[0, 0], [1, 1]]


def test_border_vote():
    obj = np.zeros((7, 7), np.int32)
    obj[:, 4:] = 1
    obj[3, 3] = 2  # a one-pixel mask inside object 0
    uv = np.array([[3.0, 3.0], [1.0, 1.0], [4.0, 0.0], [100.0, 3.0]])
    got = associate_features(obj, uv, radius=1)
    assert got.tolist() == [0, 0, 1, -1]  # the lone pixel is outvoted; outside -> -1
    assert associate_features(obj, uv, radius=0).tolist() == [2, 0, 1, -1]


def test_region_adjacency():
    obj = np.array([[0, 0, 1], [2, 2, 1]], np.int32)
    k, l, cnt = region_adjacency(obj, 3)
    assert list(zip(k.tolist(), l.tolist(), cnt.tolist(), strict=False)) == [
        (0, 1, 1),
        (0, 2, 2),
        (1, 2, 1),
    ]


# ------------------------------------------------------------------------------ merging


def test_merging_picks_contiguous_neighbour_with_smallest_gap():
    # objects: 0 supported at 10 m, 1 supported at 10.5 m, 2 under-supported at 10.4 m,
    # 3 under-supported at 30 m (no contiguous neighbour), 4 without features
    adj_k = np.array([0, 1, 2, 3, 0])
    adj_l = np.array([2, 2, 3, 4, 4])
    feat_obj = np.array([0] * 9 + [1] * 9 + [2] * 3 + [3] * 2)
    z = np.array([10.0] * 9 + [10.5] * 9 + [10.4] * 3 + [30.0] * 2)
    group, merges = merge_undersupported(5, (adj_k, adj_l), feat_obj, z, n_min=9, rho=0.1)
    assert merges == 1
    assert group[2] == group[1] != group[0]
    assert len({group[3], group[4], group[0], group[1]}) == 4


def test_merging_is_repeated_until_supported():
    # a chain of under-supported masks 0-1-2-3 (3 features each) at contiguous depths
    adj_k, adj_l = np.array([0, 1, 2]), np.array([1, 2, 3])
    feat_obj = np.repeat(np.arange(4), 3)
    z = np.repeat([10.0, 10.2, 10.4, 10.6], 3)
    group, merges = merge_undersupported(4, (adj_k, adj_l), feat_obj, z, n_min=9, rho=0.1)
    counts, _ = group_medians(group[feat_obj], z, int(group.max()) + 1)
    assert counts.min() >= 9 or len(counts) == 1
    assert merges >= 2


def test_batched_kernel_matches_per_object_reference():
    """fit_objects (all objects in padded batches) agrees with fit_object (one at a time)."""
    from mogs_node.metrizer.consensus import fit_objects

    rng = np.random.default_rng(7)
    sets = [
        _plane(rng, 40),
        _corrupt(rng, _plane(rng, 50), 0.2),
        _ellipsoid(rng, 40),
        _plane(rng, 4),
        _corrupt(rng, _plane(rng, 30), 0.1),
    ]
    X = np.concatenate(sets)
    obj = np.concatenate([np.full(len(s), i) for i, s in enumerate(sets)])
    perm = rng.permutation(len(X))  # objects interleaved: the kernel sorts them stably
    fits = fit_objects(X[perm], np.ones(len(X)), obj[perm], len(sets), rng, PARAMS)
    assert set(fits) == {0, 1, 2, 4}  # object 3 has too few points
    so = np.argsort(obj[perm], kind="stable")
    X_sorted, obj_sorted = X[perm][so], obj[perm][so]
    for k, fit in fits.items():
        pts = X_sorted[obj_sorted == k]
        ref = fit_object(pts, np.ones(len(pts)), np.random.default_rng(1), PARAMS)
        assert fit.kind == ref.kind
        assert np.array_equal(fit.inliers, ref.inliers)
        assert fit.confidence == pytest.approx(ref.confidence, abs=1e-9)
        if fit.kind == shapes.KIND_PLANE:
            nb, nr = fit.b / np.linalg.norm(fit.b), ref.b / np.linalg.norm(ref.b)
            sgn = np.sign(nb @ nr)
            assert np.allclose(sgn * nb, nr, atol=1e-9)
            assert np.isclose(
                sgn * fit.c / np.linalg.norm(fit.b), ref.c / np.linalg.norm(ref.b), atol=1e-8
            )
    assert fits[0].skipped_costly and fits[2].kind == shapes.KIND_ELLIPSOID


def test_absorb_into_models_picks_best_explaining_neighbour():
    from mogs_node.metrizer.merging import absorb_into_models

    # candidate pairs (g, u): 0->5, 0->6, 1->5, 2->6
    pair_g, pair_u = np.array([0, 0, 1, 2]), np.array([5, 6, 5, 6])
    row_pair = np.array([0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 3])
    row_ok = np.array([1, 1, 1, 0, 1, 1, 1, 1, 1, 0, 0], bool)
    target = absorb_into_models((pair_g, pair_u), (row_pair, row_ok), 7, min_fraction=0.8)
    # 0: 3/4 via 5, 4/4 via 6 -> 6; 1: 1/2 -> stays; 2: 0/1 -> stays
    assert target.tolist() == [6, 1, 2, 3, 4, 5, 6]
    none = (np.zeros(0, int), np.zeros(0, int))
    empty = absorb_into_models(none, (np.zeros(0, int), np.zeros(0, bool)), 3, 0.8)
    assert empty.tolist() == [0, 1, 2]


def test_prepare_labels_sparse_ids_and_all_negative():
    obj, n, unm = prepare_labels(np.array([[2**40, 3], [-7, 2**40]], np.int64))
    assert n == 3 and obj.tolist() == [[1, 0], [2, 1]] and unm.tolist() == [False, False, True]
    obj, n, unm = prepare_labels(np.full((2, 3), -5))
    assert n == 1 and np.all(obj == 0) and unm.tolist() == [True]
    obj, n, _ = prepare_labels(np.full((2, 2), 3, np.uint8))
    assert n == 1 and np.all(obj == 0)
