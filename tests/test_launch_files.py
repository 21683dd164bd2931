"""Every launch file: parses, names existing node classes, and its parameters (nested groups
included) parse with the classes' own parameter dataclasses; the dataset launch files carry the
dataset's calibration."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import shared_data

from mogs_node.commands.node import load_node_class
from mogs_node.launch import LaunchFile, NodeSpec, load_launch_file
from mogs_node.node import parse_params

REPO = Path(__file__).resolve().parents[1]
LAUNCH_FILES = sorted((REPO / "launch").glob("*.yaml"))
PIPELINE = ("frontend", "segmentation", "prior", "metrizer", "mapper", "report")


def _nested(spec: NodeSpec, params: Any) -> None:
    """Parse the nested parameter groups the way each node's setup() does."""
    where = spec.name
    if spec.cls.endswith(":FrontendNode"):
        params.build(where)
    elif spec.cls.endswith(":DepthPriorNode"):
        from mogs_node.depth_prior.flow_prior import FlowPriorParams

        parse_params(FlowPriorParams, params.flow, where=f"{where}.flow")
    elif spec.cls.endswith(":SegmentationNode"):
        from mogs_node.segmentation.graph import GraphSegParams

        parse_params(GraphSegParams, params.graph, where=f"{where}.graph")
    elif spec.cls.endswith(":MetrizerNode"):
        from mogs_node.metrizer.consensus import ConsensusParams
        from mogs_node.metrizer.pipeline import MetrizerParams
        from mogs_node.metrizer.refinement import CdrParams

        top = dict(params.metrizer)
        top["consensus"] = parse_params(ConsensusParams, params.consensus, where=f"{where}.c")
        top["cdr"] = parse_params(CdrParams, params.cdr, where=f"{where}.cdr")
        parse_params(MetrizerParams, top, where=f"{where}.metrizer")
    elif spec.cls.endswith(":PlayerNode") and params.source == "sim":
        from mogs_node.sim import SimConfig

        parse_params(SimConfig, params.sim, where=f"{where}.sim")


def _load(path: Path) -> tuple[LaunchFile, dict[str, Any]]:
    lf = load_launch_file(path)
    parsed = {}
    for spec in lf.nodes:
        cls = load_node_class(spec.cls)
        parsed[spec.name] = parse_params(cls.Params, spec.params, where=f"{path.stem}.{spec.name}")
        _nested(spec, parsed[spec.name])
    return lf, parsed


def test_there_are_launch_files() -> None:
    names = {p.stem for p in LAUNCH_FILES}
    assert {"demo", "kitti", "euroc", "bag", "live", "distributed"} <= names


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.stem)
def test_launch_file_parses_and_its_params_are_valid(path: Path) -> None:
    lf, parsed = _load(path)
    names = {s.name for s in lf.nodes}
    for name, p in parsed.items():  # cross references name nodes of the same file
        for other in getattr(p, "wait_for_nodes", ()):
            assert other in names, f"{name}.wait_for_nodes: no node {other!r}"
        if hasattr(p, "source_node"):
            assert p.source_node in names, f"{name}.source_node: no node {p.source_node!r}"


@pytest.mark.parametrize("name", ["demo", "kitti", "euroc", "bag", "live", "distributed"])
def test_dataset_launch_files_run_the_whole_pipeline(name: str) -> None:
    lf, _ = _load(REPO / "launch" / f"{name}.yaml")
    names = {s.name for s in lf.nodes}
    assert set(PIPELINE) <= names
    if name not in ("live", "distributed"):
        assert lf.exit_when == ("report",)


def test_distributed_launch_file_spans_hosts_over_curve_tcp() -> None:
    lf, _ = _load(REPO / "launch" / "distributed.yaml")
    assert lf.bus.pub_endpoint.startswith("tcp://") and lf.bus.sub_endpoint.startswith("tcp://")
    assert lf.bus.curve is not None and lf.allow_remote
    hosts = {s.host for s in lf.nodes}
    assert len(hosts) >= 2 and "localhost" not in hosts  # every node names its host


def _frontend_against_excerpt(launch: str, seq: Any) -> Any:
    """The frontend parameters of ``launch``, their intrinsics checked against the camera of the
    excerpt ``seq``'s first frame (the caller checks the rest)."""
    _, parsed = _load(REPO / "launch" / f"{launch}.yaml")
    fe = parsed["frontend"]
    cam = seq.frames[0].camera
    np.testing.assert_allclose(
        [fe.fx_px, fe.fy_px, fe.cx_px, fe.cy_px], [cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px]
    )
    return fe


@pytest.mark.shared_data
def test_kitti_launch_file_has_the_excerpts_calibration() -> None:
    from mogs_node.datasets import read_kitti_raw

    seq = read_kitti_raw(shared_data("kitti_raw_2011_09_26_78"))
    fe = _frontend_against_excerpt("kitti", seq)
    cam = seq.frames[0].camera
    assert (fe.width, fe.height) == (cam.width, cam.height)
    np.testing.assert_allclose(
        np.reshape(fe.T_imu_cam, (4, 4)), seq.T_imu_cam, atol=2e-6
    )  # printed to 6 decimals


@pytest.mark.shared_data
def test_euroc_launch_file_has_the_excerpts_calibration() -> None:
    from mogs_node.datasets import read_euroc

    seq = read_euroc(shared_data("euroc_v1_01_micro"))
    fe = _frontend_against_excerpt("euroc", seq)
    cam = seq.frames[0].camera  # undistorted by the player: same K, no distortion
    assert (fe.width, fe.height, fe.distortion_model) == (cam.width, cam.height, "none")
    np.testing.assert_allclose(np.reshape(fe.T_imu_cam, (4, 4)), seq.T_imu_cam, atol=1e-9)
