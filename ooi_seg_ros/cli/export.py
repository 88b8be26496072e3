"""``ooi-seg export``: a splat snapshot of training.mcap back into a 3DGS PLY."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..core.types import InputError


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "export", help="turn a splat snapshot of training.mcap into a PLY",
        description="Write the K-th splat snapshot (PointCloud2 on /train/splats) of a "
                    "training bag as a standard 3DGS PLY (SuperSplat compatible).")
    p.add_argument("bag", help="training.mcap written by ooi-seg train")
    p.add_argument("--out", required=True, help="output .ply")
    p.add_argument("--index", type=int, default=-1,
                   help="snapshot index (0 = first, -1 = last, the default)")
    p.add_argument("--topic", default="/train/splats", help="snapshot topic")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..bag import BagReader
    from ..msgconv import pointcloud2_to_fields
    from ..train.gaussians import PLY_FIELDS, from_ply_array, save_ply

    path = Path(args.bag)
    if not path.exists():
        raise InputError(f"bag {path} does not exist")
    reader = BagReader(path)
    if args.topic not in reader.topics():
        raise InputError(f"{path} has no {args.topic} topic; is it a training.mcap?")
    snaps = [(t, data) for _, _, t, data in reader.messages([args.topic])]
    if not -len(snaps) <= args.index < len(snaps):
        raise InputError(f"--index {args.index} is out of range: the bag has {len(snaps)} "
                         f"snapshots (0..{len(snaps) - 1}, or -1 for the last)")
    _, data = snaps[args.index]
    msg = reader.decode("sensor_msgs/msg/PointCloud2", data, args.topic)
    fields = pointcloud2_to_fields(msg)
    n = int(msg.width) * int(msg.height)
    arr = np.zeros((n, len(PLY_FIELDS)), dtype=np.float32)
    for j, name in enumerate(PLY_FIELDS):
        if name in fields:
            arr[:, j] = fields[name]
        elif name not in ("nx", "ny", "nz"):
            raise InputError(f"snapshot lacks field {name}; not a splat PointCloud2")
    save_ply(from_ply_array(arr), args.out)
    print(f"wrote {args.out}: {n} Gaussians (snapshot {args.index} of {len(snaps)})")
    return 0
