"""Mask quality of the segmentation, paper mode vs the improved default, on simulator captures.

For every scene and seed: a simulated orbit capture with exact GT masks, an SfM-like cloud from
``seg.proxy.depth_proxy_cloud`` (textured pixels lifted with the rendered depth; the real SfM
module is not used here), then each method on the same cloud. Prints per-run and per-scene
mean IoU / precision / recall / Dice side by side, plus ablations of the improved default.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_seg_quality.py \
        --scenes aircraft tabletop bicycle toycar --seeds 0 1 --views 30 --size 160x120
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ooi_seg_ros.seg.pipeline import make_config, segment
from ooi_seg_ros.seg.proxy import depth_proxy_cloud
from ooi_seg_ros.sim import simulate_capture

VARIANTS = {
    "paper": ("paper", {}),
    "ours": ("ours", {}),
    "ours-no-refine": ("ours", {"refine": {"enabled": False}}),
    "ours-paper-floor": ("ours", {"floor": {"mode": "paper"}}),
    "ours-no-roi": ("ours", {"roi": {"enabled": False}}),
    "ours-mesh-masks": ("ours", {"masks": {"mode": "mesh"}, "refine": {"enabled": False}}),
    "ours+hull": ("ours", {"masks": {"hull_consistency": True}}),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", nargs="+", default=["aircraft", "tabletop", "bicycle", "toycar"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    ap.add_argument("--views", type=int, default=30)
    ap.add_argument("--size", default="160x120")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS))
    args = ap.parse_args()
    w, h = (int(x) for x in args.size.split("x"))
    rows = []
    print(f"{'scene':>9} {'seed':>4} {'variant':>17} {'IoU':>6} {'prec':>6} {'recall':>6} "
          f"{'Dice':>6} {'ooi pts':>7} {'time s':>6}")
    for scene in args.scenes:
        for seed in args.seeds:
            sim = simulate_capture(scene, n_views=args.views, width=w, height=h, seed=seed)
            cloud = depth_proxy_cloud(sim, 300, seed=seed)
            for name in args.variants:
                method, ov = VARIANTS[name]
                t0 = time.perf_counter()
                try:
                    r = segment(sim.capture, cloud, make_config(method, dict(ov, seed=seed)))
                    m, n = r.metrics["mean"], len(r.ooi_cloud)
                except Exception as exc:  # noqa: BLE001 -- a failed run scores zero, reported
                    print(f"{scene:>9} {seed:>4} {name:>17} failed: {exc}")
                    m, n = {"iou": 0.0, "precision": 0.0, "recall": 0.0, "dice": 0.0}, 0
                dt = time.perf_counter() - t0
                rows.append((scene, seed, name, m))
                print(f"{scene:>9} {seed:>4} {name:>17} {m['iou']:6.3f} {m['precision']:6.3f} "
                      f"{m['recall']:6.3f} {m['dice']:6.3f} {n:7d} {dt:6.1f}", flush=True)
    print("\nper-scene means over seeds (IoU / precision / recall / Dice)")
    print(f"{'variant':>17} " + " ".join(f"{s:>27}" for s in args.scenes) + f" {'mean IoU':>9}")
    for name in args.variants:
        cells, ious = [], []
        for scene in args.scenes:
            ms = [r[3] for r in rows if r[0] == scene and r[2] == name]
            mm = {k: float(np.mean([m[k] for m in ms])) for k in ms[0]}
            ious.append(mm["iou"])
            cells.append(f"{mm['iou']:.3f}/{mm['precision']:.3f}/{mm['recall']:.3f}/"
                         f"{mm['dice']:.3f}")
        print(f"{name:>17} " + " ".join(f"{c:>27}" for c in cells) + f" {np.mean(ious):9.3f}")


if __name__ == "__main__":
    main()
