"""Depth Anything ONNX backend: pre/post-processing checked on tiny models exported here.

The tiny models (tests/_tiny_onnx.py) have the input/output signature of the common Depth Anything V2 export (input
``image`` [1, 3, h, w], output ``depth`` [1, h, w]) and compute a known per-pixel linear function
of the normalised input, so the expected output is exact.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from mogs_node.depth_prior.depth_anything_onnx import (  # noqa: E402
    IMAGENET_MEAN,
    IMAGENET_STD,
    DepthAnythingOnnx,
    DepthAnythingParams,
    preprocess_size,
)
from mogs_node.errors import ConfigError, ModelError  # noqa: E402

sys.path.insert(0, str(Path(__file__).parents[1]))  # tests/: the helpers
import _tiny_onnx  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore:torch.tensor results")

COEF, OFFSET = _tiny_onnx.DA_COEF, _tiny_onnx.DA_OFFSET


def _export(path, dynamic: bool, hw=(56, 84), out_name="depth") -> str:
    return _tiny_onnx.export_depth_anything(path, dynamic=dynamic, hw=hw, out_name=out_name)


@pytest.fixture(scope="module")
def dyn_model(tmp_path_factory) -> str:
    return _export(tmp_path_factory.mktemp("da") / "tiny_dyn.onnx", dynamic=True)


def _expected_constant(rgb_value) -> float:
    x = (np.asarray(rgb_value, np.float32) / 255.0 - IMAGENET_MEAN) / IMAGENET_STD
    return float(np.dot(COEF, x) + OFFSET)


def test_preprocess_size_multiple_of_14() -> None:
    h, w = preprocess_size(375, 1242, 518, 14)
    assert h % 14 == 0 and w % 14 == 0
    assert h == 518 and abs(w / h - 1242 / 375) < 0.02
    h, w = preprocess_size(480, 640, 518, 14)
    assert (h, w) == (518, 686)  # 518 * 4/3 = 690.7 -> nearest multiple of 14 is 686
    # upper_bound: the longer side is input_size, the shorter one rounded to a multiple of 14
    assert preprocess_size(375, 1242, 518, 14, "upper_bound") == (154, 518)  # 156.4 -> 154
    assert preprocess_size(188, 621, 518, 14, "upper_bound") == (154, 518)  # 156.8 -> 154
    assert preprocess_size(480, 640, 518, 14, "upper_bound") == (392, 518)  # 388.5 -> 392
    assert preprocess_size(1242, 375, 518, 14, "upper_bound") == (518, 154)


def test_normalisation_exact_on_constant_image(dyn_model) -> None:
    net = DepthAnythingOnnx(DepthAnythingParams(model_path=dyn_model, input_size=56))
    rgb = np.empty((60, 100, 3), np.uint8)
    rgb[:] = (200, 30, 90)
    out = net.infer(rgb)
    assert out.value.shape == (60, 100) and out.value.dtype == np.float32
    assert out.kind == "relative_inverse_depth"
    assert out.net_hw[0] % 14 == 0 and out.net_hw[1] % 14 == 0 and out.net_hw[0] == 56
    np.testing.assert_allclose(out.value, _expected_constant((200, 30, 90)), rtol=1e-5)
    assert np.all(out.confidence == 1)


def test_output_aligned_to_image(dyn_model) -> None:
    net = DepthAnythingOnnx(DepthAnythingParams(model_path=dyn_model, input_size=70))
    rgb = np.zeros((90, 260, 3), np.uint8)
    u0, v0 = 173, 41
    rgb[:, u0:] = 255  # vertical step edge between columns u0-1 and u0
    rgb[v0:, :, 2] = 128  # horizontal step in blue between rows v0-1 and v0
    val = net.infer(rgb).value
    lo, hi = _expected_constant((0, 0, 0)), _expected_constant((255, 255, 255))
    col = (val[5] - lo) / (hi - lo)  # normalised profile along a row above v0
    u_half = np.interp(0.5, col, np.arange(len(col)))
    assert abs(u_half - (u0 - 0.5)) < 1.0
    row = val[:, 20]
    r_half = np.interp(0.5, (row - row[0]) / (row[-1] - row[0]), np.arange(len(row)))
    assert abs(r_half - (v0 - 0.5)) < 1.0


def test_static_input_model_gets_its_size(tmp_path) -> None:
    path = _export(tmp_path / "tiny_static.onnx", dynamic=False, hw=(42, 70))
    net = DepthAnythingOnnx(DepthAnythingParams(model_path=path))
    out = net.infer(np.full((33, 51, 3), 77, np.uint8))
    assert out.net_hw == (42, 70) and out.value.shape == (33, 51)
    np.testing.assert_allclose(out.value, _expected_constant((77, 77, 77)), rtol=1e-5)


def test_non_positive_output_has_no_confidence(tmp_path) -> None:
    class Neg(torch.nn.Module):
        def forward(self, image):
            return image[:, 0] * 0 - 1.0 + (image[:, 1] > 0).to(image.dtype) * 3.0

    path = str(tmp_path / "neg.onnx")
    torch.onnx.export(
        Neg(),
        (torch.zeros(1, 3, 28, 28),),
        path,
        input_names=["image"],
        output_names=["depth"],
        dynamic_axes={"image": {2: "h", 3: "w"}},
        opset_version=17,
        dynamo=False,
    )
    rgb = np.zeros((28, 56, 3), np.uint8)
    rgb[:, 28:, 1] = 255  # green high -> normalised > 0 -> positive output
    out = DepthAnythingOnnx(DepthAnythingParams(model_path=path, input_size=28)).infer(rgb)
    assert np.all(out.confidence[:, :25] == 0) and np.all(out.value[:, :25] == 0)
    assert np.all(out.confidence[:, 31:] == 1)


def test_missing_malformed_and_mismatched_models(tmp_path, dyn_model) -> None:
    with pytest.raises(ModelError, match="not found"):
        DepthAnythingOnnx(DepthAnythingParams(model_path=str(tmp_path / "nope.onnx")))
    with pytest.raises(ModelError, match="not found"):
        DepthAnythingOnnx(DepthAnythingParams())
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"this is not a protobuf" * 10)
    with pytest.raises(ModelError, match="cannot load"):
        DepthAnythingOnnx(DepthAnythingParams(model_path=str(bad)))
    with pytest.raises(ModelError, match="'pixel_values' -> '' not found.*known layouts"):
        DepthAnythingOnnx(DepthAnythingParams(model_path=dyn_model, input_name="pixel_values"))
    with pytest.raises(ModelError, match="predicted_depth"):
        DepthAnythingOnnx(DepthAnythingParams(model_path=dyn_model, output_name="predicted_depth"))
    import onnxruntime as ort

    if "CUDAExecutionProvider" not in ort.get_available_providers():
        with pytest.raises(ModelError, match="CUDAExecutionProvider"):
            DepthAnythingOnnx(DepthAnythingParams(model_path=dyn_model, provider="cuda"))
    with pytest.raises(ConfigError, match="provider"):
        DepthAnythingOnnx(DepthAnythingParams(model_path=dyn_model, provider="tpu"))
    with pytest.raises(ConfigError, match="output_kind"):
        DepthAnythingParams(output_kind="disparity")
    with pytest.raises(ConfigError, match="resize_method.*'minimal'"):
        DepthAnythingParams(resize_method="minimal")


def test_known_layouts_recognised_and_unknown_refused(tmp_path) -> None:
    """Both common export layouts load without naming tensors; another one is refused by name."""
    rgb = np.full((40, 60, 3), 128, np.uint8)
    hf = _tiny_onnx.export_depth_anything(
        tmp_path / "hf.onnx", in_name="pixel_values", out_name="predicted_depth"
    )
    net = DepthAnythingOnnx(DepthAnythingParams(model_path=hf, input_size=28))
    assert (net.input_name, net.output_name) == ("pixel_values", "predicted_depth")
    assert net.infer(rgb).value.shape == (40, 60)
    odd = _tiny_onnx.export_depth_anything(tmp_path / "odd.onnx", in_name="x", out_name="y")
    with pytest.raises(ModelError, match=r"signature unknown.*'x'.*'y'.*pixel_values -> predicted"):
        DepthAnythingOnnx(DepthAnythingParams(model_path=odd))
    net = DepthAnythingOnnx(
        DepthAnythingParams(model_path=odd, input_name="x", output_name="y", input_size=28)
    )
    assert net.infer(rgb).value.dtype == np.float32
