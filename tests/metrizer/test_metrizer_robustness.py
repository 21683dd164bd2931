"""The metrizer is never worse than its own global-affine baseline (issue 16, item 3).

Sim frames (``mogs_node.sim``, 248x75) with the simulated LFM as prior; hypothesis draws the
number of sparse points (0-2000, ground truth at pixels off depth edges, 1% noise), the share of
the image with a prior (0-100%, low-frequency blobs), the share of gross outliers among the
points (0-30%, depth times exp(+-[0.3, 1.5])), the metric scale of the world (1e-2..1e3: depths
and ``d_min`` / ``d_max`` scaled together), the masks (oracle instance ids | graph
over-segmentation) and the mode (``full`` | ``no_msc``). The rule asserted (docs/metrizer.md,
"Never worse than the global affine"):

- the output is finite and valid for every draw;
- on the pixels where the ``no_msc_cdr`` baseline has a value, the AbsRel of the metrizer is at
  most 1.1 times the baseline's;
- pixels without prior (where the baseline has no value) get a value only from nearby sparse
  evidence; their AbsRel stays below an absolute bound (there is nothing to compare with).
"""

from __future__ import annotations

from functools import cache

import cv2
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mogs_node.metrizer.pipeline import MetrizerParams, metrize_depth

W, H = 248, 75
N_FRAMES = 3


@cache
def _frames():
    """Three rendered sim frames ``(rgb, depth_m, instance_id, graph labels, K)`` (once)."""
    from mogs_node.segmentation.graph import GraphSegParams, segment_graph
    from mogs_node.sim import SimConfig, make_sequence

    seq = make_sequence(SimConfig(seed=3, n_frames=12, width=W, height=H))
    out = []
    for i in (0, 5, 11):
        f = seq.render(i)
        graph = segment_graph(f.rgb, GraphSegParams(scale=1.0))
        out.append((f.rgb, f.depth_m, f.instance_id, graph, seq.camera.K))
    return out


