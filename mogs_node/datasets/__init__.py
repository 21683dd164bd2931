"""Dataset readers and writers behind one small interface (:class:`Sequence` of lazy frames).

Readers: KITTI raw (+ OXTS, projected LiDAR depth, calibration), KITTI odometry, EuRoC, a generic
visual-inertial folder with a Kalibr calibration, and rosbag1 / rosbag2 / MCAP bags. Writers: a
simulated sequence to the KITTI-raw / KITTI-odometry layouts, the generic VI folder and bags.
Bad or missing files raise :class:`mogs_node.errors.DatasetError` naming the file (and line).
"""

from mogs_node.datasets.bag import BAG_FORMATS, BagTopics, BagWriter, read_bag
from mogs_node.datasets.base import Frame, ImuSamples, Sequence, Trajectory
from mogs_node.datasets.euroc import read_euroc
from mogs_node.datasets.kitti import read_kitti_odometry, read_kitti_oxts, read_kitti_raw
from mogs_node.datasets.vi_folder import read_vi_folder
from mogs_node.datasets.writers import (
    write_kitti_odometry,
    write_kitti_raw,
    write_sim_bag,
    write_vi_folder,
)

__all__ = [
    "BAG_FORMATS",
    "BagTopics",
    "BagWriter",
    "Frame",
    "ImuSamples",
    "Sequence",
    "Trajectory",
    "read_bag",
    "read_euroc",
    "read_kitti_odometry",
    "read_kitti_oxts",
    "read_kitti_raw",
    "read_vi_folder",
    "write_kitti_odometry",
    "write_kitti_raw",
    "write_sim_bag",
    "write_vi_folder",
]
