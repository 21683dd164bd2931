"""Property tests of ``mogs_node.geometry`` (issue 19): Lie-group round trips, the camera, ray casting.

In the style of kornia's Lie-group tests: random elements drawn by hypothesis, identities that must
hold for every one of them, and the edges (angles near 0 and near pi, tiny and huge translations).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import GeometryError, ShapeError
from mogs_node.geometry import (
    PinholeCamera,
    check_array,
    hat,
    intersect_rays_plane,
    intersect_rays_quadric,
    make_T,
    pixel_to_normalized,
    quat_wxyz_from_rotmat,
    quat_wxyz_to_rotmat,
    rotmat_from_rpy,
    se3_exp,
    se3_inverse,
    se3_log,
    so3_exp,
    so3_log,
    transform_points,
)

finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
unit_axis = st.tuples(finite, finite, finite).filter(lambda v: np.linalg.norm(v) > 1e-3)
# angles in [0, pi): log is unique there; near-pi angles get their own test
angle = st.one_of(
    st.floats(0.0, 1e-9), st.floats(1e-9, 1e-4), st.floats(1e-4, np.pi - 1e-3), st.just(0.0)
)
scale_m = st.sampled_from([1e-3, 1e-1, 1.0, 10.0, 1e3])


def _phi(axis: tuple[float, float, float], theta: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    return a / np.linalg.norm(a) * theta


def _is_rotation(R: np.ndarray, tol: float = 1e-10) -> bool:
    return bool(np.allclose(R @ R.T, np.eye(3), atol=tol) and abs(np.linalg.det(R) - 1) < tol)


@given(unit_axis, angle)
def test_so3_exp_is_a_rotation_and_log_inverts_it(axis, theta) -> None:
    phi = _phi(axis, theta)
    R = so3_exp(phi)
    assert _is_rotation(R)
    np.testing.assert_allclose(so3_log(R), phi, atol=1e-9)


@given(unit_axis, st.floats(0.0, 1e-6))
def test_so3_log_near_pi_gives_the_same_rotation(axis, eps) -> None:
    phi = _phi(axis, np.pi - eps)
    R = so3_exp(phi)
    back = so3_log(R)
    # at pi the sign of the axis is ambiguous: the rotation is what must come back
    np.testing.assert_allclose(so3_exp(back), R, atol=1e-8)
    assert np.linalg.norm(back) == pytest.approx(np.pi - eps, abs=1e-6)


@given(unit_axis, angle)
def test_hat_is_the_cross_product(axis, theta) -> None:
    v = _phi(axis, theta + 0.5)
    w = np.array([0.3, -1.2, 2.0])
    np.testing.assert_allclose(hat(v) @ w, np.cross(v, w), atol=1e-12)
    np.testing.assert_allclose(hat(v), -hat(v).T)


@given(unit_axis, angle)
def test_quaternion_round_trip_up_to_sign(axis, theta) -> None:
    R = so3_exp(_phi(axis, theta))
    q = quat_wxyz_from_rotmat(R)
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(quat_wxyz_to_rotmat(q), R, atol=1e-12)
    np.testing.assert_allclose(quat_wxyz_to_rotmat(-q), R, atol=1e-12)  # q and -q: one rotation
    # a quaternion scaled by any positive factor is normalised, not rejected
    np.testing.assert_allclose(quat_wxyz_to_rotmat(3.7 * q), R, atol=1e-12)


def test_quaternion_of_zero_or_nan_is_refused() -> None:
    with pytest.raises(GeometryError, match="quat_wxyz"):
        quat_wxyz_to_rotmat(np.zeros(4))
    with pytest.raises(GeometryError, match="quat_wxyz"):
        quat_wxyz_to_rotmat(np.array([1.0, np.nan, 0.0, 0.0]))


@given(st.floats(-3.0, 3.0), st.floats(-1.5, 1.5), st.floats(-3.0, 3.0))
def test_rpy_gives_rotations(roll, pitch, yaw) -> None:
    R = rotmat_from_rpy(np.array(roll), np.array(pitch), np.array(yaw))
    assert _is_rotation(R)


@given(unit_axis, angle, st.tuples(finite, finite, finite), scale_m)
def test_se3_exp_log_round_trip_at_every_scale(axis, theta, rho, s) -> None:
    xi = np.concatenate([np.asarray(rho) * s, _phi(axis, theta)])
    T = se3_exp(xi)
    assert _is_rotation(T[:3, :3]) and np.array_equal(T[3], [0, 0, 0, 1])
    np.testing.assert_allclose(se3_log(T), xi, atol=1e-9 * max(1.0, s), rtol=1e-9)


@given(unit_axis, angle, st.tuples(finite, finite, finite), scale_m)
def test_compose_and_inverse(axis, theta, t, s) -> None:
    T_a_b = make_T(so3_exp(_phi(axis, theta)), np.asarray(t) * s)
    T_b_c = se3_exp(np.array([0.1, -0.2, 0.3, 0.4, 0.0, -0.1]) * s**0)
    T_b_a = se3_inverse(T_a_b)
    np.testing.assert_allclose(T_a_b @ T_b_a, np.eye(4), atol=1e-12 * max(1.0, s))
    np.testing.assert_allclose(
        se3_inverse(T_a_b @ T_b_c), se3_inverse(T_b_c) @ T_b_a, atol=1e-9 * s
    )
    # points: T_a_c applied once equals T_a_b after T_b_c
    P = np.array([[1.0, 2.0, 3.0], [-4.0, 0.5, 10.0]]) * s
    np.testing.assert_allclose(
        transform_points(T_a_b @ T_b_c, P),
        transform_points(T_a_b, transform_points(T_b_c, P)),
        rtol=1e-10,
        atol=1e-10 * s,
    )


def test_batched_exp_log_equal_one_by_one() -> None:
    rng = np.random.default_rng(0)
    xi = rng.normal(size=(50, 6))
    norms = np.linalg.norm(xi[:, 3:], axis=1, keepdims=True)
    xi[:, 3:] *= np.minimum(1.0, 3.0 / norms)  # angles below pi, where log is unique
    T = se3_exp(xi)
    assert T.shape == (50, 4, 4)
    for i in (0, 17, 49):
        np.testing.assert_allclose(T[i], se3_exp(xi[i]), atol=1e-14)
    np.testing.assert_allclose(se3_log(T), xi, atol=1e-9)


cameras = st.builds(
    lambda f, aspect, w, h, cxr, cyr: PinholeCamera(f, f * aspect, cxr * w, cyr * h, w, h),
    st.floats(50.0, 2000.0),
    st.floats(0.8, 1.25),
    st.integers(16, 2000),
    st.integers(16, 1200),
    st.floats(0.3, 0.7),
    st.floats(0.3, 0.7),
)


@given(cameras, st.floats(1e-2, 1e3))
@settings(max_examples=60)
def test_project_backproject_round_trip(cam, depth_m) -> None:
    rng = np.random.default_rng(1)
    uv = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], size=(64, 2))
    z = np.full(64, depth_m)
    P = cam.backproject(uv, z)
    np.testing.assert_allclose(P[:, 2], z)
    uv_back, in_front = cam.project(P)
    assert in_front.all() and cam.in_image(uv_back).all()
    np.testing.assert_allclose(uv_back, uv, atol=1e-9 * max(1.0, depth_m))


@given(cameras)
@settings(max_examples=30)
def test_pixel_grid_rays_and_depth_image_agree_with_rays(cam) -> None:
    small = cam.scaled(min(cam.width, 40), min(cam.height, 30))
    grid = small.pixel_grid_rays()
    v, u = np.mgrid[0 : small.height, 0 : small.width]
    uv = np.stack([u.ravel(), v.ravel()], -1).astype(np.float64)
    np.testing.assert_allclose(grid.reshape(-1, 3), small.rays(uv), atol=1e-12)
    depth_m = np.full((small.height, small.width), 7.5)
    np.testing.assert_allclose(
        small.backproject_depth(depth_m).reshape(-1, 3), small.rays(uv) * 7.5
    )


@given(cameras, st.integers(8, 4000), st.integers(8, 3000))
@settings(max_examples=40)
def test_scaled_camera_keeps_the_ray_of_every_image_point(cam, w, h) -> None:
    """A point seen at the image's relative position (pixel-area convention) keeps its ray."""
    other = cam.scaled(w, h)
    rel = np.array([[0.5, 0.5], [0.1, 0.9], [0.77, 0.23]])  # positions in [0, 1] of the image
    uv_a = rel * [cam.width, cam.height] - 0.5
    uv_b = rel * [w, h] - 0.5
    np.testing.assert_allclose(other.rays(uv_b), cam.rays(uv_a), atol=1e-10)
    np.testing.assert_allclose(other.scaled(cam.width, cam.height).K, cam.K, rtol=1e-10, atol=1e-9)


