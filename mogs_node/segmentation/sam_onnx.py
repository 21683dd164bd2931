"""Learned segmenter: Segment Anything (SAM) as ONNX, with automatic mask generation.

Two ONNX files in the layout of the official export (``segment_anything/utils/onnx.py``,
``scripts/export_onnx_model.py``) plus the usual separate image-encoder export:

- encoder: input ``image`` ``[1, 3, 1024, 1024]`` float32 (RGB resized so that the longest side is
  1024, normalised with SAM's pixel mean/std on the 0-255 scale, zero-padded bottom/right), output
  ``image_embeddings`` ``[1, 256, 64, 64]``;
- prompt decoder: inputs ``image_embeddings``, ``point_coords`` ``[1, N, 2]`` (in the resized
  1024 frame), ``point_labels`` ``[1, N]`` (1 foreground, -1 padding), ``mask_input``
  ``[1, 1, 256, 256]``, ``has_mask_input`` ``[1]``, ``orig_im_size`` ``[2]`` (H, W); outputs
  ``masks`` ``[1, M, H, W]`` (logits already resized to the original image), ``iou_predictions``
  ``[1, M]``, ``low_res_masks`` ``[1, M, 256, 256]``.

Automatic mask generation as ``SamAutomaticMaskGenerator``: one foreground point per cell of a
``points_per_side`` x ``points_per_side`` grid (plus the padding point the export expects); with a
multi-mask decoder (M = 4) the three multi-mask outputs are used; masks are kept when the predicted
IoU >= ``pred_iou_thresh`` and the stability score (IoU of the mask thresholded at
``mask_threshold +- stability_score_offset``) >= ``stability_score_thresh``; duplicates are removed
by greedy box NMS on the predicted IoU; tiny masks are dropped. The survivors are painted into
one int32 label image (-1 = none) in painter's order, far first, so that near masks end on top: in
a driving scene an object's nearness is read from how low in the image it reaches (its ground
contact), or from a depth map when one is given.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError, ModelError
from mogs_node.geometry import check_array
from mogs_node.ort import (
    IMAGENET_MEAN_RGB,
    IMAGENET_STD_RGB,
    check_signature,
    model_path,
    open_session,
)

__all__ = [
    "SamMasks",
    "SamOnnx",
    "SamParams",
    "adapt_decoder",
    "box_nms",
    "coarse_to_fine",
    "grid_points",
    "grid_shape",
    "paint_masks",
    "stability_score",
]

log = logging.getLogger(__name__)

PIXEL_MEAN = (255.0 * np.array(IMAGENET_MEAN_RGB)).astype(np.float32)  # SAM sees [0, 255]
PIXEL_STD = (255.0 * np.array(IMAGENET_STD_RGB)).astype(np.float32)
DECODER_INPUTS = [
    ("image_embeddings", 4),
    ("point_coords", 3),
    ("point_labels", 2),
    ("mask_input", 4),
    ("has_mask_input", 1),
    ("orig_im_size", 1),
]
DECODER_OUTPUTS = [("masks", 4), ("iou_predictions", 2), ("low_res_masks", 4)]


@dataclass(frozen=True)
class SamParams:
    """Parameters of the SAM ONNX backend and its automatic mask generation."""

    encoder_path: str = ""  # ONNX image encoder (required)
    decoder_path: str = ""  # ONNX prompt decoder, official export layout (required)
    provider: str = "cpu"  # onnxruntime execution provider: cpu | cuda | auto (CUDA when present)
    threads: int = 0  # intra-op threads (0 = onnxruntime default)
    image_size: int = 1024  # encoder input side (longest image side is resized to this)
    encoder_input: str = "image"  # encoder input name
    encoder_output: str = "image_embeddings"  # encoder output name
    points_per_side: int = 32  # prompt grid is points_per_side^2 points
    pred_iou_thresh: float = 0.88  # keep masks with predicted IoU at least this
    stability_score_thresh: float = 0.95  # keep masks with stability score at least this
    stability_score_offset: float = 1.0  # logit offset of the stability score
    mask_threshold: float = 0.0  # logit threshold of a mask
    box_nms_thresh: float = 0.7  # drop a mask whose box IoU with a better one exceeds this
    min_mask_region_px: int = 100  # drop masks smaller than this [px]
    skip_covered_prompts: bool = True  # skip a prompt that already lies in a kept mask
    flat_prompt_stride: int = 2  # in cells without structure keep every n-th prompt (1 = all)
    flat_gradient_thresh: float = 2.0  # mean Sobel magnitude [grey levels/px] below = flat cell
    square_cells: bool = False  # grid of square cells: points_per_side along the longer side
    max_prompts: int = 0  # at most this many decoder prompts per image (0 = no cap)
    max_batch: int = 8  # prompts per decoder call when the decoder takes a batch
    adapt_decoder: bool = True  # prune the unused full-size output, free the batch axis (onnx)

    def __post_init__(self) -> None:
        if self.points_per_side < 1 or self.image_size < 16:
            raise ConfigError("SamParams: points_per_side >= 1 and image_size >= 16 required")
        if not (0 <= self.pred_iou_thresh <= 1 and 0 <= self.stability_score_thresh <= 1):
            raise ConfigError("SamParams: pred_iou_thresh and stability_score_thresh in [0, 1]")
        if not 0 < self.box_nms_thresh <= 1 or self.stability_score_offset < 0:
            raise ConfigError("SamParams: box_nms_thresh in (0, 1], stability_score_offset >= 0")
        if self.flat_prompt_stride < 1 or self.max_batch < 1 or self.max_prompts < 0:
            raise ConfigError(
                "SamParams: flat_prompt_stride >= 1, max_batch >= 1 and max_prompts >= 0 required"
            )


@dataclass
class SamMasks:
    """Result of automatic mask generation."""

    labels: NDArray[np.int32]  # [H, W] label image, -1 = none
    masks: NDArray[np.bool_]  # [K, H, W] kept masks, label k = masks[k] where on top
    iou: NDArray[np.float32]  # [K] predicted IoU
    stability: NDArray[np.float32]  # [K] stability score
    points_px: NDArray[np.float64]  # [K, 2] prompt point of each kept mask (original pixels)
    stats: dict[str, float] = field(default_factory=dict)


# ------------------------------------------------------------------------------ pure helpers


def resized_hw(H: int, W: int, long_side: int) -> tuple[int, int]:
    """SAM's ``ResizeLongestSide.get_preprocess_shape``: ``(h, w)``, ``max(h, w) = long_side``."""
    scale = long_side / max(H, W)
    return int(H * scale + 0.5), int(W * scale + 0.5)


