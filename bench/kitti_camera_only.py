"""The camera-only frontend on the real KITTI excerpt, in-process, against the LiDAR (issue 16).

``launch/kitti.yaml`` runs the excerpt (no IMU) through :class:`~mogs_node.frontend.monocular.
MonocularFrontend`: the poses come from the dense tracks (essential matrix) and the road (the
metric step), and the keyframes' points are the same dense tracks triangulated with those poses.
This runs that frontend alone, every frame, with the launch file's frontend parameters and the
player's ``/camera/info`` (``bridges.sources.camera_info_of``), and scores against the excerpt's
LiDAR (the only ground truth it has):

- the frontend's speed per frame against the LiDAR-PnP trajectory of ``mogs eval depth
  --dataset kitti78`` (:func:`~mogs_node.eval.depth_kitti78.localise_pnp`: corners tracked, LiDAR
  depth at them, PnP chained; metric because the LiDAR is);
- each keyframe's points against the LiDAR return nearest their pixel (within 1 px): signed and
  absolute relative error;
- the frontend's CPU time per frame (``time.process_time``, one core).

Why (docs/frontend.md, round 11): the depth of the KITTI launch moved with every change of the
points' settings, while the points themselves did not explain it; the scale of the poses does.

    python bench/kitti_camera_only.py [--round9] [--points '{"max_tracks": 2000}'] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402

from mogs_node.eval.depth_kitti78 import DEFAULT_DIR, load_kitti78, localise_pnp  # noqa: E402
from mogs_node.node import parse_params  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LIDAR_RADIUS_PX = 1  # a point's LiDAR depth: the median return within this many pixels
CAMERA_HEIGHT_M = 1.65  # launch/kitti.yaml's player.camera_height_m (the KITTI setup)


def frontend_params(points: dict, launch: Path = ROOT / "launch" / "kitti.yaml"):
    """The launch file's frontend node parameters with ``points`` merged over its ``points``."""
    from mogs_node.frontend.node_config import FrontendNodeParams

    nodes = yaml.safe_load(launch.read_text())["nodes"]
    raw = next(n for n in nodes if n["name"] == "frontend").get("params", {})
    raw = {**raw, "points": {**raw.get("points", {}), **points}}
    return parse_params(FrontendNodeParams, raw, where="frontend")


def lidar_at(depth_m: np.ndarray, uv_px: np.ndarray, r: int = LIDAR_RADIUS_PX) -> np.ndarray:
    """Median LiDAR return within ``r`` px of each pixel [N, 2]; NaN where there is none."""
    H, W = depth_m.shape
    out = np.full(len(uv_px), np.nan)
    for i, (u, v) in enumerate(np.round(uv_px).astype(int)):
        patch = depth_m[max(v - r, 0) : v + r + 1, max(u - r, 0) : u + r + 1]
        patch = patch[patch > 0]
        if len(patch):
            out[i] = float(np.median(patch))
    return out


