"""The pure mapper core: keyframes in, an incrementally optimised 3D Gaussian map out.

MonoGS-style mapping (Matsuki et al. 2024, section 3.3) fed by MOGS metrized depth (paper
section III-D: the metric, object-consistent depth initialises the Gaussians and supervises them):

1. :meth:`GaussianMapper.add_keyframe` renders the current map at the new pose and inserts
   Gaussians where it does not explain the view (:mod:`mogs_node.mapper.insertion`), then updates
   the covisibility window (:mod:`mogs_node.mapper.window`).
2. :meth:`GaussianMapper.optimize` runs window iterations: each renders the window keyframes plus
   a few random past keyframes (against forgetting) and minimises
   ``(1 - lambda_depth) L1(exposure(render), image) + lambda_depth sum(conf |D - d| / d) / n
   + lambda_iso |log s - mean(log s)|`` with per-keyframe affine exposure ``exp(a) c + b``; only the
   Gaussians the window sees are optimised (sparse Adam in :class:`GaussianMap`), and the window
   poses optionally too (SE(3) tangents, the oldest window keyframe stays fixed).
3. After each round: pruning of transparent, oversized and unsupported Gaussians (MonoGS) and of
   redundant ones (their summed blending weight over the window views, ``sum_p alpha_i T_i``, is
   below ``prune_contrib_px`` pixels), and optional gradient-based densification (3DGS clone of
   small Gaussians with large view-space positional gradients). The policy is the same for every
   depth source; it depends on the depth only through the (depth, confidence) pair.

No I/O and no bus: arrays in, arrays out. The node shell is :mod:`mogs_node.mapper.node`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from mogs_node.errors import ConfigError, ShapeError
from mogs_node.geometry import check_array, se3_inverse
from mogs_node.mapper.gaussians import PARAM_NAMES, GaussianMap, MapChanges
from mogs_node.mapper.insertion import InsertionParams, insertion_mask, sample_gaussians
from mogs_node.mapper.projection import se3_exp_torch
from mogs_node.mapper.rasterizer import GaussianTensors, RasterParams, RenderOutput, render
from mogs_node.mapper.window import update_window

__all__ = ["GaussianMapper", "KeyframeState", "MapperParams", "export_ply"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MapperParams:
    """Mapper settings (MonoGS defaults where they exist; learning rates for metric scenes)."""

    raster: RasterParams = field(default_factory=RasterParams)  # rasterizer settings
    insertion: InsertionParams = field(default_factory=InsertionParams)  # insertion settings
    window_size: int = 8  # keyframes in the optimisation window
    overlap_min: float = 0.3  # window keyframes seeing less of the newest one's Gaussians leave
    n_random_past: int = 2  # random past (non-window) keyframes per iteration, against forgetting
    lambda_depth: float = 0.1  # weight of the confidence-weighted relative depth L1
    lambda_iso: float = 0.05  # weight of the isotropic regulariser on log-scales
    lr_means_m: float = 0.002  # Adam step size of positions (metres)
    lr_colors: float = 0.01  # of colours
    lr_opacity: float = 0.05  # of opacity logits
    lr_log_scales: float = 0.01  # of log-scales
    lr_quats: float = 0.002  # of quaternions
    exposure: bool = True  # per-keyframe affine exposure compensation exp(a) c + b
    lr_exposure: float = 0.005  # Adam step size of (a, b)
    refine_poses: bool = False  # optimise window keyframe poses (SE(3) tangents)
    lr_pose: float = 1e-4  # Adam step size of pose tangents
    prune_opacity: float = 0.005  # Gaussians below this opacity are removed
    prune_size_ratio: float = 0.2  # removed when largest sigma > ratio * distance to the newest kf
    support_kfs: int = 3  # after this many newer keyframes, a Gaussian must have ...
    support_min_obs: int = 1  # ... been seen by at least this many window keyframes (MonoGS: 3;
    # 1 here: under forward motion image borders are seen by one keyframe only)
    prune_contrib_px: float = 1.0  # redundant below this summed blending weight (pixels) over
    # the window views; applies to Gaussians the window sees, born before the newest keyframe
    densify: bool = False  # clone Gaussians with large view-space positional gradient
    densify_grad_px: float = 0.0005  # mean |d loss / d mean| * depth / f threshold for cloning
    seed: int = 0  # random past keyframe choice

    def __post_init__(self) -> None:
        if self.window_size < 1 or self.n_random_past < 0:
            raise ConfigError("MapperParams: window_size >= 1, n_random_past >= 0")
        if not 0 <= self.lambda_depth <= 1:
            raise ConfigError("MapperParams.lambda_depth: must be in [0, 1]")


class _SmallAdam:
    """Adam for one small dense tensor (exposure, pose tangent)."""

    def __init__(self, n: int) -> None:
        self.m = torch.zeros(n, dtype=torch.float64)
        self.v = torch.zeros(n, dtype=torch.float64)
        self.t = 0

    def step(self, grad: torch.Tensor, lr: float) -> torch.Tensor:
        self.t += 1
        g = torch.nan_to_num(grad.detach().double())
        self.m = 0.9 * self.m + 0.1 * g
        self.v = 0.999 * self.v + 0.001 * g * g
        mh = self.m / (1 - 0.9**self.t)
        vh = self.v / (1 - 0.999**self.t)
        return -lr * mh / (vh.sqrt() + 1e-12)


@dataclass
class KeyframeState:
    """One keyframe as the mapper keeps it."""

    keyframe_id: int
    index: int  # insertion order
    image: torch.Tensor  # [H, W, 3] uint8 as received: a quarter of f32's memory per keyframe
    # kept for the whole drive; :attr:`image_f32` converts on use (exactly the same values)
    depth_m: torch.Tensor  # [H, W] f32, 0 = no value
    confidence: torch.Tensor  # [H, W] f32 in [0, 1]
    T_cam_world: torch.Tensor  # [4, 4] f64
    exposure_ab: torch.Tensor = field(default_factory=lambda: torch.zeros(2, dtype=torch.float64))
    exposure_adam: _SmallAdam = field(default_factory=lambda: _SmallAdam(2))
    pose_adam: _SmallAdam = field(default_factory=lambda: _SmallAdam(6))
    visible_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def T_world_cam(self) -> np.ndarray:
        return se3_inverse(self.T_cam_world.numpy())

    @property
    def image_f32(self) -> torch.Tensor:
        """[H, W, 3] f32 in [0, 1] (u8 / 255 in f32, as the image was stored before)."""
        return self.image.to(torch.float32) / 255.0


class GaussianMapper:
    """Incremental Gaussian mapping for one camera (intrinsics ``K`` [3, 3], ``width x height``)."""

    def __init__(self, params: MapperParams, K: np.ndarray, width: int, height: int) -> None:
        K = check_array("K", K, shape=(3, 3), finite=True)
        self.params = params
        self.K = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        self.width, self.height = int(width), int(height)
        self.map = GaussianMap()
        self.keyframes: list[KeyframeState] = []
        self.window: list[int] = []  # indices into self.keyframes, newest first
        self.iterations = 0
        self.last_loss = float("nan")
        self.last_psnr_db = float("nan")
        self.n_pruned = 0
        self.n_densified = 0
        self._rng = np.random.default_rng(params.seed)
        self._grad_accum = torch.zeros(0)
        self._grad_count = torch.zeros(0)

    # ------------------------------------------------------------------------------ rendering
    def render_view(
        self,
        T_world_cam: np.ndarray,
        exposure_ab: torch.Tensor | None = None,
        K: tuple[float, float, float, float] | None = None,
        size: tuple[int, int] | None = None,
    ) -> RenderOutput:
        """Render the current map (no gradients) from ``T_world_cam`` [4, 4]."""
        T = check_array("T_world_cam", T_world_cam, shape=(4, 4), finite=True)
        W, H = size or (self.width, self.height)
        with torch.no_grad():
            out = render(
                self.map.tensors(),
                torch.as_tensor(se3_inverse(T)),
                K or self.K,
                W,
                H,
                params=self.params.raster,
            )
            if exposure_ab is not None:
                out.color = self._expose(out.color, exposure_ab)
        out.color = out.color.clamp(0, 1)
        return out

    @property
    def K_matrix(self) -> np.ndarray:
        """Intrinsics as a [3, 3] matrix."""
        fx, fy, cx, cy = self.K
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @staticmethod
    def _expose(color: torch.Tensor, ab: torch.Tensor) -> torch.Tensor:
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
        ``confidence`` [H, W] in [0, 1].
        """
        H, W = self.height, self.width
        img = check_array("image_rgb", image_rgb, shape=(H, W, 3), dtype=np.uint8)
        T = check_array("T_world_cam", T_world_cam, shape=(4, 4), finite=True)
        d = check_array("depth_m", depth_m, shape=(H, W), dtype=np.floating)
        c = check_array("confidence", confidence, shape=(H, W), dtype=np.floating)
        d = np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
        c = np.clip(np.nan_to_num(c), 0.0, 1.0).astype(np.float32)
        if len(self.map):
            r = self.render_view(T)
            alpha = r.alpha.numpy()
            rdepth = (r.depth / r.alpha.clamp_min(1e-6)).numpy()
            rrgb = r.color.numpy()
        else:
            alpha = rdepth = rrgb = None
        mask = insertion_mask(
            d, c, alpha, rdepth, self.params.insertion, rrgb, img.astype(np.float32) / 255.0
        )
        index = len(self.keyframes)
        new = sample_gaussians(
            img, d, c, mask, self.K_matrix, T, self.params.insertion, offset=index
        )
        self.map.add(new, birth_kf=index)
        kf = KeyframeState(
            keyframe_id=int(keyframe_id),
            index=index,
            image=torch.as_tensor(np.ascontiguousarray(img)),
            depth_m=torch.as_tensor(d),
            confidence=torch.as_tensor(c),
            T_cam_world=torch.as_tensor(se3_inverse(T)),
        )
        self.keyframes.append(kf)
        self._refresh_visibility([index])
        self.window, dropped = update_window(
            self.window,
            index,
            {k.index: k.visible_ids for k in self.keyframes},
            self.params.window_size,
            self.params.overlap_min,
        )
        log.debug(
            "keyframe %d: +%d Gaussians (map %d), window %s, dropped %s",
            keyframe_id,
            len(new["means"]),
            len(self.map),
            self.window,
            dropped,
        )
        return int(len(new["means"]))

    def _refresh_visibility(self, indices: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        """Render keyframes ``indices``; store their visible ids; rows seen by any, times seen."""
        seen = torch.zeros(len(self.map), dtype=torch.bool)
        obs = torch.zeros(len(self.map), dtype=torch.long)
        for i in indices:
            kf = self.keyframes[i]
            with torch.no_grad():
                out = render(
                    self.map.tensors(),
                    kf.T_cam_world,
                    self.K,
                    self.width,
                    self.height,
                    params=self.params.raster,
                )
            vis = out.counts > 0
            kf.visible_ids = self.map.ids[vis].numpy()
            seen |= vis
            obs += vis.long()
        return seen, obs

    # ------------------------------------------------------------------------------ optimisation
    def optimize(
        self, n_iters: int, should_stop: Callable[[], bool] | None = None
    ) -> dict[str, float]:
        """Run ``n_iters`` window iterations, then prune (and densify); returns statistics.

        ``should_stop`` is polled before each iteration: a node asked to shut down (SIGINT) ends
        the window early instead of holding the launcher past its stop timeout; the map stays
        consistent (every finished iteration is kept, pruning still runs).
        """
        if not self.keyframes or n_iters <= 0:
            return self.stats()
        p = self.params
        seen, obs = self._refresh_visibility(self.window)
        self.map.n_obs = torch.maximum(self.map.n_obs, obs)
        rows = torch.nonzero(seen).flatten()
        self._grad_accum = torch.zeros(len(rows))
        self._grad_count = torch.zeros(len(rows))
        lrs = {
            "means": p.lr_means_m,
            "colors": p.lr_colors,
            "opacity_logit": p.lr_opacity,
            "log_scales": p.lr_log_scales,
            "quats_wxyz": p.lr_quats,
        }
        past = [k.index for k in self.keyframes if k.index not in self.window]
        fixed_pose = max(self.window) if len(self.window) == 1 else min(self.window)
        for _ in range(n_iters):
            if should_stop is not None and should_stop():
                break
            views = list(self.window)
            if past and p.n_random_past:
                pick = self._rng.choice(
                    len(past), size=min(p.n_random_past, len(past)), replace=False
                )
                views += [past[i] for i in pick]
            leaves = {k: self.map.params[k][rows].clone().requires_grad_() for k in PARAM_NAMES}
            full = GaussianTensors(
                **{k: self.map.params[k].index_put((rows,), leaves[k]) for k in PARAM_NAMES}
            )
            total = torch.zeros(())
            mse_sum = 0.0
            tangents: dict[int, torch.Tensor] = {}
            exposures: dict[int, torch.Tensor] = {}
            for i in views:
                kf = self.keyframes[i]
                xi = None
                if p.refine_poses and i in self.window and i != fixed_pose:
                    xi = tangents[i] = torch.zeros(6, dtype=torch.float64, requires_grad=True)
                out = render(
                    full,
                    kf.T_cam_world,
                    self.K,
                    self.width,
                    self.height,
                    pose_tangent=xi,
                    params=p.raster,
                )
                color = out.color
                image = kf.image_f32
                if p.exposure:
                    ab = exposures[i] = kf.exposure_ab.clone().requires_grad_()
                    color = self._expose(color, ab)
                l_rgb = (color - image).abs().mean()
                dmask = kf.depth_m > 0
                if p.lambda_depth > 0 and bool(dmask.any()):
                    rel = (out.depth - kf.depth_m).abs() / kf.depth_m.clamp_min(1e-3)
                    l_depth = (kf.confidence * rel)[dmask].mean()
                else:
                    l_depth = torch.zeros(())
                total = total + (1 - p.lambda_depth) * l_rgb + p.lambda_depth * l_depth
                mse_sum += float(((color.detach().clamp(0, 1) - image) ** 2).mean())
            ls = leaves["log_scales"]
            if p.lambda_iso > 0 and len(rows):
                total = total + p.lambda_iso * (ls - ls.mean(1, keepdim=True)).abs().mean()
            grads = torch.autograd.grad(
                total,
                [*leaves.values(), *exposures.values(), *tangents.values()],
                allow_unused=True,
            )
            g_map = dict(zip(leaves.keys(), grads[: len(leaves)], strict=True))
            if p.densify and g_map["means"] is not None:
                self._accumulate_densify_stats(rows, g_map["means"])
            self.map.adam_step(rows, g_map, lrs)
            self.map.params["colors"][rows] = self.map.params["colors"][rows].clamp(0, 1)
            off = len(leaves)
            for j, i in enumerate(exposures):
                if grads[off + j] is not None:
                    kf = self.keyframes[i]
                    kf.exposure_ab = kf.exposure_ab + kf.exposure_adam.step(
                        grads[off + j], p.lr_exposure
                    )
            off += len(exposures)
            for j, i in enumerate(tangents):
                if grads[off + j] is not None:
                    kf = self.keyframes[i]
                    step = kf.pose_adam.step(grads[off + j], p.lr_pose)
                    kf.T_cam_world = se3_exp_torch(step) @ kf.T_cam_world
            self.iterations += 1
            self.last_loss = float(total.detach()) / len(views)
            mse = mse_sum / len(views)
            self.last_psnr_db = -10 * math.log10(max(mse, 1e-12))
        if p.densify:
            self._densify(rows)
        self._prune()
        return self.stats()

    def _accumulate_densify_stats(self, rows: torch.Tensor, g_means: torch.Tensor) -> None:
        kf = self.keyframes[self.window[0]]
        R, t = kf.T_cam_world[:3, :3].float(), kf.T_cam_world[:3, 3].float()
        z = (self.map.params["means"][rows] @ R.T + t)[:, 2].clamp_min(1e-3)
        self._grad_accum += g_means.norm(dim=1) * z / self.K[0]
        self._grad_count += 1

    def _densify(self, rows: torch.Tensor) -> None:
        """3DGS clone: copy Gaussians whose mean view-space gradient exceeds the threshold."""
        if len(rows) == 0:
            return
        mean_grad = self._grad_accum / self._grad_count.clamp_min(1)
        pick = rows[mean_grad > self.params.densify_grad_px]
        if len(pick) == 0:
            return
        vals = {k: self.map.params[k][pick].clone() for k in PARAM_NAMES}
        noise = torch.randn(len(pick), 3, generator=torch.Generator().manual_seed(self.iterations))
        vals["means"] = vals["means"] + noise * torch.exp(vals["log_scales"])
        self.map.add(vals, birth_kf=len(self.keyframes) - 1)
        self.n_densified += len(pick)

    def _contribution(self, indices: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-Gaussian summed blending weight ``sum_p alpha_i T_i`` [N] over keyframes ``indices``
        and whether its centre lies in front of and inside the image of any of them [N] bool.

        The weight is the gradient of the rendered colour's channel sum with respect to the
        Gaussian's colour (one backward per view); an occluded Gaussian inside the view has weight
        0."""
        contrib = torch.zeros(len(self.map))
        in_view = torch.zeros(len(self.map), dtype=torch.bool)
        prm = self.map.params
        fx, fy, cx, cy = self.K
        for i in indices:
            kf = self.keyframes[i]
            colors = prm["colors"].clone().requires_grad_()
            g = GaussianTensors(**{k: prm[k] for k in PARAM_NAMES if k != "colors"}, colors=colors)
            out = render(
                g, kf.T_cam_world, self.K, self.width, self.height, params=self.params.raster
            )
            (grad,) = torch.autograd.grad(out.color[..., 0].sum(), colors)
            contrib += torch.nan_to_num(grad[:, 0].detach())
            T = kf.T_cam_world.to(prm["means"].dtype)
            p_cam = prm["means"] @ T[:3, :3].T + T[:3, 3]
            z = p_cam[:, 2]
            zs = z.clamp_min(1e-6)
            u, v = fx * p_cam[:, 0] / zs + cx, fy * p_cam[:, 1] / zs + cy
            in_view |= (
                (z > self.params.raster.near_m)
                & (u >= 0)
                & (u < self.width)
                & (v >= 0)
                & (v < self.height)
            )
        return contrib, in_view

    def _prune(self) -> None:
        p = self.params
        if len(self.map) == 0:
            return
        prm = self.map.params
        opacity = torch.sigmoid(prm["opacity_logit"])
        newest = self.keyframes[self.window[0]]
        cam_center = torch.as_tensor(newest.T_world_cam[:3, 3], dtype=torch.float32)
        dist = (prm["means"] - cam_center).norm(dim=1)
        too_big = torch.exp(prm["log_scales"]).amax(1) > p.prune_size_ratio * dist
        old = self.map.birth_kf <= len(self.keyframes) - 1 - p.support_kfs
        unsupported = old & (self.map.n_obs < p.support_min_obs)
        mask = (opacity < p.prune_opacity) | too_big | unsupported
        if p.prune_contrib_px > 0:
            contrib, in_view = self._contribution(self.window)
            settled = self.map.birth_kf < newest.index
            mask |= in_view & settled & (contrib < p.prune_contrib_px)
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


def export_ply(mapper: GaussianMapper, path: str) -> None:
    """Write ``mapper``'s map as a standard 3DGS PLY (:mod:`mogs_node.mapper.ply`)."""
    from mogs_node.mapper.ply import write_gaussian_ply

    prm = {k: v.numpy() for k, v in mapper.map.params.items()}
    write_gaussian_ply(
        path,
        prm["means"],
        prm["quats_wxyz"],
        prm["log_scales"],
        prm["opacity_logit"],
        prm["colors"],
    )
