"""Real-size learned models with random weights, exported to ONNX as users find them (issue 20).

Our machines cannot download weights, but the architectures are published code: a network of the
real size with random weights costs what the real one costs and has the real export's signature.
That measures speed and tests loading; its outputs are meaningless and never reported as results.

Built here (extra ``models`` in pyproject.toml: transformers, segment-anything, mobilesam-mirror;
torch is a core dependency):

- Depth Anything V2 Small and Base from the published configurations (``transformers``'
  ``DepthAnythingConfig``, values of the ``depth-anything/Depth-Anything-V2-{Small,Base}-hf``
  configs), in the two common export layouts: ``hf`` (input ``pixel_values`` ``[batch, 3, height,
  width]``, output ``predicted_depth`` ``[batch, height, width]``, as the onnx-community exports)
  and ``image`` (input ``image`` ``[1, 3, h, w]``, output ``depth`` ``[1, h, w]``, as the
  Depth-Anything-ONNX exports); spatial axes dynamic (multiples of 14 expected).
- SAM ViT-B (``segment_anything.sam_model_registry["vit_b"]``) and MobileSAM
  (``mobile_sam.sam_model_registry["vit_t"]``, a TinyViT encoder before SAM's prompt decoder): the
  image encoder (input ``image`` ``[1, 3, 1024, 1024]``, output ``image_embeddings``
  ``[1, 256, 64, 64]``) and the prompt decoder exactly as the official
  ``scripts/export_onnx_model.py`` writes it (``SamOnnxModel``, ``return_single_mask=False``,
  dynamic ``num_points``, opset 17).

Exports are cached under ``$MOGS_MODEL_CACHE`` (default ``~/.cache/mogs-models``), never in the
repository. ``python -m mogs_node.eval.real_size_models [NAME ...]`` exports what is missing and
prints the paths.
"""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path

__all__ = ["MODEL_NAMES", "cache_dir", "ensure", "export_depth_anything", "export_sam"]

log = logging.getLogger(__name__)

# Published configurations (backbone DINOv2 ViT-S/14 and ViT-B/14 with the DPT head sizes).
DA_CONFIGS = {
    "vits": dict(hidden=384, heads=6, neck=[48, 96, 192, 384], fusion=64),
    "vitb": dict(hidden=768, heads=12, neck=[96, 192, 384, 768], fusion=128),
}
MODEL_NAMES = ("depth_anything_vits", "depth_anything_vitb", "sam_vit_b", "mobile_sam")


def cache_dir() -> Path:
    """Where exports live: ``$MOGS_MODEL_CACHE`` or ``~/.cache/mogs-models``."""
    return Path(os.environ.get("MOGS_MODEL_CACHE", Path.home() / ".cache" / "mogs-models"))


def _depth_anything_module(size: str):
    import torch
    from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config

    c = DA_CONFIGS[size]
    backbone = Dinov2Config(
        hidden_size=c["hidden"],
        num_attention_heads=c["heads"],
        num_hidden_layers=12,
        mlp_ratio=4,
        patch_size=14,
        image_size=518,
        out_features=["stage3", "stage6", "stage9", "stage12"],
        out_indices=[3, 6, 9, 12],
        reshape_hidden_states=False,
        layerscale_value=1.0,
    )
    cfg = DepthAnythingConfig(
        backbone_config=backbone,
        neck_hidden_sizes=c["neck"],
        fusion_hidden_size=c["fusion"],
        reassemble_hidden_size=c["hidden"],
        reassemble_factors=[4, 2, 1, 0.5],
        head_hidden_size=32,
        depth_estimation_type="relative",
    )
    torch.manual_seed(0)
    model = DepthAnythingForDepthEstimation(cfg).eval()

    class Wrap(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, x):
            return self.model(pixel_values=x).predicted_depth

    return Wrap().eval()


