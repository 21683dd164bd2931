"""Typed calibrations (issue 28): a rotation orthonormal to 1e-4 is projected to the nearest
rotation, a worse one is one error naming the parameter and the defect; static transform trees."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import GeometryError
from mogs_node.geometry import (
    make_T,
    nearest_rotation,
    rigid_transform,
    rotation_defect,
    se3_inverse,
    so3_exp,
    tf_lookup,
)

_PHI = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3).map(np.array)


@settings(max_examples=60, deadline=None)
@given(_PHI, st.integers(5, 9))
def test_rounded_rotation_is_projected_to_the_nearest_rotation(phi, decimals):
    R = so3_exp(phi)
    typed = np.round(make_T(R, [0.5, -1.0, 2.0]), decimals)
    T, defect = rigid_transform(typed.ravel().tolist(), "x.T")
    Rn = T[:3, :3]
    np.testing.assert_allclose(Rn @ Rn.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(Rn) == pytest.approx(1.0, abs=1e-12)
    assert defect == pytest.approx(rotation_defect(typed[:3, :3]))
    assert np.abs(Rn - R).max() <= 2 * 10.0**-decimals  # no further from the truth than typed
    np.testing.assert_array_equal(T[:3, 3], typed[:3, 3])


@settings(max_examples=40, deadline=None)
@given(_PHI)
def test_nearest_rotation_keeps_a_rotation(phi):
    R = so3_exp(phi)
    np.testing.assert_allclose(nearest_rotation(R), R, atol=1e-12)


def test_a_typed_rotation_off_by_1e_2_is_one_error_naming_the_parameter():
    T = make_T(so3_exp(np.array([0.1, 0.2, 0.3])), [1.0, 2.0, 3.0])
    T[1, 2] += 1e-2
    with pytest.raises(GeometryError, match=r"frontend\.T_imu_cam: the rotation is not ortho") as e:
        rigid_transform(T, "frontend.T_imu_cam")
    assert "R R^T - I| = 0.0" in str(e.value)  # the size of the defect, ~1e-2
    with pytest.raises(GeometryError, match="last row"):
        rigid_transform(np.r_[T[:3], [[0, 0, 1, 1]]], "a.T")
    with pytest.raises(GeometryError, match="16 numbers"):
        rigid_transform([1.0, 2.0], "a.T")
    with pytest.raises(GeometryError, match="not orthonormal"):  # a reflection
        rigid_transform(np.diag([1.0, 1.0, -1.0, 1.0]), "a.T")


def test_tf_lookup_walks_a_static_tree_both_ways():
    T_base_imu = make_T(so3_exp(np.array([0.0, 0.1, 0.0])), [0.1, 0.0, 0.2])
    T_base_cam = make_T(so3_exp(np.array([-1.5, 0.0, -1.5])), [0.3, 0.05, 0.1])
    edges = {("base", "imu"): T_base_imu, ("base", "cam"): T_base_cam}
    T_imu_cam = tf_lookup(edges, "imu", "cam")
    np.testing.assert_allclose(T_imu_cam, se3_inverse(T_base_imu) @ T_base_cam, atol=1e-12)
    np.testing.assert_allclose(tf_lookup(edges, "cam", "imu"), se3_inverse(T_imu_cam), atol=1e-12)
    assert tf_lookup(edges, "imu", "lidar") is None
    np.testing.assert_array_equal(tf_lookup({}, "a", "a"), np.eye(4))
