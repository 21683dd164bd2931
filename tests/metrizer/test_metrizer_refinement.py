"""CDR (paper III-C): IRLS solve of eqs. (6)-(11), fast kernel vs dense reference; alignment."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from mogs_node.metrizer.alignment import depth_from_space, fit_global_affine
from mogs_node.metrizer.fill import smooth_field
from mogs_node.metrizer.refinement import (
    CdrParams,
    CdrProblem,
    huber_weight,
    solve_cdr,
    solve_cdr_reference,
)


def _random_problem(rng, n=4, P=40, G=15, B=12):
    theta0 = np.array([0.9, 0.01])
    nfc_obj = rng.integers(0, n, P)
    x = rng.uniform(0.05, 0.5, P)
    geo_obj = rng.integers(0, n, G)
    gx = rng.uniform(0.05, 0.5, G)
    true = np.c_[rng.uniform(0.7, 1.3, n), rng.uniform(-0.02, 0.02, n)]
    gt = true[geo_obj, 0] * gx + true[geo_obj, 1]
    gt = np.abs(gt * (1 + 0.2 * rng.standard_normal(G) * (rng.random(G) < 0.2))) + 1e-3
    k = rng.integers(0, n, B)
    l = (k + 1 + rng.integers(0, n - 1, B)) % n
    return CdrProblem(
        n=n,
        theta0=np.tile(theta0, (n, 1)),
        geo_obj=geo_obj,
        geo_x=gx,
        geo_t=gt,
        geo_w=rng.uniform(0.1, 1, G),
        nfc_obj=nfc_obj,
        nfc_x=x,
        nfc_t=theta0[0] * x + theta0[1],
        nfc_w=rng.uniform(0.1, 1, P),
        sm_k=k,
        sm_l=l,
        sm_xk=rng.uniform(0.05, 0.5, B),
        sm_xl=rng.uniform(0.05, 0.5, B),
        sm_g=rng.uniform(0.05, 0.5, B),
        sm_w=rng.uniform(0, 1, B),
    )


@pytest.mark.parametrize("seed", range(5))
def test_fast_solver_matches_dense_reference(seed):
    prob = _random_problem(np.random.default_rng(seed))
    params = CdrParams(irls_iters=5, tol=0.0)
    assert_allclose(
        solve_cdr(prob, params), solve_cdr_reference(prob, params), rtol=1e-7, atol=1e-10
    )


@pytest.mark.parametrize("seed", range(3))
def test_sparse_and_dense_solves_agree(seed, monkeypatch):
    """solve_cdr factorises small systems densely, large ones with SuperLU: same solution."""
    import mogs_node.metrizer.refinement as refinement

    prob = _random_problem(np.random.default_rng(seed), n=20, P=200, G=60, B=100)
    params = CdrParams(irls_iters=3, tol=0.0)
    dense = solve_cdr(prob, params)
    monkeypatch.setattr(refinement, "_DENSE_MAX", 0)
    sparse = solve_cdr(prob, params)
    assert_allclose(dense, sparse, rtol=1e-9, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 6))
def test_fast_solver_matches_reference_property(seed, n):
    rng = np.random.default_rng(seed)
    prob = _random_problem(
        rng,
        n=n,
        P=rng.integers(1, 30),
        G=rng.integers(0, 10),
        B=0 if n == 1 else rng.integers(0, 10),
    )
    params = CdrParams(irls_iters=3, tol=0.0)
    fast, ref = solve_cdr(prob, params), solve_cdr_reference(prob, params)
    assert np.all(np.isfinite(fast))
    assert_allclose(fast, ref, rtol=1e-6, atol=1e-9)


def test_exact_geometry_is_recovered():
    """Geometric rows with exact targets and no competing terms give the true affine back."""
    rng = np.random.default_rng(0)
    n = 3
    true = np.array([[1.2, 0.01], [0.8, -0.005], [1.0, 0.02]])
    obj = np.repeat(np.arange(n), 30)
    x = rng.uniform(0.05, 0.5, len(obj))
    t = true[obj, 0] * x + true[obj, 1]
    e = np.zeros(0)
    prob = CdrProblem(
        n=n,
        theta0=np.tile([1.0, 0.0], (n, 1)),
        geo_obj=obj,
        geo_x=x,
        geo_t=t,
        geo_w=np.ones(len(obj)) / 30,
        nfc_obj=obj,
        nfc_x=x,
        nfc_t=x,
        nfc_w=np.ones(len(obj)) / 30,
        sm_k=e.astype(int),
        sm_l=e.astype(int),
        sm_xk=e,
        sm_xl=e,
        sm_g=e,
        sm_w=e,
    )
    theta = solve_cdr(prob, CdrParams(lambda_nfc=0.0, ridge=1e-12, irls_iters=10))
    assert_allclose(theta, true, rtol=1e-6)
    # with the (Huber) anchor on (its target 0-20% off), strong geometry still wins: the anchor's
    # bounded gradient moves the fit by about lambda_nfc * huber_nfc / lambda_geo at most
    for huber_nfc in (0.01, 0.05):
        params = CdrParams(irls_iters=20, huber_nfc=huber_nfc)
        theta = solve_cdr(prob, params)
        err = np.abs((theta[obj, 0] * x + theta[obj, 1]) / t - 1)
        bound = params.lambda_nfc * huber_nfc / params.lambda_geo
        assert np.mean(err) < 1.25 * bound
        assert np.max(err) < 1.5 * bound + 0.01


def test_smoothness_pulls_a_featureless_object_to_its_neighbour():
    """Object 1 has no geometry; across an edge-free border it takes object 0's calibration."""
    x = np.linspace(0.1, 0.3, 20)
    obj0, obj1 = np.zeros(20, int), np.ones(20, int)
    true0 = np.array([1.3, 0.0])
    e = np.zeros(0)
    base = dict(
        n=2,
        theta0=np.tile([1.0, 0.0], (2, 1)),
        geo_obj=obj0,
        geo_x=x,
        geo_t=true0[0] * x,
        geo_w=np.ones(20) / 20,
        nfc_obj=np.r_[obj0, obj1],
        nfc_x=np.r_[x, x],
        nfc_t=np.r_[x, x],
        nfc_w=np.ones(40) / 20,
    )
    alone = solve_cdr(
        CdrProblem(**base, sm_k=e.astype(int), sm_l=e.astype(int), sm_xk=e, sm_xl=e, sm_g=e, sm_w=e)
    )
    prob = CdrProblem(
        **base, sm_k=obj0, sm_l=obj1, sm_xk=x, sm_xl=x, sm_g=x, sm_w=np.full(20, 1.0 / 20)
    )
    assert abs(alone[1, 0] - 1.0) < 0.01  # anchored to the global alignment
    # a narrow anchor (bounded pull) yields most of the way to the neighbour ...
    coupled = solve_cdr(prob, CdrParams(lambda_sm=1.0, huber_nfc=0.01))
    assert abs(coupled[1, 0] - 1.3) < abs(alone[1, 0] - 1.3) * 0.5
    # ... the default, wider one (the pipeline anchors to a locally aligned prior) part of the way
    coupled = solve_cdr(prob, CdrParams(lambda_sm=1.0))
    assert abs(coupled[1, 0] - 1.3) < abs(alone[1, 0] - 1.3) * 0.75


