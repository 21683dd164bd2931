"""The container files, checked without a docker daemon (there is none on the build machines):
every compose service runs a valid ``mogs`` command whose node class exists and whose params and
bus parse; the CURVE keys it names are the ones its ``keys`` service writes, and with those keys
(and the hosts mapped to loopback) the compose bus configuration really carries messages between
two services; the Dockerfiles' basics hold (COPY sources exist, pinned torch, non-root user,
exec-form entry point)."""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import re
import shlex
import socket
import time
from pathlib import Path

import pytest
import yaml
from _reliability_harness import broker_thread

from mogs_node import msgs
from mogs_node.bus import BusConfig, Publisher, Subscriber, generate_keys
from mogs_node.cli import SUBCOMMANDS
from mogs_node.commands.node import load_node_class
from mogs_node.params import parse_params

REPO = Path(__file__).resolve().parents[1]
DOCKER = REPO / "docker"
DOCKERFILES = ("Dockerfile", "Dockerfile.cuda")


def _parser() -> argparse.ArgumentParser:
    """The ``mogs`` command line, every subcommand included (as ``mogs_node.cli`` builds it)."""
    parser = argparse.ArgumentParser(prog="mogs", exit_on_error=False)
    sub = parser.add_subparsers(dest="subcommand", required=True)
    for name, (module_name, _) in SUBCOMMANDS.items():
        if name in ("keys", "broker", "node"):
            importlib.import_module(module_name).add_arguments(sub.add_parser(name))
    return parser


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


def _parsed(compose: dict) -> dict[str, argparse.Namespace]:
    parser = _parser()
    out = {}
    for name, svc in compose["services"].items():
        cmd = svc["command"]
        argv = shlex.split(cmd) if isinstance(cmd, str) else [str(a) for a in cmd]
        try:
            out[name] = parser.parse_args(argv)
        except (argparse.ArgumentError, SystemExit) as err:  # pragma: no cover - the failure
            pytest.fail(f"service {name}: {argv} is not a valid mogs command: {err}")
    return out


def test_every_service_runs_a_valid_mogs_command(compose: dict) -> None:
    args = _parsed(compose)
    kinds = {n: a.subcommand for n, a in args.items()}
    assert kinds.pop("keys") == "keys" and kinds.pop("broker") == "broker"
    assert set(kinds.values()) == {"node"}
    # the pipeline of the demo, one container per node
    demo = yaml.safe_load((REPO / "launch/demo.yaml").read_text())
    assert set(kinds) == {n["name"] for n in demo["nodes"]}
    for name, a in args.items():
        if a.subcommand != "node":
            continue
        cls = load_node_class(a.cls)  # the class exists and is a Node
        assert a.name == name
        parse_params(cls.Params, json.loads(a.params_json), where=name)  # params parse strictly
        bus = BusConfig.from_dict(json.loads(a.bus_json))
        assert bus.pub_endpoint.startswith("tcp://broker:") and bus.curve is not None
        svc = compose["services"][name]
        assert svc["image"] == compose["services"]["broker"]["image"]
        assert svc["depends_on"]["keys"]["condition"] == "service_completed_successfully"


