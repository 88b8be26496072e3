"""``ooi-seg record --out BAG TOPIC...``: record live topics into a rosbag2-compatible MCAP."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("record",
                       help="record ROS 2 topics into an MCAP bag (like ros2 bag record)")
    p.add_argument("topics", nargs="+", help="topics to record")
    p.add_argument("--out", required=True, help="output .mcap file")
    p.add_argument("--chunk-size", type=int, default=1 << 20,
                   help="bytes per MCAP chunk (what a SIGKILL can lose at most)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from ..nodes.bagplay import BagRecorder

    rclpy.init()
    rec = None
    try:
        rec = BagRecorder(args.out, args.topics, chunk_size=args.chunk_size)
        rclpy.spin(rec)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if rec is not None:
            rec.close()
            total = sum(rec.counts.values())
            print(f"recorded {total} messages into {args.out}: "
                  + ", ".join(f"{t}={n}" for t, n in sorted(rec.counts.items())), flush=True)
            rec.destroy_node()
        rclpy.try_shutdown()
    return 0
