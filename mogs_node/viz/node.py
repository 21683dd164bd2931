"""Viz node: the pipeline's topics -> a rerun viewer (spawned or connected) or an ``.rrd`` file.

A sink only: it never publishes data and never slows the pipeline down. Per-frame topics (camera
image, odometry, render) are best-effort (latest wins); keyframe-rate topics are reliable, and the
incremental ``/mapper/gaussians`` must be, to keep the cloud consistent. Needs ``rerun-sdk``
(``pip install -e .[viz]``); without it the node refuses to start with a clear error.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mogs_node import msgs
from mogs_node.errors import ConfigError
from mogs_node.node import Node
from mogs_node.params import check_choice
from mogs_node.viz import rerun_log as vl

__all__ = ["VizNode", "VizParams", "import_rerun"]

MODES = ("save", "spawn", "connect")


@dataclass(frozen=True)
class VizParams:
    """Parameters of the viz node."""

    mode: str = "save"  # save: write rrd_path; spawn: start a viewer; connect: to connect_url
    rrd_path: str = "runs/latest/mogs.rrd"  # the recording file (mode save)
    connect_url: str = ""  # mode connect: the viewer's gRPC URL ("" = rerun's default)
    application_id: str = "mogs"  # rerun application id (groups recordings in the viewer)
    image_every: int = 1  # log every n-th camera image (1 = all that arrive)
    max_gaussians: int = 2_000_000  # centres logged per update at most (an even subset beyond)
    camera_image: bool = True  # log /camera/image (the largest stream)

    def __post_init__(self) -> None:
        check_choice("viz.mode", self.mode, MODES)
        if self.mode == "save" and not self.rrd_path:
            raise ConfigError("viz.rrd_path: required in mode save")
        if self.image_every < 1 or self.max_gaussians < 1:
            raise ConfigError("viz.image_every and viz.max_gaussians: must be >= 1")


def import_rerun() -> Any:
    """The ``rerun`` module, or a ConfigError saying how to install it."""
    try:
        return importlib.import_module("rerun")
    except ImportError as err:
        raise ConfigError(
            "the viz node needs rerun-sdk: pip install -e '.[viz]' (or pip install rerun-sdk)"
        ) from err


class VizNode(Node):
    """Logs what the pipeline publishes to rerun (see the module docstring)."""

    Params = VizParams

    def setup(self) -> None:
        p: VizParams = self.params
        self.rr = rr = import_rerun()
        self.rec = rr.RecordingStream(p.application_id)
        if p.mode == "save":
            Path(p.rrd_path).parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(p.rrd_path)
        elif p.mode == "spawn":
            self.rec.spawn()
        else:
            connect = getattr(self.rec, "connect_grpc", None) or self.rec.connect
            connect(p.connect_url) if p.connect_url else connect()
        self.traj = vl.Trajectory()
        self.cloud = vl.GaussianCloud()
        self._K: np.ndarray | None = None
        self._size: tuple[int, int] | None = None
        self._n_images = 0
        self.counters["viz_logged"] = 0
        if p.camera_image:
            self.subscribe("/camera/image", self.on_image, reliable=False, msg_type=msgs.Image)
        self.subscribe(
            "/frontend/odometry", self.on_odometry, reliable=False, msg_type=msgs.Odometry
        )
        self.subscribe("/frontend/keyframe", self.on_keyframe, msg_type=msgs.Keyframe)
        self.subscribe("/seg/masks", self._logged(vl.log_masks), msg_type=msgs.Masks)
        self.subscribe("/prior/depth", self.on_prior, msg_type=msgs.DepthMap)
        self.subscribe("/metrizer/depth", self._logged(vl.log_depth), msg_type=msgs.DepthMap)
        self.subscribe("/mapper/gaussians", self.on_gaussians, msg_type=msgs.GaussianUpdate)
        self.subscribe(
            "/mapper/render", self._logged(vl.log_render), reliable=False, msg_type=msgs.Render
        )
        self.subscribe("/mapper/stats", self._logged(vl.log_stats), msg_type=msgs.MapStats)

    def _logged(self, fn: Any) -> Any:
        def handler(msg: msgs.Message) -> None:
            fn(self.rr, self.rec, msg)
            self.counters["viz_logged"] += 1

        return handler

    def on_image(self, msg: msgs.Image) -> None:
        self._n_images += 1
        if (self._n_images - 1) % self.params.image_every == 0:
            vl.log_image(self.rr, self.rec, msg)
            self.counters["viz_logged"] += 1

    def on_odometry(self, msg: msgs.Odometry) -> None:
        vl.log_odometry(self.rr, self.rec, msg, self.traj, self._K, self._size)
        self.counters["viz_logged"] += 1

    def on_keyframe(self, msg: msgs.Keyframe) -> None:
        self._K = np.asarray(msg.K, dtype=np.float64)
        self._size = (int(msg.image.shape[1]), int(msg.image.shape[0]))
        vl.log_keyframe(self.rr, self.rec, msg)
        self.counters["viz_logged"] += 1

    def on_prior(self, msg: msgs.DepthMap) -> None:
        vl.log_depth(self.rr, self.rec, msg, prior=True)
        self.counters["viz_logged"] += 1

    def on_gaussians(self, msg: msgs.GaussianUpdate) -> None:
        vl.log_gaussians(self.rr, self.rec, msg, self.cloud, self.params.max_gaussians)
        self.counters["viz_logged"] += 1

    def teardown(self) -> None:
        flush = getattr(self.rec, "flush", None)
        if flush is not None:
            flush()
        disconnect = getattr(self.rec, "disconnect", None)
        if disconnect is not None:
            disconnect()
