"""Writing the evaluation's pictures: one place for the matplotlib save and the titled image strip
that the depth evaluations draw (docs/*.png)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["save_figure", "write_titled_strip"]


def save_figure(fig: Any, path: Path, *, dpi: int = 110) -> None:
    """Lay out a matplotlib figure, write it to ``path`` (folders made) and free it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


def write_titled_strip(
    path: Path,
    panels: list[NDArray[np.uint8]],
    titles: list[str],
    *,
    font_scale: float = 0.45,
    margin_px: int = 4,
    line_type: int = cv2.LINE_8,
) -> None:
    """Stack RGB uint8 ``[H, W, 3]`` panels top to bottom, each with its title in white on a black
    box at the top left (drawn into the panels), and write the strip as PNG/JPEG to ``path``."""
    if len(panels) != len(titles):
        raise ValueError(f"write_titled_strip: {len(panels)} panels but {len(titles)} titles")
    font = cv2.FONT_HERSHEY_SIMPLEX
    for img, title in zip(panels, titles, strict=True):
        (tw, th), _ = cv2.getTextSize(title, font, font_scale, 1)
        cv2.rectangle(img, (0, 0), (tw + 2 * margin_px, th + 2 * margin_px), (0, 0, 0), -1)
        cv2.putText(
            img, title, (margin_px, th + margin_px), font, font_scale, (255, 255, 255), 1, line_type
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(panels, 0)[..., ::-1])