def grid_shape(H: int, W: int, points_per_side: int, square_cells: bool) -> tuple[int, int]:
    """Prompt grid ``(rows, cols)``: ``n x n`` as SAM, or with ``square_cells`` ``n`` along the
    longer side and as many along the shorter one as keep the cells about square (a 1242x375
    KITTI frame: 16 x 5 instead of 16 x 16 cells of 78x23 px)."""
    n = points_per_side
    if not square_cells:
        return n, n
    short = max(1, int(round(n * min(H, W) / max(H, W))))
    return (short, n) if W >= H else (n, short)


def grid_points(
    H: int, W: int, points_per_side: int, square_cells: bool = False
) -> NDArray[np.float64]:
    """Prompt grid in original pixels ``[rows*cols, 2]`` (u, v): cell centres, row-major.

    As ``build_point_grid``: normalised ``(i + 0.5) / n`` scaled by the image width/height.
    """
    rows, cols = grid_shape(H, W, points_per_side, square_cells)
    u, v = np.meshgrid((np.arange(cols) + 0.5) / cols * W, (np.arange(rows) + 0.5) / rows * H)
    return np.stack([u.ravel(), v.ravel()], -1)


def coarse_to_fine(points: NDArray[np.floating]) -> NDArray[np.int64]:
    """Order of ``points`` ``[N, 2]`` by farthest-point sampling from their centroid: each next
    point is the one farthest from those before it, so any prefix is spread over the image (a
    coarse grid first, refined by the later points where earlier masks left the image uncovered;
    ties to the lower index)."""
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return np.zeros(0, np.int64)
    order = np.empty(len(pts), np.int64)
    d = np.sum((pts - pts.mean(0)) ** 2, axis=1)
    order[0] = int(np.argmin(d))
    d = np.sum((pts - pts[order[0]]) ** 2, axis=1)
    for k in range(1, len(pts)):
        order[k] = int(np.argmax(d))
        d = np.minimum(d, np.sum((pts - pts[order[k]]) ** 2, axis=1))
    return order