@pytest.mark.parametrize(
    "vals",
    [
        (0.0, 100.0, 50.0, 50.0, 100, 100),
        (100.0, -1.0, 50.0, 50.0, 100, 100),
        (np.nan, 100.0, 50.0, 50.0, 100, 100),
        (100.0, 100.0, np.inf, 50.0, 100, 100),
        (100.0, 100.0, 50.0, 50.0, 0, 100),
    ],
)
def test_invalid_cameras_are_refused(vals) -> None:
    with pytest.raises(GeometryError, match="PinholeCamera"):
        PinholeCamera(*vals)


def test_points_behind_the_camera_are_flagged_not_divided_by_zero() -> None:
    cam = PinholeCamera(100.0, 100.0, 50.0, 40.0, 100, 80)
    uv, in_front = cam.project(np.array([[1.0, 1.0, -2.0], [0.0, 0.0, 0.0], [1.0, 2.0, 5.0]]))
    assert in_front.tolist() == [False, False, True]
    assert np.isfinite(uv).all()


@given(unit_axis, st.floats(-50.0, 50.0), scale_m)
def test_ray_plane_hits_lie_on_the_plane(normal, offset, s) -> None:
    n = np.asarray(normal) / np.linalg.norm(normal)
    rng = np.random.default_rng(2)
    dirs = rng.normal(size=(100, 3))
    origin = np.array([0.1, -0.2, 0.3]) * s
    t = intersect_rays_plane(origin, dirs, n, offset * s)
    hit = np.isfinite(t)
    assert (t[hit] > 0).all()
    pts = origin + t[hit, None] * dirs[hit]
    np.testing.assert_allclose(
        pts @ n + offset * s, 0.0, atol=1e-7 * s * (1 + np.abs(t[hit]).max())
    )
    # a miss is exactly the rays that point away from the plane (or are parallel to it)
    toward = (dirs @ n) * -(origin @ n + offset * s) > 0
    assert np.array_equal(hit, toward)


