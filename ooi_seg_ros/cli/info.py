"""``ooi-seg info BAG``: topics, types, message counts, time span and image sizes of a bag.

Given a dataset folder instead (COLMAP, nerfstudio, image folder) it summarises the capture.
"""

from __future__ import annotations

import argparse

from ..core.types import InputError

_IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage",
                "sensor_msgs/msg/CameraInfo")


def register(subparsers) -> None:
    p = subparsers.add_parser("info", help="summarise a bag (.mcap file or rosbag2 folder)",
                              description=__doc__)
    p.add_argument("bag", help=".mcap file or rosbag2 bag folder (or a dataset folder)")
    p.set_defaults(func=run)


def _frame_size(reader, topic: str, type_name: str) -> str:
    """"W x H" of the first message of an image/camera_info topic ("?" when unreadable)."""
    for _t, ty, _ts, data in reader.messages(topics=[topic]):
        try:
            msg = reader.decode(ty, data, topic)
            if type_name.endswith("CompressedImage"):
                from .. import msgconv
                rgb = msgconv.compressed_to_rgb(msg)
                return f"{rgb.shape[1]}x{rgb.shape[0]} ({msg.format})"
            enc = f" {msg.encoding}" if hasattr(msg, "encoding") else ""
            return f"{msg.width}x{msg.height}{enc}"
        except InputError as exc:
            return f"? ({exc})"
    return "-"


def summarise(path: str) -> str:
    """The text ``ooi-seg info`` prints."""
    from ..bag import BagReader

    reader = BagReader(path)
    topics = reader.topics()
    t0, t1 = reader.time_span()
    total = sum(i.count for i in topics.values())
    lines = [f"bag:      {path} ({len(reader.files)} file(s))",
             f"messages: {total}",
             f"span:     {(t1 - t0) / 1e9:.3f} s  ({t0} .. {t1} ns)" if total else
             "span:     (no messages)"]
    for w in reader.warnings:
        lines.append(f"warning:  {w}")
    width = max([len(t) for t in topics] + [5])
    tw = max([len(i.type) for i in topics.values()] + [4])
    lines.append(f"{'topic':<{width}}  {'type':<{tw}}  {'count':>7}  frame")
    for name in sorted(topics):
        info = topics[name]
        size = (_frame_size(reader, name, info.type)
                if info.type in _IMAGE_TYPES and info.count else "")
        lines.append(f"{name:<{width}}  {info.type:<{tw}}  {info.count:>7}  {size}".rstrip())
    return "\n".join(lines)


def summarise_capture(path: str) -> str:
    """Views, image sizes, poses and ground truth of a non-bag capture folder."""
    from ..capture_io import input_kind, read_capture

    kind = input_kind(path)
    cap = read_capture(path)
    sizes = sorted({f"{v.camera.width}x{v.camera.height}" for v in cap.views})
    posed = sum(v.pose is not None for v in cap.views)
    masks = sum(v.gt_mask is not None for v in cap.views)
    gt = 0 if cap.gt_ooi_points is None else len(cap.gt_ooi_points)
    return "\n".join([f"capture:  {path} ({kind})", f"views:    {len(cap)}",
                      f"frames:   {', '.join(sizes)}", f"poses:    {posed} of {len(cap)}",
                      f"gt masks: {masks}", f"gt ooi points: {gt}"])


def run(args: argparse.Namespace) -> int:
    from ..capture_io import input_kind

    if input_kind(args.bag) != "bag":
        print(summarise_capture(args.bag))
    else:
        print(summarise(args.bag))
    return 0
