"""Insertion: a pixel the map covers but draws in the wrong colour is unexplained
(``InsertionParams.color_tol``), the same rule for every depth source; the mapper node passes it."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.mapper.insertion import InsertionParams, insertion_mask

H, W = 4, 8


def opaque_scene(depth_m: float) -> tuple[np.ndarray, ...]:
    """An opaque map rendering exactly the new depth (no disagreement anywhere); its colour is
    off by 0.3 in the right half and by 0.1 in the left half."""
    d = np.full((H, W), depth_m, np.float32)
    c = np.ones((H, W), np.float32)
    alpha = np.ones((H, W), np.float32)
    img = np.full((H, W, 3), 0.4, np.float32)
    rgb = img + np.float32(0.1)
    rgb[:, W // 2 :] = img[:, W // 2 :] + np.float32(0.3)
    return d, c, alpha, d.copy(), rgb, img


def test_a_wrong_colour_is_unexplained_above_the_tolerance_only() -> None:
    d, c, alpha, rdepth, rgb, img = opaque_scene(5.0)
    assert not insertion_mask(d, c, alpha, rdepth, InsertionParams(), rgb, img).any()  # 0: off
    m = insertion_mask(d, c, alpha, rdepth, InsertionParams(color_tol=0.2), rgb, img)
    assert not m[:, : W // 2].any() and m[:, W // 2 :].all()
    # a pixel without depth gets nothing from this rule (the far sphere handles the sky)
    d[0, -1] = 0.0
    m = insertion_mask(d, c, alpha, rdepth, InsertionParams(color_tol=0.2), rgb, img)
    assert not m[0, -1] and m[1, -1]
    # no rendered colour given: the rule cannot apply
    assert not insertion_mask(d, c, alpha, rdepth, InsertionParams(color_tol=0.2)).any()


def test_the_colour_rule_reads_neither_the_depth_values_nor_the_confidence() -> None:
    """Random depth at confidence 0 and metric depth at confidence 1 with the same render: the
    colour rule marks the same pixels (Table II's one policy for every source)."""
    d, c, alpha, rdepth, rgb, img = opaque_scene(5.0)
    p = InsertionParams(color_tol=0.2)
    metric = insertion_mask(d, c, alpha, rdepth, p, rgb, img)
    rng = np.random.default_rng(0)
    d_rand = rng.uniform(1.0, 50.0, (H, W)).astype(np.float32)
    c0 = np.zeros((H, W), np.float32)
    random = insertion_mask(d_rand, c0, alpha, rdepth, p, rgb, img)
    np.testing.assert_array_equal(metric, random)


@settings(max_examples=50, deadline=None)
@given(
    low=st.floats(0.0, 1.0),
    high=st.floats(0.0, 1.0),
    err=st.floats(0.0, 1.0),
    conf=st.floats(0.0, 1.0),
    behind=st.floats(-10.0, 100.0),
)
def test_a_higher_colour_tolerance_never_inserts_more(
    low: float, high: float, err: float, conf: float, behind: float
) -> None:
    low, high = sorted((low, high))
    d = np.full((H, W), 5.0, np.float32)
    c = np.full((H, W), conf, np.float32)
    alpha = np.full((H, W), 0.95, np.float32)
    rdepth = np.maximum(d + np.float32(behind), 0.0)
    img = np.zeros((H, W, 3), np.float32)
    rgb = np.full((H, W, 3), err, np.float32)
    lo = insertion_mask(d, c, alpha, rdepth, InsertionParams(color_tol=low), rgb, img)
    hi = insertion_mask(d, c, alpha, rdepth, InsertionParams(color_tol=high), rgb, img)
    plain = insertion_mask(d, c, alpha, rdepth, InsertionParams(), rgb, img)
    if low > 0:
        assert not (hi & ~lo).any()
    assert not (plain & ~hi).any() and not (plain & ~lo).any()  # it only ever adds pixels


def test_the_mapper_node_params_reach_the_core() -> None:
    from mogs_node.mapper.node import MapperNodeParams

    ins = MapperNodeParams().mapper_params().insertion
    assert ins.color_tol == 0.0 and ins.disagree_color_tol == 0.0  # the defaults: off
    ins = (
        MapperNodeParams(insertion_color_tol=0.2, insertion_disagree_color_tol=0.1)
        .mapper_params()
        .insertion
    )
    assert ins.color_tol == 0.2 and ins.disagree_color_tol == 0.1
