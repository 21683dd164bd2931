"""``mogs sim``: writes a readable sequence and a preview strip."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from mogs_node.cli import main
from mogs_node.datasets import read_bag, read_kitti_raw
from mogs_node.datasets.vi_folder import read_user_poses
from mogs_node.sim import SimConfig, make_sequence
from mogs_node.sim.preview import colorize_depth, colorize_instances, preview_strip


def test_mogs_sim_kitti_with_preview(tmp_path: Path) -> None:
    out = tmp_path / "drive"
    rc = main(
        ["sim", "--out", str(out), "--frames", "3", "--size", "96x40", "--seed", "2", "--preview"]
    )
    assert rc == 0
    s = read_kitti_raw(out)
    assert len(s) == 3 and s[0].image.shape == (40, 96, 3)
    ref = make_sequence(SimConfig(seed=2, n_frames=3, width=96, height=40))
    np.testing.assert_array_equal(s[1].image, ref.render(1).rgb)
    prev = cv2.imread(str(out / "preview.png"))
    assert prev.shape == (3 * 40 + 2 * 4, 3 * 96 + 2 * 4, 3)


def test_mogs_sim_bag_and_explicit_preview(tmp_path: Path) -> None:
    bag = tmp_path / "s.bag"
    png = tmp_path / "p" / "strip.png"
    rc = main(
        [
            "sim",
            "--out",
            str(bag),
            "--format",
            "rosbag1",
            "--frames",
            "2",
            "--size",
            "64x32",
            "--no-imu-noise",
            "--preview",
            str(png),
        ]
    )
    assert rc == 0 and png.exists()
    b = read_bag(bag)
    assert len(b) == 2 and b.camera.width == 64


def test_mogs_sim_poses_out_reads_back_as_the_player_poses(tmp_path: Path) -> None:
    """``--poses-out`` writes the drive's camera poses (TUM) that ``player.poses`` reads back at
    the frames' stamps: the ground truth a "poses = ground truth" run maps with (issue 18)."""
    txt = tmp_path / "gt" / "poses.txt"
    argv = ["sim", "--frames", "4", "--size", "64x32", "--seed", "3", "--static-start", "0.2"]
    assert main([*argv, "--poses-out", str(txt)]) == 0
    ref = make_sequence(SimConfig(seed=3, n_frames=4, width=64, height=32, static_start_s=0.2))
    poses = read_user_poses(txt, ref.stamps_ns)
    assert len(poses) == 4 and all(T is not None for T in poses)
    np.testing.assert_allclose(np.stack(poses), ref.T_world_cam, atol=1e-7)


def test_mogs_sim_errors(tmp_path: Path) -> None:
    assert main(["sim", "--size", "12by3", "--preview"]) == 1
    assert main(["sim", "--frames", "2", "--size", "64x32"]) == 1  # neither --out nor --preview


def test_preview_panels() -> None:
    d = np.array([[1.0, 10.0], [np.inf, 0.0]], dtype=np.float32)
    c = colorize_depth(d)
    assert c.dtype == np.uint8 and np.all(c[1] == 0) and not np.array_equal(c[0, 0], c[0, 1])
    ids = np.array([[-1, 0], [1, 1]], dtype=np.int32)
    ci = colorize_instances(ids)
    assert (
        np.all(ci[0, 0] == 0)
        and np.array_equal(ci[1, 0], ci[1, 1])
        and not np.array_equal(ci[0, 1], ci[1, 0])
    )
    seq = make_sequence(SimConfig(n_frames=2, width=700, height=100))
    strip = preview_strip([seq.render(0), seq.render(1)], max_panel_width=350)
    assert strip.shape == (2 * 50 + 4, 3 * 350 + 8, 3)
