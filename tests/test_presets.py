"""Presets (issue 27): every launch file resolves and validates with each preset; the order of
precedence file < preset < --set; nested groups merged key by key; roles a file lacks skipped;
an unknown name is one clear error; a short sim drive runs end to end with each preset (slow)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st
from test_launch_files import LAUNCH_FILES, _nested

from mogs_node.commands.launch import parse_overrides
from mogs_node.commands.node import load_node_class
from mogs_node.errors import ConfigError
from mogs_node.launch import load_launch_file, parse_launch
from mogs_node.params import parse_params
from mogs_node.presets import PRESETS, ROLES, apply_preset, deep_merge, help_text, role_of

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("preset", list(PRESETS))
@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.stem)
def test_every_launch_file_resolves_and_validates_with_each_preset(path: Path, preset: str):
    lf = load_launch_file(path, preset=preset)
    plain = {s.name: s.params for s in load_launch_file(path).nodes}
    for spec in lf.nodes:
        parsed = parse_params(
            load_node_class(spec.cls).Params, spec.params, where=f"{path.stem}.{spec.name}"
        )
        _nested(spec, parsed)
        # the preset's table for this node's role, and nothing else, moved its parameters
        table = PRESETS[preset].get(role_of(spec.cls) or "", {})
        assert spec.params == deep_merge(plain[spec.name], table)


def _demo(preset_key: str | None = None) -> dict:
    data = yaml.safe_load((REPO / "launch" / "demo.yaml").read_text())
    if preset_key is not None:
        data["preset"] = preset_key
    return data


def _params(lf, name: str) -> dict:
    return next(s.params for s in lf.nodes if s.name == name)


def test_precedence_file_then_preset_then_set() -> None:
    # no preset anywhere: balanced, the file's own values
    data = _demo()
    own = next(n for n in data["nodes"] if n["name"] == "mapper")["params"]["iters_per_keyframe"]
    lf = parse_launch(data)
    assert _params(lf, "mapper")["iters_per_keyframe"] == own
    assert own != PRESETS["fast"]["mapper"]["iters_per_keyframe"]  # so that the next check bites
    # the preset overrides the file; nested groups merge: the prior keeps its own flow keys
    fast = PRESETS["fast"]
    data = _demo()
    metrizer = next(n for n in data["nodes"] if n["name"] == "metrizer")
    metrizer["params"]["cdr"] = {"lambda_sm": 0.2}  # a nested group the file and fast both set
    lf = parse_launch(data, preset="fast")
    mapper, cdr = _params(lf, "mapper"), _params(lf, "metrizer")["cdr"]
    assert mapper["iters_per_keyframe"] == fast["mapper"]["iters_per_keyframe"]
    assert mapper["background_depth_m"] == 200.0  # a key the preset does not name
    assert cdr == {"lambda_sm": 0.2, "irls_iters": fast["metrizer"]["cdr"]["irls_iters"]}
    # `preset:` in the file, and --preset over it
    assert _params(parse_launch(_demo("quality")), "mapper")["train_downsample"] == 1
    assert (
        _params(parse_launch(_demo("quality"), preset="fast"), "mapper")["train_downsample"]
        == (fast["mapper"]["train_downsample"])
    )
    # an explicit --set wins over the preset
    over = parse_overrides(["mapper.iters_per_keyframe=13"])
    lf = parse_launch(_demo(), preset="fast", overrides=over)
    assert _params(lf, "mapper")["iters_per_keyframe"] == 13
    assert _params(lf, "mapper")["train_downsample"] == fast["mapper"]["train_downsample"]


def test_roles_absent_from_a_file_are_skipped() -> None:
    data = {"name": "tiny", "nodes": [{"name": "m", "class": "mogs_node.mapper.node:MapperNode"}]}
    lf = parse_launch(data, preset="fast")
    assert lf.nodes[0].params == PRESETS["fast"]["mapper"]
    # a node of no role is left alone
    assert apply_preset("bridges.player:PlayerNode", {"a": 1}, "quality") == {"a": 1}
    assert set(ROLES) >= {r for table in PRESETS.values() for r in table}


@pytest.mark.parametrize("where", ["argument", "file"])
def test_unknown_preset_is_one_clear_error_listing_the_valid_ones(where: str) -> None:
    with pytest.raises(ConfigError) as err:
        if where == "argument":
            parse_launch(_demo(), preset="turbo")
        else:
            parse_launch(_demo("turbo"))
    assert "'turbo'" in str(err.value)
    assert all(name in str(err.value) for name in PRESETS)
    with pytest.raises(ConfigError, match="preset"):
        parse_launch(_demo(["fast"]))  # type: ignore[arg-type]


def test_cli_unknown_preset_exits_with_the_error() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "mogs_node.cli", "launch", "launch/demo.yaml", "--preset", "x"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode != 0
    assert "unknown preset 'x'" in proc.stderr + proc.stdout
    assert "fast, balanced, quality" in proc.stderr + proc.stdout


def test_help_lists_the_presets_with_their_measured_figures(tmp_path: Path) -> None:
    figures = {
        "fast": {
            "cpu_s_per_frame": 0.5,
            "depth_absrel": 0.2,
            "ate_pct": 0.3,
            "heldout_psnr_db": 20.0,
        },
        "_measured": "bench/front.py, test",
    }
    path = tmp_path / "measured.json"
    path.write_text(json.dumps(figures))
    text = help_text(path)
    assert "fast: 0.50 CPU-s/frame, depth AbsRel 0.200, ATE 0.30 % of the path" in text
    assert "balanced (default): not measured yet" in text
    assert "bench/front.py, test" in text
    assert "quality" in help_text(tmp_path / "absent.json")


_values = st.recursive(
    st.integers(0, 5) | st.text("ab", max_size=2),
    lambda c: st.dictionaries(st.sampled_from("xyz"), c, max_size=3),
    max_leaves=8,
)


@given(
    st.dictionaries(st.sampled_from("abc"), _values),
    st.dictionaries(st.sampled_from("abc"), _values),
)
def test_deep_merge_keeps_unnamed_keys_and_takes_named_ones(base: dict, over: dict) -> None:
    merged = deep_merge(base, over)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(base.get(k), dict):
            assert merged[k] == deep_merge(base[k], v)
        else:
            assert merged[k] == v
    for k in set(base) - set(over):
        assert merged[k] == base[k]
    assert deep_merge(merged, {}) == merged


@pytest.mark.slow
@pytest.mark.timeout(3600)
@pytest.mark.parametrize("preset", list(PRESETS))
def test_short_sim_drive_runs_end_to_end_with_each_preset(preset: str, tmp_path: Path) -> None:
    run = tmp_path / "run"
    sim = {"seed": 0, "n_frames": 36, "width": 621, "height": 188, "static_start_s": 1.0}
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "mogs_node.cli",
            "launch",
            "launch/demo.yaml",
            "--preset",
            preset,
            "--run-dir",
            str(run),
            "--timeout",
            "1500",
            "--set",
            f"player.sim={json.dumps(sim)}",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=1700,
    )
    assert proc.returncode == 0, proc.stdout[-4000:]
    fig = json.loads((run / "summary.json").read_text())
    assert fig["keyframes"] >= 3
    assert fig["keyframes_with_depth"] == fig["keyframes"]
    assert fig["keyframes_mapped"] == fig["keyframes"]
    assert fig["depth"]["keyframes_scored"] == fig["keyframes"]
    assert (run / "map.ply").stat().st_size > 0
