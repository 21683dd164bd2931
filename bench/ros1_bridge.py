"""The same ROS 1 bag replayed directly (``launch/bag.yaml``) and through a real ROS 1 graph
(``roscore`` + ``rosbag play --clock`` + ``launch/ros1.yaml``), in one run.

The bag is a sim drive written by the official ``rosbag`` writer (bz2 chunks, mono8 on
``/cam0/image_raw``, IMU on ``/imu0``, CameraInfo, ground truth, 2011 epoch stamps). Figures:

- ATE (SE(3)-aligned, every frame with odometry) of both against the bag's ground truth, and
  the difference in % of the path length;
- the bridge run: latency from a camera message to its odometry, both as a rospy listener on the
  graph receives them (p50 / p95), frames dropped by the bridge, frames without odometry.

Needs ROS 1 (Debian: README "On a ROS 1 robot"). Usage::

    python bench/ros1_bridge.py [--frames 60] [--rate 0.5] [--json PATH] [--no-docs]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))  # the roscore / official-bag / listener helpers

from _reliability_harness import cli_argv  # noqa: E402
from _ros1 import (  # noqa: E402
    EPOCH_2011_NS,
    GT_POSE_TOPIC,
    TOPICS,
    read_listener,
    rosbag_play_argv,
    roscore,
    set_param,
    start_listener,
    stop,
    wait_for_subscriber,
    write_sim_bag_official,
)

from mogs_node.eval.bench_docs import (  # noqa: E402
    add_output_options,
    machine_line,
    update_markdown_section,
    write_json,
)
from mogs_node.eval.traj import trajectory_metrics  # noqa: E402
from mogs_node.frontend.trajectory_io import read_tum  # noqa: E402
from mogs_node.geometry import make_T, quat_wxyz_to_rotmat  # noqa: E402
from mogs_node.sim import SimConfig, make_sequence  # noqa: E402

TOPIC_SETS = [
    f"player.bag_image_topic={TOPICS['image']}",
    f"player.bag_imu_topic={TOPICS['imu']}",
    f"player.bag_camera_info_topic={TOPICS['camera_info']}",
    f"player.bag_pose_topic={GT_POSE_TOPIC}",
    "player.groundtruth_depth=false",
]
#: both runs: the trajectory is measured, not the map (keyframes inserted, not optimised; the
#: report renders one keyframe of the final map, no held-out views: minutes on shared cores)
MAPPER_SETS = [
    "mapper.iters_per_keyframe=0",
    "mapper.publish_render=false",
    "report.heldout_views=0",
    "report.max_keyframe_views=1",
    "report.save_renders=false",
]


def _sets(items: list[str]) -> list[str]:
    return [a for s in items for a in ("--set", s)]


def _launch_argv(launch: str, run_dir: Path, sets: list[str], *extra: str) -> list[str]:
    """``mogs launch launch/LAUNCH --run-dir RUN_DIR --grace 60 EXTRA --set ...``: the direct and
    the bridged run start the same way (a long grace: the mapper writes its map at the end)."""
    head = ["launch", str(REPO / "launch" / launch), "--run-dir", str(run_dir), "--grace", "60"]
    return cli_argv(*head, *extra, *_sets(sets))


def _ate(stamps: np.ndarray, poses: np.ndarray, gt: dict[int, np.ndarray]) -> dict:
    keep = [i for i, t in enumerate(stamps) if int(t) in gt]
    s = np.asarray(stamps, np.int64)[keep]
    return {
        "frames": len(keep),
        **trajectory_metrics(s, poses[keep], np.array([gt[int(t)] for t in s])),
    }


def _nearest(stamps_ns: np.ndarray, grid_ns: np.ndarray) -> np.ndarray:
    """Each stamp onto the nearest of the bag's (a trajectory file may round them)."""
    idx = np.clip(np.searchsorted(grid_ns, stamps_ns), 1, len(grid_ns) - 1)
    left, right = grid_ns[idx - 1], grid_ns[idx]
    return np.where(stamps_ns - left < right - stamps_ns, left, right)