def stability_score(logits: NDArray[np.floating], threshold: float, offset: float) -> NDArray:
    """IoU of ``logits > threshold + offset`` and ``logits > threshold - offset``.

    ``logits`` ``[K, H, W]`` -> ``[K]``.
    """
    hi = (logits > threshold + offset).sum(axis=(-2, -1), dtype=np.int64)
    lo = (logits > threshold - offset).sum(axis=(-2, -1), dtype=np.int64)
    return np.where(lo > 0, hi / np.maximum(lo, 1), 0.0).astype(np.float32)


def _boxes(masks: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Tight boxes ``[K, 4]`` (u0, v0, u1, v1), inclusive pixel bounds, of masks ``[K, H, W]``."""
    rows, cols = masks.any(axis=2), masks.any(axis=1)
    H, W = masks.shape[1:]
    v0 = np.argmax(rows, axis=1)
    v1 = H - 1 - np.argmax(rows[:, ::-1], axis=1)
    u0 = np.argmax(cols, axis=1)
    u1 = W - 1 - np.argmax(cols[:, ::-1], axis=1)
    return np.stack([u0, v0, u1, v1], -1).astype(np.float64)


def box_nms(
    boxes: NDArray[np.floating], scores: NDArray[np.floating], iou_thresh: float
) -> NDArray[np.int64]:
    """Greedy NMS: indices ``[K']`` of kept boxes ``[K, 4]`` (u0, v0, u1, v1), best score first."""
    b = np.asarray(boxes, np.float64)
    order = np.argsort(-np.asarray(scores), kind="stable")
    area = (b[:, 2] - b[:, 0] + 1) * (b[:, 3] - b[:, 1] + 1)
    keep = []
    while order.size:
        i = order[0]
        keep.append(int(i))
        rest = order[1:]
        iw = np.minimum(b[i, 2], b[rest, 2]) - np.maximum(b[i, 0], b[rest, 0]) + 1
        ih = np.minimum(b[i, 3], b[rest, 3]) - np.maximum(b[i, 1], b[rest, 1]) + 1
        inter = np.clip(iw, 0, None) * np.clip(ih, 0, None)
        iou = inter / (area[i] + area[rest] - inter)
        order = rest[iou <= iou_thresh]
    return np.asarray(keep, np.int64)


def paint_masks(
    masks: NDArray[np.bool_], depth_m: NDArray[np.floating] | None = None
) -> tuple[NDArray[np.int32], NDArray[np.int64]]:
    """Painter's order, near masks on top; returns (labels ``[H, W]`` int32, order ``[K]``).

    Nearness of mask ``k``: its median depth when ``depth_m`` ``[H, W]`` is given (pixels with a
    positive depth), else the lowest image row it reaches (larger row = nearer for objects standing
    on the ground). Masks are painted far to near; label ``k`` refers to ``masks[k]``. Ties: larger
    masks first, so smaller ones stay visible.
    """
    K = masks.shape[0]
    H, W = masks.shape[1:]
    labels = np.full((H, W), -1, np.int32)
    if K == 0:
        return labels, np.zeros(0, np.int64)
    area = masks.sum(axis=(1, 2))
    if depth_m is not None:
        d = check_array("depth_m", depth_m, shape=(H, W))
        near = np.empty(K)
        for k in range(K):  # loop over masks, not pixels
            vals = d[masks[k] & (d > 0)]
            near[k] = -np.median(vals) if vals.size else -np.inf
    else:
        near = _boxes(masks)[:, 3]
    order = np.lexsort((-area, near))  # far (small 'near') first; within ties large first
    for k in order:
        labels[masks[k]] = k
    return labels, order


def adapt_decoder(path: str) -> bytes | None:
    """The official decoder export without its ``masks`` output, with a free prompt-batch axis.

    ONNX Runtime computes every node of a graph whatever outputs are asked for: the export's
    ``masks`` (low-res logits upsampled to 1024x1024, cropped, resized to ``orig_im_size``) cost
    ~10 % of a decoder call and are not used here (:meth:`SamOnnx.upsample` resizes only the
    masks that survive the filters). The export declares ``point_coords`` ``[1, N, 2]``; its graph
    repeats the image embedding per prompt (``predict_masks``), so a batch axis works when
    declared free (checked by :class:`SamOnnx` before use). ``None`` when the ``onnx`` package
    is missing (a core dependency; an install without it runs the file as it is).
    """
    try:
        import onnx
        from onnx.utils import Extractor
    except ImportError:
        log.info("%s: the onnx package is missing: decoder run as exported", path)
        return None
    model = onnx.load(str(model_path(path)))
    inputs = [i.name for i in model.graph.input]
    model = Extractor(model).extract_model(inputs, ["iou_predictions", "low_res_masks"])
    for inp in model.graph.input:
        if inp.name in ("point_coords", "point_labels"):
            inp.type.tensor_type.shape.dim[0].dim_param = "prompts"
    return model.SerializeToString()


# ------------------------------------------------------------------------------ the model


class SamOnnx:
    """Loaded SAM encoder + decoder; :meth:`generate` runs automatic mask generation."""

    def __init__(self, params: SamParams) -> None:
        self.params = params
        self.encoder = open_session(
            params.encoder_path, provider=params.provider, threads=params.threads
        )
        check_signature(
            self.encoder,
            params.encoder_path,
            [(params.encoder_input, 4)],
            [(params.encoder_output, 4)],
            known="a SAM / MobileSAM image-encoder export",
        )
        self.decoder = open_session(
            params.decoder_path, provider=params.provider, threads=params.threads
        )
        check_signature(
            self.decoder,
            params.decoder_path,
            DECODER_INPUTS,
            DECODER_OUTPUTS,
            known="the official SAM / MobileSAM prompt-decoder export (scripts/export_onnx_model.py)",
        )
        shapes = {i.name: i.shape for i in self.decoder.get_inputs()}
        # The official export fixes the prompt batch at 1; an export with a free batch axis
        # takes up to max_batch prompts per call.
        self.batched = not isinstance(shapes["point_coords"][0], int)
        mh, mw = shapes["mask_input"][2:]
        self.mask_input_hw = (
            mh if isinstance(mh, int) else 256,
            mw if isinstance(mw, int) else 256,
        )
        self.model_ms = 0.0  # time spent inside the two networks (running total)
        self.adapted = False
        if params.adapt_decoder:
            self._adapt(shapes)
        self.batch = params.max_batch if self.batched else 1

    def _adapt(self, shapes: dict) -> None:
        """Swap in :func:`adapt_decoder`'s copy of the decoder when it gives the same outputs as
        the file's for two prompts run one by one (checked here, at start-up)."""
        p = self.params
        model = adapt_decoder(p.decoder_path)
        if model is None:
            return
        fast = open_session(p.decoder_path, provider=p.provider, threads=p.threads, model=model)
        shape = shapes["image_embeddings"]
        shape = shape if all(isinstance(d, int) for d in shape) else (1, 256, 64, 64)
        emb = np.random.default_rng(0).standard_normal(shape).astype(np.float32)
        pts, H, W = np.array([[100.0, 80.0], [400.0, 200.0]]), 300, 500
        one = [self.decode(emb, pt[None], H, W) for pt in pts]  # the file's decoder, batch 1
        file_decoder, batched = self.decoder, self.batched

        def same_as_file(n: int) -> bool:
            low, iou = self.decode(emb, pts[:n], H, W)
            return all(
                np.allclose(low[b], one[b][0][0], rtol=1e-3, atol=1e-3)
                and np.allclose(iou[b], one[b][1][0], rtol=1e-3, atol=1e-3)
                for b in range(n)
            )

        self.decoder, self.batched = fast, True
        try:
            same = same_as_file(2)
        except Exception as err:  # onnxruntime's own error types: the graph is batch-1 only
            log.debug("%s: batched prompts failed (%s)", p.decoder_path, err)
            same = False
        self.batched = same or batched
        # without a batch the pruned copy still skips the full-size masks, one prompt a call
        if not (same or same_as_file(1)):
            log.warning("%s: the pruned decoder differs from the file's: not used", p.decoder_path)
            self.decoder, self.batched = file_decoder, batched
            return
        self.adapted = True
        self.model_ms = 0.0
        log.info(
            "%s: decoder without the full-size masks output%s",
            p.decoder_path,
            ", prompts batched" if self.batched else "",
        )

    def preprocess(self, rgb: NDArray[np.uint8]) -> NDArray[np.float32]:
        """``[H, W, 3]`` uint8 RGB -> ``[1, 3, S, S]``: resize longest side, normalise, pad."""
        img = check_array("rgb", rgb, shape=(None, None, 3), dtype=np.uint8)
        S = self.params.image_size
        h, w = resized_hw(img.shape[0], img.shape[1], S)
        x = cv2.resize(img, (w, h), interpolation=cv2.INTER_LINEAR).astype(np.float32)
        x = (x - PIXEL_MEAN) / PIXEL_STD
        out = np.zeros((1, 3, S, S), np.float32)
        out[0, :, :h, :w] = x.transpose(2, 0, 1)
        return out

    def embed(self, rgb: NDArray[np.uint8]) -> NDArray[np.float32]:
        """Image embeddings ``[1, C, h, w]`` of the encoder."""
        x = self.preprocess(rgb)
        t0 = time.perf_counter()
        (emb,) = self.encoder.run([self.params.encoder_output], {self.params.encoder_input: x})
        self.model_ms += (time.perf_counter() - t0) * 1e3
        return np.asarray(emb, np.float32)

    def to_model_coords(self, points_px: NDArray[np.floating], H: int, W: int) -> NDArray:
        """Original pixels ``[N, 2]`` -> resized 1024 frame (``ResizeLongestSide.apply_coords``)."""
        h, w = resized_hw(H, W, self.params.image_size)
        return np.asarray(points_px, np.float64) * np.array([w / W, h / H])

    def decode(
        self, embeddings: NDArray[np.float32], points_px: NDArray[np.floating], H: int, W: int
    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Decoder on single foreground points ``[B, 2]``: low-res logits ``[B, M, L, L]``, IoU
        ``[B, M]``; one call when the decoder takes a batch, else one call per point."""
        pts = self.to_model_coords(np.asarray(points_px, np.float64).reshape(-1, 2), H, W)
        B = len(pts)
        if not self.batched and B > 1:
            outs = [self.decode(embeddings, p[None], H, W) for p in points_px]
            return np.concatenate([o[0] for o in outs]), np.concatenate([o[1] for o in outs])
        coords = np.zeros((B, 2, 2), np.float32)  # each prompt: its point + the padding point
        coords[:, 0] = pts
        labels = np.tile(np.array([[1.0, -1.0]], np.float32), (B, 1))
        feeds = {
            "image_embeddings": embeddings,
            "point_coords": coords,
            "point_labels": labels,
            "mask_input": np.zeros((1, 1, *self.mask_input_hw), np.float32),
            "has_mask_input": np.zeros(1, np.float32),
            "orig_im_size": np.array([H, W], np.float32),
        }
        names = {i.name for i in self.decoder.get_inputs()}
        feeds = {k: v for k, v in feeds.items() if k in names}
        t0 = time.perf_counter()
        iou, low = self.decoder.run(["iou_predictions", "low_res_masks"], feeds)
        self.model_ms += (time.perf_counter() - t0) * 1e3
        low, iou = np.asarray(low, np.float32), np.asarray(iou, np.float32)
        if low.ndim != 4 or low.shape[:2] != iou.shape or low.shape[0] != B:
            raise ModelError(
                f"{self.params.decoder_path}: low_res_masks {list(low.shape)} and "
                f"iou_predictions {list(iou.shape)} do not match {B} prompts"
            )
        return low, iou

    def upsample(self, low: NDArray[np.float32], H: int, W: int) -> NDArray[np.float32]:
        """Low-res logits ``[L, L]`` -> ``[H, W]`` as the export's ``mask_postprocessing``:
        bilinear to the encoder frame, crop the resized image, bilinear to the original size."""
        S = self.params.image_size
        h, w = resized_hw(H, W, S)
        up = cv2.resize(low, (S, S), interpolation=cv2.INTER_LINEAR)[:h, :w]
        return cv2.resize(up, (W, H), interpolation=cv2.INTER_LINEAR)

    def prompt_points(self, rgb: NDArray[np.uint8]) -> NDArray[np.float64]:
        """Grid prompts ``[N, 2]`` (u, v) in the order they are run (:func:`coarse_to_fine`),
        thinned to every ``flat_prompt_stride``-th row and column in cells whose mean Sobel
        magnitude is below ``flat_gradient_thresh``."""
        p = self.params
        H, W = rgb.shape[:2]
        pts = grid_points(H, W, p.points_per_side, p.square_cells)
        if p.flat_prompt_stride > 1:
            rows, cols = grid_shape(H, W, p.points_per_side, p.square_cells)
            grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
            mag = cv2.magnitude(
                cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1)
            )
            cell = cv2.resize(mag / 8.0, (cols, rows), interpolation=cv2.INTER_AREA)  # cell mean
            i, j = np.divmod(np.arange(rows * cols), cols)
            on_coarse = (i % p.flat_prompt_stride == 0) & (j % p.flat_prompt_stride == 0)
            pts = pts[(cell.ravel() >= p.flat_gradient_thresh) | on_coarse]
        return pts[coarse_to_fine(pts)] if p.skip_covered_prompts or p.max_prompts else pts

    def _filter(
        self, low: NDArray[np.float32], iou: NDArray[np.float32], H: int, W: int
    ) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
        """Candidates ``[B*M]`` (flattened) passing the IoU and stability filters, and their
        stability; both scores on the low-res logits cropped to the image (vectorised)."""
        p = self.params
        S, L = self.params.image_size, low.shape[-1]
        h, w = resized_hw(H, W, S)
        lh, lw = int(np.ceil(h * L / S)), int(np.ceil(w * L / S))
        flat = low[:, :, :lh, :lw].reshape(-1, lh, lw)
        cand = np.flatnonzero(iou.ravel() >= p.pred_iou_thresh)
        stab = stability_score(flat[cand], p.mask_threshold, p.stability_score_offset)
        ok = stab >= p.stability_score_thresh
        return cand[ok], stab[ok]

    def generate(
        self, rgb: NDArray[np.uint8], depth_m: NDArray[np.floating] | None = None
    ) -> SamMasks:
        """Automatic mask generation on ``rgb`` ``[H, W, 3]`` uint8 (see module docstring)."""
        p = self.params
        rgb = check_array("rgb", rgb, shape=(None, None, 3), dtype=np.uint8)
        H, W = rgb.shape[:2]
        model_ms0 = self.model_ms
        emb = self.embed(rgb)
        pts = self.prompt_points(rgb)
        covered = np.zeros((H, W), bool)
        # Candidates are kept cropped to their box (a full-size mask per prompt would need
        # gigabytes for a 32x32 grid on a 1242x375 image).
        boxes, crops, keep_iou, keep_stab, keep_pts = [], [], [], [], []
        n_total = n_calls = n_run = 0
        pending = np.arange(len(pts))
        budget = p.max_prompts or len(pts)
        while pending.size and n_run < budget:
            take = min(self.batch, budget - n_run)
            batch, pending = pending[:take], pending[take:]
            low, iou = self.decode(emb, pts[batch], H, W)
            n_calls += 1 if self.batched else len(batch)
            n_run += len(batch)
            if low.shape[1] == 4:  # multi-mask decoder: SAM's AMG uses outputs 1..3
                low, iou = low[:, 1:], iou[:, 1:]
            n_total += iou.size
            idx, stab = self._filter(low, iou, H, W)
            for c, s in zip(idx, stab):  # loop over surviving masks only
                b, k = divmod(int(c), low.shape[1])
                m = self.upsample(low[b, k], H, W) > p.mask_threshold
                if np.count_nonzero(m) < max(p.min_mask_region_px, 1):
                    continue
                rows = np.flatnonzero(m.any(axis=1))
                cols = np.flatnonzero(m.any(axis=0))
                box = (cols[0], rows[0], cols[-1], rows[-1])
                boxes.append(box)
                crops.append(m[box[1] : box[3] + 1, box[0] : box[2] + 1].copy())
                keep_iou.append(iou[b, k])
                keep_stab.append(s)
                keep_pts.append(pts[batch[b]])
                covered |= m
            if p.skip_covered_prompts and pending.size:
                uv = np.clip(np.floor(pts[pending]).astype(np.int64), 0, [W - 1, H - 1])
                pending = pending[~covered[uv[:, 1], uv[:, 0]]]
        n_filtered = len(crops)
        ious = np.asarray(keep_iou, np.float32)
        stabs = np.asarray(keep_stab, np.float32)
        kpts = np.asarray(keep_pts, np.float64).reshape(-1, 2)
        idx = (
            box_nms(np.asarray(boxes, np.float64), ious, p.box_nms_thresh)
            if crops
            else np.zeros(0, np.int64)
        )
        masks = np.zeros((len(idx), H, W), bool)
        for j, i in enumerate(idx):  # paste the survivors (loop over masks, not pixels)
            u0, v0, u1, v1 = boxes[i]
            masks[j, v0 : v1 + 1, u0 : u1 + 1] = crops[i]
        ious, stabs, kpts = ious[idx], stabs[idx], kpts[idx]
        labels, _ = paint_masks(masks, depth_m)
        stats = {
            "n_prompts": float(len(pts)),
            "n_prompts_run": float(n_run),
            "n_decoder_calls": float(n_calls),
            "n_candidates": float(n_total),
            "n_after_filters": float(n_filtered),
            "n_masks": float(len(masks)),
            "coverage": float(np.mean(labels >= 0)),
            "model_ms": self.model_ms - model_ms0,
        }
        log.debug("SAM AMG: %s", stats)
        return SamMasks(
            labels=labels,
            masks=masks,
            iou=ious.astype(np.float32),
            stability=stabs.astype(np.float32),
            points_px=kpts,
            stats=stats,
        )