def _case(frame, n_points, coverage, outliers, scale, masks, seed):
    """Metrizer keyword arguments, params and the scaled ground truth (0 = none) of one draw."""
    from mogs_node.eval.depth_sim import _depth_edge_free
    from mogs_node.sim import LfmParams, simulated_lfm

    rgb, depth, inst, graph, K = _frames()[frame]
    rng = np.random.default_rng(seed)
    d = depth.astype(np.float64)
    ok = np.flatnonzero((np.isfinite(d) & (d > 0) & _depth_edge_free(depth)).ravel())
    pick = rng.choice(ok, min(n_points, len(ok)), replace=False)
    uv = np.c_[pick % W, pick // W] + rng.uniform(-0.3, 0.3, (len(pick), 2))
    z = d.ravel()[pick] * (1.0 + 0.01 * rng.standard_normal(len(pick)))
    bad = rng.random(len(z)) < outliers
    z[bad] *= np.exp(rng.choice([-1.0, 1.0], bad.sum()) * rng.uniform(0.3, 1.5, bad.sum()))
    prior = simulated_lfm(depth, rng, LfmParams())
    blobs = cv2.resize(
        rng.random((H // 8, W // 8)).astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR
    )
    conf = (blobs < np.quantile(blobs, coverage)).astype(np.float32)
    if coverage >= 1.0:
        conf[:] = 1.0
    kw = dict(
        K=K,
        labels=inst if masks == "oracle" else graph,
        feature_uv_px=uv,
        feature_depth_m=z * scale,
        feature_weight=np.ones(len(z)),
        prior=prior,
        prior_confidence=conf,
        prior_kind="relative_inverse_depth",
        image_rgb=rgb,
    )
    params = MetrizerParams(d_min_m=0.1 * scale, d_max_m=80.0 * scale)
    gt = np.where(np.isfinite(d) & (d > 0) & (d < 80.0), d * scale, 0.0)
    return kw, params, gt


def _absrel(pred, gt, mask):
    return float(np.mean(np.abs(pred[mask] - gt[mask]) / gt[mask]))


def _check_valid(out, d_max):
    d, c = out.depth_m, out.confidence
    assert d.shape == (H, W) and np.all(np.isfinite(d)) and np.all(np.isfinite(c))
    assert np.all(d >= 0) and np.all(d <= d_max)
    assert np.all((c >= 0) & (c <= 1)) and np.all(c[d == 0] == 0)


def _metrize_within_baseline(kw, params, gt, mode="full"):
    """Metrized and global-affine depth ``(d, b)`` of one case, after the checks every stress
    test makes: both valid, every baseline pixel covered, AbsRel within 10 % of the baseline's."""
    out = metrize_depth(**kw, params=params, mode=mode)
    base = metrize_depth(**kw, params=params, mode="no_msc_cdr")
    for o in (out, base):
        _check_valid(o, params.d_max_m)
    d, b = out.depth_m, base.depth_m
    shared = (gt > 0) & (b > 0) & (d > 0)
    # the metrizer covers every pixel the baseline covers (it never drops a prior pixel)
    assert np.all(d[(gt > 0) & (b > 0)] > 0)
    if shared.any():
        assert _absrel(d, gt, shared) <= 1.1 * _absrel(b, gt, shared) + 1e-4
    return d, b


@settings(
    max_examples=30,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(
    frame=st.integers(0, N_FRAMES - 1),
    n_points=st.sampled_from([0, 1, 2, 5, 10, 40, 150, 600, 2000]),
    coverage=st.sampled_from([0.0, 0.05, 0.2, 0.5, 0.9, 1.0]),
    outliers=st.floats(0.0, 0.3),
    log_scale=st.floats(-2.0, 3.0),
    masks=st.sampled_from(["oracle", "graph"]),
    mode=st.sampled_from(["full", "no_msc"]),
    seed=st.integers(0, 2**16),
)
def test_never_worse_than_global_affine(
    frame, n_points, coverage, outliers, log_scale, masks, mode, seed
):
    kw, params, gt = _case(frame, n_points, coverage, outliers, 10.0**log_scale, masks, seed)
    d, b = _metrize_within_baseline(kw, params, gt, mode)
    hole = (gt > 0) & (b == 0) & (d > 0)
    if hole.sum() >= 50:  # pixels without prior: filled from the frame's own metric evidence
        # (nearby features, an object's plane), so never much worse than the depth it extends;
        # where the sparse points mis-scale the whole frame (5 points, one an outlier: the
        # global affine 3x off), the whole-mask plane carries that scale into the holes
        shared = (gt > 0) & (b > 0) & (d > 0)
        frame_err = _absrel(d, gt, shared) if shared.sum() >= 50 else 0.0
        assert _absrel(d, gt, hole) <= max(0.6, 1.5 * frame_err)


def test_no_prior_and_no_points_gives_nothing_but_sky_free_zeros():
    """No prior and no sparse points: no evidence at all, so no depth anywhere."""
    kw, params, _ = _case(0, 0, 0.0, 0.0, 1.0, "oracle", 0)
    out = metrize_depth(**kw, params=params)
    _check_valid(out, params.d_max_m)
    assert np.all(out.depth_m == 0)


def test_gross_outliers_do_not_seed_the_fill_of_pixels_without_prior():
    """600 points, 30% gross outliers, no prior: the filled pixels stay accurate (the outliers
    are rejected by their neighbours) and far from evidence nothing is invented."""
    kw, params, gt = _case(1, 600, 0.0, 0.3, 1.0, "oracle", 1)
    out = metrize_depth(**kw, params=params)
    d = out.depth_m
    filled = (gt > 0) & (d > 0)
    assert filled.sum() > 0.3 * (gt > 0).sum()
    assert _absrel(d, gt, filled) < 0.1