def _path_ates(heard: dict, gt: dict[int, np.ndarray]) -> tuple[dict, dict]:
    """ATE of the keyframe path as the listener first saw each keyframe and as it ended."""
    rows = heard["path"]["poses"]
    stamps = np.array([int(r[0]) for r in rows], np.int64)

    def poses(vals: list) -> np.ndarray:
        return np.array(
            [
                make_T(quat_wxyz_to_rotmat(np.array(v[3:7], float)), np.array(v[:3], float))
                for v in vals
            ]
        )

    final = poses([r[1:] for r in rows])
    first = poses([heard["path_first"][str(int(t))] for t in stamps])
    return _ate(stamps, first, gt), _ate(stamps, final, gt)


def _path_max_move(heard: dict) -> float:
    final = {str(int(r[0])): r[1:4] for r in heard["path"]["poses"]}
    return max(
        float(np.linalg.norm(np.subtract(v, heard["path_first"][k][:3]))) for k, v in final.items()
    )


def run_direct(bag: Path, out: Path, timeout_s: float) -> tuple[np.ndarray, np.ndarray, float]:
    t0 = time.monotonic()
    with (out.parent / "direct.log").open("w") as log:
        proc = subprocess.run(
            _launch_argv(
                "bag.yaml",
                out,
                [f"player.path={bag}", *TOPIC_SETS, *MAPPER_SETS],
                "--timeout",
                str(timeout_s),
            ),
            cwd=REPO,
            env={**os.environ, "MOGS_NO_CPP_EXT": "1"},  # the mapper's pure-PyTorch compositor
            stdout=log,
            stderr=subprocess.STDOUT,
            timeout=timeout_s + 120,
        )
    if proc.returncode != 0:
        raise SystemExit(f"direct run failed: {(out.parent / 'direct.log').read_text()[-3000:]}")
    stamps_ns, poses = read_tum(out / "trajectory_frames.tum")
    return np.asarray(stamps_ns, np.int64), np.asarray(poses), time.monotonic() - t0


