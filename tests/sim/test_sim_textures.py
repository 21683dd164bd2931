"""Box-filtered texture patterns against brute-force integration (fast kernel vs slow reference)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.sim import SimConfig, make_sequence
from mogs_node.sim import textures as tx


def _brute(f, x: float, w: float, n: int = 20001) -> float:
    s = np.linspace(x - w / 2, x + w / 2, n)
    return float(np.mean(f(s)))


@settings(max_examples=80, deadline=None)
@given(x=st.floats(-20, 20), w=st.floats(0.01, 3.0), a=st.floats(-2, 2), width=st.floats(0.01, 2.0))
def test_band_coverage_is_box_filter(x: float, w: float, a: float, width: float) -> None:
    b = a + width
    got = float(tx.band_coverage(np.array([x]), a, b, np.array([w]))[0])
    ref = _brute(lambda s: ((s >= a) & (s <= b)).astype(float), x, w)
    assert abs(got - ref) < 2e-3


@settings(max_examples=80, deadline=None)
@given(
    x=st.floats(-20, 20),
    w=st.floats(0.01, 5.0),
    a=st.floats(-1, 1),
    frac=st.floats(0.01, 0.99),
    period=st.floats(0.2, 3.0),
)
def test_periodic_band_coverage_is_box_filter(
    x: float, w: float, a: float, frac: float, period: float
) -> None:
    b = a + frac * period
    got = float(tx.periodic_band_coverage(np.array([x]), a, b, period, np.array([w]))[0])
    ref = _brute(lambda s: (np.mod(s - a, period) < (b - a)).astype(float), x, w)
    assert abs(got - ref) < 2e-3


def test_filtered_cells_match_cells_away_from_edges_and_blend_at_edges() -> None:
    rng = np.random.default_rng(0)
    u, v = rng.uniform(-50, 50, 2000), rng.uniform(-50, 50, 2000)
    w = np.full(2000, 1e-4)
    np.testing.assert_allclose(
        tx.filtered_cell_hash2(u, v, 0.6, w, 3), tx.cell_hash2(u, v, 0.6, 3), atol=1e-3
    )
    # exactly on a cell edge (in u) with a wide filter: the average of the two cells
    ue = np.array([1.2])
    ve = np.array([0.3])
    got = tx.filtered_cell_hash2(ue, ve, 0.6, np.array([0.2]), 3)
    both = 0.5 * (tx.cell_hash2(ue - 0.01, ve, 0.6, 3) + tx.cell_hash2(ue + 0.01, ve, 0.6, 3))
    np.testing.assert_allclose(got, both, atol=1e-6)
    # cells much smaller than the footprint average out to 0.5
    np.testing.assert_allclose(
        tx.filtered_cell_hash3(u, v, u, 0.1, np.full(2000, 5.0)), 0.5, atol=1e-6
    )


def test_hash_is_uniform_and_deterministic() -> None:
    i = np.arange(-50000, 50000)
    h = tx.hash_u01(i, 7 * i, seed=5)
    assert h.min() >= 0.0 and h.max() < 1.0
    assert abs(h.mean() - 0.5) < 0.01 and abs(h.std() - np.sqrt(1 / 12)) < 0.01
    np.testing.assert_array_equal(h, tx.hash_u01(i, 7 * i, seed=5))
    assert not np.array_equal(h, tx.hash_u01(i, 7 * i, seed=6))


def test_single_frame_sequence() -> None:
    s = make_sequence(SimConfig(n_frames=1, width=32, height=16))
    assert len(s) == 1 and s.render(0).rgb.shape == (16, 32, 3)
