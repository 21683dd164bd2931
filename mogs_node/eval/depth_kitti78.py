"""``mogs eval depth --dataset kitti78``: the depth path on real KITTI images against LiDAR.

Protocol (issue 5; the excerpt has no IMU, so the visual-inertial frontend cannot run):

1. Sparse metric points: the frontend's tracker (Shi-Tomasi + KLT,
   :mod:`mogs_node.frontend.tracker`) runs over all frames; each tracked corner takes the LiDAR
   depth of the nearest projected LiDAR pixel within ``SAMPLE_RADIUS_PX`` (rejected when the
   depths in that window spread by more than ``SAMPLE_MAX_SPREAD``, i.e. on depth edges). This
   is a documented stand-in for the VI-SfM points of paper III-A: metric, sparse, on image
   corners. Weight omega grows with track length.
2. Poses: relative pose of each frame to the previous one by PnP (``cv2.solvePnPRansac`` then
   Levenberg-Marquardt refinement on the inliers) from the previous frame's metric points and
   their tracked pixels; chained into ``T_world_cam``.
3. Masks: the default graph segmenter; prior: the flow backend (two-view DIS depth with the PnP
   poses, declared ``metric`` since the poses are metric).
4. Methods (DESIGN.md section 7 names): ``no_msc_cdr`` (the prior globally aligned),
   ``interp_nearest`` and ``interp_edge_aware`` (sparse points only), ``no_msc`` and ``full``
   (MOGS, paper III-B/III-C) from :mod:`mogs_node.metrizer.baselines`.
5. Ground truth: the LiDAR pixels not used as sparse input (every LiDAR pixel inside a sampling
   window of a used corner is excluded). Metrics are pooled over all evaluated pixels of all
   frames: AbsRel, RMSE, delta1, overall and per depth range 0-20, 20-40, 40-80 m. The primary
   figures use the pixels where every method predicts a depth (methods differ in coverage: the
   flow prior covers ~30% of LiDAR pixels); each method's figures on its own coverage are under
   ``"own"``.

With ``--points tracks`` step 1's sparse points are the system's own instead (issue 16): the
frontend's dense tracker (:class:`~mogs_node.frontend.track_points.TrackPointsParams`) runs over
the frames and each evaluated frame gets every well-triangulated track, exactly as a keyframe of
the frontend does (:func:`~mogs_node.frontend.track_points.keyframe_points`: multi-view DLT +
Gauss-Newton, paper IV-A, with its gates and depth-edge tests), from the PnP poses of step 2.
LiDAR then serves only those poses and the ground truth (every LiDAR pixel is held out).
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.depth_prior.flow_prior import (
    FlowPriorParams,
    choose_references,
    compute_flow_prior,
    fit_scale_huber,
)
from mogs_node.errors import ConfigError, DatasetError
from mogs_node.eval.bench_docs import machine_line, update_markdown_section
from mogs_node.eval.figures import write_titled_strip
from mogs_node.eval.metrics import depth_metrics, depth_metrics_by_range
from mogs_node.frontend.track_points import TrackPointsParams
from mogs_node.geometry import PinholeCamera, make_T, se3_inverse
from mogs_node.segmentation.graph import GraphSegParams, segment_graph
from mogs_node.shared_data import shared_data_dir

__all__ = [
    "POINT_SOURCES",
    "Kitti78",
    "evaluate",
    "load_kitti78",
    "localise_pnp",
    "sample_lidar",
    "track_points",
]

log = logging.getLogger(__name__)

DEFAULT_DIR = shared_data_dir("kitti_raw_2011_09_26_78")
METHODS = ("no_msc_cdr", "interp_nearest", "interp_edge_aware", "no_msc", "full")
RANGES = (0.0, 20.0, 40.0, 80.0)
SAMPLE_RADIUS_PX = 2
SAMPLE_MAX_SPREAD = 0.1
PNP_THRESH_PX = 1.0
TRACKER_MAX_FEATURES = 300
POINT_SOURCES = ("lidar", "tracks")  # --points: LiDAR at the corners, or triangulated tracks


@dataclass
class Kitti78:
    """The excerpt in memory."""

    rgb: list[NDArray[np.uint8]]  # [H, W, 3] per frame
    lidar_m: list[NDArray[np.float32]]  # [H, W] projected LiDAR depth, 0 = no return
    K: NDArray[np.float64]  # [3, 3] rectified intrinsics of image_02
    names: list[str]


def load_kitti78(folder: str | Path) -> Kitti78:
    """Images, projected LiDAR depth (``velodyne_raw``) and ``P_rect_02`` of the excerpt, in memory.

    Reads through :func:`mogs_node.datasets.kitti.read_kitti_raw`.
    """
    from mogs_node.datasets.kitti import read_kitti_raw

    seq = read_kitti_raw(folder, depth="velodyne_raw")
    if seq.meta.get("depth") != "velodyne_raw":
        raise DatasetError(f"{folder}: no proj_depth/velodyne_raw/image_02 LiDAR depth")
    rgb, lidar = [], []
    for f in seq.frames:
        img, d = f.image, f.depth_m()
        if d is None or d.shape != img.shape[:2]:
            raise DatasetError(f"{f.source}: LiDAR depth missing or of another size")
        rgb.append(np.ascontiguousarray(img))
        lidar.append(d.astype(np.float32))
    return Kitti78(
        rgb=rgb, lidar_m=lidar, K=seq.camera.K, names=[Path(f.source).stem for f in seq.frames]
    )


def sample_lidar(
    depth_m: NDArray[np.float32],
    uv_px: NDArray[np.floating],
    radius: int = SAMPLE_RADIUS_PX,
    max_spread: float = SAMPLE_MAX_SPREAD,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """LiDAR depth at pixels ``uv_px`` ``[N, 2]``: nearest return within ``radius`` (0 = none).

    Returns ``(z [N], used [H, W])``; ``used`` marks every LiDAR pixel inside the window of a
    sampled point (excluded from ground truth). Windows whose returns spread by more than
    ``max_spread`` (relative) straddle a depth edge and give no sample.
    """
    H, W = depth_m.shape
    uv = np.asarray(uv_px, np.float64)
    u = np.round(uv[:, 0]).astype(np.intp)
    v = np.round(uv[:, 1]).astype(np.intp)
    offs = np.arange(-radius, radius + 1)
    du, dv = np.meshgrid(offs, offs)
    uu = np.clip(u[:, None] + du.ravel()[None], 0, W - 1)  # [N, w*w]
    vv = np.clip(v[:, None] + dv.ravel()[None], 0, H - 1)
    z = depth_m[vv, uu]
    has = z > 0
    dist = np.where(has, (uu - uv[:, :1]) ** 2 + (vv - uv[:, 1:]) ** 2, np.inf)
    best = np.argmin(dist, axis=1)
    zb = z[np.arange(len(uv)), best].astype(np.float64)
    zmax = np.where(has, z, 0).max(axis=1)
    zmin = np.where(has, z, np.inf).min(axis=1)
    ok = has.any(axis=1) & ((zmax - zmin) <= max_spread * zmin)
    zb = np.where(ok, zb, 0.0)
    used = np.zeros((H, W), bool)
    used[vv[ok].ravel(), uu[ok].ravel()] = True
    return zb, used & (depth_m > 0)


@dataclass
class _Frame:
    uv: NDArray[np.float64]
    z: NDArray[np.float64]
    w: NDArray[np.float64]
    used: NDArray[np.bool_]


def _static_pnp(
    X: NDArray[np.float64], x: NDArray[np.float64], K: NDArray[np.float64], n_models: int = 3
) -> tuple[NDArray[np.float64], int]:
    """``T_cur_prev`` from points ``X`` ``[N, 3]`` (previous camera) seen at ``x`` ``[N, 2]``.

    In traffic, corners on other vehicles can outnumber static ones, and plain RANSAC then
    returns the motion relative to a truck. Sequential RANSAC finds up to ``n_models`` motions
    (each on the points the previous ones left); the static world is the largest one that a car
    can perform: no backward motion (> 1 cm), lateral and vertical translation at most
    ``0.2 |t_z| + 0.02`` m per frame (non-holonomic vehicle). Each model is refined by
    Levenberg-Marquardt on its inliers.
    Returns ``(T, n_inliers)``, ``(I, 0)`` when no model qualifies.
    """
    idx = np.arange(len(X))
    best, best_n = np.eye(4), 0
    for _ in range(n_models):
        if len(idx) < 8:
            break
        ok, rv, tv, inl = cv2.solvePnPRansac(
            X[idx],
            x[idx],
            K,
            None,
            reprojectionError=PNP_THRESH_PX,
            iterationsCount=300,
            flags=cv2.SOLVEPNP_EPNP,
        )
        if not ok or inl is None or len(inl) < 6:
            break
        inl = idx[inl[:, 0]]
        _, rv, tv = cv2.solvePnP(X[inl], x[inl], K, None, rv, tv, True, cv2.SOLVEPNP_ITERATIVE)
        t = tv[:, 0]
        R = cv2.Rodrigues(rv)[0]
        fwd = -(R.T @ t)[2]  # forward motion of the camera centre [m]
        if fwd >= -0.01 and np.hypot(t[0], t[1]) <= 0.2 * abs(t[2]) + 0.02 and len(inl) > best_n:
            best, best_n = make_T(R, t), len(inl)
        idx = np.setdiff1d(idx, inl)
    return best, best_n


def localise_pnp(data: Kitti78) -> tuple[NDArray[np.float64], list[_Frame], dict[str, float]]:
    """Track corners, sample LiDAR at them and chain PnP poses; ``T_world_cam`` ``[F, 4, 4]``."""
    from mogs_node.frontend.camera import CameraModel
    from mogs_node.frontend.tracker import FeatureTracker, TrackerParams

    H, W = data.lidar_m[0].shape
    tracker = FeatureTracker(
        TrackerParams(max_features=TRACKER_MAX_FEATURES),
        CameraModel(PinholeCamera.from_K(data.K, W, H)),
    )
    poses = [np.eye(4)]
    frames: list[_Frame] = []
    prev = None
    n_inl = []
    n_fallback = 0
    last_motion = np.eye(4)
    for i, rgb in enumerate(data.rgb):
        res = tracker.track(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
        z, used = sample_lidar(data.lidar_m[i], res.uv_px)
        w = np.minimum(1.0, res.track_len / 4.0)
        ok = z > 0
        frames.append(_Frame(uv=res.uv_px[ok], z=z[ok], w=w[ok], used=used))
        if prev is not None:
            pid, puv, pz = prev
            _, ia, ib = np.intersect1d(pid, res.ids, return_indices=True)
            m = pz[ia] > 0
            X = PinholeCamera.from_K(data.K, W, H).backproject(puv[ia][m], pz[ia][m])
            x = res.uv_px[ib][m]
            T_cur_prev, n = _static_pnp(X, x, data.K)
            if n:
                n_inl.append(n)
                last_motion = T_cur_prev
            else:
                T_cur_prev = last_motion
                n_fallback += 1
                log.info("frame %d: no vehicle-consistent PnP motion, constant velocity", i)
            poses.append(poses[-1] @ se3_inverse(T_cur_prev))
        prev = (res.ids, res.uv_px, z)
    steps = np.linalg.norm(np.diff(np.array(poses)[:, :3, 3], axis=0), axis=1)
    stats = {
        "path_length_m": float(steps.sum()),
        "pnp_inliers_mean": float(np.mean(n_inl)),
        "pnp_fallback_frames": float(n_fallback),
        "sparse_points_mean": float(np.mean([len(f.z) for f in frames])),
    }
    return np.array(poses), frames, stats


def track_points(
    data: Kitti78,
    T_world_cams: NDArray[np.float64],
    frames: set[int],
    params: TrackPointsParams | None = None,
) -> dict[int, _Frame]:
    """The system's own sparse points of ``frames``: dense KLT tracks triangulated with the poses.

    ``T_world_cams`` [F, 4, 4]: the PnP poses of :func:`localise_pnp`. The frontend's dense
    tracker runs over the frames (no rotation prediction: the excerpt has no IMU); at each frame
    of ``frames`` :func:`~mogs_node.frontend.track_points.keyframe_points` triangulates the tracks
    alive in it from the frames they were seen in (paper IV-A) and gates them, as the frontend
    does for a keyframe. No LiDAR pixel is used (``used`` stays empty).
    """
    from mogs_node.frontend.camera import CameraModel
    from mogs_node.frontend.track_points import TrackHistory, keyframe_points
    from mogs_node.frontend.tracker import FeatureTracker

    pp = params or TrackPointsParams()
    H, W = data.lidar_m[0].shape
    camera = PinholeCamera.from_K(data.K, W, H)
    tracker = FeatureTracker(pp.tracker(), CameraModel(camera))
    history = TrackHistory(pp.history_frames)
    out: dict[int, _Frame] = {}
    for i, rgb in enumerate(data.rgb[: max(frames, default=-1) + 1]):
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        res = tracker.track(gray)
        history.add(i, res.ids, res.uv_px, gray)
        history.set_pose(i, T_world_cams[i])
        if i in frames:
            pts = keyframe_points(history, camera, pp)
            out[i] = _Frame(
                uv=pts.uv_px.astype(np.float64),
                z=pts.xyz_cam_m[:, 2].astype(np.float64),
                w=pts.weight.astype(np.float64),
                used=np.zeros((H, W), bool),
            )
    return out


def _colour(depth: NDArray, valid: NDArray, vmax: float = 40.0) -> NDArray[np.uint8]:
    """Inverse-depth colour map (near warm), black where not valid; RGB uint8."""
    inv = np.where(valid, np.clip(3.0 / np.maximum(depth, 1e-3) * (vmax / 40.0), 0, 1), 0)
    img = cv2.applyColorMap((inv * 255).astype(np.uint8), cv2.COLORMAP_MAGMA)[..., ::-1]
    return np.where(valid[..., None], img, 0).astype(np.uint8)


def _viz(path: Path, rgb, labels, prior, prior_conf, depth, gt, gt_mask) -> None:
    rgb = rgb.copy()
    rng = np.random.default_rng(0)
    lut = rng.integers(40, 255, (int(labels.max()) + 2, 3)).astype(np.uint8)
    masks = np.where((labels >= 0)[..., None], lut[labels], 0).astype(np.uint8)
    err = np.zeros(gt.shape, np.float32)
    m = gt_mask & (depth > 0)
    err[m] = np.abs(depth[m] - gt[m]) / gt[m]
    err_img = cv2.applyColorMap(
        (np.clip(err / 0.3, 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_JET
    )[..., ::-1]
    err_img = cv2.dilate(np.where(m[..., None], err_img, 0).astype(np.uint8), np.ones((3, 3)))
    panels = [rgb, masks, _colour(prior, prior_conf > 0), _colour(depth, depth > 0), err_img]
    titles = [
        "image",
        "masks (graph segmenter)",
        "flow prior (confident pixels)",
        "metrized depth (full MOGS)",
        "AbsRel vs held-out LiDAR, 0 (blue) .. 0.3 (red)",
    ]
    write_titled_strip(path, panels, titles, font_scale=0.6, margin_px=6, line_type=cv2.LINE_AA)


def _score_methods(cat: dict[str, NDArray], g: NDArray) -> tuple[NDArray, dict[str, dict]]:
    """Each method's figures on the pixels every method predicts (a fair comparison), and on its
    own coverage under "own"; also that common mask."""
    common = np.ones(len(g), bool)
    for name in METHODS:
        common &= cat[name] > 0
    methods: dict[str, dict] = {}
    for name, p in cat.items():
        com = depth_metrics(p, g, common)
        own = depth_metrics(p, g)
        entry = {k: com[k] for k in ("absrel", "rmse", "delta1")}
        entry["count"] = com["count"]
        entry["by_range"] = depth_metrics_by_range(p, g, common, edges_m=RANGES)
        entry["own"] = {k: own[k] for k in ("absrel", "rmse", "delta1", "count")}
        entry["own"]["coverage"] = float(own["count"] / max(len(g), 1))
        entry["own"]["by_range"] = depth_metrics_by_range(p, g, edges_m=RANGES)
        methods[name] = entry
    return common, methods


def _sparse_point_errors(data, frames, eligible: list[int]) -> dict[str, float]:
    """The triangulated points against the LiDAR return at their pixel: relative error median
    and 90th percentile."""
    rel = []
    for i in eligible:
        z_lidar, _ = sample_lidar(data.lidar_m[i], frames[i].uv)
        ok = z_lidar > 0
        rel.append(np.abs(frames[i].z[ok] - z_lidar[ok]) / z_lidar[ok])
    rel_all = np.concatenate(rel) if rel else np.zeros(0)
    return {
        "sparse_rel_err_median": float(np.median(rel_all)) if len(rel_all) else 0.0,
        "sparse_rel_err_p90": float(np.percentile(rel_all, 90)) if len(rel_all) else 0.0,
    }


def evaluate(args: argparse.Namespace) -> dict:
    """Run the protocol of the module docstring; returns the DESIGN.md section 7 dict."""
    from mogs_node.metrizer.baselines import BASELINES
    from mogs_node.metrizer.pipeline import MetrizerInputs, MetrizerParams

    source = getattr(args, "points", None) or "lidar"
    if source not in POINT_SOURCES:
        raise ConfigError(f"points: {source!r} is not one of {POINT_SOURCES}")
    folder = Path(args.data) if getattr(args, "data", None) else DEFAULT_DIR
    t0 = time.perf_counter()
    data = load_kitti78(folder)
    poses, frames, loc_stats = localise_pnp(data)
    fp = FlowPriorParams()
    seg = GraphSegParams()
    mp = MetrizerParams()
    eligible = [i for i in range(len(data.rgb)) if choose_references(poses[i], poses[:i], fp)]
    n_want = getattr(args, "frames", None)
    if n_want and n_want < len(eligible):
        pick = np.unique(np.round(np.linspace(0, len(eligible) - 1, n_want)).astype(int))
        eligible = [eligible[k] for k in pick]
    ms_per: dict[str, float] = {m: 0.0 for m in ("seg", "prior", *METHODS)}
    viz_dir = Path(args.viz) if getattr(args, "viz", None) else None
    if source == "tracks":
        tic = time.perf_counter()
        for i, fr in track_points(data, poses, set(eligible)).items():
            frames[i] = fr
        ms_per["tracks"] = (time.perf_counter() - tic) * 1e3
    pred: dict[str, list[NDArray]] = {m: [] for m in (*METHODS, "prior_raw")}
    gts: list[NDArray] = []
    prior_cov, prior_scale = [], []
    for n, i in enumerate(eligible):
        rgb, gt, f = data.rgb[i], data.lidar_m[i], frames[i]
        gt_mask = (gt > 0) & ~f.used
        tic = time.perf_counter()
        labels = segment_graph(rgb, seg)
        ms_per["seg"] += (time.perf_counter() - tic) * 1e3
        tic = time.perf_counter()
        refs = choose_references(poses[i], poses[:i], fp)
        prior = compute_flow_prior(
            rgb, data.K, poses[i], [(data.rgb[j], poses[j]) for j in refs], fp
        )
        ms_per["prior"] += (time.perf_counter() - tic) * 1e3
        m_gt = gt_mask
        gts.append(gt[m_gt])
        pc = prior.confidence > 0
        prior_cov.append(float((pc & (gt > 0)).sum() / max((gt > 0).sum(), 1)))
        prior_scale.append(fit_scale_huber(prior.depth_m[pc & gt_mask], gt[pc & gt_mask]))
        pred["prior_raw"].append(np.where(pc, prior.depth_m, 0.0)[m_gt])
        inputs = MetrizerInputs(
            K=data.K,
            labels=labels,
            feature_uv_px=f.uv,
            feature_depth_m=f.z,
            feature_weight=f.w,
            prior=prior.depth_m,
            prior_confidence=prior.confidence,
            prior_kind="metric",
            image_rgb=rgb,
        )
        full_depth = None
        for name in METHODS:
            tic = time.perf_counter()
            out = BASELINES[name](**inputs, params=mp)
            ms_per[name] += (time.perf_counter() - tic) * 1e3
            pred[name].append(out.depth_m[m_gt])
            if name == "full":
                full_depth = out.depth_m
        if viz_dir is not None:
            _viz(
                viz_dir / f"kitti78_{data.names[i]}.png",
                rgb,
                labels,
                prior.depth_m,
                prior.confidence,
                full_depth,
                gt,
                gt_mask,
            )
        log.info("frame %d (%d/%d) done", i, n + 1, len(eligible))
    g = np.concatenate(gts) if gts else np.zeros(0)
    cat = {name: (np.concatenate(parts) if parts else np.zeros(0)) for name, parts in pred.items()}
    common, methods = _score_methods(cat, g)
    n_f = max(len(eligible), 1)
    n_pts = [len(frames[i].z) for i in eligible]
    loc_stats["sparse_points_mean"] = float(np.mean(n_pts)) if n_pts else 0.0
    loc_stats["sparse_points_median"] = float(np.median(n_pts)) if n_pts else 0.0
    if source == "tracks":
        loc_stats.update(_sparse_point_errors(data, frames, eligible))
    out = {
        "dataset": "kitti78",
        "points": source,
        "frames": len(eligible),
        "methods": methods,
        "gt_points": int(len(g)),
        "common_points": int(common.sum()),
        "prior": {
            "coverage_of_lidar": float(np.mean(prior_cov)) if prior_cov else 0.0,
            "huber_scale_vs_lidar_median": float(np.nanmedian(prior_scale))
            if prior_scale
            else float("nan"),
        },
        "localisation": loc_stats,
        "ms_per_frame": {k: v / n_f for k, v in ms_per.items()},
        "wall_s": time.perf_counter() - t0,
    }
    whole = n_want is None and getattr(args, "data", None) is None
    if whole and getattr(args, "write_docs", False):
        # Only a run over the whole default excerpt replaces the table in docs/benchmarks.md.
        section = "depth_kitti78" if source == "lidar" else "depth_kitti78_tracks"
        update_markdown_section(section, _markdown(out, args))
    return out


def _markdown(res: dict, args: argparse.Namespace) -> str:
    tracks = res.get("points") == "tracks"
    cmd = "mogs eval depth --dataset kitti78" + (" --points tracks" if tracks else "")
    cmd += " --json kitti78.json"
    source = (
        "Sparse metric points = the system's own: the frontend's dense KLT tracks triangulated "
        "(multi-view DLT + Gauss-Newton, gated, depth-edge tests: docs/frontend.md) with the PnP "
        "poses; LiDAR serves only those poses and the ground truth (every LiDAR pixel is held "
        "out)"
        if tracks
        else "Sparse metric points = LiDAR at the tracker's corners (stand-in for VI-SfM points, "
        "no IMU in the excerpt); poses by PnP on them"
    )
    names = {
        "no_msc_cdr": "prior, globally aligned (w/o MSC, CDR)",
        "interp_nearest": "sparse only, nearest",
        "interp_edge_aware": "sparse only, edge-aware",
        "no_msc": "MOGS w/o MSC",
        "full": "MOGS (full)",
        "prior_raw": "flow prior itself (where confident)",
    }
    lines = [
        "## Depth on real KITTI (kitti_raw_2011_09_26_78) against LiDAR"
        + (", the system's own sparse points" if tracks else ""),
        "",
        f"Command: `{cmd}` ({res['frames']} frames, {res['gt_points']} held-out LiDAR pixels, "
        f"{res['wall_s']:.0f} s). Machine: {machine_line()}.",
        "",
        source + "; masks from the graph segmenter; prior from the flow backend. Ground truth = "
        "LiDAR pixels not used as sparse input. AbsRel / RMSE "
        "[m] / delta1, pooled over pixels. First table: on the pixels where every compared method "
        "predicts a depth (the globally aligned prior covers the fewest), so all rows use the same "
        "pixels; coverage = share of all held-out LiDAR pixels used.",
        "",
        "| method | AbsRel | RMSE | delta1 | coverage | AbsRel 0-20 | AbsRel 20-40 "
        "| AbsRel 40-80 |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    order = ("no_msc_cdr", "interp_nearest", "interp_edge_aware", "no_msc", "full", "prior_raw")
    for name in order:
        m = res["methods"][name]
        br = m["by_range"]
        lines.append(
            f"| {names[name]} (`{name}`) | {m['absrel']:.4f} | {m['rmse']:.3f} | "
            f"{m['delta1']:.4f} | {m['count'] / max(res['gt_points'], 1):.3f} | "
            f"{br['0-20']['absrel']:.4f} | {br['20-40']['absrel']:.4f} | "
            f"{br['40-80']['absrel']:.4f} |"
        )
    lines += [
        "",
        "Each method on its own coverage (pixels where it predicts a depth):",
        "",
        "| method | AbsRel | RMSE | delta1 | coverage | AbsRel 0-20 | AbsRel 20-40 "
        "| AbsRel 40-80 |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name in order:
        m = res["methods"][name]["own"]
        br = m["by_range"]
        lines.append(
            f"| `{name}` | {m['absrel']:.4f} | {m['rmse']:.3f} | {m['delta1']:.4f} | "
            f"{m['coverage']:.3f} | {br['0-20']['absrel']:.4f} | {br['20-40']['absrel']:.4f} | "
            f"{br['40-80']['absrel']:.4f} |"
        )
    pr = res["prior"]
    loc = res["localisation"]
    lines += [
        "",
        f"Flow prior: covers {pr['coverage_of_lidar']:.1%} of LiDAR pixels per frame on average; "
        f"median Huber scale vs LiDAR {pr['huber_scale_vs_lidar_median']:.3f}. PnP path length "
        f"{loc['path_length_m']:.2f} m, {loc['sparse_points_mean']:.0f} sparse points per frame"
        + (
            f" (median relative depth error against the LiDAR return at their pixel "
            f"{loc['sparse_rel_err_median']:.1%}, 90th percentile {loc['sparse_rel_err_p90']:.1%})."
            if tracks
            else "."
        ),
        "Per frame [ms]: " + ", ".join(f"{k} {v:.0f}" for k, v in res["ms_per_frame"].items()),
    ]
    return "\n".join(lines)