def test_compose_is_generated_from_the_demo_launch_file(compose: dict) -> None:
    """Up to date with launch/demo.yaml; if not: python docker/make_compose.py launch/demo.yaml >
    docker/compose.yaml"""
    spec = importlib.util.spec_from_file_location("make_compose", DOCKER / "make_compose.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    demo = yaml.safe_load((REPO / "launch/demo.yaml").read_text())
    assert (DOCKER / "compose.yaml").read_text() == mod.make_compose(demo, "launch/demo.yaml")
    by_name = {n["name"]: n for n in demo["nodes"]}
    for name, a in _parsed(compose).items():
        if a.subcommand == "node":  # the launch file's class and params, outputs in /runs
            assert a.cls == by_name[name]["class"]
            params = json.loads(a.params_json)
            want = {
                **(by_name[name].get("params") or {}),
                **{k: v for k, v in mod.OUTPUT_PATHS.items() if k in params},
            }
            assert params == want, name


def test_curve_keys_of_every_service_are_written_by_the_keys_service(compose: dict) -> None:
    args = _parsed(compose)
    clients = set(args["keys"].clients)
    assert args["keys"].dir == "/keys"
    broker = BusConfig.from_dict(json.loads(args["broker"].bus_json))
    assert args["broker"].allow_remote and broker.curve is not None  # remote only with CURVE
    assert broker.curve.server_secret_key == "/keys/broker.key_secret"
    assert broker.curve.authorized_keys_dir == "/keys/authorized"
    for name, a in args.items():
        if a.subcommand == "node":
            curve = BusConfig.from_dict(json.loads(a.bus_json)).curve
            assert curve.server_public_key == "/keys/broker.key"
            assert curve.client_secret_key == f"/keys/{name}.key_secret" and name in clients
            # the keys volume is read-only for every service but `keys`
            assert "keys:/keys:ro" in compose["services"][name]["volumes"]


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _localised(bus_json: str, keys: Path, ports: dict[str, int]) -> BusConfig:
    """A compose bus configuration with /keys -> ``keys`` and the broker's host -> loopback."""
    text = bus_json.replace("/keys/", f"{keys}/")
    for port, local in ports.items():
        text = re.sub(rf"tcp://[\w.]+:{port}", f"tcp://127.0.0.1:{local}", text)
    return BusConfig.from_dict(json.loads(text))


def test_compose_bus_carries_messages_between_services_and_rejects_others(
    compose: dict, tmp_path: Path
) -> None:
    """The keys `mogs keys` writes + the services' bus JSON: player -> report gets through, a
    peer with a key the broker does not know gets nothing."""
    args = _parsed(compose)
    keys = tmp_path / "keys"
    generate_keys(keys, ["broker", *args["keys"].clients])
    generate_keys(tmp_path / "other", ["intruder"])
    ports = {"7700": _port(), "7701": _port()}
    broker = _localised(args["broker"].bus_json, keys, ports)
    player = _localised(args["player"].bus_json, keys, ports)
    report = _localised(args["report"].bus_json, keys, ports)
    intruder = _localised(
        args["report"].bus_json.replace(
            "/keys/report.key_secret", str(tmp_path / "other/intruder.key_secret")
        ),
        keys,
        ports,
    )
    with broker_thread(broker) as ctx:
        sub = Subscriber(report, context=ctx)
        sub.subscribe("/mapper/stats")
        bad = Subscriber(intruder, context=ctx)
        bad.subscribe("/mapper/stats")
        pub = Publisher(player, context=ctx)
        assert pub.wait_for_subscriber("/mapper/stats", 5)
        time.sleep(0.3)
        for k in range(20):
            pub.publish(
                "/mapper/stats",
                msgs.MapStats(
                    stamp_ns=k,
                    frame_id="",
                    keyframe_id=k,
                    n_gaussians=1,
                    n_keyframes=1,
                    iterations=1,
                    loss=0.0,
                    psnr_db=0.0,
                ),
            )
        got, deadline = [], time.monotonic() + 2
        while time.monotonic() < deadline and len(got) < 20:
            env = sub.receive(timeout_ms=100)
            if env is not None:
                got.append(env.msg.stamp_ns)
        assert got == list(range(20))
        assert bad.receive(timeout_ms=300) is None
        for s in (sub, bad):
            s.close()
        pub.close(0)


def _instructions(path: Path) -> list[tuple[str, str]]:
    """Dockerfile instructions (keyword, arguments) with continuation lines joined."""
    text = re.sub(r"\\\n", " ", path.read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            kw, _, rest = line.partition(" ")
            out.append((kw.upper(), rest.strip()))
    return out


@pytest.mark.parametrize("name", DOCKERFILES)
def test_dockerfile_basics(name: str) -> None:
    ins = _instructions(DOCKER / name)
    kws = [k for k, _ in ins]
    assert kws[0] in ("FROM", "ARG") and "FROM" in kws
    for kw, rest in ins:
        if kw == "FROM":
            image = rest.split()[0]
            assert ":" in image and not image.endswith(":latest"), image  # a pinned tag
        if kw == "COPY":  # sources exist in the build context (the repository root)
            *srcs, _dst = rest.split()
            for src in srcs:
                assert (REPO / src).exists(), f"{name}: COPY {src} does not exist"
        if kw == "RUN" and "apt-get install" in rest:
            assert "--no-install-recommends" in rest and "rm -rf /var/lib/apt/lists" in rest
        if kw in ("ENTRYPOINT", "CMD"):
            json.loads(rest)  # exec form: signals reach mogs (clean node shutdown)
    users = [rest for kw, rest in ins if kw == "USER"]
    assert users and users[-1] not in ("root", "0")
    # torch is pinned to the project's version and comes from a wheel index chosen by build arg
    args = dict(re.findall(r'ARG (\w+)="?([^"\s]*)"?', (DOCKER / name).read_text()))
    make = (REPO / "Makefile").read_text()
    assert args["TORCH_SPEC"] == re.search(r"TORCH_SPEC \?= (\S+)", make).group(1)
    assert "TORCH_INDEX_URL" in args
    install = " ".join(rest for kw, rest in ins if kw == "RUN" and "pip install" in rest)
    assert '--index-url "${TORCH_INDEX_URL}" "${TORCH_SPEC}"' in install
    extra = ".[cuda]" if name.endswith("cuda") else "."
    assert f'pip install "{extra}"' in install or f"pip install {extra}" in install
    if name.endswith("cuda"):
        assert "cu" in args["TORCH_INDEX_URL"].rsplit("/", 1)[-1]
        pyproject = (REPO / "pyproject.toml").read_text()
        assert re.search(r"^cuda = \[.*gsplat", pyproject, re.M)
    else:
        assert args["TORCH_INDEX_URL"].endswith("/cpu")
        assert ins[0] == ("FROM", "python:3.11-slim") or ("FROM", "python:3.11-slim") in ins


def test_compose_builds_from_the_cpu_dockerfile(compose: dict) -> None:
    for name, svc in compose["services"].items():
        if "build" in svc:
            assert (DOCKER / svc["build"]["context"] / svc["build"]["dockerfile"]).resolve() == (
                DOCKER / "Dockerfile"
            ).resolve(), name
