"""What the ROS 1 bridge and the ROS 2 mirror share as node shells: counting malformed ROS input,
putting the calibration on the bus, and subscribing to the pipeline's outputs (the pure work is
:class:`~bridges.ros_inputs.RosInputs`' and :class:`~bridges.ros_outputs.RosOutputs`'; this mixin
only logs, counts, publishes and subscribes)."""

from __future__ import annotations

import logging
import time
from typing import Any

from bridges.ros_inputs import RosInputs
from mogs_node import msgs

__all__ = ["RosBridgeShell"]


class RosBridgeShell:
    """Mixed into a :class:`~mogs_node.node.Node` subclass that holds ``self.inputs``
    (:class:`RosInputs`) and names the bus topic of the calibration in ``bus_camera_info_topic``."""

    inputs: RosInputs
    counters: dict[str, Any]
    log: logging.Logger
    publish: Any
    subscribe: Any

    @property
    def bus_camera_info_topic(self) -> str:
        raise NotImplementedError

    def _bad(self, what: str, err: Exception) -> None:
        line = self.inputs.count_malformed(what, err)
        self.counters["ros_malformed"] = self.inputs.malformed
        if line is not None:
            self.log.warning("%s", line)

    def _calibration_due(self) -> None:
        """The calibration on the bus once its T_imu_cam is known (:class:`RosInputs`)."""
        due = self.inputs.calibration_due(time.monotonic())
        if due is None:
            return
        self.log.info(
            "calibration on %s: T_imu_cam %s",
            self.bus_camera_info_topic,
            f"from {due[1]}" if due[1] else "unknown (the frontend's launch value)",
        )
        self._republish_calibration()

    def _subscribe_outputs(self) -> None:
        """The pipeline's outputs the bridge sends to ROS (handlers ``on_*`` of the bridge)."""
        s: Any = self
        s.subscribe("/frontend/odometry", s.on_odometry, reliable=False, queue_size=64)
        s.subscribe("/frontend/keyframe", s.on_keyframe, msg_type=msgs.Keyframe)
        s.subscribe("/frontend/refined_pose", s.on_keyframe_pose, msg_type=msgs.PoseStamped)
        s.subscribe("/metrizer/depth", s.on_depth, msg_type=msgs.DepthMap)
        s.subscribe("/mapper/gaussians", s.on_gaussians, msg_type=msgs.GaussianUpdate)
        s.subscribe("/mapper/stats", s.on_stats, msg_type=msgs.MapStats)

    def _republish_calibration(self) -> None:
        if self.inputs.calibration_msg is not None:
            self.publish(self.bus_camera_info_topic, self.inputs.calibration_msg)
