"""Capture I/O throughput: capture bags (rgb8 / png) and folders vs a bare-MCAP baseline.

Baseline (same run): the same messages serialised with rclpy and written with a plain
``mcap.writer.Writer`` / read with ``mcap.reader`` (no schemas built, no padding zeroing, no
conversion to numpy). Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_bag_io.py --views 30 --size 640x480
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from ooi_seg_ros import capture_io, msgconv
from ooi_seg_ros.core.geometry import look_at
from ooi_seg_ros.core.types import CameraIntrinsics, Capture, View


def make_capture(n: int, w: int, h: int, seed: int = 0) -> Capture:
    """Deterministic views with camera-like content (gradients + mild noise) and GT masks."""
    rng = np.random.default_rng(seed)
    cam = CameraIntrinsics(w, h, 1.1 * w, 1.1 * w, (w - 1) / 2, (h - 1) / 2)
    yy, xx = np.mgrid[:h, :w]
    views = []
    for i in range(n):
        a = 2 * np.pi * i / n
        base = np.stack([(xx + 7 * i) // 3, yy // 2, (xx + yy) // 4], -1) % 256
        img = np.clip(base + rng.normal(0, 4, base.shape), 0, 255).astype(np.uint8)
        mask = (xx - w / 2) ** 2 + (yy - h / 2) ** 2 < (h / 4) ** 2
        t = 1_700_000_000_000_000_000 + i * 100_000_000
        views.append(View(str(t), t, cam,
                          look_at(np.array([2 * np.cos(a), 2 * np.sin(a), 1.0]), np.zeros(3)),
                          img, mask))
    return Capture(views, gt_ooi_points=rng.normal(size=(2000, 3)))


def _size(p: Path) -> int:
    if p.is_file():
        return p.stat().st_size
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())


def baseline(cap: Capture, d: Path) -> tuple[float, float, int]:
    """Bare mcap + rclpy: write and read the same image/info/pose/mask messages."""
    from mcap.reader import make_reader
    from mcap.writer import Writer
    from rclpy.serialization import serialize_message

    p = d / "baseline.mcap"
    t0 = time.perf_counter()
    with open(p, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="baseline")
        sid = w.register_schema("x", "ros2msg", b"")
        chans = {k: w.register_channel(k, "cdr", sid) for k in ("img", "info", "pose", "mask")}
        for v in cap.views:
            s = v.stamp_ns
            for k, m in (("pose", msgconv.pose_to_pose_stamped(v.pose, s)),
                         ("info", msgconv.intrinsics_to_camera_info(v.camera, s)),
                         ("img", msgconv.rgb_to_image(v.image, s)),
                         ("mask", msgconv.mask_to_image(v.gt_mask, s))):
                w.add_message(chans[k], s, serialize_message(m), s)
        w.finish()
    tw = time.perf_counter() - t0
    t0 = time.perf_counter()
    with open(p, "rb") as f:
        n = sum(len(m.data) for _s, _c, m in make_reader(f).iter_messages())
    tr = time.perf_counter() - t0
    return tw, tr, n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=30)
    ap.add_argument("--size", default="640x480")
    args = ap.parse_args()
    w, h = (int(x) for x in args.size.split("x"))
    cap = make_capture(args.views, w, h)
    mb = args.views * w * h * 3 / 1e6
    print(f"{args.views} views {w}x{h} ({mb:.1f} MB of RGB), 1 thread "
          f"(OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')})")
    print(f"{'path':34s} {'write s':>8s} {'read s':>8s} {'size MB':>8s} {'ms/view w+r':>12s}")
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        tw, tr, _ = baseline(cap, d)
        print(f"{'baseline: bare mcap + rclpy bytes':34s} {tw:8.2f} {tr:8.2f} "
              f"{_size(d / 'baseline.mcap') / 1e6:8.2f} {1e3 * (tw + tr) / args.views:12.1f}")
        for name, out, kw in (("capture bag, rgb8 (zstd)", d / "raw.mcap", {}),
                              ("capture bag, png", d / "png.mcap", {"compressed": True}),
                              ("nerfstudio folder, png", d / "folder", {})):
            t0 = time.perf_counter()
            capture_io.write_capture(cap, out, **kw)
            tw = time.perf_counter() - t0
            t0 = time.perf_counter()
            back = capture_io.read_capture(out)
            for v in back.views:
                v.get_image()
            tr = time.perf_counter() - t0
            ok = all(np.array_equal(a.image, b.get_image()) for a, b in zip(cap.views, back.views))
            print(f"{name:34s} {tw:8.2f} {tr:8.2f} {_size(out) / 1e6:8.2f} "
                  f"{1e3 * (tw + tr) / args.views:12.1f}" + ("" if ok else "  IMAGES DIFFER"))


if __name__ == "__main__":
    main()
