"""Operating points a user picks by name: ``mogs launch FILE --preset fast|balanced|quality``.

A preset is a table of parameter overrides per node *role* (frontend, segmentation, prior,
metrizer, mapper), recognised by the node's class, not its name; roles a launch file does not
have are skipped. The order of precedence is: the launch file's own parameters, then the preset
(``--preset`` or ``preset:`` in the file; ``balanced`` when neither), then ``--set``. Nested
parameter groups (``prior.flow``, ``metrizer.cdr`` ...) are merged key by key, so a preset moves
only the keys it names.

``balanced`` is each launch file's own tuned values (an empty table): the demo's are the point
measured as ``balanced``. ``fast`` and ``quality`` move the knobs that cost time, as measured by
``bench/front.py`` on the demo drive (docs/benchmarks.md, section ``front``); that bench writes
the figures of each preset to :data:`FIGURES_PATH`, which ``mogs launch --help`` prints.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import json
from pathlib import Path
from typing import Any

from mogs_node.errors import ConfigError

__all__ = [
    "DEFAULT_PRESET",
    "FIGURES_PATH",
    "PRESETS",
    "ROLES",
    "apply_preset",
    "balanced_value",
    "deep_merge",
    "help_text",
    "role_of",
    "validate_preset",
]

DEFAULT_PRESET = "balanced"

# role -> the class-name suffix of its node (launch files name nodes freely)
ROLES: dict[str, str] = {
    "frontend": ":FrontendNode",
    "segmentation": ":SegmentationNode",
    "prior": ":DepthPriorNode",
    "metrizer": ":MetrizerNode",
    "mapper": ":MapperNode",
}

# role -> parameter overrides (nested groups merged key by key). Why each value: the knob table
# of docs/benchmarks.md "front" (each knob moved alone from balanced, its cost and errors).
PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "fast": {
        # the mapper is most of the CPU: fewer, smaller iterations on a shorter window, no
        # refinement after the drive. The prior keeps DIS "medium": "fast" saved ~2 % of the
        # CPU and cost AbsRel 0.131 -> 0.197 (knob table)
        "mapper": {
            "iters_per_keyframe": 4,
            "train_downsample": 4,
            "window_size": 4,
            "final_refine_iters": 0,
        },
        "metrizer": {"cdr": {"irls_iters": 1}},
        "frontend": {"points": {"max_tracks": 500}},
    },
    "balanced": {},
    "quality": {
        # full-resolution optimisation, more iterations per keyframe (with the refinement after
        # the drive at 300 iterations, session 9: held-out PSNR 23.6 -> 24.6 dB with 600 here;
        # balanced refines 800 times, with a learning-rate schedule: docs/mapper.md);
        # CDR with one IRLS iteration on every
        # 3rd pixel instead of three on every 6th: AbsRel 0.131 -> 0.129 (screened with
        # final_refine_iters 0, which leaves the depth as is; more sparse tracks, 1500, made it
        # worse: 0.137; the fill at full resolution changed nothing), knob table
        "mapper": {"iters_per_keyframe": 20, "train_downsample": 1, "final_refine_iters": 800},
        "metrizer": {"cdr": {"irls_iters": 1}, "metrizer": {"sample_stride": 3}},
    },
}

# written by bench/front.py (full grid): {preset: {cpu_s_per_frame, depth_absrel, ...}}
FIGURES_PATH = Path(__file__).with_name("presets_measured.json")


def validate_preset(name: str) -> str:
    """``name`` if it is a preset, else one error listing the valid ones."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; the presets are {', '.join(PRESETS)}")
    return name


def role_of(cls: str) -> str | None:
    """The role of a node class ``module:Class`` (None: no preset applies to it)."""
    return next((role for role, suffix in ROLES.items() if cls.endswith(suffix)), None)


def deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``over`` merged in: mappings key by key (recursively), anything else
    replaced. Neither input is modified."""
    out = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def apply_preset(cls: str, params: dict[str, Any], preset: str) -> dict[str, Any]:
    """A node's parameters with the preset's overrides of its role merged in."""
    role = role_of(cls)
    table = PRESETS[validate_preset(preset)].get(role or "", {})
    return deep_merge(params, table) if table else dict(params)


# "role.group" -> the dataclass whose defaults fill that nested group of the node's parameters
GROUP_DEFAULTS: dict[str, str] = {
    "frontend.points": "mogs_node.frontend.track_points:TrackPointsParams",
    "metrizer.cdr": "mogs_node.metrizer.refinement:CdrParams",
    "metrizer.consensus": "mogs_node.metrizer.consensus:ConsensusParams",
    "metrizer.metrizer": "mogs_node.metrizer.pipeline:MetrizerParams",
    "prior.flow": "mogs_node.depth_prior.flow_prior:FlowPriorParams",
    "segmentation.graph": "mogs_node.segmentation.graph:GraphSegParams",
}


def _load(ref: str) -> Any:
    module, _, name = ref.partition(":")
    return getattr(importlib.import_module(module), name)


def balanced_value(launch: Any, path: str) -> Any:
    """The value of a knob ``role.param[.sub]`` as a launch file runs it: the file's own value,
    else the default of its parameter class (``dataclasses.MISSING`` when neither has it)."""
    role, *keys = path.split(".")
    spec = next((s for s in launch.nodes if role_of(s.cls) == role), None)
    if spec is None or not keys:
        return dataclasses.MISSING
    value: Any = spec.params
    for k in keys:
        value = value.get(k, dataclasses.MISSING) if isinstance(value, dict) else value
    if value is not dataclasses.MISSING:
        return value
    if len(keys) == 1:
        owner = _load(spec.cls).Params
    else:
        group = GROUP_DEFAULTS.get(".".join([role, *keys[:-1]]))
        if group is None:
            return dataclasses.MISSING
        owner = _load(group)
    field = next((f for f in dataclasses.fields(owner) if f.name == keys[-1]), None)
    return dataclasses.MISSING if field is None else field.default


def measured_figures(path: Path = FIGURES_PATH) -> dict[str, dict[str, Any]]:
    """The presets' figures as bench/front.py measured them ({} before any measurement)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def help_text(path: Path = FIGURES_PATH) -> str:
    """One line per preset for ``mogs launch --help``: its measured cost and errors."""
    figures = measured_figures(path)
    lines = []
    for name in PRESETS:
        f = figures.get(name)
        default = " (default)" if name == DEFAULT_PRESET else ""
        if not f:
            lines.append(f"  {name}{default}: not measured yet (python bench/front.py)")
            continue
        lines.append(
            f"  {name}{default}: {f['cpu_s_per_frame']:.2f} CPU-s/frame, "
            f"depth AbsRel {f['depth_absrel']:.3f}, ATE {f['ate_pct']:.2f} % of the path, "
            f"held-out PSNR {f['heldout_psnr_db']:.2f} dB"
        )
    where = f" ({figures['_measured']})" if isinstance(figures.get("_measured"), str) else ""
    return "presets, measured on the demo drive" + where + ":\n" + "\n".join(lines)