def test_huber_weight():
    assert_allclose(huber_weight(np.array([0.0, 0.05, -0.1, 1.0]), 0.05), [1, 1, 0.5, 0.05])


def test_global_affine_recovers_scale_and_shift_robustly():
    rng = np.random.default_rng(0)
    z = rng.uniform(3, 60, 200)
    x = 0.2 / z + 0.004  # relative inverse depth = (1/z) * 0.2 + 0.004
    t = 1.0 / z
    z_bad = z.copy()
    z_bad[:30] *= 2.0  # 15% gross outliers
    theta, n = fit_global_affine(x, 1.0 / z_bad, np.ones(200), "relative_inverse_depth")
    assert n == 200
    d = depth_from_space(theta[0] * x + theta[1], "relative_inverse_depth", 0.1, 1000.0)
    assert np.median(np.abs(d / z - 1)) < 1e-3
    # degenerate inputs fall back gracefully
    th1, _ = fit_global_affine(x[:1], t[:1], np.ones(1), "relative_inverse_depth")
    assert_allclose(th1[0] * x[0] + th1[1], t[0])
    th0, n0 = fit_global_affine(np.zeros(0), np.zeros(0), np.zeros(0), "relative_depth")
    assert n0 == 0 and th0.tolist() == [1.0, 0.0]
    thc, _ = fit_global_affine(np.full(5, 0.3), t[:5], np.ones(5), "relative_inverse_depth")
    assert np.all(np.isfinite(thc)) and thc[0] > 0