@given(st.floats(1e-2, 1e3), st.floats(2.0, 10.0))
def test_ray_sphere_nearest_hit(radius_m, dist_factor) -> None:
    """A sphere of radius r at distance d on the optical axis: the axis ray hits at d - r."""
    d = radius_m * dist_factor
    centre = np.array([0.0, 0.0, d])
    # x^T I x - 2 c^T x + |c|^2 - r^2 = 0
    A, b, c = np.eye(3), -2 * centre, centre @ centre - radius_m**2
    dirs = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    t = intersect_rays_quadric(np.zeros(3), dirs, A, b, c)
    assert t[0] == pytest.approx(d - radius_m, rel=1e-9)
    assert np.isinf(t[1]) and np.isinf(t[2])


def test_ray_cylinder_parallel_to_the_axis_misses_cleanly() -> None:
    """An infinite cylinder along z (A of rank 2): a ray along z is the linear, degenerate case."""
    A = np.diag([1.0, 1.0, 0.0])
    t = intersect_rays_quadric(
        np.array([[3.0, 0.0, 0.0], [0.0, 0.0, 0.0]]),
        np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
        A,
        np.zeros(3),
        -1.0,
    )
    assert np.isinf(t[0])  # outside the cylinder, parallel to it: never hits
    assert t[1] == pytest.approx(1.0)  # from the axis outwards: hits the wall at r = 1


def test_check_array_names_what_is_wrong() -> None:
    with pytest.raises(ShapeError, match=r"points: expected shape \[Nx3\], got \[4, 2\]"):
        check_array("points", np.zeros((4, 2)), shape=(None, 3))
    with pytest.raises(ShapeError, match="K: contains NaN"):
        check_array("K", np.full((3, 3), np.nan), shape=(3, 3), finite=True)
    with pytest.raises(ShapeError, match="ids: expected dtype"):
        check_array("ids", np.zeros(3), dtype=np.integer)
    with pytest.raises(ShapeError, match="T_dst_src"):
        transform_points(np.eye(3), np.zeros((2, 3)))


@given(cameras, st.floats(1e-2, 1e3))
@settings(max_examples=40)
def test_pixel_to_normalized_is_the_cameras_ray_and_broadcasts(cam, depth_m) -> None:
    rng = np.random.default_rng(2)
    uv = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], size=(32, 2))
    x, y = pixel_to_normalized(cam.K, uv[:, 0], uv[:, 1])
    np.testing.assert_array_equal(np.stack([x, y, np.ones(32)], -1), cam.rays(uv))
    P = np.stack([x * depth_m, y * depth_m, np.full(32, depth_m)], -1)
    np.testing.assert_allclose(cam.project(P)[0], uv, atol=1e-9 * max(1.0, depth_m))
    xg, yg = pixel_to_normalized(cam.K, np.arange(5)[None, :], np.arange(3)[:, None])
    assert xg.shape == (1, 5) and yg.shape == (3, 1)
