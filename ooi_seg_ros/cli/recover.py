"""``ooi-seg recover``: a recording cut short (SIGKILL, power loss) rewritten as a finished bag."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..core.types import InputError


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "recover", help="rewrite a bag cut short as a finished, rosbag2-compatible MCAP",
        description="A recorder killed with SIGKILL leaves an MCAP file without its summary "
                    "and footer. ooi-seg's own reader reads it up to the damage, but rosbags, "
                    "Foxglove's readers and ros2 bag reject it. This copies every readable "
                    "message (times, sequence numbers, definitions and QoS kept) into a new, "
                    "finished file.")
    p.add_argument("src", help="the damaged .mcap file (or rosbag2 folder)")
    p.add_argument("--out", required=True, help="the finished .mcap file to write")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..bag.mcap_bag import recover_bag

    src = Path(args.src)
    if not src.exists():
        raise InputError(f"bag {src} does not exist")
    n = recover_bag(src, args.out)
    print(f"wrote {args.out}: {n} messages recovered from {src}")
    return 0