def road_aligned(T_cam0_cams: np.ndarray) -> np.ndarray:
    """Poses [F, 4, 4] in the first camera's frame (x right, y down, z ahead) as ``T_world_cam``
    in a road-aligned world (x ahead, y left, z up, the first camera ``CAMERA_HEIGHT_M`` above the
    origin), the world the camera-only frontend and the prior's road model use."""
    A = np.eye(4)
    A[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
    A[2, 3] = CAMERA_HEIGHT_M
    return A[None] @ np.asarray(T_cam0_cams, np.float64)


def run(
    points: dict, folder: Path, given_poses: bool = False, drop: frozenset[int] = frozenset()
) -> dict:
    """Every frame of the excerpt through the camera-only frontend; figures against the LiDAR.
    ``given_poses``: the LiDAR-PnP poses are given to the frontend (as ``player.poses`` would):
    the points' errors are then the triangulation's, not the estimated poses'. ``drop``: frames
    left out (as a live run's superseded frames: the launch at ``rate: 1.0`` drops 1-2)."""
    from bridges.sources import camera_info_of
    from mogs_node.datasets.kitti import read_kitti_raw

    cv2.setNumThreads(1)
    seq = read_kitti_raw(folder)
    info = camera_info_of(seq, camera_height_m=CAMERA_HEIGHT_M)
    fe = frontend_params(points).build_monocular("frontend", info, given_poses=given_poses)
    data = load_kitti78(folder)
    T_pnp = road_aligned(localise_pnp(data)[0])
    period_ns = 100_000_000  # the player's stamps: the excerpt has no timestamps.txt
    cpu, pos, kfs = [], {}, []
    for i, rgb in enumerate(data.rgb):
        if i in drop:
            continue
        c0 = time.process_time()
        outs = fe.add_image(i * period_ns, rgb, T_pnp[i] if given_poses else None)
        cpu.append(time.process_time() - c0)
        for o in outs:
            if o.T_world_cam is not None:
                pos[o.stamp_ns // period_ns] = o.T_world_cam[:3, 3].copy()
            if o.keyframe is not None:
                kfs.append(o.keyframe)
    n = len(data.rgb)
    true_step = np.linalg.norm(np.diff(T_pnp[:, :3, 3], axis=0), axis=1)
    fe_pos = np.array([pos.get(i, np.full(3, np.nan)) for i in range(n)])
    for i in range(1, n):  # a dropped frame: halfway (the path is what counts)
        if i not in pos and i - 1 in pos and i + 1 in pos:
            fe_pos[i] = (pos[i - 1] + pos[i + 1]) / 2
    fe_step = np.linalg.norm(np.diff(fe_pos, axis=0), axis=1)
    rows, rel_all = [], []
    for k in kfs:
        f = int(k.stamp_ns // period_ns)
        zl = lidar_at(data.lidar_m[f], k.feature_uv_px)
        ok = np.isfinite(zl)
        rel = (k.feature_xyz_cam_m[ok, 2] - zl[ok]) / zl[ok]
        rel_all.append(rel)
        lo = max(f - 10, 0)  # the motion the keyframe's tracks saw (10 frames of history)
        rows.append(
            {
                "frame": f,
                "points": len(k.feature_ids),
                "points_with_lidar": int(ok.sum()),
                "points_rel_err_signed_median": float(np.median(rel)) if ok.any() else None,
                "points_rel_err_median": float(np.median(np.abs(rel))) if ok.any() else None,
                "path_m": float(np.nansum(fe_step[:f])),
                "path_lidar_pnp_m": float(true_step[:f].sum()),
                "step_ratio_last_10": float(
                    np.nansum(fe_step[lo:f]) / max(true_step[lo:f].sum(), 1e-9)
                ),
            }
        )
    rel = np.concatenate(rel_all) if rel_all else np.zeros(0)
    return {
        "points": points,
        "given_poses": given_poses,
        "frames": n,
        "cpu_ms_per_frame": 1e3 * float(np.mean(cpu[1:])),
        "keyframes": rows,
        "path_m": float(np.nansum(fe_step)),
        "path_lidar_pnp_m": float(true_step.sum()),
        "speed_m_s": [None if not np.isfinite(s) else round(10 * float(s), 3) for s in fe_step],
        "speed_lidar_pnp_m_s": [round(10 * float(s), 3) for s in true_step],
        "points_vs_lidar": int(len(rel)),
        "points_rel_err_median": float(np.median(np.abs(rel))) if len(rel) else None,
        "points_rel_err_signed_median": float(np.median(rel)) if len(rel) else None,
        "counters": {k: v for k, v in fe.counters.items() if v},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    options = {
        "--data": dict(default=str(DEFAULT_DIR), help="the KITTI excerpt's folder"),
        "--points": dict(default="{}", help="frontend.points overrides (JSON)"),
        "--round9": dict(action="store_true", help="bench/frontend.py's ROUND9 points"),
        "--given-poses": dict(action="store_true", help="give the frontend the LiDAR-PnP poses"),
        "--write-poses": dict(
            metavar="PATH", help="write the LiDAR-PnP poses (road-aligned, KITTI format) and exit"
        ),
        "--json": dict(metavar="PATH", help="write the figures here"),
        "--drop": dict(default="", help="frames left out, comma-separated (a live run's)"),
    }
    for flag, kw in options.items():
        ap.add_argument(flag, **kw)
    args = ap.parse_args()
    if args.write_poses:
        T = road_aligned(localise_pnp(load_kitti78(Path(args.data)))[0])
        np.savetxt(args.write_poses, T[:, :3, :].reshape(len(T), 12), fmt="%.9f")
        return
    points = json.loads(args.points)
    if args.round9:
        from bench.frontend import ROUND9

        points = {**ROUND9, **points}
    drop = frozenset(int(f) for f in args.drop.split(",") if f.strip())
    out = run(points, Path(args.data), args.given_poses, drop)
    for r in out["keyframes"]:
        print(json.dumps(r))
    print(
        json.dumps(
            {
                k: v
                for k, v in out.items()
                if k not in ("keyframes", "speed_m_s", "speed_lidar_pnp_m_s")
            }
        )
    )
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
