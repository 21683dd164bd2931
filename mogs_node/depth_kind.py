"""What a dense depth array holds (:class:`DepthKind`), and how it is resampled to another size.

One enum for the three kinds that were three string tuples (``msgs.DepthMap.KINDS``, the
metrizer's prior kinds, the Depth Anything backend's output kinds). ``DepthKind`` is a ``StrEnum``:
a member equals its string, so messages keep carrying the plain string on the wire.

Resampling policy (one per role of the array, stated here and used by every node):

- a **prior** (any kind, on ``/prior/depth``, into the metrizer) and its confidence are resampled
  **bilinearly** (:func:`resample_prior`): a prior is a smooth field that the metrizer calibrates
  per object, and bilinear keeps it smooth; for the depth kinds (``metric``, ``relative_depth``)
  0 means "no value", and the metrizer zeroes the confidence where the resampled prior is <= 0.
- a **metrized depth** (kind ``metric``, on ``/metrizer/depth``: the mapper's input, the flow
  prior's history) and its confidence are resampled **nearest-neighbour**
  (:func:`resample_metrized`): no depth is invented across an object's edge, where bilinear would
  put points between a car and the facade behind it.
"""

from __future__ import annotations

from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError

__all__ = ["DEPTH_KINDS", "DepthKind", "resample_metrized", "resample_prior"]


class DepthKind(StrEnum):
    """What the values of a dense depth array are."""

    METRIC = "metric"  # metres along the optical axis (z); 0 = no value
    RELATIVE_DEPTH = "relative_depth"  # depth up to an unknown affine map; 0 = no value
    RELATIVE_INVERSE_DEPTH = "relative_inverse_depth"  # 1 / depth up to an unknown affine map

    @classmethod
    def parse(cls, value: str, where: str) -> DepthKind:
        """``value`` as a kind, or one :class:`ConfigError` naming ``where`` and the choices."""
        try:
            return cls(value)
        except ValueError:
            raise ConfigError(f"{where}: expected one of {DEPTH_KINDS}, got {value!r}") from None


#: the kinds' strings, in one order (messages, parameters, error texts)
DEPTH_KINDS: tuple[str, ...] = tuple(k.value for k in DepthKind)


def _resample(
    values: NDArray[np.float32], confidence: NDArray[np.float32], width: int, height: int, how: str
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    import cv2  # here: the message schema imports this module and stays free of OpenCV

    if values.shape[:2] == (height, width):
        return values, confidence
    interp = cv2.INTER_LINEAR if how == "linear" else cv2.INTER_NEAREST
    return (
        cv2.resize(values, (width, height), interpolation=interp),
        cv2.resize(confidence, (width, height), interpolation=interp),
    )


def resample_prior(
    prior: NDArray[np.float32], confidence: NDArray[np.float32], width: int, height: int
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """A prior ``[h, w]`` f32 and its confidence at ``width x height``, bilinear (see above)."""
    return _resample(prior, confidence, width, height, "linear")


def resample_metrized(
    depth_m: NDArray[np.float32], confidence: NDArray[np.float32], width: int, height: int
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """A metrized depth ``[h, w]`` f32 and its confidence at ``width x height``, nearest."""
    return _resample(depth_m, confidence, width, height, "nearest")
