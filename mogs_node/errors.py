"""One exception hierarchy for the whole package.

Every domain raises a subclass of :class:`MogsError` so that callers (node shells, the CLI) can
catch project errors without catching programming errors.
"""

from __future__ import annotations

__all__ = [
    "BusError",
    "ConfigError",
    "DatasetError",
    "DeviceError",
    "GeometryError",
    "MessageError",
    "ModelError",
    "MogsError",
    "Ros1UnavailableError",
    "Ros2UnavailableError",
    "ShapeError",
]


class MogsError(Exception):
    """Base class of every error raised on purpose by mogs_node."""


class ShapeError(MogsError, ValueError):
    """An array argument has the wrong shape, dtype or contents; the message names the argument."""


class GeometryError(MogsError, ValueError):
    """A geometric quantity is invalid (non-finite pose, non-positive focal length, ...)."""


class MessageError(MogsError, ValueError):
    """A wire message is malformed; ``field`` names the offending field when known."""

    def __init__(self, message: str, *, field: str | None = None) -> None:
        super().__init__(f"{field}: {message}" if field else message)
        self.field = field


class BusError(MogsError, RuntimeError):
    """Transport-level failure (bad endpoint, security set-up, closed socket)."""


class ConfigError(MogsError, ValueError):
    """A launch file or parameter set is invalid; the message names the key."""


class DatasetError(MogsError, ValueError):
    """A dataset file is missing or malformed; the message names the file (and line)."""


class ModelError(MogsError, RuntimeError):
    """A user-supplied model file is missing, unreadable or has the wrong signature."""


class DeviceError(MogsError, RuntimeError):
    """A live device (camera, serial port, socket) is missing or failed; the message names it."""


class Ros1UnavailableError(MogsError, RuntimeError):
    """rospy (Debian's ROS 1 packages) is needed and missing."""


class Ros2UnavailableError(MogsError, RuntimeError):
    """rclpy (a ROS 2 installation) is needed and missing."""
