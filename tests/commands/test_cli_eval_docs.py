"""``mogs eval`` writes docs/ only with ``--write-docs`` (issue 18: ``mogs eval depth`` rewrote the
tracked docs/benchmarks.md, leaving ``git status`` dirty)."""

from __future__ import annotations

import argparse

import pytest

from mogs_node.commands import eval as eval_cmd
from mogs_node.eval import depth_sim


def _parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    eval_cmd.add_arguments(parser)
    return parser.parse_args(list(argv))


@pytest.mark.parametrize("what", ["depth", "traj", "map"])
def test_every_eval_command_has_write_docs_off_by_default(what: str) -> None:
    assert _parse(what).write_docs is False
    assert _parse(what, "--write-docs").write_docs is True


@pytest.mark.parametrize("write_docs", [False, True])
def test_the_standard_depth_eval_writes_docs_only_when_asked(
    monkeypatch: pytest.MonkeyPatch, write_docs: bool
) -> None:
    real_make_cases = depth_sim.make_cases
    # the standard run (20 keyframes, default size, both mask sources), rendered tiny
    monkeypatch.setattr(
        depth_sim,
        "make_cases",
        lambda n, seed, size, masks: real_make_cases(n, seed, (64, 24), masks=masks),
    )
    written: list[dict] = []
    monkeypatch.setattr(depth_sim, "_write_markdown", lambda fig, args: written.append(fig))
    args = _parse("depth", *(["--write-docs"] if write_docs else []))
    figures = depth_sim.evaluate(args)
    assert figures["frames"] == 20
    assert len(written) == (1 if write_docs else 0)
