"""A picture a person can look at: image | depth | instances, one row per frame."""

from __future__ import annotations

import cv2
import numpy as np

from mogs_node.sim.sequence import SimFrame

__all__ = ["colorize_depth", "colorize_instances", "preview_strip"]


def colorize_depth(depth_m: np.ndarray, max_depth_m: float = 80.0) -> np.ndarray:
    """z-depth f32 ``[H, W]`` -> RGB uint8 (inverse-depth turbo colour map; sky/no value black)."""
    d = np.asarray(depth_m, dtype=np.float32)
    valid = np.isfinite(d) & (d > 0)
    inv = np.where(valid, 1.0 / np.maximum(d, 1e-3), 0.0)
    lo = 1.0 / max_depth_m
    hi = max(float(np.percentile(inv[valid], 99)) if valid.any() else 1.0, lo * 2)
    x = np.clip((inv - lo) / (hi - lo), 0, 1)
    rgb = cv2.applyColorMap((x * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    rgb[~valid] = 0
    return np.ascontiguousarray(rgb)


def colorize_instances(instance_id: np.ndarray) -> np.ndarray:
    """Instance ids int32 ``[H, W]`` -> RGB uint8 with a hashed colour per id (-1 black)."""
    ids = np.asarray(instance_id, dtype=np.int64)
    h = (ids * 2654435761) % (2**32)
    rgb = np.stack([(h >> 0) & 255, (h >> 8) & 255, (h >> 16) & 255], -1).astype(np.uint8)
    rgb = (rgb // 2 + 96).astype(np.uint8)
    rgb[ids < 0] = 0
    return rgb


def preview_strip(frames: list[SimFrame], max_panel_width: int = 640) -> np.ndarray:
    """RGB uint8 image: per frame a row ``rgb | depth | instances`` (panels downscaled to fit)."""
    rows = []
    for f in frames:
        panels = [f.rgb, colorize_depth(f.depth_m), colorize_instances(f.instance_id)]
        H, W = f.rgb.shape[:2]
        if max_panel_width < W:
            s = max_panel_width / W
            size = (max_panel_width, max(int(round(H * s)), 1))
            panels = [
                cv2.resize(p, size, interpolation=cv2.INTER_AREA if i == 0 else cv2.INTER_NEAREST)
                for i, p in enumerate(panels)
            ]
        for p, name in zip(panels, ("image", "depth", "instances"), strict=True):
            cv2.putText(
                p,
                f"{name}  t={f.stamp_ns * 1e-9:.1f}s" if name == "image" else name,
                (6, 16),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.45,
                (255, 255, 255),
                1,
                cv2.LINE_AA,
            )
        gap = np.full((panels[0].shape[0], 4, 3), 255, np.uint8)
        rows.append(np.concatenate([panels[0], gap, panels[1], gap, panels[2]], axis=1))
    sep = np.full((4, rows[0].shape[1], 3), 255, np.uint8)
    out = [rows[0]]
    for r in rows[1:]:
        out += [sep, r]
    return np.concatenate(out, axis=0)
