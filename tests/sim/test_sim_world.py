"""Ground truth of the synthetic world is exact: ray-cast depth equals analytic depth."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.geometry import PinholeCamera, make_T
from mogs_node.sim import (
    KIND_BOX,
    KIND_CYLINDER,
    KIND_ELLIPSOID,
    KIND_PLANE,
    Box,
    Cylinder,
    Ellipsoid,
    PlaneRect,
    World,
)
from mogs_node.sim.primitives import _unit_quadric_t

CAM = PinholeCamera(300.0, 300.0, 159.5, 99.5, 320, 200)
# camera looking along world +x, z up (x_cam = -y_world, y_cam = -z_world, z_cam = x_world)
R_FWD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _rays_world(T: np.ndarray) -> np.ndarray:
    return CAM.pixel_grid_rays() @ T[:3, :3].T


def test_tilted_plane_depth_is_analytic() -> None:
    # a facade rectangle, rotated 30 deg about z, 12 m ahead
    a = np.deg2rad(30)
    u = np.array([np.sin(a), np.cos(a), 0.0])
    plane = PlaneRect(np.array([12.0, 0.5, 1.0]), u, np.array([0.0, 0.0, 1.0]), 3.0, 2.0, seed=3)
    T = make_T(R_FWD, np.array([0.0, 0.0, 1.2]))
    out = World((plane,)).render(T, CAM)
    n = np.cross(u, [0.0, 0.0, 1.0])
    # analytic: points o + t d on the plane n.(x - c) = 0 -> t = n.(c - o) / n.d
    d = _rays_world(T)
    t = (n @ (plane.center - T[:3, 3])) / (d @ n)
    p = T[:3, 3] + t[..., None] * d
    q = p - plane.center
    inside = (np.abs(q @ u) <= 3.0) & (np.abs(q[..., 2]) <= 2.0)
    assert inside.sum() > 2000
    assert np.all(out.instance_id[inside] == 0)
    np.testing.assert_allclose(out.depth_m[inside], t[inside], rtol=1e-6)
    border = np.abs(np.abs(q @ u) - 3.0) < 0.02
    away = ~inside & ~border & (np.abs(np.abs(q[..., 2]) - 2.0) > 0.02)
    assert np.all(np.isinf(out.depth_m[away])) and np.all(out.instance_id[away] == -1)


def test_cylinder_depth_is_analytic() -> None:
    D, r = 10.0, 0.8
    cyl = Cylinder(np.array([D, 0.0]), r, 0.0, 5.0, "trunk", seed=1)
    T = make_T(R_FWD, np.array([0.0, 0.0, 1.5]))
    out = World((cyl,)).render(T, CAM)
    # horizontal angle of each pixel's ray from the forward axis (camera x is world -y)
    x = (np.arange(CAM.width) - CAM.cx_px) / CAM.fx_px
    alpha = np.arctan(x)
    with np.errstate(invalid="ignore"):
        rho = D * np.cos(alpha) - np.sqrt(r**2 - (D * np.sin(alpha)) ** 2)  # horizontal range
    z_col = rho * np.cos(alpha)  # forward (z) component
    y = (np.arange(CAM.height) - CAM.cy_px) / CAM.fy_px
    Z = np.broadcast_to(z_col[None, :], (CAM.height, CAM.width))
    height = 1.5 - y[:, None] * Z  # world z of the hit
    hit = np.isfinite(Z) & (height > 0.0) & (height < 5.0)
    inner = hit & (np.abs(x[None, :] * D) < r * 0.97) & (height > 0.05) & (height < 4.95)
    assert inner.sum() > 1000
    np.testing.assert_allclose(out.depth_m[inner], Z[inner], rtol=1e-6)
    assert np.all(out.instance_id[inner] == 0)
    # the rays closest to the axis see about D - r
    assert out.depth_m[CAM.height // 2, int(CAM.cx_px)] == pytest.approx(D - r, rel=1e-4)
    assert np.all(np.isinf(out.depth_m[~hit & ~np.isfinite(Z)]))


def test_ellipsoid_depth_is_analytic() -> None:
    a, b, c, D = 2.0, 1.0, 1.5, 9.0
    ell = Ellipsoid(np.array([0.0, 0.0, D]), np.array([a, b, c]), 0.0, "car", seed=2)
    T = np.eye(4)  # camera frame = world frame here: looking along +z
    out = World((ell,)).render(T, CAM)
    # analytic: (t x / a)^2 + (t y / b)^2 + ((t - D) / c)^2 = 1 ; nearest root
    g = CAM.pixel_grid_rays()
    x, y = g[..., 0], g[..., 1]
    A = (x / a) ** 2 + (y / b) ** 2 + 1 / c**2
    B = -2 * D / c**2
    C = D**2 / c**2 - 1
    disc = B * B - 4 * A * C
    hit = disc > 1e-3
    t = (-B - np.sqrt(np.where(hit, disc, 0.0))) / (2 * A)
    assert hit.sum() > 2000
    np.testing.assert_allclose(out.depth_m[hit], t[hit], rtol=1e-5)
    assert np.all(np.isinf(out.depth_m[disc < -1e-3]))
    # centre pixel: exactly D - c (the ray along the optical axis)
    assert out.depth_m[int(CAM.cy_px + 0.5), int(CAM.cx_px + 0.5)] == pytest.approx(
        (-B - np.sqrt(B * B - 4 * A[100, 160] * C)) / (2 * A[100, 160]), rel=1e-6
    )


def test_box_front_face_depth() -> None:
    box = Box(np.array([0.0, 0.0, 8.0]), np.array([1.0, 0.8, 0.5]), 0.0, seed=4)
    out = World((box,)).render(np.eye(4), CAM)
    g = CAM.pixel_grid_rays()
    front = (np.abs(g[..., 0] * 7.5) < 0.98) & (np.abs(g[..., 1] * 7.5) < 0.78)
    np.testing.assert_allclose(out.depth_m[front], 7.5, rtol=1e-6)
    assert np.all(out.instance_id[front] == 0)


def test_occlusion_and_instance_kinds() -> None:
    near = Ellipsoid(np.array([0.0, 0.0, 5.0]), np.array([0.5, 0.5, 0.5]))
    far = PlaneRect(
        np.array([0.0, 0.0, 20.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), 10.0, 10.0
    )
    cyl = Cylinder(np.array([3.0, 0.0]), 0.3, -10.0, 10.0)
    box = Box(np.array([-3.0, 0.0, 10.0]), np.array([0.5, 0.5, 0.5]))
    w = World((far, near, cyl, box))
    out = w.render(np.eye(4), CAM)
    assert list(w.instance_kind) == [KIND_PLANE, KIND_ELLIPSOID, KIND_CYLINDER, KIND_BOX]
    c = (int(CAM.cy_px + 0.5), int(CAM.cx_px + 0.5))
    assert out.instance_id[c] == 1 and out.depth_m[c] == pytest.approx(4.5, rel=1e-4)
    hit = out.instance_id >= 0
    assert np.all(np.isfinite(out.depth_m[hit])) and np.all(np.isinf(out.depth_m[~hit]))
    assert set(np.unique(out.instance_id)) == {-1, 0, 1, 2, 3}
    # the plane is behind everything else: its depth is the largest
    assert out.depth_m[out.instance_id == 0].min() > out.depth_m[out.instance_id == 1].max()


finite = st.floats(-3.0, 3.0, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(
    center=st.tuples(finite, finite, st.floats(4.0, 30.0)),
    radii=st.tuples(st.floats(0.2, 3.0), st.floats(0.2, 3.0), st.floats(0.2, 3.0)),
    yaw=st.floats(-np.pi, np.pi),
    seed=st.integers(0, 1000),
)
def test_fast_ellipsoid_kernel_matches_reference(center, radii, yaw, seed) -> None:
    e = Ellipsoid(np.array(center), np.array(radii), yaw)
    rng = np.random.default_rng(seed)
    d = np.concatenate([rng.normal(0, 0.3, (400, 2)), np.ones((400, 1))], 1)
    o = rng.normal(0, 0.5, 3)
    fast, ref = e.intersect(o, d), e.intersect_reference(o, d)
    np.testing.assert_array_equal(np.isinf(fast), np.isinf(ref))
    m = np.isfinite(ref)
    np.testing.assert_allclose(fast[m], ref[m], rtol=1e-7)


@settings(max_examples=60, deadline=None)
@given(
    cx=st.floats(3.0, 30.0),
    cy=finite,
    r=st.floats(0.05, 2.0),
    z1=st.floats(0.5, 8.0),
    seed=st.integers(0, 1000),
)
def test_fast_cylinder_kernel_matches_reference(cx, cy, r, z1, seed) -> None:
    c = Cylinder(np.array([cx, cy]), r, 0.0, z1)
    rng = np.random.default_rng(seed)
    d = np.concatenate([np.ones((400, 1)), rng.normal(0, 0.3, (400, 2))], 1)
    o = np.array([0.0, 0.0, 1.5])
    fast, ref = c.intersect(o, d), c.intersect_reference(o, d)
    np.testing.assert_array_equal(np.isinf(fast), np.isinf(ref))
    m = np.isfinite(ref)
    np.testing.assert_allclose(fast[m], ref[m], rtol=1e-7)


def test_unit_quadric_inside_takes_far_root() -> None:
    t = _unit_quadric_t(np.zeros(3), np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0]]))
    np.testing.assert_allclose(t, [1.0, 0.5])
