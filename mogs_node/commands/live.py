"""``mogs live camera|imu-lines|imu-zmq``: stream a live sensor onto the bus (node in-process).

Examples::

    mogs live camera 0 --size 640x480 --fps 30          # first V4L2 device
    mogs live camera rtsp://192.168.1.10/stream
    mogs live imu-lines udp://127.0.0.1:9870            # text lines t_ns,gx,gy,gz,ax,ay,az
    mogs live imu-lines /dev/ttyUSB0                    # after: stty -F /dev/ttyUSB0 115200 raw
    mogs live imu-zmq --endpoint tcp://127.0.0.1:9871   # msgpack {t_ns, gyro, accel} via PUSH

The broker must be running; ``--launch`` / ``--bus-name`` pick its endpoints.
"""

from __future__ import annotations

import argparse

from mogs_node.commands.broker import bus_from_args
from mogs_node.commands.play import _endpoint_args

HELP = "stream a live camera or IMU onto the bus"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="kind", metavar="SOURCE", required=True)
    c = sub.add_parser("camera", help="OpenCV VideoCapture: device index, path, file or URL")
    c.add_argument("device", help="e.g. 0, /dev/video2, video.mp4, rtsp://host/stream")
    c.add_argument("--size", default=None, help="requested WxH")
    c.add_argument("--fps", type=float, default=0.0, help="requested frame rate")
    c.add_argument("--encoding", default="rgb8", choices=["rgb8", "bgr8", "mono8"])
    c.add_argument("--frames", type=int, default=0, help="stop after N frames (0 = never)")
    c.add_argument("--topic", default="/camera/image")
    c.add_argument("--wait", type=float, default=0.0, help="seconds to wait for a subscriber")
    s = sub.add_parser("imu-lines", help="IMU text lines from udp://HOST:PORT or a serial port")
    s.add_argument("source", help="udp://HOST:PORT (bound here) or a serial port / FIFO / file")
    s.add_argument("--samples", type=int, default=0, help="stop after N samples (0 = never)")
    s.add_argument("--topic", default="/imu")
    s.add_argument("--wait", type=float, default=0.0, help="seconds to wait for a subscriber")
    z = sub.add_parser("imu-zmq", help="msgpack IMU maps on a ZeroMQ PULL or SUB socket")
    z.add_argument("--endpoint", default="tcp://127.0.0.1:9871")
    z.add_argument("--socket", choices=["pull", "sub"], default="pull")
    z.add_argument("--connect", action="store_true", help="connect instead of binding")
    z.add_argument("--samples", type=int, default=0, help="stop after N samples (0 = never)")
    z.add_argument("--topic", default="/imu")
    for p in (c, s, z):
        _endpoint_args(p)


def command(args: argparse.Namespace) -> int:
    from bridges.live import LineImuNode, LiveCameraNode, ZmqImuNode
    from mogs_node.commands.sim import parse_size

    bus = bus_from_args(args)
    if args.kind == "camera":
        w, h = parse_size(args.size) if args.size else (0, 0)
        params = {
            "device": args.device,
            "width": w,
            "height": h,
            "fps": args.fps,
            "encoding": args.encoding,
            "max_frames": args.frames,
            "topic": args.topic,
            "wait_for_subscriber_s": args.wait,
        }
        node = LiveCameraNode("camera", params, bus)
    elif args.kind == "imu-lines":
        node = LineImuNode(
            "imu",
            {
                "source": args.source,
                "max_samples": args.samples,
                "topic": args.topic,
                "wait_for_subscriber_s": args.wait,
            },
            bus,
        )
    else:
        node = ZmqImuNode(
            "imu",
            {
                "endpoint": args.endpoint,
                "socket": args.socket,
                "bind": not args.connect,
                "max_samples": args.samples,
                "topic": args.topic,
            },
            bus,
        )
    return node.run()
