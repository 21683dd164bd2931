"""Insertion: a depth disagreement inserts only where the map also draws the wrong colour
(``InsertionParams.disagree_color_tol``), the same rule for every depth source."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.mapper.insertion import InsertionParams, insertion_mask

H, W = 4, 6


def scene() -> tuple[np.ndarray, ...]:
    """New depth 5 m (confidence 1) where the opaque map renders a surface at 10 m: every pixel
    disagrees; the rendered colour matches the image in the left half, is off in the right."""
    d = np.full((H, W), 5.0, np.float32)
    c = np.ones((H, W), np.float32)
    alpha = np.ones((H, W), np.float32)
    rdepth = np.full((H, W), 10.0, np.float32)
    img = np.full((H, W, 3), 0.5, np.float32)
    rgb = img.copy()
    rgb[:, W // 2 :] += 0.2
    return d, c, alpha, rdepth, rgb, img


def test_a_disagreement_where_the_map_draws_the_right_colour_inserts_nothing() -> None:
    d, c, alpha, rdepth, rgb, img = scene()
    every = insertion_mask(d, c, alpha, rdepth, InsertionParams(), rgb, img)
    assert every.all()  # 0: every disagreement counts (the former rule)
    p = InsertionParams(disagree_color_tol=0.05)
    m = insertion_mask(d, c, alpha, rdepth, p, rgb, img)
    assert not m[:, : W // 2].any() and m[:, W // 2 :].all()
    # no rendered colour given: the disagreement alone decides, as before
    assert insertion_mask(d, c, alpha, rdepth, p).all()
    # transparent pixels are unexplained whatever the colour
    alpha[0] = 0.0
    assert insertion_mask(d, c, alpha, rdepth, p, rgb, img)[0].all()


@settings(max_examples=50, deadline=None)
@given(
    tol=st.floats(0.0, 1.0),
    conf=st.floats(0.0, 1.0),
    err=st.floats(0.0, 1.0),
    behind=st.floats(0.0, 100.0),
)
def test_the_colour_gate_only_removes_disagreements(
    tol: float, conf: float, err: float, behind: float
) -> None:
    d = np.full((H, W), 5.0, np.float32)
    c = np.full((H, W), conf, np.float32)
    alpha = np.ones((H, W), np.float32)
    rdepth = d + np.float32(behind)
    img = np.zeros((H, W, 3), np.float32)
    rgb = np.full((H, W, 3), err, np.float32)
    gated = insertion_mask(d, c, alpha, rdepth, InsertionParams(disagree_color_tol=tol), rgb, img)
    plain = insertion_mask(d, c, alpha, rdepth, InsertionParams(), rgb, img)
    assert not (gated & ~plain).any()  # never inserts more
    if tol == 0 or err > tol:
        assert np.array_equal(gated, plain)