def run_bridge(bag: Path, tmp: Path, rate: float) -> tuple[dict, str]:
    run = tmp / "bridge"
    with roscore(tmp) as env:
        env["MOGS_NO_CPP_EXT"] = "1"  # as the direct run: no C++ build in the measurement
        set_param(env, "/use_sim_time", "true")
        listener = start_listener(env, tmp / "heard.json")
        log_path = tmp / "bridge.log"
        with log_path.open("w") as log:
            launch = subprocess.Popen(
                _launch_argv(
                    "ros1.yaml",
                    run,
                    [
                        f"ros1.image_topic={TOPICS['image']}",
                        f"ros1.imu_topic={TOPICS['imu']}",
                        f"ros1.camera_info_topic={TOPICS['camera_info']}",
                        "ros1.wait_for_nodes_s=900",
                        *MAPPER_SETS,
                    ],
                ),
                cwd=REPO,
                env=env,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
            try:
                if not wait_for_subscriber(env, TOPICS["image"], "mogs", 1200):
                    raise SystemExit(f"bridge not up: {log_path.read_text()[-3000:]}")
                subprocess.run(
                    rosbag_play_argv(bag, rate),
                    env=env,
                    check=True,
                    capture_output=True,
                    timeout=3600,
                )
                launch.wait(1800)  # the bridge ends the run: the camera is quiet
            finally:
                stop(launch, 120)
                stop(listener, 20)
    return read_listener(tmp / "heard.json"), log_path.read_text()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--rate", type=float, default=0.5, help="rosbag play rate (1 = real time)")
    ap.add_argument("--timeout", type=float, default=1800.0)
    add_output_options(ap)
    args = ap.parse_args(argv)

    tmp = Path(tempfile.mkdtemp(prefix="mogs-bench-ros1-"))
    seq = make_sequence(
        SimConfig(
            seed=0,
            n_frames=args.frames,
            width=621,
            height=188,
            static_start_s=2.0,
            start_ns=EPOCH_2011_NS,
        )
    )
    bag = write_sim_bag_official(tmp / "drive.bag", seq, "mono8")
    grid = np.asarray(seq.stamps_ns, np.int64)
    gt = {int(t): T for t, T in zip(grid, seq.T_world_cam)}

    d_stamps_ns, d_poses, direct_wall_s = run_direct(bag, tmp / "direct", args.timeout)
    d_stamps = _nearest(d_stamps_ns, grid)  # matched onto the bag's stamps
    direct = _ate(d_stamps, d_poses, gt)

    heard, log = run_bridge(bag, tmp, args.rate)
    rows = np.array(heard["odometry"], dtype=object)
    b_stamps = np.array([int(r[0]) for r in rows], np.int64)
    b_poses = np.array(
        [
            make_T(quat_wxyz_to_rotmat(np.array(r[4:8], float)), np.array(r[1:4], float))
            for r in rows
        ]
    )
    bridge = _ate(b_stamps, b_poses, gt)
    path_first, path_final = _path_ates(heard, gt)
    cam_rx = {int(t): int(rx) for t, rx in heard["images"]}
    lat_ms = np.array([(int(r[8]) - cam_rx[int(r[0])]) / 1e6 for r in rows if int(r[0]) in cam_rx])
    m = re.search(r"ROS 1 bridge: (\d+) frames in, (\d+) dropped here", log)
    frames_in, dropped = (int(m.group(1)), int(m.group(2))) if m else (-1, -1)
    path_m = direct["path_length_m"]
    fig = {
        "frames_in_bag": len(grid),
        "rosbag_play_rate": args.rate,
        "path_length_m": path_m,
        "direct_frames_with_odometry": direct["frames"],
        "direct_ate_se3_rmse_m": direct["ate_se3_rmse_m"],
        "bridge_frames_with_odometry": bridge["frames"],
        "bridge_ate_se3_rmse_m": bridge["ate_se3_rmse_m"],
        "ate_difference_pct_of_path": 100
        * abs(bridge["ate_se3_rmse_m"] - direct["ate_se3_rmse_m"])
        / path_m,
        "bridge_latency_p50_ms": float(np.percentile(lat_ms, 50)),
        "bridge_latency_p95_ms": float(np.percentile(lat_ms, 95)),
        "bridge_frames_received": frames_in,
        "bridge_frames_dropped": dropped,
        "bridge_frames_without_odometry": len(grid) - bridge["frames"],
        "path_keyframes": path_final["frames"],
        "path_ate_first_shown_m": path_first["ate_se3_rmse_m"],
        "path_ate_refined_m": path_final["ate_se3_rmse_m"],
        "path_max_move_m": _path_max_move(heard),
        "direct_wall_s": direct_wall_s,
    }
    print(json.dumps(fig, indent=2))
    if args.json:
        write_json(args.json, fig)
    if not args.no_docs:
        body = f"""## ROS 1 bridge: the bag directly vs through a ROS 1 graph

`python bench/ros1_bridge.py --frames {args.frames} --rate {args.rate}` ({machine_line()}). A sim drive
({len(grid)} frames at 10 Hz, 621x188 mono8, IMU 200 Hz) written by the official rosbag writer (bz2,
2011 stamps), replayed by `launch/bag.yaml` (player in fast mode: no frame dropped) and by
`rosbag play --clock -r {args.rate}` into `launch/ros1.yaml` (live: the frontend keeps its latest image).

| | direct (`bag.yaml`) | through ROS 1 (`ros1.yaml`) |
| --- | --- | --- |
| frames with odometry | {direct["frames"]} | {bridge["frames"]} |
| ATE SE(3) RMSE | {direct["ate_se3_rmse_m"]:.3f} m | {bridge["ate_se3_rmse_m"]:.3f} m |
| ATE difference | | {fig["ate_difference_pct_of_path"]:.2f} % of the {path_m:.1f} m path |
| camera message -> its odometry on the graph, p50 / p95 | | {fig["bridge_latency_p50_ms"]:.0f} / {fig["bridge_latency_p95_ms"]:.0f} ms |
| frames dropped by the bridge / without odometry | | {dropped} / {fig["bridge_frames_without_odometry"]} |
| `/mogs/path`: keyframes, ATE as first shown -> after the window's refinements | | {path_final["frames"]}, {path_first["ate_se3_rmse_m"]:.3f} m -> {path_final["ate_se3_rmse_m"]:.3f} m (largest move {fig["path_max_move_m"] * 100:.1f} cm) |

Frames without odometry are those before the frontend's static initialisation (no pose, nothing
sent on ROS) and those the live policy dropped while the pipeline was behind. The latency is the wall time between a rospy listener receiving a camera message and
receiving its odometry (one host; 2 cores shared with other work: the figures of a loaded machine).
The path's keyframes move while the frontend's sliding window refines them (the frontend publishes
each move on `/frontend/refined_pose`, the bridge sends the path again); its ATE is over the
keyframes, against the bag's ground truth. Both runs use the mapper's pure-PyTorch compositor and insert keyframes without optimising them
(the trajectory is measured here, not the map).
"""
        update_markdown_section("ros1-bridge", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
