"""`mogs eval depth --dataset sim` building blocks on a tiny sequence (no docs are written)."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from mogs_node.eval.depth_sim import _pool, _summary, make_cases, run_methods


def test_sim_cases_and_methods():
    cases = make_cases(n_frames=2, seed=0, size=(310, 94), max_corners=300)
    assert len(cases) == 2
    acc: dict[str, list] = {}
    for case in cases:
        H, W = case.gt_m.shape
        assert case.prior.shape == (H, W) and case.masks["graph"].shape == (H, W)
        assert len(case.z) > 20 and np.all(case.z > 0)
        valid = np.isfinite(case.gt_m) & (case.gt_m <= 80)
        res = run_methods(case, "oracle")
        assert {"full", "no_msc", "no_msc_cdr", "full_eq6", "interp_nearest"} <= set(res)
        for name, r in res.items():
            _pool(acc, name, r.depth_m, case.gt_m, valid)
    table = _summary(acc)
    assert table["full"]["absrel"] < table["no_msc_cdr"]["absrel"]
    assert table["full"]["absrel"] < 0.1
    json.dumps(table)


@pytest.mark.slow
def test_eval_command_end_to_end(tmp_path, monkeypatch):
    """The full command (20 keyframes); it rewrites its docs/benchmarks.md section, so slow-only."""
    from mogs_node.eval import depth_sim

    monkeypatch.setattr(depth_sim, "update_markdown_section", lambda *a, **k: None)
    args = argparse.Namespace(
        frames=20,
        seed=0,
        masks="both",
        size=None,
        viz=None,
        json=str(tmp_path / "d.json"),
        dataset="sim",
        data=None,
    )
    fig = depth_sim.evaluate(args)
    m = fig["methods"]
    assert fig["frames"] == 20 and fig["dataset"] == "sim"
    assert m["full"]["absrel"] < m["no_msc"]["absrel"] < m["no_msc_cdr"]["absrel"]
    assert m["full"]["absrel"] <= 0.5 * m["no_msc_cdr"]["absrel"]
