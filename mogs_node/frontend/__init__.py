"""Visual-inertial frontend (VINS-Mono style): KLT tracking, IMU preintegration, GTSAM sliding
window, static/dynamic initialisation, keyframes with sparse metric points. See docs/frontend.md.

Pure modules (no bus): :mod:`camera`, :mod:`tracker`, :mod:`preintegration`, :mod:`estimator`,
:mod:`initialization`, :mod:`keyframes`, :mod:`frontend`, :mod:`trajectory_io`, :mod:`runs`;
the node shell is :mod:`node`.
"""

from mogs_node.frontend.camera import CameraModel
from mogs_node.frontend.frontend import FrameOutput, Frontend, FrontendParams, KeyframeOutput

__all__ = ["CameraModel", "FrameOutput", "Frontend", "FrontendParams", "KeyframeOutput"]
