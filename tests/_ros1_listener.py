"""A rospy listener (a separate process: rospy initialises one node per process) that records what
the ROS 1 bridge publishes, decoded by the official genpy message classes, not by our conversions.

    python tests/_ros1_listener.py OUT.json [--image-topic /cam0/image_raw] [--prefix /mogs]

Writes ``OUT.json`` every 0.5 s and on SIGINT/SIGTERM; ``OUT.json.ready`` once subscribed.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import threading
import time
from pathlib import Path

import numpy as np

from bridges.ros1 import require_rospy


def _stamp(h) -> int:
    return int(h.stamp.secs) * 1_000_000_000 + int(h.stamp.nsecs)


class Recorder:
    """What the listener has seen, one callback per topic; every field guarded by one lock."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.rec: dict = {
            "odometry": [],
            "images": [],
            "path": None,
            "path_count": 0,
            "path_first": {},
            "map_cloud": None,
            "map_cloud_count": 0,
            "depth": None,
            "depth_count": 0,
            "tf": {"count": 0, "pairs": []},
            "diagnostics": {"count": 0, "names": []},
        }

    def on_odo(self, m) -> None:
        p, q = m.pose.pose.position, m.pose.pose.orientation
        row = [_stamp(m.header), p.x, p.y, p.z, q.w, q.x, q.y, q.z, time.time_ns()]
        with self.lock:
            self.rec["odometry"].append(row)
            self.rec["odometry_frames"] = [m.header.frame_id, m.child_frame_id]

    def on_image(self, m) -> None:
        with self.lock:
            self.rec["images"].append([_stamp(m.header), time.time_ns()])

    def on_path(self, m) -> None:
        poses = [
            [
                _stamp(ps.header),
                ps.pose.position.x,
                ps.pose.position.y,
                ps.pose.position.z,
                ps.pose.orientation.w,
                ps.pose.orientation.x,
                ps.pose.orientation.y,
                ps.pose.orientation.z,
            ]
            for ps in m.poses
        ]
        with self.lock:
            self.rec["path"] = {"frame_id": m.header.frame_id, "poses": poses}
            for row in poses:  # each keyframe's pose as the path first showed it
                self.rec["path_first"].setdefault(str(row[0]), row[1:])
            self.rec["path_count"] += 1

    def on_cloud(self, m) -> None:
        fields = [[f.name, f.offset, f.datatype, f.count] for f in m.fields]
        data = np.frombuffer(m.data, np.uint8).reshape(-1, m.point_step)
        xyz = data[:, :12].copy().view("<f4")
        rgb = data[:, 12:16].copy().view("<u4").reshape(-1)
        with self.lock:
            self.rec["map_cloud"] = {
                "frame_id": m.header.frame_id,
                "height": m.height,
                "width": m.width,
                "point_step": m.point_step,
                "row_step": m.row_step,
                "fields": fields,
                "finite": bool(np.isfinite(xyz).all()),
                "distinct_colours": int(len(np.unique(rgb))),
                "centroid": xyz.mean(0).tolist() if len(xyz) else None,
            }
            self.rec["map_cloud_count"] += 1

    def on_depth(self, m) -> None:
        d = np.frombuffer(m.data, "<f4").reshape(m.height, m.width)
        fin = d[np.isfinite(d)]
        with self.lock:
            self.rec["depth"] = {
                "encoding": m.encoding,
                "height": m.height,
                "width": m.width,
                "step": m.step,
                "frame_id": m.header.frame_id,
                "finite_fraction": float(np.isfinite(d).mean()),
                "min_m": float(fin.min()) if fin.size else math.nan,
                "max_m": float(fin.max()) if fin.size else math.nan,
                "any_zero": bool((d == 0).any()),
            }
            self.rec["depth_count"] += 1

    def on_tf(self, m) -> None:
        with self.lock:
            self.rec["tf"]["count"] += 1
            for t in m.transforms:
                pair = [t.header.frame_id, t.child_frame_id]
                if pair not in self.rec["tf"]["pairs"]:
                    self.rec["tf"]["pairs"].append(pair)

    def on_diag(self, m) -> None:
        with self.lock:
            self.rec["diagnostics"]["count"] += 1
            for s in m.status:
                if s.name not in self.rec["diagnostics"]["names"]:
                    self.rec["diagnostics"]["names"].append(s.name)
            self.rec["diagnostics"]["last"] = {kv.key: kv.value for kv in m.status[0].values}

    def dump(self, out: Path) -> None:
        """Write the record atomically (a reader never sees half a file)."""
        with self.lock:
            text = json.dumps(self.rec)
        tmp = out.with_suffix(".tmp")
        tmp.write_text(text)
        tmp.replace(out)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--image-topic", default="/cam0/image_raw")
    ap.add_argument("--image-type", default="sensor_msgs/Image")
    ap.add_argument("--prefix", default="/mogs")
    args = ap.parse_args()
    rospy = require_rospy()
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from nav_msgs.msg import Path as RosPath
    from sensor_msgs.msg import CompressedImage, Image, PointCloud2
    from tf2_msgs.msg import TFMessage

    r = Recorder()
    rospy.init_node("mogs_test_listener", anonymous=True, disable_signals=True)
    pre = args.prefix.rstrip("/")
    image_cls = CompressedImage if args.image_type.endswith("CompressedImage") else Image
    subs = [
        rospy.Subscriber(f"{pre}/odometry", Odometry, r.on_odo, queue_size=1000),
        rospy.Subscriber(f"{pre}/path", RosPath, r.on_path, queue_size=10),
        rospy.Subscriber(f"{pre}/map_cloud", PointCloud2, r.on_cloud, queue_size=2),
        rospy.Subscriber(f"{pre}/depth", Image, r.on_depth, queue_size=10),
        rospy.Subscriber("/tf", TFMessage, r.on_tf, queue_size=1000),
        rospy.Subscriber("/diagnostics", DiagnosticArray, r.on_diag, queue_size=100),
        rospy.Subscriber(args.image_topic, image_cls, r.on_image, queue_size=1000),
    ]
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    out = Path(args.out)
    r.dump(out)
    Path(str(out) + ".ready").write_text(str(len(subs)))
    while not stop.wait(0.5):
        r.dump(out)
    r.dump(out)
    rospy.signal_shutdown("done")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
