"""The camera-only scale's pure parts (docs/frontend.md, round 12): the distance from a
keyframe's points, the road height of triangulated points, the speed memory. Exact
expectations on synthetic geometry; hypothesis at the edges."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import ConfigError, ShapeError
from mogs_node.frontend.ground import road_height_of_points
from mogs_node.frontend.point_scale import distance_from_points
from mogs_node.frontend.speed_memory import SpeedMemory
from mogs_node.geometry import so3_exp

N_UP = np.array([0.0, 1.0, 0.0])  # a level camera: the road is along +y (down)


def _scene(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points [n, 3] ahead of the keyframe camera, 4-40 m."""
    return np.c_[rng.uniform(-8, 8, n), rng.uniform(-3, 1.6, n), rng.uniform(4, 40, n)]


def _observe(X: np.ndarray, R: np.ndarray, d: np.ndarray, s: float) -> np.ndarray:
    Y = (X - s * d) @ R.T
    return Y[:, :2] / Y[:, 2:]


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    s=st.floats(0.0, 3.0),
    rot=st.tuples(*[st.floats(-0.05, 0.05)] * 3),
    scale=st.floats(1e-3, 1e3),
)
def test_distance_from_points_is_exact_and_scale_equivariant(seed, s, rot, scale):
    rng = np.random.default_rng(seed)
    X = _scene(rng, 60)
    R = so3_exp(np.array(rot))
    d = np.array([0.05, -0.02, 1.0])
    d /= np.linalg.norm(d)
    xy = _observe(X, R, d, s)
    got = distance_from_points(X, xy, R, d)
    assert got is not None and got[2] == 60
    assert got[0] == pytest.approx(s, abs=1e-7)
    # the points' units are the distance's: scaled points, scaled distance
    got_scaled = distance_from_points(X * scale, xy, R, d * 7.0)  # any length of the direction
    assert got_scaled is not None
    assert got_scaled[0] == pytest.approx(s * scale, rel=1e-6, abs=1e-7 * scale)


def test_distance_from_points_resists_outliers_and_refuses_too_few():
    rng = np.random.default_rng(3)
    X = _scene(rng, 100)
    R, d = np.eye(3), np.array([0.0, 0.0, 1.0])
    xy = _observe(X, R, d, 1.2)
    xy[:25] += rng.normal(0, 0.05, (25, 2))  # a quarter of the tracks off by ~36 px
    got = distance_from_points(X, xy, R, d)
    assert got is not None and abs(got[0] - 1.2) < 0.02 and got[1] < 0.05
    assert distance_from_points(X[:9], xy[:9], R, d) is None  # min_points 10
    behind = X.copy()
    behind[:, 2] *= -1
    assert distance_from_points(behind, xy, R, d) is None  # behind the camera: not used
    assert distance_from_points(X, xy, R, np.zeros(3)) is None
    with pytest.raises(ShapeError, match="xy_cur"):
        distance_from_points(X, xy[:5], R, d)


def _road_scene(rng: np.random.Generator, h: float) -> np.ndarray:
    """Road points exactly ``h`` below a level camera (lane within 3 m, 5-25 m ahead), points
    on vehicles above it, and a few of a vehicle moving ahead triangulated too far (below)."""
    road = np.c_[rng.uniform(-3, 3, 30), np.full(30, h), rng.uniform(5, 25, 30)]
    cars = np.c_[rng.uniform(-3, 3, 40), rng.uniform(-1.0, 0.6 * h, 40), rng.uniform(6, 20, 40)]
    moving = np.c_[rng.uniform(-1, 1, 6), rng.uniform(2.5 * h, 3.5 * h, 6), rng.uniform(9, 12, 6)]
    return np.r_[road, cars, moving]


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(1e-2, 1e2))
def test_road_height_of_points_is_the_road_at_any_scale(seed, scale):
    rng = np.random.default_rng(seed)
    X = _road_scene(rng, 1.65)
    got = road_height_of_points(X * scale, N_UP)
    assert got is not None
    assert got[0] == pytest.approx(1.65 * scale, rel=1e-9)  # the road, not a quantile
    # a normal tilted by 0.1 deg (the mount known this well): heights along it within 5 %
    n = np.array([0.0, np.cos(0.002), np.sin(0.002)])
    tilted = road_height_of_points(X * scale, n)
    assert tilted is not None and tilted[0] == pytest.approx(1.65 * scale, rel=0.05)


def test_road_height_of_points_edges():
    rng = np.random.default_rng(0)
    X = _road_scene(rng, 1.65)
    assert road_height_of_points(X[:4], N_UP) is None  # fewer than min_points
    assert road_height_of_points(np.zeros((0, 3)), N_UP) is None
    above = X.copy()
    above[:, 1] = -np.abs(above[:, 1])  # nothing below the camera
    assert road_height_of_points(above, N_UP) is None
    nan = X.copy()
    nan[::2] = np.nan  # non-finite points are left out
    assert road_height_of_points(nan, N_UP) is not None
    with pytest.raises(ConfigError, match="window"):
        road_height_of_points(X, N_UP, window=0.0)
    with pytest.raises(ConfigError, match="optical axis"):
        road_height_of_points(X, np.array([0.0, 0.0, 1.0]))
    with pytest.raises(ShapeError, match="xyz_cam"):
        road_height_of_points(X[:, :2], N_UP)


def test_speed_memory_gate_rescale_and_interval_ratio():
    m = SpeedMemory(gate_rel=0.3, gate_window=9, relock_after=3)
    events = [m.gate(v) for v in (1.0, 1.1, 0.9, 3.0)]
    assert [e[1] for e in events] == ["ground_measurements"] * 3 + ["ground_gated"]
    assert events[-1][0] == 1.0 and m.speed_m_s == 1.0
    m.rescale(2.0)
    assert m.road_gain == 2.0 and m.speed_m_s == 2.0 and m.recent == [2.0, 2.2, 1.8]
    assert m.gated_run == [6.0]
    m.rescale(0.5, gain=False)  # the road was the reference: its gain stays
    assert m.road_gain == 2.0 and m.speed_m_s == 1.0
    m.remember(1.5)
    assert m.speed_m_s == 1.5 and m.gated_run == [] and m.recent[-1] == 1.5
    for road, chain in ((0.3, 0.1), (None, 0.1), (0.3, 0.1)):
        m.note(road, chain)
    assert m.interval_ratio() == pytest.approx(3.0)  # over the frames with both
    assert m.interval_ratio() is None  # reset: nothing since
    m.note(None, 0.1)
    m.note(None, 0.1)
    m.note(0.1, 0.1)
    assert m.interval_ratio() is None  # the road measured fewer than half the frames
