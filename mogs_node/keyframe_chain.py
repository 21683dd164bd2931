"""The keyframe chain's answer when a worker has none for a keyframe (issue 28).

The metrizer waits for each keyframe's masks and prior as long as their workers advance (a late
input is used, never dropped). So a worker that fails on a keyframe must say so, or the metrizer
would wait for an answer that never comes: it publishes a *failure notice* on its usual topic, a
message of the usual type with no content (labels all -1, confidence all 0) whose ``backend`` /
``source`` field starts with :data:`FAILED_PREFIX` followed by the reason. Every consumer of the
topic already handles "no mask" / "no prior" pixels; the metrizer reads the reason and metrizes
that keyframe without the input, with a warning that names the reason.
"""

from __future__ import annotations

import numpy as np

from mogs_node import msgs

__all__ = ["FAILED_PREFIX", "failed_masks", "failed_prior", "failure_reason"]

FAILED_PREFIX = "failed: "
MAX_REASON_CHARS = 300  # a traceback's last line, not the whole traceback


def _reason(err: BaseException | str) -> str:
    text = err if isinstance(err, str) else f"{type(err).__name__}: {err}"
    text = " ".join(str(text).split())
    return FAILED_PREFIX + (text[:MAX_REASON_CHARS] or "unknown error")


def failed_masks(kf: msgs.Keyframe, err: BaseException | str) -> msgs.Masks:
    """The segmentation worker's notice that it has no masks for ``kf`` (and why)."""
    H, W = kf.image.shape[:2]
    return msgs.Masks(
        **kf.result_header(), labels=np.full((H, W), -1, np.int32), backend=_reason(err)
    )


def failed_prior(kf: msgs.Keyframe, err: BaseException | str) -> msgs.DepthMap:
    """The prior worker's notice that it has no prior for ``kf`` (and why)."""
    H, W = kf.image.shape[:2]
    zeros = np.zeros((H, W), np.float32)
    return msgs.DepthMap(
        **kf.result_header(),
        kind="metric",
        depth=zeros,
        confidence=zeros,
        source=_reason(err),
        object_labels=None,
        object_model=None,
    )


def failure_reason(msg: msgs.Message) -> str | None:
    """The reason of a failure notice (without the prefix); None for an ordinary message."""
    tag = getattr(msg, "source", None)
    if not isinstance(tag, str):
        tag = getattr(msg, "backend", None)
    if isinstance(tag, str) and tag.startswith(FAILED_PREFIX):
        return tag[len(FAILED_PREFIX) :]
    return None
