"""Insertion: a depth disagreement inserts only where the map also draws the wrong colour
(``InsertionParams.disagree_color_tol``), the same rule for every depth source."""

from __future__ import annotations

import numpy as np
from hypothesis import example, given, settings
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
@example(tol=2.2e-308, conf=1.0, err=1.68e-303, behind=2.0)
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
    # the gate compares the float32 per-pixel colour error with the tolerance in float32 (NumPy
    # 2's promotion): err = 1.7e-303 is 0 there and does not pass tol = 2.2e-308
    err_px = np.abs(rgb - img).mean(-1)[0, 0]
    if tol == 0 or err_px > np.float32(tol):
        assert np.array_equal(gated, plain)