def test_depth_from_space_bounds():
    y = np.array([-1.0, 0.0, 1e-9, 0.5, 100.0, np.nan, np.inf])
    d = depth_from_space(y, "relative_inverse_depth", 0.1, 80.0)
    assert np.all(np.isfinite(d)) and np.all((d >= 0.1) & (d <= 80.0))
    assert d[3] == 2.0
    d2 = depth_from_space(y, "relative_depth", 0.1, 80.0)
    assert np.all((d2 >= 0.1) & (d2 <= 80.0)) and d2[3] == 0.5


# ------------------------------------------------------------------------------ anchor field


def test_smooth_field_reproduces_a_constant_and_decays_with_shrink():
    """Dense samples of a constant give that constant (at any pixel, full image or ``at``);
    with ``shrink`` the field is pulled towards 0 by exactly den / (den + k) far from evidence."""
    H, W = 60, 160
    rng = np.random.default_rng(0)
    idx = rng.choice(H * W, 2000, replace=False)
    full = smooth_field((H, W), idx, np.full(2000, 0.2), np.ones(2000), 0.05)
    assert_allclose(full, 0.2, rtol=1e-5)
    at = rng.choice(H * W, 300, replace=False)
    part = smooth_field((H, W), idx, np.full(2000, 0.2), np.ones(2000), 0.05, at=at)
    assert part.shape == (300,)
    assert_allclose(part, 0.2, rtol=1e-5)
    # one sample in the left corner: shrink leaves the value there nearly untouched when the
    # sample weighs much more than the pseudo-observation, and takes it to ~0 on the far side
    one = np.array([5 * W + 5])
    heavy = smooth_field((H, W), one, np.array([0.3]), np.array([1e4]), 0.05, shrink=1.0)
    assert abs(heavy[5, 5] - 0.3) < 0.01
    light = smooth_field((H, W), one, np.array([0.3]), np.array([1.0]), 0.05, shrink=1.0)
    assert abs(light[H - 5, W - 5]) < 1e-3
    assert abs(full[H - 5, W - 5] - 0.2) < 1e-5  # without shrink: extrapolated unchanged
    assert np.all(np.abs(light) <= 0.3 + 1e-6)


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(0, 50),
    scale=st.floats(-2, 2),
    shrink=st.floats(0, 10),
    seed=st.integers(0, 2**16),
)
def test_smooth_field_is_finite_and_bounded(n, scale, shrink, seed):
    rng = np.random.default_rng(seed)
    H, W = 7, 23
    idx = rng.integers(0, H * W, n)
    val = scale * rng.standard_normal(n)
    wt = rng.uniform(0, 2, n)
    f = smooth_field((H, W), idx, val, wt, 0.05, clip=0.5, shrink=shrink)
    g = smooth_field((H, W), idx, val, wt, 0.05, clip=0.5, shrink=shrink, at=np.arange(H * W))
    for x in (f.ravel(), g):
        assert np.all(np.isfinite(x)) and np.all(np.abs(x) <= 0.5)
        if n:
            assert np.all(x >= min(val.min(), 0) - 1e-5) and np.all(x <= max(val.max(), 0) + 1e-5)


def test_global_shift_prior_decides_only_an_undetermined_shift():
    """Features at one depth leave the shift of ``1/D = a x + b`` free: the fit without the prior
    may end the far field anywhere; the weak pull to the pure scale keeps it. Features spread over
    depth determine the shift: the prior moves the result by a fraction of the noise only."""
    rng = np.random.default_rng(3)
    far_err = {0.0: [], 0.05: []}
    for _ in range(20):
        x = rng.uniform(0.08, 0.12, 40)  # relative inverse depth, 8-12 m: one depth band
        t = x * (1.0 + 0.02 * rng.standard_normal(40))  # truth a = 1, b = 0, 2 % noise
        for sp in far_err:
            th, _ = fit_global_affine(x, t, np.ones(40), "relative_inverse_depth", shift_prior=sp)
            far_err[sp].append(abs(th[0] * 0.01 + th[1] - 0.01) / 0.01)  # at 100 m
    assert np.mean(far_err[0.05]) < 0.5 * np.mean(far_err[0.0])
    x = rng.uniform(0.01, 0.5, 200)  # 2-100 m
    t = 1.3 * x - 0.004
    th0, _ = fit_global_affine(x, t, np.ones(200), "relative_inverse_depth")
    th1, _ = fit_global_affine(x, t, np.ones(200), "relative_inverse_depth", shift_prior=0.05)
    np.testing.assert_allclose(th0, [1.3, -0.004], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(th1, th0, rtol=0.02, atol=4e-4)
