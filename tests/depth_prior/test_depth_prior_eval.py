"""Scoring of the dense prior: coverage, AbsRel and the error-against-confidence bins."""

from __future__ import annotations

import numpy as np
import pytest

from mogs_node.depth_prior.dense_prior import SOURCES, DensePrior
from mogs_node.eval.depth_prior_eval import calibration_bins, prior_params, score_priors


def _prior(depth: np.ndarray, conf: np.ndarray, source: int) -> DensePrior:
    return DensePrior(
        depth_m=depth.astype(np.float32),
        confidence=conf.astype(np.float32),
        rel_err=np.where(conf > 0, 0.05, np.inf).astype(np.float32),
        source=np.where(conf > 0, source, 0).astype(np.int8),
        sky=np.zeros(depth.shape, bool),
    )


def test_calibration_bins_exact() -> None:
    gt = np.full((2, 4), 10.0)
    gt[1, 3] = 0.0  # no ground truth: not scored
    depth = np.array([[11.0, 11.0, 10.5, 10.0], [10.0, 0.0, 12.0, 99.0]])
    conf = np.array([[0.95, 0.95, 0.45, 0.45], [0.45, 0.0, 0.02, 0.9]])
    bins = calibration_bins([_prior(depth, conf, SOURCES["flow"])], [gt])
    by = {(b["conf_lo"], b["conf_hi"]): b for b in bins}
    top = by[(0.9, 1.0)]
    assert top["pixels"] == 2 and top["absrel"] == pytest.approx(0.1)
    mid = by[(0.4, 0.5)]
    assert mid["pixels"] == 3 and mid["absrel"] == pytest.approx(0.05 / 3)
    assert mid["median_rel_err"] == pytest.approx(0.0)
    low = by[(0.0, 0.05)]
    assert low["pixels"] == 1 and low["absrel"] == pytest.approx(0.2)
    assert sum(b["pixels"] for b in bins) == 6
    assert sum(b["share"] for b in bins) == pytest.approx(1.0)
    assert top["share_flow"] == 1.0 and top["share_road"] == 0.0
    assert by[(0.5, 0.6)]["pixels"] == 0 and np.isnan(by[(0.5, 0.6)]["absrel"])


def test_score_priors_coverage_and_absrel() -> None:
    gt = np.full((2, 2), 10.0)
    a = np.array([[11.0, 0.0], [0.0, 0.0]])  # a quarter covered, 10 % off
    b = np.full((2, 2), 10.0)  # all covered, exact
    s = score_priors([a, b], [gt, gt], [0, 1])
    assert s["coverage"] == pytest.approx((0.25 + 1.0) / 2)
    assert s["min_keyframe_coverage"] == pytest.approx(0.25)
    assert s["absrel"] == pytest.approx(0.1 / 5)  # pooled over the 5 pixels


def test_prior_params_from_a_launch_section() -> None:
    f, r, u = prior_params(
        {"prior": {"flow": {"camera_height_m": 1.2}, "road": {"up_world": None}, "fusion": {}}}
    )
    assert f.camera_height_m == 1.2 and r.up_world is None and u.carry
    from mogs_node.errors import ConfigError

    with pytest.raises(ConfigError, match="nope"):
        prior_params({"prior": {"fusion": {"nope": 1}}})
