"""Shape primitives of MSC (paper III-B): exact fits, eq. (2) residual, ray intersection."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from mogs_node.geometry import intersect_rays_quadric
from mogs_node.metrizer import shapes


def _rot(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _plane_points(rng, n):
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    e1 = np.cross(normal, [1.0, 0, 0] if abs(normal[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    p0 = np.array([0.3, 1.2, 9.0])
    uv = rng.uniform(-3, 3, (n, 2))
    return p0 + uv[:, :1] * e1 + uv[:, 1:] * e2, normal, -normal @ p0


def _cylinder_points(rng, n, axis, centre, r):
    axis = axis / np.linalg.norm(axis)
    e1 = np.cross(axis, [1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    th = rng.uniform(0, 2 * np.pi, n)
    h = rng.uniform(-2, 2, n)
    return centre + r * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2) + h[:, None] * axis


def _ellipsoid_points(rng, n, R, semi, centre):
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return (u * semi) @ R.T + centre


@pytest.mark.parametrize("seed", range(5))
def test_plane_exact_recovery(seed):
    rng = np.random.default_rng(seed)
    X, n_true, d_true = _plane_points(rng, 20)
    A, n, d, ok = shapes.fit_plane_minimal(X[None, :3])
    assert ok[0]
    sign = np.sign(n[0] @ n_true)
    assert_allclose(sign * n[0], n_true, atol=1e-9)
    assert_allclose(sign * d[0], d_true, atol=1e-8)
    A, n, d, ok = shapes.fit_plane(X)
    assert ok
    assert_allclose(abs(n @ n_true), 1.0, atol=1e-12)
    assert np.max(shapes.quadric_residual(A[None], n[None], np.array([d]), X)) < 1e-9


@pytest.mark.parametrize("seed", range(5))
def test_cylinder_exact_recovery(seed):
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    centre, r = np.array([1.0, -0.5, 10.0]), rng.uniform(0.3, 2.0)
    X = _cylinder_points(rng, 40, axis, centre, r)
    Xn, mu, s = shapes.normalise_points(X)
    for sample in (Xn[None, :9], Xn[None]):
        A, b, c, ok = shapes.fit_cylinder(sample)
        assert ok[0]
        A, b, c = shapes.denormalise_quadric(A, b, c, mu, s)
        assert np.max(shapes.quadric_residual(A, b, c, X)) < 1e-7
        # A = I - a a^T: the null vector is the axis
        w, V = np.linalg.eigh(A[0])
        assert_allclose(abs(V[:, 0] @ axis), 1.0, atol=1e-7)
        # the radius: eq. (2) at distance rho from the axis is (rho^2 - r^2) / (2 rho)
        e1 = np.cross(axis, [0, 0, 1.0])
        e1 /= np.linalg.norm(e1)
        rho = r + 0.1
        got = shapes.quadric_residual(A, b, c, (centre + rho * e1)[None])[0, 0]
        assert_allclose(got, (rho**2 - r**2) / (2 * rho), rtol=1e-6)


@pytest.mark.parametrize("seed", range(5))
def test_ellipsoid_exact_recovery(seed):
    rng = np.random.default_rng(seed)
    R = _rot(rng)
    semi = rng.uniform(0.5, 2.5, 3)
    centre = np.array([0.5, 0.0, 12.0])
    X = _ellipsoid_points(rng, 40, R, semi, centre)
    Xn, mu, s = shapes.normalise_points(X)
    for sample in (Xn[None, :9], Xn[None]):
        A, b, c, ok = shapes.fit_ellipsoid(sample)
        assert ok[0]
        A, b, c = shapes.denormalise_quadric(A, b, c, mu, s)
        assert np.max(shapes.quadric_residual(A, b, c, X)) < 1e-7
        x0 = -0.5 * np.linalg.solve(A[0], b[0])
        assert_allclose(x0, centre, atol=1e-7)
        k = x0 @ A[0] @ x0 - c[0]
        got = np.sort(1.0 / np.sqrt(np.linalg.eigvalsh(A[0] / k)))
        assert_allclose(got, np.sort(semi), rtol=1e-7)


def test_degenerate_samples_are_invalid():
    rng = np.random.default_rng(0)
    line = np.array([0, 0, 5.0]) + rng.uniform(-1, 1, (9, 1)) * np.array([1.0, 0.2, 0.3])
    assert not shapes.fit_plane_minimal(line[None, :3])[3][0]
    assert not shapes.fit_plane(line)[3]
    X, _, _ = _plane_points(rng, 12)  # coplanar: no quadric is determined
    Xn, _, _ = shapes.normalise_points(X)
    assert not shapes.fit_ellipsoid(Xn[None, :9])[3][0]
    assert not shapes.fit_cylinder(Xn[None, :9])[3][0]
    dup = np.repeat(X[:1], 9, axis=0)
    assert not shapes.fit_quadric_coeffs(dup[None])[1][0]
    # a sphere is not a cylinder
    Y = _ellipsoid_points(rng, 12, np.eye(3), np.ones(3), np.zeros(3))
    assert not shapes.fit_cylinder(Y[None, :9])[3][0]


def test_residual_fast_matches_reference():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(4, 3, 3))
    A = A + np.swapaxes(A, 1, 2)
    A[0] = 0.0
    b, c, X = rng.normal(size=(4, 3)), rng.normal(size=4), rng.normal(size=(25, 3))
    assert_allclose(
        shapes.quadric_residual(A, b, c, X),
        shapes.quadric_residual_reference(A, b, c, X),
        rtol=1e-12,
    )


def test_residual_is_first_order_distance():
    n = np.array([0.0, -1.0, 0.0])  # plane y = 1.5 (road below the camera)
    X = np.array([[0.0, 1.0, 5.0], [2.0, 2.0, 7.0]])
    r = shapes.quadric_residual(np.zeros((1, 3, 3)), n[None], np.array([1.5]), X)
    assert_allclose(r[0], [0.5, 0.5])
    A, b, c = shapes.cylinder_quadric(
        np.array([[0, 1.0, 0]]), np.array([[0, 0, 10.0]]), np.array([1.0])
    )
    pts = np.array([[1.05, 0.3, 10.0], [0.0, -2.0, 9.02]])
    rho = np.array([1.05, 0.98])
    assert_allclose(
        shapes.quadric_residual(A, b, c, pts)[0], np.abs(rho**2 - 1) / (2 * rho), rtol=1e-9
    )


def test_ray_depth_plane_analytic():
    # road plane y = 1.65 m: depth at image row with ray y-component ry is 1.65 / ry
    ry = np.linspace(0.05, 0.6, 12)
    rays = np.stack([np.linspace(-0.5, 0.5, 12), ry, np.ones(12)], 1)
    t = shapes.ray_depth(np.zeros((3, 3)), np.array([0, 1.0, 0]), -1.65, rays)
    assert_allclose(t, 1.65 / ry, rtol=1e-12)
    rays_up = rays * np.array([1, -1, 1.0])  # above the horizon: miss
    assert np.all(
        np.isinf(shapes.ray_depth(np.zeros((3, 3)), np.array([0, 1.0, 0]), -1.65, rays_up))
    )


def test_ray_depth_sphere_analytic_and_vs_geometry():
    centre, r = np.array([0.5, 0.2, 10.0]), 2.0
    A, b, c = np.eye(3), -2 * centre, centre @ centre - r * r
    rng = np.random.default_rng(1)
    rays = np.column_stack([rng.uniform(-0.4, 0.4, (200, 2)), np.ones(200)])
    t = shapes.ray_depth(A, b, c, rays)
    # analytic: nearest root of |t d - centre|^2 = r^2
    dd = np.einsum("ij,ij->i", rays, rays)
    dc = rays @ centre
    disc = dc**2 - dd * (centre @ centre - r * r)
    hit = disc >= 0
    assert hit.any() and (~hit).any()
    assert_allclose(t[hit], (dc[hit] - np.sqrt(disc[hit])) / dd[hit], rtol=1e-10)
    assert np.all(np.isinf(t[~hit]))
    t_geo = intersect_rays_quadric(np.zeros(3), rays, A, b, c)
    assert_allclose(t[hit], t_geo[hit], rtol=1e-10)


@pytest.mark.parametrize("seed", range(3))
def test_ray_depth_matches_reference_for_cylinders_and_ellipsoids(seed):
    rng = np.random.default_rng(seed)
    rays = np.column_stack([rng.uniform(-0.6, 0.6, (60, 2)), np.ones(60)])
    A, b, c = shapes.cylinder_quadric(
        rng.normal(size=(1, 3)), np.array([[0.5, 0, 8.0]]), np.array([1.5])
    )
    for Aq, bq, cq in (
        (A[0], b[0], c[0]),
        (np.diag([1.0, 0.5, 2.0]), np.array([0, 0, -40.0]), 190.0),
    ):
        fast = shapes.ray_depth(Aq, bq, cq, rays)
        ref = shapes.ray_depth_reference(Aq, bq, cq, rays)
        assert_allclose(fast, ref, rtol=1e-7)
        # per-ray model arrays give the same answer
        P = len(rays)
        many = shapes.ray_depth(
            np.broadcast_to(Aq, (P, 3, 3)), np.broadcast_to(bq, (P, 3)), np.full(P, cq), rays
        )
        assert_allclose(many, fast, rtol=1e-12)