def export_depth_anything(size: str, path: str | Path, *, layout: str = "hf") -> Path:
    """Depth Anything V2 ``size`` (``vits``/``vitb``), random weights, to ONNX at ``path``."""
    import torch

    if size not in DA_CONFIGS or layout not in ("hf", "image"):
        raise ValueError(
            f"size in {sorted(DA_CONFIGS)}, layout in ('hf', 'image'): got {size}, {layout}"
        )
    inp, out = ("pixel_values", "predicted_depth") if layout == "hf" else ("image", "depth")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    axes = {inp: {0: "batch", 2: "height", 3: "width"}, out: {0: "batch", 1: "height", 2: "width"}}
    with torch.no_grad():
        torch.onnx.export(
            _depth_anything_module(size),
            (torch.zeros(1, 3, 518, 686),),
            str(path),
            input_names=[inp],
            output_names=[out],
            dynamic_axes=axes,
            opset_version=17,
            dynamo=False,
        )
    return path


_STUBS: dict = {}  # stand-in modules, in sys.modules only while SAM's code is imported


def _timm_stub() -> None:
    """MobileSAM's TinyViT imports four helpers from ``timm``; ``timm`` needs a
    ``torchvision`` built for the installed torch, which a CPU-only torch often lacks. For
    random-weight inference the helpers are: stochastic depth (identity in eval mode), a pair
    maker, truncated-normal init and a model registry (unused); provided when ``timm`` cannot be
    imported."""
    import types

    try:
        import timm.models.layers  # noqa: F401

        return
    except Exception:  # ImportError, or torchvision's operator registration failing
        pass
    import torch

    class DropPath(torch.nn.Module):
        def __init__(self, drop_prob: float = 0.0) -> None:
            super().__init__()
            self.drop_prob = drop_prob

        def forward(self, x):
            return x

    layers = types.ModuleType("timm.models.layers")
    layers.DropPath = DropPath
    layers.to_2tuple = lambda x: tuple(x) if isinstance(x, (tuple, list)) else (x, x)
    layers.trunc_normal_ = torch.nn.init.trunc_normal_
    registry = types.ModuleType("timm.models.registry")
    registry.register_model = lambda fn: fn  # registers TinyViT variants by name: unused here
    models = types.ModuleType("timm.models")
    models.layers, models.registry = layers, registry
    timm = types.ModuleType("timm")
    timm.models = models
    _STUBS.update(
        {
            "timm": timm,
            "timm.models": models,
            "timm.models.layers": layers,
            "timm.models.registry": registry,
        }
    )


def _torchvision_stub() -> None:
    """``segment_anything`` and ``mobile_sam`` import ``torchvision`` in their image transforms
    and automatic mask generator, neither of which the export uses; a CPU-only torch often has no
    matching ``torchvision``. Stand-ins that raise if called are installed when it cannot be
    imported."""
    import types

    try:
        import torchvision.transforms.functional  # noqa: F401

        return
    except Exception:  # ImportError, or its operator registration failing
        pass

    def unavailable(*args, **kwargs):
        raise NotImplementedError("torchvision is not installed (export-only stand-in)")

    mods = {
        n: types.ModuleType(n)
        for n in (
            "torchvision",
            "torchvision.transforms",
            "torchvision.transforms.functional",
            "torchvision.ops",
            "torchvision.ops.boxes",
        )
    }
    for name in ("resize", "to_pil_image"):
        setattr(mods["torchvision.transforms.functional"], name, unavailable)
    for name in ("batched_nms", "box_area"):
        setattr(mods["torchvision.ops.boxes"], name, unavailable)
    _STUBS.update(mods)


def _sam_model(kind: str):
    import sys

    import torch

    if kind not in ("vit_b", "vit_t"):
        raise ValueError(f"SAM kind: expected 'vit_b' or 'vit_t', got {kind!r}")
    torch.manual_seed(0)
    _torchvision_stub()
    if kind == "vit_t":
        _timm_stub()
    sys.modules.update(_STUBS)
    try:  # the stand-ins must not outlive the import: transformers probes for torchvision/timm
        if kind == "vit_b":
            from segment_anything import sam_model_registry
            from segment_anything.utils.onnx import SamOnnxModel
        else:
            from mobile_sam import sam_model_registry
            from mobile_sam.utils.onnx import SamOnnxModel
    finally:
        for name, mod in _STUBS.items():
            if sys.modules.get(name) is mod:
                del sys.modules[name]
    sam = sam_model_registry[kind](checkpoint=None).eval()
    return sam, SamOnnxModel


