"""MonoGS keyframe window: which keyframes are optimised together.

MonoGS (Matsuki et al. 2024, section 3.3.2) keeps a small window of keyframes that overlap the
newest one; a keyframe leaves the window when its covisibility with the newest keyframe (overlap of
the Gaussian sets they see) falls below a threshold, or, when the window is full, the one with the
least overlap leaves. Visibility sets are the ids of Gaussians with a non-zero pixel count in the
keyframe's last render (:attr:`RenderOutput.counts`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["overlap_coefficient", "update_window"]


def overlap_coefficient(a: np.ndarray, b: np.ndarray) -> float:
    """``|a & b| / min(|a|, |b|)`` of two id sets given as int arrays (0 when either is empty)."""
    if len(a) == 0 or len(b) == 0:
        return 0.0
    return float(len(np.intersect1d(a, b, assume_unique=True)) / min(len(a), len(b)))


def update_window(
    window: list[int], new_kf: int, visible: dict[int, np.ndarray], size: int, overlap_min: float
) -> tuple[list[int], list[int]]:
    """Insert ``new_kf`` at the front of ``window`` and drop keyframes as MonoGS does.

    ``visible[k]`` are the ids keyframe ``k`` sees. Returns ``(new_window, dropped)``; the newest
    keyframe is always kept.
    """
    win = [new_kf] + [k for k in window if k != new_kf]
    newest = visible.get(new_kf, np.zeros(0, np.int64))
    ov = {k: overlap_coefficient(visible.get(k, np.zeros(0, np.int64)), newest) for k in win[1:]}
    dropped = [k for k in win[1:] if ov[k] < overlap_min and len(newest) > 0]
    win = [k for k in win if k not in dropped]
    while len(win) > size:
        worst = min(win[1:], key=lambda k: ov[k])
        win.remove(worst)
        dropped.append(worst)
    return win, dropped
