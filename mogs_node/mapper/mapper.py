"""The pure mapper core: keyframes in, an incrementally optimised 3D Gaussian map out.

MonoGS-style mapping (Matsuki et al. 2024, section 3.3) fed by MOGS metrized depth (paper
section III-D: the metric, object-consistent depth initialises the Gaussians and supervises them):

1. :meth:`GaussianMapper.add_keyframe` renders the current map at the new pose and inserts
   Gaussians where it does not explain the view (:mod:`mogs_node.mapper.insertion`), then updates
   the covisibility window (:mod:`mogs_node.mapper.window`).
2. :meth:`GaussianMapper.optimize` runs window iterations: each renders ONE sampled view
   (MonoGS's one-random-view-per-iteration; the newest keyframe every other iteration, otherwise
   an older window keyframe or a random past keyframe against forgetting), optionally at a
   fraction of the resolution (``train_downsample``), and minimises
   ``(1 - lambda_depth) L1(exposure(render), image) + lambda_depth sum(conf |D - d| / d) / n
   + lambda_iso |log s - mean(log s)|`` with per-keyframe affine exposure ``exp(a) c + b``; only the
   Gaussians the view's projection keeps (in front, on screen) are rendered and optimised (sparse
   Adam in :class:`GaussianMap`), and the window poses optionally too (SE(3) tangents, the oldest
   window keyframe stays fixed). With ``converge_rel > 0`` a round ends early once the newest
   view's photometric error stops falling.
3. After each round: pruning of transparent, oversized and unsupported Gaussians (MonoGS) and of
   redundant ones (their summed blending weight over the window views, ``sum_p alpha_i T_i``, is
   below ``prune_contrib_px`` pixels; the weights come out of each view's latest forward pass,
   no extra rendering), and optional gradient-based densification (3DGS clone of small Gaussians
   with large view-space positional gradients). The policy is the same for every depth source; it
   depends on the depth only through the (depth, confidence) pair.

``MapperParams.device``: ``"cpu"`` (default; deterministic: the same inputs give the same map bit
for bit) or ``"cuda"``/``"cuda:N"`` (map, keyframe and optimiser tensors on the GPU, gsplat
rasterizer); the pixel-grid insertion runs in numpy on the CPU either way.

No I/O and no bus: arrays in, arrays out. The node shell is :mod:`mogs_node.mapper.node`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np
import torch

from mogs_node.errors import ConfigError, ShapeError
from mogs_node.geometry import check_array, se3_inverse
from mogs_node.mapper.gaussians import PARAM_NAMES, GaussianMap, MapChanges
from mogs_node.mapper.image_metrics import ssim_torch
from mogs_node.mapper.insertion import background_mask, insertion_mask, sample_gaussians
from mogs_node.mapper.keyframe import KeyframeState
from mogs_node.mapper.mapper_params import MapperParams, resolve_device
from mogs_node.mapper.ply import export_ply
from mogs_node.mapper.projection import ScreenView, cull_gaussians, se3_exp_torch
from mogs_node.mapper.rasterizer import GaussianTensors, RenderOutput, render
from mogs_node.mapper.support import blending_contribution, rows_of
from mogs_node.mapper.window import update_window

__all__ = ["GaussianMapper", "KeyframeState", "MapperParams", "export_ply", "resolve_device"]

log = logging.getLogger(__name__)


def _upsample_nearest(x: np.ndarray, f: int, height: int, width: int) -> np.ndarray:
    """``x`` [h, w, ...] rendered at 1/``f`` (:meth:`GaussianMapper._train_camera`: block u'
    covers u = f u' .. f u' + f - 1) -> [height, width, ...], each block's value repeated; a
    trailing partial block takes the last value."""
    if f == 1:
        return x
    up = np.repeat(np.repeat(x, f, axis=0), f, axis=1)[:height, :width]
    pad = [(0, height - up.shape[0]), (0, width - up.shape[1])] + [(0, 0)] * (x.ndim - 2)
    return np.pad(up, pad, mode="edge")


def _scatter_rows(values: torch.Tensor, rows: torch.Tensor, n: int) -> torch.Tensor:
    """``values`` [R] of the rows ``rows`` [R] of an [n] map, as [n] (0 elsewhere)."""
    full = torch.zeros(n, dtype=values.dtype, device=values.device)
    full[rows.to(values.device)] = values
    return full


class GaussianMapper:
    """Incremental Gaussian mapping for one camera (intrinsics ``K`` [3, 3], ``width x height``)."""

    def __init__(self, params: MapperParams, K: np.ndarray, width: int, height: int) -> None:
        K = check_array("K", K, shape=(3, 3), finite=True)
        self.params = params
        self.device = resolve_device(params.device)
        self.K = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        self.width, self.height = int(width), int(height)
        f = params.train_downsample
        if self.width // f < 1 or self.height // f < 1:
            raise ConfigError(
                f"MapperParams.train_downsample: {f} leaves no pixel of {width}x{height}"
            )
        self.train_K, self.train_size = self._train_camera(f)
        self.map = GaussianMap(self.device)
        self.keyframes: list[KeyframeState] = []
        self.window: list[int] = []  # indices into self.keyframes, newest first
        # keyframes whose images are on disk with their region (mapper/submaps.py): not sampled
        self.offloaded_kfs: set[int] = set()
        self.iterations = 0
        self.last_loss = float("nan")
        self.last_psnr_db = float("nan")
        self.n_pruned = 0
        self.n_densified = 0
        self._rng = np.random.default_rng(params.seed)
        self._refine_next = 0  # the keyframe the next refinement iteration starts from
        self.refine_done = 0  # refinement iterations run so far (its learning-rate schedule)
        self._grad_accum = torch.zeros(0, device=self.device)
        self._grad_count = torch.zeros(0, device=self.device)

    def _train_camera(self, f: int) -> tuple[tuple[float, float, float, float], tuple[int, int]]:
        """Intrinsics and (width, height) of the 1/``f`` training resolution; pixel centres at
        integer coordinates: block u' covers u = f u' .. f u' + f - 1."""
        fx, fy, cx, cy = self.K
        K = (fx / f, fy / f, (cx - (f - 1) / 2) / f, (cy - (f - 1) / 2) / f)
        return K, (self.width // f, self.height // f)

    # ------------------------------------------------------------------------------ rendering
    def render_view(
        self,
        T_world_cam: np.ndarray,
        exposure_ab: torch.Tensor | None = None,
        K: tuple[float, float, float, float] | None = None,
        size: tuple[int, int] | None = None,
    ) -> RenderOutput:
        """Render the current map (no gradients) from ``T_world_cam`` [4, 4]; CPU tensors out.

        Only the rows the view's cheap cull keeps are projected and composited (the image is the
        whole map's, bit for bit: :meth:`_visible_rows`); ``counts`` and ``weights`` are [N] over
        the whole map, 0 for the rows culled."""
        T = check_array("T_world_cam", T_world_cam, shape=(4, 4), finite=True)
        K, size = K or self.K, size or (self.width, self.height)
        T_cam_world = torch.as_tensor(se3_inverse(T))
        with torch.no_grad():
            rows = self._visible_rows(T_cam_world, K, size)
            seen = GaussianTensors(*(t[rows] for t in self.map.tensors().tensors()))
            out = render(seen, T_cam_world, K, size[0], size[1], params=self.params.raster)
            out.counts = _scatter_rows(out.counts, rows, len(self.map))
            if out.weights is not None:
                out.weights = _scatter_rows(out.weights, rows, len(self.map))
            if exposure_ab is not None:
                out.color = self._expose(out.color, exposure_ab)
        out.color = out.color.clamp(0, 1)
        if out.color.device.type != "cpu":
            out = RenderOutput(
                *(t.cpu() for t in (out.color, out.depth, out.alpha, out.counts)),
                None if out.weights is None else out.weights.cpu(),
            )
        return out

    @property
    def K_matrix(self) -> np.ndarray:
        """Intrinsics as a [3, 3] matrix."""
        fx, fy, cx, cy = self.K
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @staticmethod
    def _expose(color: torch.Tensor, ab: torch.Tensor) -> torch.Tensor:
        ab = ab.to(color.device)
        return torch.exp(ab[0]).to(color.dtype) * color + ab[1].to(color.dtype)

    # ------------------------------------------------------------------------------ keyframes
    def add_keyframe(
        self,
        keyframe_id: int,
        image_rgb: np.ndarray,
        T_world_cam: np.ndarray,
        depth_m: np.ndarray,
        confidence: np.ndarray,
    ) -> int:
        """Add a keyframe and insert Gaussians where the map does not explain it; returns how many.

        ``image_rgb`` [H, W, 3] uint8, ``T_world_cam`` [4, 4], ``depth_m`` [H, W] (0 = no value),
        ``confidence`` [H, W] in [0, 1]. The one render of the current map at the new pose
        decides where to insert and is the new keyframe's first visibility record.
        """
        H, W = self.height, self.width
        img = check_array("image_rgb", image_rgb, shape=(H, W, 3), dtype=np.uint8)
        T = check_array("T_world_cam", T_world_cam, shape=(4, 4), finite=True)
        d = check_array("depth_m", depth_m, shape=(H, W), dtype=np.floating)
        c = check_array("confidence", confidence, shape=(H, W), dtype=np.floating)
        d = np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
        c = np.clip(np.nan_to_num(c), 0.0, 1.0).astype(np.float32)
        next_id_before = self.map.next_id
        seen_ids = np.zeros(0, np.int64)
        seen_w = np.zeros(0, np.float32)
        if len(self.map):
            f = self.params.insert_downsample
            K_f, size_f = self._train_camera(f)
            r = self.render_view(T, K=K_f, size=size_f)
            alpha, rdepth, rrgb = (
                _upsample_nearest(x.numpy(), f, H, W)
                for x in (r.alpha, r.depth / r.alpha.clamp_min(1e-6), r.color)
            )
            vis = (r.counts > 0).to(self.device)
            seen_ids = self.map.ids[vis].cpu().numpy()
            if r.weights is not None:  # in full-resolution pixels
                seen_w = (r.weights[vis.cpu()] * float(f**2)).numpy().astype(np.float32)
            else:  # no weights from this backend: unknown until the view is trained
                seen_w = np.zeros(len(seen_ids), np.float32)
                next_id_before = 0
        else:
            alpha = rdepth = rrgb = None
        mask = insertion_mask(
            d, c, alpha, rdepth, self.params.insertion, rrgb, img.astype(np.float32) / 255.0
        )
        index = len(self.keyframes)
        ins = self.params.insertion
        d_ins, c_ins = d, c
        bg = background_mask(d, alpha, ins)
        if bg.any():  # far-sphere Gaussians where nothing has depth or is drawn (sky)
            d_ins = np.where(bg, np.float32(ins.background_depth_m), d)
            c_ins = np.where(bg, np.float32(0.0), c)
            mask = mask | bg
        new = sample_gaussians(img, d_ins, c_ins, mask, self.K_matrix, T, ins, offset=index)
        new_ids = self.map.add(new, birth_kf=index)
        dev = self.device
        kf = KeyframeState(
            keyframe_id=int(keyframe_id),
            index=index,
            image=torch.as_tensor(np.array(img, copy=True)).to(dev),  # own, writable copy
            depth_m=torch.as_tensor(d).to(dev),
            confidence=torch.as_tensor(c).to(dev),
            T_cam_world=torch.as_tensor(se3_inverse(T)),
            visible_ids=np.concatenate([seen_ids, new_ids.cpu().numpy()]),
            # aligned with visible_ids; the new Gaussians' 0 is never read as a measurement:
            # their ids are >= weights_next_id, so this record does not judge them
            visible_weights=np.concatenate([seen_w, np.zeros(len(new_ids), np.float32)]),
            weights_next_id=next_id_before,
        )
        self.keyframes.append(kf)
        self.window, dropped = update_window(
            self.window,
            index,
            {k.index: k.visible_ids for k in self.keyframes},
            self.params.window_size,
            self.params.overlap_min,
        )
        # observations are recorded when they are made, not when pruning next runs: a keyframe
        # mapped while behind (no iterations, no pruning) may have left the window by then
        self._record_support()
        log.debug(
            "keyframe %d: +%d Gaussians (map %d), window %s, dropped %s",
            keyframe_id,
            len(new["means"]),
            len(self.map),
            self.window,
            dropped,
        )
        return int(len(new["means"]))

    # ------------------------------------------------------------------------------ optimisation
    def optimize(
        self,
        n_iters: int,
        should_stop: Callable[[], bool] | None = None,
        after_iteration: Callable[[int], bool] | None = None,
    ) -> dict[str, float]:
        """Run up to ``n_iters`` window iterations, then prune (and densify); returns statistics.

        One sampled view per iteration (:meth:`_pick_view`). With ``converge_rel > 0`` the round
        ends early (after at least ``min_iters``) once an iteration of the newest keyframe lowered
        its L1 photometric error by less than that fraction of the previous one.
        ``should_stop`` is polled before each iteration: a node asked to shut down (SIGINT) ends
        the window early instead of holding the launcher past its stop timeout; the map stays
        consistent (every finished iteration is kept, pruning still runs).
        ``after_iteration(it)``: called after iteration ``it``; True ends the round (benches).
        """
        if not self.keyframes or n_iters <= 0 or len(self.map) == 0:
            return self.stats()  # an empty map (first keyframes without depth) has nothing to fit
        p = self.params
        self._grad_accum = torch.zeros(len(self.map), device=self.device)
        self._grad_count = torch.zeros(len(self.map), device=self.device)
        lrs = self._lrs()
        newest = self.window[0]
        past = [
            k.index
            for k in self.keyframes
            if k.index not in self.window and k.index not in self.offloaded_kfs
        ]
        fixed_pose = max(self.window) if len(self.window) == 1 else min(self.window)
        prev_err = None
        for it in range(n_iters):
            if should_stop is not None and should_stop():
                break
            view = self._pick_view(it, past)
            err = self._train_step(view, fixed_pose, lrs)
            if after_iteration is not None and after_iteration(it):
                break
            if view != newest:
                continue
            if (
                p.converge_rel > 0
                and prev_err is not None
                and it + 1 >= p.min_iters
                and prev_err - err < p.converge_rel * prev_err
            ):
                break
            prev_err = err
        if p.densify:
            self._densify()
        self._prune()
        return self.stats()

    def catch_up(
        self, n_iters: int, should_stop: Callable[[], bool] | None = None
    ) -> dict[str, float]:
        """Owed iterations (a node that mapped keyframes while behind runs them when idle):
        each trains the in-RAM keyframe with the fewest iterations so far (ties: the newest), so
        the keyframes that got none while behind get theirs, then pruning as after a round.
        Same loss and schedule as :meth:`optimize`; deterministic."""
        if not self.keyframes or n_iters <= 0 or len(self.map) == 0:
            return self.stats()
        lrs = self._lrs()
        fixed_pose = max(self.window) if len(self.window) == 1 else min(self.window)
        for _ in range(n_iters):
            if should_stop is not None and should_stop():
                break
            live = [k for k in self.keyframes if k.index not in self.offloaded_kfs]
            if not live:
                break
            kf = min(live, key=lambda k: (k.iterations, -k.index))
            self._train_step(kf.index, fixed_pose, lrs)
        self._prune()
        return self.stats()

    def refine(
        self,
        n_iters: int,
        downsample: int = 1,
        should_stop: Callable[[], bool] | None = None,
        total_iters: int = 0,
    ) -> dict[str, float]:
        """Final refinement of the whole map (MonoGS's colour refinement at the end of a run):
        ``n_iters`` iterations, one view each, over **every** keyframe in turn (keyframe order,
        round-robin: deterministic, and each keyframe gets its share), at 1/``downsample`` of the
        resolution (1: full resolution, which sharpens what half-resolution training blurred),
        then pruning. Same loss and exposure as :meth:`optimize` (depth weight
        ``refine_lambda_depth``, D-SSIM weight ``refine_lambda_ssim``); poses stay. The map's
        learning rates are ``refine_lr_scale`` x :meth:`optimize`'s, decayed exponentially to
        ``refine_lr_final`` of that over ``total_iters`` refinement iterations (a caller running
        the refinement in chunks passes the whole count; 0: this call's ``n_iters``).
        ``should_stop`` is polled before each iteration (a node's time budget or shutdown)."""
        if downsample < 1:
            raise ConfigError(f"refine: downsample must be >= 1, got {downsample}")
        # an offloaded region's keyframes hold empty placeholders (their data is in the submap
        # file): the refinement runs over the keyframes in RAM
        live = [k.index for k in self.keyframes if k.index not in self.offloaded_kfs]
        if not live or n_iters <= 0 or len(self.map) == 0:
            return self.stats()
        p = self.params
        total = max(total_iters, n_iters, 1)
        fixed = -1  # no window pose refinement here: -1 is no keyframe index
        for it in range(n_iters):
            if should_stop is not None and should_stop():
                break
            frac = min(self.refine_done / total, 1.0)
            gain = p.refine_lr_scale * p.refine_lr_final**frac
            lrs = {k: v * gain for k, v in self._lrs().items()}
            i = live[(self._refine_next + it) % len(live)]
            self._train_step(
                i,
                fixed,
                lrs,
                factor=downsample,
                refine_pose=False,
                ssim_w=p.refine_lambda_ssim,
                depth_w=p.lambda_depth if p.refine_lambda_depth < 0 else p.refine_lambda_depth,
            )
            self.refine_done += 1
        self._refine_next = (self._refine_next + n_iters) % len(live)
        self._prune()
        return self.stats()

    def _lrs(self) -> dict[str, float]:
        p = self.params
        return {
            "means": p.lr_means_m,
            "colors": p.lr_colors,
            "opacity_logit": p.lr_opacity,
            "log_scales": p.lr_log_scales,
            "quats_wxyz": p.lr_quats,
        }

    def _pick_view(self, it: int, past: list[int]) -> int:
        """Even iterations: the newest keyframe; odd: one of the older window keyframes and
        ``n_random_past`` past keyframes drawn afresh, uniformly (``self._rng``: deterministic)."""
        older = list(self.window[1:])
        if it % 2 == 0 or not (older or past):
            return self.window[0]
        pool = older
        if past and self.params.n_random_past:
            pick = self._rng.choice(
                len(past), size=min(self.params.n_random_past, len(past)), replace=False
            )
            pool += [past[i] for i in pick]
        if not pool:
            return self.window[0]
        return pool[int(self._rng.integers(len(pool)))]

    def _visible_rows(
        self,
        T_cam_world: torch.Tensor,
        K: tuple[float, float, float, float] | None = None,
        size: tuple[int, int] | None = None,
    ) -> torch.Tensor:
        """Rows [R] of the Gaussians the training view may draw: a superset of the projection
        step's cull (in front, opacity above ``alpha_min``, support box on screen;
        :func:`cull_gaussians`). Rendering only these gives the same image as the whole map."""
        K = self.train_K if K is None else K  # default: the training camera
        size = self.train_size if size is None else size
        prm = self.map.params
        T = T_cam_world.to(device=self.device, dtype=prm["means"].dtype)
        view = ScreenView.of(T, K, size, self.params.raster)
        valid = cull_gaussians(prm["means"], prm["log_scales"], prm["opacity_logit"], view)
        return torch.nonzero(valid).flatten()

    def _train_step(
        self,
        i: int,
        fixed_pose: int,
        lrs: dict[str, float],
        factor: int | None = None,
        refine_pose: bool = True,
        ssim_w: float | None = None,
        depth_w: float | None = None,
    ) -> float:
        """One iteration on keyframe ``i`` at 1/``factor`` resolution (default
        ``train_downsample``) with D-SSIM weight ``ssim_w`` (default ``lambda_ssim``) and depth
        weight ``depth_w`` (default ``lambda_depth``); returns its L1 photometric error (after
        exposure)."""
        p = self.params
        ssim_w = p.lambda_ssim if ssim_w is None else ssim_w
        depth_w = p.lambda_depth if depth_w is None else depth_w
        f = p.train_downsample if factor is None else factor
        K_f, (W, H) = (
            (self.train_K, self.train_size) if f == p.train_downsample else (self._train_camera(f))
        )
        kf = self.keyframes[i]
        rows = self._visible_rows(kf.T_cam_world, K_f, (W, H))
        # indexing copies: the leaves are the view's own tensors
        leaves = {k: self.map.params[k][rows].requires_grad_() for k in PARAM_NAMES}
        xi = None
        if refine_pose and p.refine_poses and i in self.window and i != fixed_pose:
            xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
        out = render(
            GaussianTensors(**leaves),
            kf.T_cam_world,
            K_f,
            W,
            H,
            pose_tangent=xi,
            params=p.raster,
        )
        weights = out.weights
        if weights is None:  # gsplat: d(sum of a colour channel) / d colour_i = sum_p alpha_i T_i
            (g_col,) = torch.autograd.grad(
                out.color[..., 0].sum(), leaves["colors"], retain_graph=True
            )
            weights = g_col[:, 0].detach()
        image, depth_m, conf = kf.targets(f)
        color = out.color
        ab = None
        if p.exposure and not (p.exposure_gauge and i == 0):
            ab = kf.exposure_ab.clone().requires_grad_()
            color = self._expose(color, ab)
        l_rgb = (color - image).abs().mean()
        l_photo = l_rgb
        if ssim_w > 0:  # 3DGS eq. 7
            d_ssim = 1 - ssim_torch(color, image.to(color.dtype))
            l_photo = (1 - ssim_w) * l_rgb + ssim_w * d_ssim
        total = (1 - depth_w) * l_photo
        dmask = depth_m > 0
        if depth_w > 0 and bool(dmask.any()):
            rel = (out.depth - depth_m).abs() / depth_m.clamp_min(1e-3)
            total = total + depth_w * (conf * rel)[dmask].mean()
        ls = leaves["log_scales"]
        if p.lambda_iso > 0 and len(rows):
            total = total + p.lambda_iso * (ls - ls.mean(1, keepdim=True)).abs().mean()
        extra = [t for t in (ab, xi) if t is not None]
        grads = torch.autograd.grad(total, [*leaves.values(), *extra], allow_unused=True)
        g_map = dict(zip(leaves.keys(), grads[: len(leaves)], strict=True))
        if p.densify and g_map["means"] is not None:
            self._accumulate_densify_stats(kf, rows, g_map["means"])
        # Adam only for the Gaussians this view drew (the others have no photometric gradient:
        # they neither move nor age)
        drawn = out.counts > 0
        g_map = {k: None if g is None else g[drawn] for k, g in g_map.items()}
        upd = rows[drawn]
        self.map.adam_step(upd, g_map, lrs)
        self.map.params["colors"][upd] = self.map.params["colors"][upd].clamp(0, 1)
        g_extra = list(grads[len(leaves) :])
        if ab is not None:
            g_ab = g_extra.pop(0)
            if g_ab is not None:
                kf.exposure_ab = kf.exposure_ab + kf.exposure_adam.step(g_ab, p.lr_exposure)
        if xi is not None and g_extra[0] is not None:
            step = kf.pose_adam.step(g_extra[0], p.lr_pose)
            kf.T_cam_world = se3_exp_torch(step) @ kf.T_cam_world
        # this render is the keyframe's visibility and blending-weight record (for the window and
        # pruning); weights in full-resolution pixels
        vis = out.counts > 0
        kf.visible_ids = self.map.ids[rows[vis]].cpu().numpy()
        scale = float(f**2)
        kf.visible_weights = (weights[vis].float() * scale).cpu().numpy()
        kf.weights_next_id = self.map.next_id
        kf.iterations += 1
        self.iterations += 1
        self.last_loss = float(total.detach())
        mse = float(((color.detach().clamp(0, 1) - image) ** 2).mean())
        self.last_psnr_db = -10 * math.log10(max(mse, 1e-12))
        return float(l_rgb.detach())

    def _accumulate_densify_stats(
        self, kf: KeyframeState, rows: torch.Tensor, g_means: torch.Tensor
    ) -> None:
        T = kf.T_cam_world.to(device=self.device, dtype=torch.float32)
        z = (self.map.params["means"][rows] @ T[:3, :3].T + T[:3, 3])[:, 2].clamp_min(1e-3)
        self._grad_accum[rows] += g_means.norm(dim=1) * z / self.K[0]
        self._grad_count[rows] += 1

    def _densify(self) -> None:
        """3DGS clone: copy Gaussians whose mean view-space gradient exceeds the threshold."""
        if len(self._grad_accum) == 0:
            return
        seen = self._grad_count > 0
        mean_grad = self._grad_accum / self._grad_count.clamp_min(1)
        pick = torch.nonzero(seen & (mean_grad > self.params.densify_grad_px)).flatten()
        if len(pick) == 0:
            return
        vals = {k: self.map.params[k][pick].clone() for k in PARAM_NAMES}
        gen = torch.Generator().manual_seed(self.iterations)  # CPU: the same noise on any device
        noise = torch.randn(len(pick), 3, generator=gen).to(self.device)
        vals["means"] = vals["means"] + noise * torch.exp(vals["log_scales"])
        self.map.add(vals, birth_kf=len(self.keyframes) - 1)
        self.n_densified += len(pick)

    def _contribution(self, indices: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        """Blending weight and judgeability per Gaussian over ``indices``' views (support.py)."""
        kfs = [self.keyframes[i] for i in indices]
        size = (self.width, self.height)
        return blending_contribution(self.map, kfs, self.K, size, self.params.raster.near_m)

    def _record_support(self) -> None:
        """``n_obs``: the most window keyframes that have seen each Gaussian at once (their
        latest renders' records), kept as a running maximum."""
        obs = torch.zeros(len(self.map), dtype=torch.long, device=self.device)
        for i in self.window:
            rows, _ = rows_of(self.map, self.keyframes[i].visible_ids)
            obs[rows] += 1
        self.map.n_obs = torch.maximum(self.map.n_obs, obs)

    def _prune(self) -> None:
        """Remove transparent and oversized Gaussians (any), and unsupported and redundant ones
        among those optimised at least ``prune_min_steps`` times: a Gaussian no iteration has
        drawn yet (its keyframe was mapped while the mapper was behind) has its inserted values,
        and its support and blending weight say nothing about the optimised map."""
        p = self.params
        if len(self.map) == 0:
            return
        prm = self.map.params
        self._record_support()
        optimised = self.map.steps >= p.prune_min_steps
        opacity = torch.sigmoid(prm["opacity_logit"])
        newest = self.keyframes[self.window[0]]
        cam_center = torch.as_tensor(
            newest.T_world_cam[:3, 3], dtype=torch.float32, device=self.device
        )
        dist = (prm["means"] - cam_center).norm(dim=1)
        too_big = torch.exp(prm["log_scales"]).amax(1) > p.prune_size_ratio * dist
        old = self.map.birth_kf <= len(self.keyframes) - 1 - p.support_kfs
        unsupported = old & optimised & (self.map.n_obs < p.support_min_obs)
        mask = (opacity < p.prune_opacity) | too_big | unsupported
        if p.prune_contrib_px > 0:
            contrib, judged = self._contribution(self.window)
            settled = self.map.birth_kf < newest.index
            mask |= judged & settled & optimised & (contrib < p.prune_contrib_px)
        self.n_pruned += self.map.remove(mask)

    # ------------------------------------------------------------------------------ outputs
    def stats(self) -> dict[str, float]:
        return {
            "n_gaussians": float(len(self.map)),
            "n_keyframes": float(len(self.keyframes)),
            "iterations": float(self.iterations),
            "loss": self.last_loss,
            "psnr_db": self.last_psnr_db,
            "n_pruned": float(self.n_pruned),
            "n_densified": float(self.n_densified),
            "window": float(len(self.window)),
        }

    def drain_changes(self) -> MapChanges:
        """Gaussians added/changed and ids removed since the last call (incremental map update)."""
        return self.map.drain_changes()

    def keyframe_pose(self, keyframe_id: int) -> np.ndarray:
        """Current (possibly refined) ``T_world_cam`` of a keyframe."""
        for kf in self.keyframes:
            if kf.keyframe_id == keyframe_id:
                return kf.T_world_cam
        raise ShapeError(f"keyframe_id: unknown keyframe {keyframe_id}")
