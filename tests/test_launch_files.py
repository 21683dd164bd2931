"""Every launch file: parses, names existing node classes, and its parameters (nested groups
included) parse with the classes' own parameter dataclasses; the dataset launch files carry the
dataset's calibration."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bridges.sources import camera_info_of, open_sequence
from mogs_node.commands.node import load_node_class
from mogs_node.launch import LaunchFile, NodeSpec, load_launch_file
from mogs_node.params import parse_params

REPO = Path(__file__).resolve().parents[1]
_SIM_INFO = camera_info_of(open_sequence("sim", sim={"n_frames": 1, "width": 64, "height": 32}))
LAUNCH_FILES = sorted((REPO / "launch").glob("*.yaml"))
PIPELINE = ("frontend", "segmentation", "prior", "metrizer", "mapper", "report")


def _nested(spec: NodeSpec, params: Any) -> None:
    """Parse the nested parameter groups the way each node's setup() does."""
    where = spec.name
    if spec.cls.endswith(":FrontendNode"):  # calibration from a source's CameraInfo unless typed
        params.build(where, None if params.overrides_all() else _SIM_INFO)
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


def _calibration_from_player(launch: str) -> tuple[Any, Any, Any]:
    """``launch``'s frontend built from what its player publishes on /camera/info, and the
    player's sequence: the calibration is typed nowhere in the launch file."""
    lf, parsed = _load(REPO / "launch" / f"{launch}.yaml")
    fe, pl = parsed["frontend"], parsed["player"]
    from mogs_node.frontend.node import CALIBRATION_FIELDS

    assert all(getattr(fe, k) is None for k in CALIBRATION_FIELDS), "calibration typed twice"
    assert "camera_height_m" not in fe.ground
    path = pl.path if Path(pl.path).is_absolute() else str(REPO / pl.path)
    seq = open_sequence(pl.source, path)
    info = camera_info_of(seq, camera_height_m=pl.camera_height_m)
    return fe.build("frontend", info), seq, info


@pytest.mark.shared_data
def test_kitti_launch_file_takes_the_excerpts_calibration_from_the_player() -> None:
    (fp, cam, T), seq, info = _calibration_from_player("kitti")
    c = seq.frames[0].camera
    assert cam.pinhole == c and cam.model == "none"
    np.testing.assert_allclose(T, seq.T_imu_cam, atol=1e-6)  # the devkit chain, orthonormalised
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert fp.ground.camera_height_m == 1.65 and info.camera_height_m == 1.65  # typed once


@pytest.mark.shared_data
def test_euroc_launch_file_takes_the_excerpts_calibration_from_the_player() -> None:
    (fp, cam, T), seq, info = _calibration_from_player("euroc")
    assert cam.pinhole == seq.frames[0].camera  # undistorted by the player: same K
    assert cam.model == "none" and info.distortion_model == "none"
    np.testing.assert_allclose(T, seq.T_imu_cam, atol=1e-9)
    # imu0/sensor.yaml's densities, times the frontend's inflation (what euroc.yaml typed before)
    assert fp.imu.gyro_noise_rad_s_rthz == pytest.approx(2 * 1.6968e-04)
    assert fp.imu.accel_walk_m_s3_rthz == pytest.approx(2 * 3.0e-3)
