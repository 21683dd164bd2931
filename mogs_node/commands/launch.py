"""``mogs launch FILE``: start the broker and every node of a launch file; Ctrl-C stops all.

``--run-dir DIR`` puts the run's journal, report, map and checkpoints in ``DIR``;
``--resume DIR`` continues the run stored there: the journal and the mapper's checkpoint are
reopened, every node catches up from the journal and the player goes on after the last frame
the journal holds (docs/reliability.md, "Resume"). A run that ends cleanly removes its journal and
checkpoints unless ``--keep-journal``; one stopped by Ctrl-C or a timeout keeps them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import yaml

from mogs_node.errors import ConfigError
from mogs_node.launch import (
    Launcher,
    load_launch_file,
    respawns_without_journal,
    run_dir_overrides,
)
from mogs_node.presets import DEFAULT_PRESET, PRESETS, validate_preset
from mogs_node.presets import help_text as presets_help_text


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", help="launch file (YAML), e.g. launch/demo.yaml")
    parser.add_argument(
        "--preset",
        default=None,
        metavar="NAME",
        help=f"operating point: {' | '.join(PRESETS)} (default: the file's `preset:`, else "
        f"{DEFAULT_PRESET}); --set wins over it",
    )
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = presets_help_text()
    add_run_options(parser, "stop everything after this many seconds", grace_s=3.0)
    parser.add_argument(
        "--run-dir", default=None, metavar="DIR", help="keep journal, report, map, checkpoints here"
    )
    parser.add_argument(
        "--resume", default=None, metavar="RUN_DIR", help="continue the run stored in RUN_DIR"
    )
    add_keep_journal(parser)


def add_run_options(
    parser: argparse.ArgumentParser,
    timeout_help: str,
    *,
    timeout_s: float | None = None,
    grace_s: float | None = None,
) -> None:
    """The options of every command that runs a launch file (launch, demo, batch): ``--set``
    overrides (read by :func:`parse_overrides`), ``--timeout`` and, given ``grace_s``,
    ``--grace``."""
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NODE.PARAM=VALUE",
        help="override a node parameter (value parsed as YAML), e.g. mapper.device=cuda; "
        "repeatable",
    )
    parser.add_argument("--timeout", type=float, default=timeout_s, help=timeout_help)
    if grace_s is not None:
        help_ = f"seconds between SIGINT and SIGKILL of a node (default {grace_s:g})"
        parser.add_argument("--grace", type=float, default=grace_s, help=help_)


def add_keep_journal(parser: argparse.ArgumentParser) -> None:
    """``--keep-journal``: the run's journal and checkpoints stay after a clean end."""
    parser.add_argument(
        "--keep-journal",
        action="store_true",
        help="keep the journal and checkpoints of a run that ends cleanly (default: removed)",
    )


def parse_overrides(items: list[str]) -> dict[str, dict]:
    out: dict[str, dict] = {}
    for item in items:
        key, sep, value = item.partition("=")
        node, dot, param = key.partition(".")
        if not (sep and dot and node and param):
            raise ConfigError(f"--set {item!r}: expected NODE.PARAM=VALUE")
        out.setdefault(node, {})[param] = yaml.safe_load(value)
    return out


def command(args: argparse.Namespace) -> int:
    overrides = parse_overrides(args.set)
    preset = validate_preset(args.preset) if args.preset else None
    run_dir = args.resume or args.run_dir
    if args.resume and args.run_dir:
        raise ConfigError("--resume RUN_DIR already names the run folder; drop --run-dir")
    if args.resume and not (Path(args.resume) / "journal" / "journal.log").exists():
        raise ConfigError(f"--resume {args.resume}: no journal/journal.log there to resume from")
    if run_dir:
        base = load_launch_file(args.file, preset=preset)
        merged = run_dir_overrides(base, run_dir, resume=bool(args.resume))
        for node, params in overrides.items():  # --set wins
            merged.setdefault(node, {}).update(params)
        overrides = merged
    launch = load_launch_file(args.file, overrides=overrides, preset=preset)
    lonely = respawns_without_journal(launch)
    if lonely:
        print(
            f"[launch] warning: no journal node in {args.file}: a respawned {', '.join(lonely)} "
            "has nothing to catch up from (add `class: mogs_node.journal.node:JournalNode`, "
            "docs/reliability.md)",
            flush=True,
        )
    launcher = Launcher(
        launch, grace_s=args.grace, resume=bool(args.resume), keep_journal=args.keep_journal
    )
    return launcher.run(timeout_s=args.timeout)
