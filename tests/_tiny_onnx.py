"""Tiny ONNX models exported with torch for the learned-backend tests and bench/workers.py.

They have the input/output names and shapes of the real exports and compute known functions, so
the pre/post-processing around them can be checked exactly. Never used as a real model.

SAM (official export layout).

Encoder: ``image`` [1, 3, 1024, 1024] -> ``image_embeddings`` [1, 256, 64, 64] (16x16 average
pooling of the normalised input, channel 0 repeated). Decoder: the official export's inputs and
outputs; output mask ``m`` is a disc of radius ``RADII[m]`` (1024-frame units) around the first
foreground point, with logit slope ``GAINS[m]``, computed on the 256x256 low-res grid and then
post-processed exactly like ``SamOnnxModel.mask_postprocessing`` (upsample to 1024, crop to the
resized image, resize to ``orig_im_size``). ``iou_predictions`` are ``IOUS`` (plus a negligible
term of the embeddings so that the graph uses them).
"""

from __future__ import annotations

import torch
from torch.nn import functional as F  # noqa: N812

__all__ = ["DA_COEF", "DA_OFFSET", "IOUS", "RADII", "export", "export_depth_anything"]

RADII = (30.0, 60.0, 100.0, 160.0)
GAINS = (1.0, 4.0, 0.02, 1.0)  # output 2 is blurry: low stability score
IOUS = (0.5, 0.95, 0.95, 0.9)


class TinyEncoder(torch.nn.Module):
    def forward(self, image: torch.Tensor) -> torch.Tensor:
        pooled = F.avg_pool2d(image, 16)  # [1, 3, 64, 64]
        return pooled[:, :1].repeat(1, 256, 1, 1)


class TinyDecoder(torch.nn.Module):
    img_size = 1024

    def forward(
        self, image_embeddings, point_coords, point_labels, mask_input, has_mask_input, orig_im_size
    ):
        fg = (point_labels == 1).to(torch.float32)  # [1, N]
        p = (point_coords * fg[..., None]).sum(1) / fg.sum(1, keepdim=True)  # [1, 2]
        c = torch.arange(256, dtype=torch.float32) * 4.0 + 1.5  # low-res cell centres (1024 frame)
        du = c[None, :] - p[0, 0]
        dv = c[:, None] - p[0, 1]
        dist = torch.sqrt(du * du + dv * dv)  # [256, 256]
        radii = torch.tensor(RADII).view(4, 1, 1)
        gains = torch.tensor(GAINS).view(4, 1, 1)
        low = ((radii - dist[None]) * gains)[None]  # [1, 4, 256, 256]
        low = low + 0.0 * mask_input * has_mask_input
        masks = F.interpolate(
            low, size=(self.img_size, self.img_size), mode="bilinear", align_corners=False
        )
        size = orig_im_size.to(torch.float32)
        scale = self.img_size / torch.max(size)
        pre = torch.floor(scale * size + 0.5).to(torch.int64)
        masks = masks[..., : pre[0], : pre[1]]
        hw = orig_im_size.to(torch.int64)
        masks = F.interpolate(masks, size=(hw[0], hw[1]), mode="bilinear", align_corners=False)
        iou = torch.tensor(IOUS)[None] + 1e-4 * torch.tanh(image_embeddings.mean())
        return masks, iou, low


def export(tmpdir) -> tuple[str, str]:
    enc = str(tmpdir / "sam_tiny_encoder.onnx")
    dec = str(tmpdir / "sam_tiny_decoder.onnx")
    torch.onnx.export(
        TinyEncoder(),
        (torch.zeros(1, 3, 1024, 1024),),
        enc,
        input_names=["image"],
        output_names=["image_embeddings"],
        opset_version=17,
        dynamo=False,
    )
    args = (
        torch.zeros(1, 256, 64, 64),
        torch.tensor([[[100.0, 100.0], [0.0, 0.0]]]),
        torch.tensor([[1.0, -1.0]]),
        torch.zeros(1, 1, 256, 256),
        torch.zeros(1),
        torch.tensor([200.0, 300.0]),
    )
    torch.onnx.export(
        TinyDecoder(),
        args,
        dec,
        input_names=[
            "image_embeddings",
            "point_coords",
            "point_labels",
            "mask_input",
            "has_mask_input",
            "orig_im_size",
        ],
        output_names=["masks", "iou_predictions", "low_res_masks"],
        dynamic_axes={
            "point_coords": {1: "num_points"},
            "point_labels": {1: "num_points"},
            "masks": {2: "h", 3: "w"},
        },
        opset_version=17,
        dynamo=False,
    )
    return enc, dec


# ----------------------------------------------------------------------- Depth Anything layout

DA_COEF = (0.5, -0.25, 1.0)
DA_OFFSET = 10.0


class TinyDepth(torch.nn.Module):
    """depth = sum_c DA_COEF[c] * x_c + DA_OFFSET as [1, h, w] (input ``image`` [1, 3, h, w])."""

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        w = torch.tensor(DA_COEF, dtype=image.dtype).view(1, 3, 1, 1)
        return (F.avg_pool2d(image, 1) * w).sum(1) + DA_OFFSET


def export_depth_anything(
    path, dynamic: bool = True, hw=(56, 84), out_name="depth", in_name="image"
) -> str:
    x = torch.zeros(1, 3, *hw)
    axes = {in_name: {2: "h", 3: "w"}, out_name: {1: "h", 2: "w"}} if dynamic else None
    torch.onnx.export(
        TinyDepth(),
        (x,),
        str(path),
        input_names=[in_name],
        output_names=[out_name],
        dynamic_axes=axes,
        opset_version=17,
        dynamo=False,
    )
    return str(path)
