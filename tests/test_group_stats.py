"""Per-group statistics (mogs_node/group_stats.py), shared by the depth prior and the metrizer."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.group_stats import group_medians


def test_group_medians_of_a_small_example() -> None:
    counts, med = group_medians(np.array([1, 1, 1, 0, 1]), np.array([3.0, 1.0, 2.0, 7.0, 9.0]), 3)
    assert counts.tolist() == [1, 4, 0]
    assert med[0] == 7.0 and med[1] == 2.5 and np.isnan(med[2])


def test_no_values_give_zero_counts_and_nan_medians() -> None:
    counts, med = group_medians(np.zeros(0, np.intp), np.zeros(0), 4)
    assert counts.tolist() == [0, 0, 0, 0]
    assert med.shape == (4,) and np.isnan(med).all()
    counts, med = group_medians(np.zeros(0, np.intp), np.zeros(0), 0)
    assert counts.shape == med.shape == (0,)


def test_a_nan_sorts_last_in_its_group() -> None:
    keys = np.array([0, 0, 0, 1, 1, 1])
    _, med = group_medians(keys, np.array([np.nan, 1.0, 2.0, np.nan, np.nan, 5.0]), 2)
    assert med[0] == 2.0  # [1, 2, nan]: the middle value is 2
    assert np.isnan(med[1])  # [5, nan, nan]: the middle value is nan


@settings(max_examples=60, deadline=None)
@given(
    st.integers(1, 6),
    st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=0, max_size=60),
    st.integers(0, 2**31 - 1),
    st.sampled_from([np.float64, np.float32]),
)
def test_group_medians_match_numpy(n_groups, values, seed, dtype) -> None:
    v = np.asarray(values, dtype)
    g = np.random.default_rng(seed).integers(0, n_groups, len(v))
    counts, got = group_medians(g, v, n_groups)
    assert got.dtype == np.float64
    assert np.array_equal(counts, np.bincount(g, minlength=n_groups))
    for k in range(n_groups):
        if (g == k).any():
            want = np.median(v[g == k].astype(np.float64))
            assert got[k] == pytest.approx(
                want, rel=1e-6 if dtype == np.float32 else 1e-12, abs=1e-12
            )
        else:
            assert np.isnan(got[k])
