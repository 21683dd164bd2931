"""``mogs eval depth --dataset demo``: strips and the demo drive's figures."""

from __future__ import annotations

import argparse

import cv2
import numpy as np
import pytest

from mogs_node.eval.depth_demo import write_strip


def test_strip_has_five_panels_and_marks_the_error(tmp_path) -> None:
    H, W = 40, 60
    rgb = np.full((H, W, 3), 128, np.uint8)
    gt = np.full((H, W), 10.0, np.float32)
    gt[:5] = 0.0  # sky: no ground truth
    depth = gt.copy()
    depth[20:, :30] = 20.0  # 100 % wrong
    depth[20:, 30:] = 0.0  # no value
    prior = np.full((H, W), 0.1, np.float32)
    write_strip(tmp_path / "s.png", rgb, np.array([[5.0, 5.0]]), prior, prior * 0, depth, gt)
    img = cv2.imread(str(tmp_path / "s.png"))[..., ::-1]
    assert img.shape == (5 * H, W, 3)
    err = img[4 * H :]
    red, blue, grey = err[30, 10], err[15, 40], err[30, 50]
    assert red[0] > 100 and red[2] < 100  # AbsRel 1 -> red end
    assert blue[2] > red[2] and blue[0] < red[0]  # AbsRel 0 -> blue end
    assert np.all(grey == 40)  # no depth
    assert not img[H : 2 * H][20:].any()  # prior with confidence 0: black


@pytest.mark.slow
def test_demo_eval_scores_every_keyframe(tmp_path) -> None:
    from mogs_node.eval.depth_demo import evaluate

    fig = evaluate(argparse.Namespace(frames=None, seed=0, viz=str(tmp_path), launch=None))
    assert fig["dataset"] == "demo" and fig["frames"] >= 10
    full, base = fig["methods"]["full"], fig["methods"]["no_msc_cdr"]
    assert np.isfinite(full["absrel"]) and 0 < full["coverage"] <= 1
    assert full["absrel"] <= 1.1 * base["absrel"]  # never worse than the global affine
    assert len(list(tmp_path.glob("demo_kf*.png"))) == fig["frames"]
