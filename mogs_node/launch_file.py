"""Launch files: parsed and checked before anything starts (the launcher: :mod:`mogs_node.launch`).

A launch file (YAML)::

    name: demo                      # names the default ipc endpoints
    bus:                            # optional; default: ipc endpoints in /tmp/mogs-$UID
      pub_endpoint: tcp://127.0.0.1:7700
      sub_endpoint: tcp://127.0.0.1:7701
      allow_remote: false           # listen on non-loopback addresses only if true
      curve: {server_public_key: keys/broker.key, client_secret_key: keys/client.key_secret,
              server_secret_key: keys/broker.key_secret, authorized_keys_dir: keys/authorized}
    exit_when: [source]             # stop everything once these nodes have exited with code 0
    preset: balanced                # fast | balanced | quality (mogs_node/presets.py; --preset wins)
    nodes:
      - name: source
        class: mogs_node.demo_nodes:SyntheticSource   # module:Class, a Node subclass
        params: {rate_hz: 10}
        respawn: on_failure         # never | on_failure | always
        max_respawns: 5
        host: localhost             # only localhost is started by this launcher
        nice: 0                     # CPU priority 0..19 (real-time files: the mapper below the
        cpus: []                    #   keyframe chain); CPUs it may use (empty: all; Linux)

"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mogs_node.bus import BusConfig, default_bus_config
from mogs_node.errors import ConfigError
from mogs_node.params import check_choice
from mogs_node.presets import DEFAULT_PRESET, apply_preset, validate_preset
from mogs_node.yaml_file import read_yaml

__all__ = [
    "LaunchFile",
    "NodeSpec",
    "RESPAWN_POLICIES",
    "load_launch_file",
    "parse_launch",
    "respawns_without_journal",
    "run_dir_overrides",
]

RESPAWN_POLICIES = ("never", "on_failure", "always")


@dataclass(frozen=True)
class NodeSpec:
    """One node of a launch file."""

    name: str
    cls: str  # "package.module:ClassName"
    params: dict[str, Any] = field(default_factory=dict)
    respawn: str = "on_failure"
    max_respawns: int = 5
    respawn_delay_s: float = 0.5
    heartbeat_timeout_s: float = (
        30.0  # kill + respawn a node silent on /diagnostics this long (0: off)
    )
    # kill + respawn a node busy this long without progress (its heartbeat's busy_s; 0: off):
    # one step of real work may take minutes on a loaded machine, a stuck node never moves
    progress_timeout_s: float = 900.0
    # a node not yet heard from at all (imports, model loading, a first-use compile) gets this
    # long before heartbeat supervision applies (a startup probe, as in Kubernetes)
    startup_timeout_s: float = 300.0
    host: str = "localhost"
    env: dict[str, str] = field(default_factory=dict)
    # CPU priority (issue 28): the node's niceness (0..19: higher yields the CPU to the others)
    # and the CPUs it may run on (empty: all), where the OS allows (Linux sched_setaffinity)
    nice: int = 0
    cpus: tuple[int, ...] = ()


@dataclass(frozen=True)
class LaunchFile:
    name: str
    bus: BusConfig
    nodes: tuple[NodeSpec, ...]
    exit_when: tuple[str, ...] = ()
    allow_remote: bool = False
    start_broker: bool = True
    path: Path | None = None


def _require(d: dict, key: str, types: type | tuple[type, ...], where: str) -> Any:
    if key not in d:
        raise ConfigError(f"{where}: missing key '{key}'")
    if not isinstance(d[key], types):
        raise ConfigError(f"{where}.{key}: expected {types}, got {d[key]!r}")
    return d[key]


def _cpu_priority(nd: dict, where: str) -> dict[str, Any]:
    """A node's ``nice`` (int 0..19) and ``cpus`` (list of CPU indices), checked."""
    nice = nd.get("nice", 0)
    if isinstance(nice, bool) or not isinstance(nice, int) or not 0 <= nice <= 19:
        raise ConfigError(f"{where}.nice: expected an integer 0..19, got {nice!r}")
    cpus = nd.get("cpus") or []
    if not isinstance(cpus, list) or not all(
        isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in cpus
    ):
        raise ConfigError(f"{where}.cpus: expected a list of CPU indices >= 0, got {cpus!r}")
    return {"nice": nice, "cpus": tuple(cpus)}


