"""Opening user-supplied ONNX models with onnxruntime, strictly (DESIGN.md section 3).

A missing or malformed model, an unavailable execution provider or a wrong input/output signature
raises :class:`ModelError` at start-up; there is never a silent fallback to another backend or
provider (``provider: auto`` asks for CUDA when this onnxruntime has it, else CPU, and logs which).
Shared by the learned depth-prior and segmentation backends.

Session options (docs/workers.md "Session options"): all graph optimisations (operator fusion of
the ViT blocks; ``ORT_ENABLE_ALL``); ``threads`` intra-op threads with one inter-op thread (the
graphs are sequential); and no spin-waiting of idle worker threads
(``session.intra_op.allow_spinning = 0``): on a small shared CPU a spinning pool burns the cores
the other nodes need between the many short decoder calls, for no gain in latency.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

from mogs_node.errors import ModelError
from mogs_node.params import check_choice

__all__ = [
    "IMAGENET_MEAN_RGB",
    "IMAGENET_STD_RGB",
    "PROVIDERS",
    "check_signature",
    "model_path",
    "open_session",
]

log = logging.getLogger(__name__)

PROVIDERS = {"cpu": "CPUExecutionProvider", "cuda": "CUDAExecutionProvider", "auto": ""}
#: ImageNet's per-channel mean and standard deviation (RGB in [0, 1]): the learned backends'
#: networks expect their input normalised with them (Depth Anything in [0, 1], SAM in [0, 255])
IMAGENET_MEAN_RGB = (0.485, 0.456, 0.406)
IMAGENET_STD_RGB = (0.229, 0.224, 0.225)


def model_path(path: str | Path) -> Path:
    """``path`` with ``~`` and ``$VAR`` expanded (launch files may say either)."""
    return Path(os.path.expandvars(str(path))).expanduser()


def open_session(
    path: str | Path, *, provider: str = "cpu", threads: int = 0, model: bytes | None = None
):
    """An ``onnxruntime.InferenceSession`` for the model at ``path`` on ``provider``.

    Args:
        path: ONNX file.
        model: serialised ONNX model to run instead of the file's (an adapted copy of it, see
            :func:`mogs_node.segmentation.sam_onnx.adapt_decoder`); ``path`` names it in messages.
        provider: ``"cpu"``, ``"cuda"`` (must be available: no fallback to CPU) or ``"auto"``
            (CUDA when available, else CPU).
        threads: intra-op threads (0 = onnxruntime's default).
    """
    import onnxruntime as ort

    check_choice("provider", provider, sorted(PROVIDERS))
    p = model_path(path)
    if not str(path) or not p.is_file():
        raise ModelError(f"model file not found: {str(path)!r}")
    name = PROVIDERS[provider]
    if provider == "auto":
        cuda = PROVIDERS["cuda"] in ort.get_available_providers()
        name = PROVIDERS["cuda" if cuda else "cpu"]
    if name not in ort.get_available_providers():
        raise ModelError(
            f"{p.name}: execution provider {name} is not available in this onnxruntime "
            f"(available: {ort.get_available_providers()})"
        )
    opts = ort.SessionOptions()
    if threads > 0:
        opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    try:
        src = str(p) if model is None else model
        sess = ort.InferenceSession(src, sess_options=opts, providers=[name])
    except Exception as err:  # onnxruntime raises its own exception types on bad files
        raise ModelError(f"{p}: cannot load ONNX model ({err})") from err
    log.info("loaded %s on %s", p, name)
    return sess


def check_signature(
    sess,
    where: str,
    inputs: Sequence[tuple[str, int]],
    outputs: Sequence[tuple[str, int]],
    *,
    known: str = "",
) -> None:
    """Check that ``sess`` has the named inputs/outputs with the given ranks (``ModelError``).

    The message names the model's whole signature, what was expected and (``known``) which
    export layout that is, so that a user holding another export sees what to change.
    """
    have_in = {i.name: len(i.shape) for i in sess.get_inputs()}
    have_out = {o.name: len(o.shape) for o in sess.get_outputs()}
    layout = f" of {known}" if known else ""
    expected = (
        f"expected the signature{layout}: inputs {dict(inputs)}, outputs {dict(outputs)} "
        f"(name: rank); the model has inputs {have_in}, outputs {have_out}"
    )
    for kind, have, want in (("input", have_in, inputs), ("output", have_out, outputs)):
        for name, rank in want:
            if name not in have:
                raise ModelError(f"{where}: model has no {kind} {name!r}; {expected}")
            if have[name] != rank:
                raise ModelError(
                    f"{where}: {kind} {name!r} has rank {have[name]}, expected {rank}; {expected}"
                )