def export_sam(kind: str, encoder_path: str | Path, decoder_path: str | Path) -> tuple[Path, Path]:
    """SAM (``vit_b``) or MobileSAM (``vit_t``), random weights: encoder + official decoder."""
    import torch

    sam, SamOnnxModel = _sam_model(kind)
    enc, dec = Path(encoder_path), Path(decoder_path)
    enc.parent.mkdir(parents=True, exist_ok=True)
    with torch.no_grad():
        torch.onnx.export(
            sam.image_encoder,
            (torch.zeros(1, 3, 1024, 1024),),
            str(enc),
            input_names=["image"],
            output_names=["image_embeddings"],
            opset_version=17,
            dynamo=False,
        )
        # As segment_anything's scripts/export_onnx_model.py (its defaults).
        onnx_model = SamOnnxModel(sam, return_single_mask=False)
        emb = sam.prompt_encoder.image_embedding_size
        dummy = {
            "image_embeddings": torch.randn(1, sam.prompt_encoder.embed_dim, *emb),
            "point_coords": torch.randint(0, 1024, (1, 5, 2), dtype=torch.float),
            "point_labels": torch.randint(0, 4, (1, 5), dtype=torch.float),
            "mask_input": torch.randn(1, 1, 4 * emb[0], 4 * emb[1]),
            "has_mask_input": torch.tensor([1], dtype=torch.float),
            "orig_im_size": torch.tensor([1500, 2250], dtype=torch.float),
        }
        torch.onnx.export(
            onnx_model,
            tuple(dummy.values()),
            str(dec),
            input_names=list(dummy),
            output_names=["masks", "iou_predictions", "low_res_masks"],
            dynamic_axes={"point_coords": {1: "num_points"}, "point_labels": {1: "num_points"}},
            opset_version=17,
            do_constant_folding=True,
            dynamo=False,
        )
    return enc, dec


def ensure(name: str, *, layout: str = "hf") -> dict[str, str]:
    """Paths of the cached export ``name`` (one of :data:`MODEL_NAMES`), exporting it if missing.

    Returns ``{"model_path": ...}`` for Depth Anything, ``{"encoder_path", "decoder_path"}`` for SAM.
    """
    root = cache_dir()
    if name.startswith("depth_anything_"):
        size = name.rsplit("_", 1)[1]
        path = root / f"{name}_{layout}.onnx"
        if not path.is_file():
            log.info("exporting %s to %s", name, path)
            export_depth_anything(size, path.with_suffix(".tmp.onnx"), layout=layout)
            path.with_suffix(".tmp.onnx").rename(path)
        return {"model_path": str(path)}
    kinds = {"sam_vit_b": "vit_b", "mobile_sam": "vit_t"}
    if name not in kinds:
        raise ValueError(f"model name: expected one of {MODEL_NAMES}, got {name!r}")
    enc, dec = root / f"{name}_encoder.onnx", root / f"{name}_decoder.onnx"
    if not (enc.is_file() and dec.is_file()):
        log.info("exporting %s to %s", name, root)
        tmp_e, tmp_d = enc.with_suffix(".tmp.onnx"), dec.with_suffix(".tmp.onnx")
        export_sam(kinds[name], tmp_e, tmp_d)
        tmp_e.rename(enc)
        tmp_d.rename(dec)
    return {"encoder_path": str(enc), "decoder_path": str(dec)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", default=list(MODEL_NAMES), choices=[*MODEL_NAMES, []])
    ap.add_argument("--layout", default="hf", choices=("hf", "image"), help="Depth Anything layout")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for name in args.names:
        for key, path in ensure(name, layout=args.layout).items():
            print(f"{name} {key}: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
