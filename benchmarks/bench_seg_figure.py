"""Overlay figure of the default segmentation on the cached real-SfM simulator captures.

Rows = scenes, columns = views; green = object in both, red = predicted but background,
blue = object missed. Uses the SfM cache of ``bench_seg_quality.py`` (run it first).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_seg_figure.py --out docs/seg_sim_masks.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_seg_quality import load_case  # noqa: E402

from ooi_seg_ros.core.types import Capture  # noqa: E402
from ooi_seg_ros.seg.pipeline import make_config, segment  # noqa: E402


def colour(img: np.ndarray, pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Image dimmed, with TP green, FP red and FN blue."""
    out = img.astype(float) * 0.55
    out[pred & gt] += [0, 110, 0]
    out[pred & ~gt] += [140, 0, 0]
    out[~pred & gt] += [0, 0, 140]
    return np.clip(out, 0, 255).astype(np.uint8)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", nargs="+", default=["aircraft", "tabletop", "bicycle", "toycar"])
    ap.add_argument("--views", type=int, default=60)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--columns", type=int, nargs="+", default=[4, 24, 44])
    ap.add_argument("--cache", default="/tmp/ooi_seg_bench_cache")
    ap.add_argument("--out", default="docs/seg_sim_masks.png")
    args = ap.parse_args()
    w, h = (int(x) for x in args.size.split("x"))
    rows = []
    for scene in args.scenes:
        cap, cloud, _ = load_case(scene, 0, args.views, (w, h), "sfm", Path(args.cache))
        sub = Capture([cap.views[i] for i in args.columns])
        r = segment(sub, cloud, make_config("ours"))
        tiles = [colour(v.get_image(), r.masks[v.key], v.gt_mask) for v in sub.views]
        ious = [r.metrics["per_view"][v.key]["iou"] for v in sub.views]
        print(scene, " ".join(f"{x:.3f}" for x in ious))
        rows.append(np.concatenate(tiles, 1))
    Image.fromarray(np.concatenate(rows, 0)).save(args.out)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
