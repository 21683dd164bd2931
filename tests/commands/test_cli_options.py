"""Options that set a field of a parameter record read back by their ``dest`` prefix."""

from __future__ import annotations

import argparse
import dataclasses

from mogs_node.commands.options import field_option, fields_from_args
from mogs_node.commands.sim import add_arguments
from mogs_node.sim import SimConfig


def test_fields_come_back_by_prefix_only() -> None:
    p = argparse.ArgumentParser()
    field_option(p, "a.", "--frames", "n_frames", type=int, default=3)
    field_option(p, "b.", "--rate", "rate_hz", type=float, default=1.0)
    p.add_argument("--other", default="x")
    args = p.parse_args(["--frames", "5"])
    assert fields_from_args(args, "a.") == {"n_frames": 5}
    assert fields_from_args(args, "b.") == {"rate_hz": 1.0}
    assert "FRAMES" in p.format_help()  # the flag's metavar, not the dest's


def test_every_mogs_sim_config_option_names_a_sim_config_field() -> None:
    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["--frames", "9", "--fps", "5", "--speed", "3", "--motion", "handheld"])
    values = fields_from_args(args, "sim.")
    names = {f.name for f in dataclasses.fields(SimConfig)}
    assert set(values) <= names
    cfg = SimConfig(**values)
    assert (cfg.n_frames, cfg.frame_rate_hz, cfg.speed_m_s, cfg.motion) == (9, 5.0, 3.0, "handheld")
