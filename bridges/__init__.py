"""Sources and sinks outside the bus (see docs/bridges.md).

- :mod:`bridges.player`: the player node (KITTI, EuRoC, bags, the synthetic world, recordings)
- :mod:`bridges.replay`: its pure timing and flow-control helpers
- :mod:`bridges.sources`: opening a dataset sequence
- :mod:`bridges.live`: live camera and IMU adapters; :mod:`bridges.imu_text`: the IMU parser
- :mod:`bridges.recording`: MCAP recordings of bus traffic
- :mod:`bridges.ros2`: ROS 2 message conversions and the rclpy mirror

Submodules are imported explicitly (``from bridges.player import PlayerNode``) so that importing
one bridge never pulls in another's dependencies.
"""
