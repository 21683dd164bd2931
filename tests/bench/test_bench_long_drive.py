"""bench/long_drive.py: distance along the keyframes, the saved trace, the plot (no processes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.long_drive import Trace, _path_lengths, _plot, load_trace, save_trace


def _trace() -> Trace:
    t = Trace(frames=40)
    for k, x in enumerate([0.0, 3.0, 7.0, 12.0]):  # keyframes along x, then 4 m up in z
        t.kf_pos[k] = np.array([x, 0.0, 0.0])
    t.kf_pos[4] = np.array([12.0, 0.0, 4.0])
    for k in range(5):
        t.mapped[k] = {"map_ms": 100.0 + k, "n_gaussians": 10 * k}
        t.mapped_at.append((k, 10.0 + k))
        if k:
            t.cpu_ms[k] = 50.0 + k
    t.rss = [(9.5 + 0.5 * i, 8 * i, 300.0 + i) for i in range(12)]
    return t


def test_distance_is_the_path_length_along_the_keyframes() -> None:
    assert _path_lengths(_trace()) == pytest.approx({0: 0.0, 1: 3.0, 2: 7.0, 3: 12.0, 4: 16.0})
    assert _path_lengths(Trace()) == {}


def test_a_saved_trace_reads_back_and_plots(tmp_path: Path) -> None:
    t = _trace()
    dist = _path_lengths(t)
    save_trace(t, dist, tmp_path / "trace.json")
    back, dist_back = load_trace(tmp_path / "trace.json")
    assert dist_back == pytest.approx(dist)
    assert back.mapped == t.mapped and back.mapped_at == t.mapped_at
    assert back.cpu_ms == t.cpu_ms and back.rss == t.rss
    _plot(back, tmp_path / "p.png", dist_back)
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
