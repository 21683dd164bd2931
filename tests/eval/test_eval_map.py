"""``mogs eval map`` helpers (``eval/map.py``): the init comparison's ratios and the parameter
overrides every init shares."""

from __future__ import annotations

import pytest

from mogs_node.errors import ConfigError
from mogs_node.eval.map import _parse_override, _ratios, overrides_from
from mogs_node.mapper.insertion import InsertionParams


def test_map_eval_ratios_bound_when_random_never_reaches_target() -> None:
    inits = {
        "mogs": {"iters_to_target": 60, "gaussians_at_target": 900, "gaussians_at_budget": 1000},
        "random": {
            "iters_to_target": None,
            "gaussians_at_target": None,
            "gaussians_at_budget": 500,
        },
    }
    r = _ratios(inits, budget=300)
    assert r["iters_ratio_mogs_vs_random"] == pytest.approx(0.2) and r["iters_ratio_is_upper_bound"]
    assert r["gaussians_ratio_mogs_vs_random"] is None
    assert r["gaussians_at_budget_ratio_mogs_vs_random"] == pytest.approx(2.0)
    assert r["gaussians_ratio_mogs_target_vs_random_budget"] == pytest.approx(1.8)
    inits["random"]["iters_to_target"] = 120
    inits["random"]["gaussians_at_target"] = 1800
    r = _ratios(inits, budget=300)
    assert (
        r["iters_ratio_mogs_vs_random"] == pytest.approx(0.5)
        and not r["iters_ratio_is_upper_bound"]
    )
    assert r["gaussians_ratio_mogs_vs_random"] == pytest.approx(0.5)


def test_map_eval_overrides_parse_into_one_policy_for_every_init() -> None:
    pairs = [_parse_override(s) for s in ("densify=true", "insertion.color_tol=0.1")]
    o = overrides_from(pairs + [_parse_override("densify_grad_px=6e-6")])
    assert o["densify"] is True and o["densify_grad_px"] == pytest.approx(6e-6)
    assert o["insertion"] == InsertionParams(color_tol=0.1)
    with pytest.raises(ConfigError, match="no_such"):
        overrides_from([("no_such", 1)])
    with pytest.raises(ConfigError, match="raster"):
        overrides_from([("raster", 1)])
