"""Overlay figure of the default segmentation on the cached real-SfM simulator captures.

Rows = scenes, columns = views; green = object in both, red = predicted but background,
blue = object missed. Uses the SfM cache of ``bench_seg_quality.py`` (run it first).
``--bonsai DIR`` instead draws a 2x2 sample of the masks an ``ooi-seg segment`` run wrote to
DIR on the bonsai photos (mask outline in green, background dimmed).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_seg_figure.py --out docs/seg_sim_masks.png
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_seg_figure.py --size 640x360 \
        --scenes aircraft tabletop --out docs/seg_sim_masks_640.png
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_seg_figure.py --scenes toycar \
        --seeds 1 4 5 6 --out docs/seg_toycar_seeds.png
    .venv/bin/python benchmarks/bench_seg_figure.py --bonsai OUT --out docs/seg_bonsai_masks.png
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_seg_quality import load_case  # noqa: E402

from ooi_seg_ros.seg.pipeline import make_config, segment  # noqa: E402


def colour(img: np.ndarray, pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Image dimmed, with TP green, FP red and FN blue."""
    out = img.astype(float) * 0.55
    out[pred & gt] += [0, 110, 0]
    out[pred & ~gt] += [140, 0, 0]
    out[~pred & gt] += [0, 0, 140]
    return np.clip(out, 0, 255).astype(np.uint8)


def bonsai_figure(run_dir: Path, out: str, n: int = 4) -> None:
    """2x2 grid of masks from a segment run (input.json names the source images)."""
    from scipy import ndimage
    info = json.loads((run_dir / "input.json").read_text())
    keys, srcs = info["image_keys"], info["image_sources"]
    tiles = []
    for i in np.linspace(0, len(keys) - 1, n + 1)[:n].astype(int):
        m = np.asarray(Image.open(run_dir / "masks" / f"{keys[i]}.png")) > 127
        img = np.asarray(Image.open(srcs[i]).convert("RGB").resize((m.shape[1], m.shape[0])))
        a = img.astype(float)
        a[~m] *= 0.3
        edge = m & ~ndimage.binary_erosion(m, iterations=2)
        a[edge] = [40, 255, 40]
        tiles.append(a.astype(np.uint8))
    grid = np.concatenate([np.concatenate(tiles[:2], 1), np.concatenate(tiles[2:4], 1)], 0)
    im = Image.fromarray(grid)
    im.resize((800, int(800 * grid.shape[0] / grid.shape[1]))).save(out)
    print("wrote", out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", nargs="+", default=["aircraft", "tabletop", "bicycle", "toycar"])
    ap.add_argument("--views", type=int, default=60)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0],
                    help="one row per scene and seed (simulator seed = another capture)")
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--columns", type=int, nargs="+", default=[4, 24, 44])
    ap.add_argument("--cache", default="/tmp/ooi_seg_bench_cache_v2")
    ap.add_argument("--out", default="docs/seg_sim_masks.png")
    ap.add_argument("--bonsai", help="folder of an `ooi-seg segment` run on the bonsai")
    args = ap.parse_args()
    if args.bonsai:
        bonsai_figure(Path(args.bonsai), args.out)
        return
    w, h = (int(x) for x in args.size.split("x"))
    rows = []
    for scene, seed in [(sc, sd) for sc in args.scenes for sd in args.seeds]:
        cap, cloud, _ = load_case(scene, seed, args.views, (w, h), "sfm", Path(args.cache))
        shown = [cap.views[i] for i in args.columns]
        # every view is context (point stages, plane-check neighbours); only the shown views
        # are masked -- the same masks a full run gives them
        r = segment(cap, cloud, make_config("ours", {"seed": seed}),
                    mask_keys=[v.key for v in shown])
        tiles = [colour(v.get_image(), r.masks[v.key], v.gt_mask) for v in shown]
        ious = [r.metrics["per_view"][v.key]["iou"] for v in shown]
        print(scene, "seed", seed, "shown views IoU", " ".join(f"{x:.3f}" for x in ious))
        rows.append(np.concatenate(tiles, 1))
    Image.fromarray(np.concatenate(rows, 0)).save(args.out)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
