"""Learned depth prior: monocular relative depth from an ONNX model, Depth Anything V2 style.

The paper's LFM (section III-A) is a large foundation model for monocular depth. Users who have an
ONNX export of Depth Anything V2 can run it here. The two common export layouts are recognised by
their names (:data:`KNOWN_SIGNATURES`): input ``image`` -> output ``depth`` (the Depth-Anything-ONNX
exports, ``[1, 3, h, w]`` -> ``[1, h, w]``) and input ``pixel_values`` -> output
``predicted_depth`` (the ``transformers`` / onnx-community exports, ``[batch, 3, height, width]``
-> ``[batch, height, width]``); ``h, w`` multiples of 14, static or dynamic. Another layout is
refused with a message naming what the model has and what is known, unless ``input_name`` and
``output_name`` name its tensors explicitly.

Pre-processing as the reference implementation: RGB to [0, 1], resize so that the shorter side is
``input_size`` keeping the aspect ratio with both sides rounded to a multiple of 14 (bicubic),
ImageNet normalisation; or, with ``resize_method: upper_bound``, the longer side (the cost is
quadratic in the ViT tokens: docs/workers.md "Cost"). A model with static spatial input dimensions is fed exactly that size.
Post-processing: the output is resized back to the image (bilinear), so pixel ``(u, v)`` of the
result belongs to pixel ``(u, v)`` of the input. The output kind is declared by the user
(``relative_inverse_depth`` for Depth Anything V2 relative models, ``metric`` for its metric
fine-tunes); confidence is 1 where the value is usable (finite, > 0) and 0 elsewhere.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.depth_kind import DEPTH_KINDS as OUTPUT_KINDS
from mogs_node.errors import ConfigError, ModelError
from mogs_node.geometry import check_array
from mogs_node.ort import check_signature, open_session

__all__ = [
    "KNOWN_SIGNATURES",
    "DepthAnythingOnnx",
    "DepthAnythingParams",
    "MonoDepth",
    "preprocess_size",
]

log = logging.getLogger(__name__)

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)
RESIZE_METHODS = ("lower_bound", "upper_bound")
# (input name, output name) of the export layouts users find.
KNOWN_SIGNATURES = (("image", "depth"), ("pixel_values", "predicted_depth"))


@dataclass(frozen=True)
class DepthAnythingParams:
    """Parameters of the ONNX monocular depth backend."""

    model_path: str = ""  # ONNX file (required)
    provider: str = "cpu"  # onnxruntime execution provider: cpu | cuda | auto (CUDA when present)
    threads: int = 0  # intra-op threads (0 = onnxruntime default)
    input_size: int = 518  # shorter (lower_bound) or longer (upper_bound) side fed to the net
    resize_method: str = "lower_bound"  # lower_bound (the reference's) | upper_bound (cheaper)
    multiple_of: int = 14  # both sides rounded to a multiple of this (ViT patch size)
    output_kind: str = "relative_inverse_depth"  # what the model outputs (declared, not guessed)
    input_name: str = ""  # model input name ("" = recognise a known export layout)
    output_name: str = ""  # model output name ("" = recognise a known export layout)

    def __post_init__(self) -> None:
        if self.output_kind not in OUTPUT_KINDS:
            raise ConfigError(
                f"output_kind: expected one of {OUTPUT_KINDS}, got {self.output_kind!r}"
            )
        if self.resize_method not in RESIZE_METHODS:
            raise ConfigError(
                f"resize_method: expected one of {RESIZE_METHODS}, got {self.resize_method!r}"
            )
        if self.input_size < self.multiple_of or self.multiple_of < 1:
            raise ConfigError("input_size must be >= multiple_of >= 1")


@dataclass
class MonoDepth:
    """Network output aligned to the input image."""

    value: NDArray[np.float32]  # [H, W] in the declared kind, 0 where unusable
    confidence: NDArray[np.float32]  # [H, W] 1 where usable, 0 elsewhere
    kind: str  # the declared output kind
    net_hw: tuple[int, int]  # size the network ran at
    model_ms: float = 0.0  # time spent inside the network


def preprocess_size(
    H: int, W: int, input_size: int, multiple_of: int, method: str = "lower_bound"
) -> tuple[int, int]:
    """Network input ``(h, w)``, aspect kept, both sides multiples of ``multiple_of`` (14).

    As Depth Anything's ``Resize(keep_aspect_ratio=True, resize_method=method)``:
    ``lower_bound`` (the reference's default) scales the shorter side to ``input_size``, each side
    rounded to the nearest multiple and raised to at least ``input_size`` rounded up;
    ``upper_bound`` scales the longer side to ``input_size``, each side rounded to the nearest
    multiple and lowered to at most ``input_size`` (a 1242x375 frame at 518: 154x518, 407 ViT
    tokens, instead of 518x1722, 4551 tokens).
    """
    if method == "upper_bound":
        scale = input_size / max(H, W)

        def fit(x: float) -> int:
            y = int(round(x / multiple_of) * multiple_of)
            if y > input_size:
                y = int(np.floor(x / multiple_of) * multiple_of)
            return max(y, multiple_of)

        return fit(H * scale), fit(W * scale)
    scale = input_size / min(H, W)

    def fit_lower(x: float) -> int:
        y = int(round(x / multiple_of) * multiple_of)
        if y < input_size:
            y = int(np.ceil(x / multiple_of) * multiple_of)
        return max(y, multiple_of)

    return fit_lower(H * scale), fit_lower(W * scale)


def _signature(sess, params: DepthAnythingParams) -> tuple[str, str]:
    """(input, output) names: the ones named in ``params``, else the known layout the model has."""
    ins = {i.name: list(i.shape) for i in sess.get_inputs()}
    outs = {o.name: list(o.shape) for o in sess.get_outputs()}
    asked = params.input_name or params.output_name
    if asked:
        pair = (params.input_name, params.output_name)
        if pair[0] in ins and pair[1] in outs:
            return pair
    else:
        for pair in KNOWN_SIGNATURES:
            if pair[0] in ins and pair[1] in outs:
                return pair
    known = ", ".join(f"{a} -> {b}" for a, b in KNOWN_SIGNATURES)
    what = f"{params.input_name!r} -> {params.output_name!r} not found" if asked else "unknown"
    raise ModelError(
        f"{params.model_path}: depth model signature {what}: the model has inputs {ins} and "
        f"outputs {outs}; known layouts: {known} (or name both with input_name/output_name)"
    )


class DepthAnythingOnnx:
    """A loaded ONNX monocular depth model; :meth:`infer` is pure given the session."""

    def __init__(self, params: DepthAnythingParams) -> None:
        self.params = params
        self.session = open_session(
            params.model_path, provider=params.provider, threads=params.threads
        )
        self.input_name, self.output_name = _signature(self.session, params)
        check_signature(self.session, params.model_path, [(self.input_name, 4)], [])
        outs = {o.name: o.shape for o in self.session.get_outputs()}
        if len(outs[self.output_name]) not in (3, 4):
            raise ModelError(
                f"{params.model_path}: expected output {self.output_name!r} of "
                f"shape [1, h, w] or [1, 1, h, w], model has {outs}"
            )
        shape = next(i.shape for i in self.session.get_inputs() if i.name == self.input_name)
        if isinstance(shape[1], int) and shape[1] != 3:
            raise ModelError(
                f"{params.model_path}: input {self.input_name!r} must have 3 "
                f"channels, has {shape[1]}"
            )
        static = all(isinstance(s, int) for s in shape[2:])
        self.static_hw = (shape[2], shape[3]) if static else None
        if self.static_hw and any(s % params.multiple_of for s in self.static_hw):
            raise ModelError(
                f"{params.model_path}: static input size {self.static_hw} is not a "
                f"multiple of {params.multiple_of}"
            )

    def net_size(self, H: int, W: int) -> tuple[int, int]:
        if self.static_hw is not None:
            return self.static_hw
        p = self.params
        return preprocess_size(H, W, p.input_size, p.multiple_of, p.resize_method)

    def preprocess(self, rgb: NDArray[np.uint8]) -> NDArray[np.float32]:
        """``[H, W, 3]`` uint8 RGB -> ``[1, 3, h, w]`` float32, resized and ImageNet-normalised."""
        img = check_array("rgb", rgb, shape=(None, None, 3), dtype=np.uint8)
        h, w = self.net_size(*img.shape[:2])
        x = cv2.resize(img.astype(np.float32) / 255.0, (w, h), interpolation=cv2.INTER_CUBIC)
        x = (x - IMAGENET_MEAN) / IMAGENET_STD
        return np.ascontiguousarray(x.transpose(2, 0, 1)[None], dtype=np.float32)

    def infer(self, rgb: NDArray[np.uint8]) -> MonoDepth:
        """Depth of ``rgb`` ``[H, W, 3]`` uint8, aligned to the image."""
        H, W = np.shape(rgb)[:2]
        x = self.preprocess(rgb)
        t0 = time.perf_counter()
        (out,) = self.session.run([self.output_name], {self.input_name: x})
        model_ms = (time.perf_counter() - t0) * 1e3
        out = np.asarray(out, np.float32)
        if out.ndim == 4:
            out = out[:, 0]
        if out.ndim != 3 or out.shape[0] != 1:
            raise ModelError(
                f"{self.params.model_path}: output shape {list(out.shape)}, expected [1, h, w]"
            )
        value = cv2.resize(out[0], (W, H), interpolation=cv2.INTER_LINEAR)
        ok = np.isfinite(value) & (value > 0)
        return MonoDepth(
            value=np.where(ok, value, 0.0).astype(np.float32),
            confidence=ok.astype(np.float32),
            kind=self.params.output_kind,
            net_hw=(int(x.shape[2]), int(x.shape[3])),
            model_ms=model_ms,
        )
