"""complete_planar_masks: an object's plane over its holes only where the plane is supported."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.metrizer.fill import complete_planar_masks

H, W = 60, 80
K = np.array([[70.0, 0, 40.0], [0, 70.0, 30.0], [0, 0, 1]])


def plane_depth(n: np.ndarray, d: float) -> np.ndarray:
    """z-depth of the plane ``n . X = d`` (camera frame) at every pixel."""
    v, u = np.mgrid[0:H, 0:W].astype(float)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return (d / (rays @ n)).astype(np.float32)


@settings(max_examples=30, deadline=None)
@given(
    nx=st.floats(-0.5, 0.5),
    ny=st.floats(-0.5, 0.5),
    dist=st.floats(6.0, 40.0),
    hole_share=st.floats(0.05, 0.6),
)
def test_fills_holes_of_a_plane_exactly(nx: float, ny: float, dist: float, hole_share: float):
    n = np.array([nx, ny, 1.0])
    n /= np.linalg.norm(n)
    truth = plane_depth(n, dist)
    depth = truth.copy()
    hole = np.zeros((H, W), bool)
    hole[:, : int(hole_share * W)] = True  # a band: the plane is extrapolated into it
    depth[hole] = 0
    conf = np.where(hole, 0.0, 0.8).astype(np.float32)
    objects = np.zeros((H, W), np.int32)
    max_depth_m = 72.0
    n_filled = complete_planar_masks(
        depth, conf, objects, 1, extrapolation=10.0, max_depth_m=max_depth_m
    )
    # every hole pixel whose plane depth is within the fill's range gets it; beyond (a steep plane
    # towards its horizon) the hole stays empty
    fill = hole & (truth <= max_depth_m)
    assert n_filled == fill.sum()
    np.testing.assert_allclose(depth[fill], truth[fill], rtol=1e-4)
    assert np.all((conf[fill] > 0) & (conf[fill] <= 0.4 + 1e-6))
    assert np.all(depth[hole & ~fill] == 0)


def test_two_surfaces_in_one_mask_are_not_filled():
    """An under-segmented mask (a near wall and a far facade) has no plane: its hole stays."""
    depth = np.where(np.arange(W)[None, :] < W // 2, 8.0, 30.0) * np.ones((H, 1))
    depth = depth.astype(np.float32)
    depth[:20] = 0
    conf = (depth > 0).astype(np.float32)
    objects = np.zeros((H, W), np.int32)
    assert complete_planar_masks(depth, conf, objects, 1) == 0
    assert np.all(depth[:20] == 0)


def test_unsupported_near_and_other_objects_untouched():
    truth = plane_depth(np.array([0.0, 0.0, 1.0]), 10.0)
    objects = np.zeros((H, W), np.int32)
    objects[:, W // 2 :] = 1  # object 1: covered on 10% only
    depth = truth.copy()
    depth[:10, : W // 2] = 0  # object 0: a hole, well supported
    depth[6:, W // 2 :] = 0
    conf = (depth > 0).astype(np.float32)
    n = complete_planar_masks(depth, conf, objects, 2, min_share=0.3)
    assert n == 10 * (W // 2)
    assert np.all(depth[6:, W // 2 :] == 0)
    near = truth * 0.3  # 3 m: below min_depth_m
    near[:10] = 0
    assert complete_planar_masks(near, np.ones_like(near), np.zeros((H, W), np.int32), 1) == 0


def test_sky_and_empty_inputs():
    depth = np.full((H, W), 80.0, np.float32)  # all far: nothing to fit
    depth[:5] = 0
    assert complete_planar_masks(depth, np.ones_like(depth), np.zeros((H, W), np.int32), 1) == 0
    z = np.zeros((H, W), np.float32)
    assert complete_planar_masks(z, z.copy(), np.zeros((H, W), np.int32), 1) == 0
