"""``ooi-seg play BAG``: publish a bag's messages with their original timing and QoS."""

from __future__ import annotations

import argparse
import threading
import time


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("play", help="replay a bag onto ROS 2 topics (like ros2 bag play)")
    p.add_argument("bag", help="an .mcap file or a rosbag2 directory")
    p.add_argument("--rate", type=float, default=1.0, help="playback speed factor")
    p.add_argument("--start", type=float, default=0.0, help="skip the first S seconds")
    p.add_argument("--loop", action="store_true", help="play again from the start when done")
    p.add_argument("--topics", nargs="+", default=None, help="only these topics")
    p.add_argument("--remap", nargs="+", default=[], metavar="FROM:=TO",
                   help="publish topic FROM as TO")
    p.add_argument("--delay", type=float, default=0.5,
                   help="seconds to wait for discovery before the first message")
    p.add_argument("--wait-for-subscribers", type=float, default=0.0, metavar="S",
                   help="wait up to S seconds until every topic has a subscriber")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from ..nodes.bagplay import BagPlayer, parse_remaps, stderr_progress

    rclpy.init()
    player = None
    ex = spinner = None
    try:
        player = BagPlayer(args.bag, rate=args.rate, start_s=args.start, loop=args.loop,
                           topics=args.topics, remap=parse_remaps(args.remap),
                           progress=stderr_progress)
        ex = SingleThreadedExecutor()
        ex.add_node(player)
        spinner = threading.Thread(target=ex.spin, daemon=True)
        spinner.start()
        if args.wait_for_subscribers > 0:
            player.wait_for_subscribers(list(player.pubs), args.wait_for_subscribers)
        time.sleep(max(args.delay, 0.0))
        n = player.play()
        time.sleep(0.2)  # let the middleware hand out the last messages
        print(f"published {n} messages", flush=True)
        return 0
    except KeyboardInterrupt:
        return 130
    finally:
        if player is not None:
            player.stop()
        if ex is not None:
            ex.shutdown(timeout_sec=2.0)
            spinner.join(timeout=2.0)
        if player is not None:
            player.destroy_node()
        rclpy.try_shutdown()
