"""Segmentation worker node in one process: keyframes in, label images out."""

from __future__ import annotations

import numpy as np
import pytest

from mogs_node import msgs
from mogs_node.errors import ConfigError, ModelError
from mogs_node.segmentation.graph import GraphSegParams, segment_graph
from mogs_node.segmentation.node import SegmentationNode


def _kf(kid: int, image: np.ndarray) -> msgs.Keyframe:
    return msgs.Keyframe(
        stamp_ns=kid,
        frame_id="cam",
        keyframe_id=kid,
        image=image,
        K=np.array([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]]),
        T_world_cam=np.eye(4),
        feature_ids=np.zeros(0, np.int64),
        feature_uv_px=np.zeros((0, 2), np.float32),
        feature_xyz_cam_m=np.zeros((0, 3), np.float32),
        feature_weight=np.zeros(0, np.float32),
    )


def test_graph_node_publishes_labels(inproc_bus, wired_node) -> None:
    bus, ctx = inproc_bus
    node = SegmentationNode(
        "seg", {"graph": {"scale": 1.0, "k": 200.0}}, bus, context=ctx, diagnostics_period_s=0
    )
    w = wired_node(node, ("/frontend/keyframe",), "/seg/masks")
    rng = np.random.default_rng(0)
    rgb = np.zeros((60, 80, 3), np.uint8)
    rgb[:, 40:] = (200, 40, 40)
    rgb = np.clip(rgb + rng.normal(0, 3, rgb.shape), 0, 255).astype(np.uint8)
    grey = rgb[..., 0].copy()
    w.pub.publish("/frontend/keyframe", _kf(3, rgb))
    w.pub.publish("/frontend/keyframe", _kf(4, grey))
    got = w.collect(2, 10)
    assert [m.keyframe_id for m in got] == [3, 4]
    assert got[0].backend == "graph" and got[0].labels.dtype == np.int32
    np.testing.assert_array_equal(
        got[0].labels, segment_graph(rgb, GraphSegParams(scale=1.0, k=200.0))
    )
    assert got[1].labels.shape == grey.shape


def test_sam_backend_without_model_fails_at_start(inproc_bus, tmp_path) -> None:
    bus, ctx = inproc_bus
    with pytest.raises(ModelError, match="not found"):
        SegmentationNode(
            "seg",
            {
                "backend": "sam",
                "sam": {"encoder_path": str(tmp_path / "e"), "decoder_path": str(tmp_path / "d")},
            },
            bus,
            context=ctx,
            diagnostics_period_s=0,
        )


def test_sam_node_publishes_painted_masks(inproc_bus, wired_node, tmp_path) -> None:
    pytest.importorskip("torch")
    import sys
    import warnings
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parents[1]))  # tests/: the helpers
    import _tiny_onnx

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        enc, dec = _tiny_onnx.export(tmp_path)
    bus, ctx = inproc_bus
    node = SegmentationNode(
        "seg",
        {
            "backend": "sam",
            "sam": {
                "encoder_path": enc,
                "decoder_path": dec,
                "points_per_side": 3,
                "flat_prompt_stride": 1,
            },
        },
        bus,
        context=ctx,
        diagnostics_period_s=0,
    )
    w = wired_node(node, ("/frontend/keyframe",), "/seg/masks")
    rgb = np.zeros((90, 120, 3), np.uint8)
    w.pub.publish("/frontend/keyframe", _kf(9, rgb))
    got = w.collect_one(10)
    assert got is not None and got.keyframe_id == 9 and got.backend == "sam"
    assert node.sam is not None
    np.testing.assert_array_equal(got.labels, node.sam.generate(rgb).labels)
    assert (got.labels >= 0).mean() > 0.5


def test_graph_backend_without_opencv_contrib_fails_at_start(inproc_bus, monkeypatch) -> None:
    """An OpenCV without ximgproc (opencv-python instead of the contrib build) stops the node at
    start-up with the package to install, not with an AttributeError on every keyframe."""
    import cv2

    monkeypatch.delattr(cv2, "ximgproc")
    bus, ctx = inproc_bus
    with pytest.raises(ConfigError, match="opencv-contrib-python-headless"):
        SegmentationNode("seg", {}, bus, context=ctx, diagnostics_period_s=0)
    with pytest.raises(ConfigError, match="no ximgproc"):
        segment_graph(np.zeros((8, 8, 3), np.uint8))