def parse_launch(
    data: Any,
    *,
    path: Path | None = None,
    overrides: dict[str, Any] | None = None,
    preset: str | None = None,
) -> LaunchFile:
    """Validate a launch file's parsed YAML; errors name the offending key. Parameters: the
    file's, then the preset's (``preset``, else the file's ``preset:``, else ``balanced``;
    :mod:`mogs_node.presets`), then ``overrides``."""
    where = str(path) if path else "launch file"
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping at top level")
    known = {"name", "bus", "nodes", "exit_when", "description", "preset"}
    unknown = set(data) - known
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}")
    preset = preset or data.get("preset") or DEFAULT_PRESET
    if not isinstance(preset, str):
        raise ConfigError(f"{where}.preset: expected a preset name, got {preset!r}")
    validate_preset(preset)
    name = data.get("name", path.stem if path else "default")
    if not isinstance(name, str) or not name.replace("-", "").replace("_", "").isalnum():
        raise ConfigError(f"{where}.name: expected a simple name, got {name!r}")
    bus_d = dict(data.get("bus") or {})
    allow_remote = bool(bus_d.pop("allow_remote", False))
    start_broker = bool(bus_d.pop("start_broker", True))
    if "pub_endpoint" not in bus_d and "sub_endpoint" not in bus_d:
        default = default_bus_config(name)
        bus_d.update(pub_endpoint=default.pub_endpoint, sub_endpoint=default.sub_endpoint)
    bus = BusConfig.from_dict(bus_d, base_dir=path.parent if path else None)
    nodes_raw = _require(data, "nodes", list, where)
    nodes = []
    seen = set()
    for i, nd in enumerate(nodes_raw):
        w = f"{where}.nodes[{i}]"
        if not isinstance(nd, dict):
            raise ConfigError(f"{w}: expected a mapping")
        unknown = set(nd) - {
            "name",
            "class",
            "params",
            "respawn",
            "max_respawns",
            "respawn_delay_s",
            "heartbeat_timeout_s",
            "progress_timeout_s",
            "startup_timeout_s",
            "host",
            "env",
            "nice",
            "cpus",
        }
        if unknown:
            raise ConfigError(f"{w}: unknown key(s) {sorted(unknown)}")
        nname = _require(nd, "name", str, w)
        if nname in seen or nname == "broker":
            raise ConfigError(f"{w}.name: duplicate or reserved node name {nname!r}")
        seen.add(nname)
        cls = _require(nd, "class", str, w)
        if ":" not in cls:
            raise ConfigError(f"{w}.class: expected 'package.module:ClassName', got {cls!r}")
        if not isinstance(nd.get("params") or {}, dict):
            raise ConfigError(f"{w}.params: expected a mapping, got {nd['params']!r}")
        params = apply_preset(cls, dict(nd.get("params") or {}), preset)
        if overrides and nname in overrides:
            params.update(overrides[nname])
        respawn = nd.get("respawn", "on_failure")
        check_choice(f"{w}.respawn", respawn, RESPAWN_POLICIES)
        nodes.append(
            NodeSpec(
                name=nname,
                cls=cls,
                params=params,
                respawn=respawn,
                max_respawns=int(nd.get("max_respawns", 5)),
                respawn_delay_s=float(nd.get("respawn_delay_s", 0.5)),
                heartbeat_timeout_s=float(nd.get("heartbeat_timeout_s", 30.0)),
                progress_timeout_s=float(nd.get("progress_timeout_s", 900.0)),
                startup_timeout_s=float(nd.get("startup_timeout_s", 300.0)),
                host=str(nd.get("host", "localhost")),
                env={str(k): str(v) for k, v in (nd.get("env") or {}).items()},
                **_cpu_priority(nd, w),
            )
        )
    unknown_nodes = sorted(set(overrides or {}) - seen)
    if unknown_nodes:
        raise ConfigError(
            f"{where}: parameter override(s) for unknown node(s) {unknown_nodes}; "
            f"the nodes are {sorted(seen)}"
        )
    exit_when = tuple(data.get("exit_when") or ())
    for n in exit_when:
        if n not in seen:
            raise ConfigError(f"{where}.exit_when: no node named {n!r}")
    return LaunchFile(
        name=name,
        bus=bus,
        nodes=tuple(nodes),
        exit_when=exit_when,
        allow_remote=allow_remote,
        start_broker=start_broker,
        path=path,
    )


def load_launch_file(
    path: str | Path, overrides: dict[str, Any] | None = None, preset: str | None = None
) -> LaunchFile:
    p = Path(path)
    data = read_yaml(p, ConfigError)
    return parse_launch(data, path=p, overrides=overrides, preset=preset)


def _node_class(cls: str) -> type:
    """The node class ``module:Class`` (imports the module)."""
    import importlib

    module, _, name = cls.partition(":")
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as err:
        raise ConfigError(f"cannot import node class {cls}: {err}") from err


def _params_fields(cls: str) -> set[str]:
    """Parameter names of the node class ``module:Class`` (imports the module)."""
    import dataclasses

    return {f.name for f in dataclasses.fields(_node_class(cls).Params)}


def respawns_without_journal(launch: LaunchFile) -> list[str]:
    """Nodes that are respawned after a crash and would catch up from a journal (their ``setup``
    calls :meth:`~mogs_node.node.Node.catch_up`), in a launch file without a journal node: a
    respawned one starts from nothing (a mapper loses every keyframe before its last checkpoint).
    """
    if any(s.cls.endswith(":JournalNode") for s in launch.nodes):
        return []
    out = []
    for spec in launch.nodes:
        if spec.respawn == "never" or spec.max_respawns <= 0:
            continue
        setup = getattr(_node_class(spec.cls), "setup", None)
        if setup is not None and "catch_up" in setup.__code__.co_names:
            out.append(spec.name)
    return out


def run_dir_overrides(launch: LaunchFile, run_dir: str | Path, *, resume: bool) -> dict[str, dict]:
    """Parameter overrides that put a run's state in ``run_dir``: the journal (``journal/``),
    the report, the mapper's PLY and checkpoints (``checkpoints/``); with ``resume`` the mapper
    loads its latest checkpoint. Nodes are recognised by their parameters, not their names."""
    d = Path(run_dir).resolve()
    out: dict[str, dict] = {}
    for spec in launch.nodes:
        fields = _params_fields(spec.cls)
        o: dict[str, Any] = {}
        if spec.cls.endswith(":JournalNode"):
            o["dir"] = str(d / "journal")
        if spec.cls.endswith(":RunReportNode"):
            o["out_dir"] = str(d)
        if "ply_path" in fields:
            o["ply_path"] = str(d / "map.ply")
        if "checkpoint_dir" in fields:
            o["checkpoint_dir"] = str(d / "checkpoints")
            if resume and "resume" in fields:
                o["resume"] = True
        if o:
            out[spec.name] = o
    return out
