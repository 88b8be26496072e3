"""``python -m ooi_seg_ros.bag.recover IN OUT``: a bag cut short rewritten as a finished file.

A recorder killed with SIGKILL leaves an MCAP file without summary and footer. Our reader
reads it up to the damage, but rosbags, Foxglove's readers and ``ros2 bag`` reject it; this
writes everything readable into a new, finished, rosbag2-compatible file.
"""

from __future__ import annotations

import argparse
import sys
from typing import Optional

from ..core.types import InputError
from .mcap_bag import recover_bag


def main(argv: Optional[list[str]] = None) -> int:
    """Exit status 0 when the copy was written, 1 on bad input."""
    p = argparse.ArgumentParser(prog="python -m ooi_seg_ros.bag.recover",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("src", help="the damaged .mcap file (or rosbag2 folder)")
    p.add_argument("dst", help="the finished .mcap file to write")
    args = p.parse_args(argv)
    try:
        n = recover_bag(args.src, args.dst)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {args.dst}: {n} messages")
    return 0


if __name__ == "__main__":
    sys.exit(main())
