"""How one segmentation setting changes the real bonsai's masks against another (no ground truth).

The Mip-NeRF 360 bonsai in ``../shared/data/mipnerf360-bonsai`` has no true masks, so a change
that the simulator scores as a gain has to be looked at there. This reads the reference COLMAP
model once (at ``--downscale``), runs ``segment`` under ``ours`` and under each ``--set``
override (the same capture and cloud), and prints for each override: OOI points, how many
masks change by more than 5% / 10% of their pixels, and the pixels that join and leave in all
views. ``--figure PNG`` draws the ``--show`` views that change most (each override's first
variant against ``ours``: green = joined under the override, red = left), for judging by eye
whether what joins is tree, pot and stand or cloth, wall and floor.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_seg_bonsai_diff.py --downscale 2 \\
        --set 'rel={"density":{"drop_fraction":0,"relative_cut":0.1}}' --figure /tmp/diff.png
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

BONSAI = ROOT.parent / "shared" / "data" / "mipnerf360-bonsai"


def change(base: dict, other: dict) -> dict:
    """Per-view and total pixel changes of the masks ``other`` against ``base``."""
    joined = left = 0
    frac = {}
    for k, m in base.items():
        o = other[k]
        j, lft = int((o & ~m).sum()), int((m & ~o).sum())
        joined += j
        left += lft
        frac[k] = (j + lft) / max(1, int(m.sum()))
    f = np.array(list(frac.values()))
    return {"joined": joined, "left": left, "over5": int((f > 0.05).sum()),
            "over10": int((f > 0.10).sum()), "frac": frac}


def figure(path: Path, cap, base: dict, other: dict, frac: dict, n: int) -> None:
    """The ``n`` views that change most: photo, green = joined, red = left, grey = both."""
    from PIL import Image
    keys = sorted(frac, key=lambda k: -frac[k])[:n]
    views = {v.key: v for v in cap.views}
    tiles = []
    for k in keys:
        img = views[k].get_image().astype(np.float32)
        if img.max() <= 1.0:
            img = img * 255.0
        b, o = base[k], other[k]
        out = img * 0.45
        out[b & o] = img[b & o] * 0.8 + np.array([60, 60, 60]) * 0.2
        out[o & ~b] = np.array([40, 230, 40])
        out[b & ~o] = np.array([230, 40, 40])
        tiles.append(np.hstack([img, out]).clip(0, 255).astype(np.uint8))
    h = max(t.shape[0] for t in tiles)
    tiles = [np.pad(t, ((0, h - t.shape[0]), (0, 0), (0, 0))) for t in tiles]
    Image.fromarray(np.vstack(tiles)).save(path)
    print(f"figure: {path} (views {', '.join(keys)})")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=BONSAI)
    ap.add_argument("--downscale", type=float, default=2.0)
    ap.add_argument("--set", action="append", default=[], metavar="NAME=JSON",
                    help="override of ours to compare with ours (repeatable)")
    ap.add_argument("--figure", type=Path, help="PNG of the most-changed views (first --set)")
    ap.add_argument("--show", type=int, default=4)
    ap.add_argument("--save", type=Path, help="write every run's masks here (npz per run)")
    a = ap.parse_args(argv)
    if not a.set:
        ap.error("give at least one --set NAME=JSON to compare with ours")
    from ooi_seg_ros.seg.pipeline import make_config, segment
    from ooi_seg_ros.sfm.colmap_io import load_colmap_model
    t0 = time.perf_counter()
    cap, cloud, *_ = load_colmap_model(a.data / "sparse" / "0", a.data / "images", a.downscale)
    print(f"{len(cap.views)} views, {len(cloud)} points, read in {time.perf_counter() - t0:.0f} s")
    runs = {"ours": {}}
    runs.update({s.split("=", 1)[0]: json.loads(s.split("=", 1)[1]) for s in a.set})
    masks = {}
    print(f"{'variant':>10} {'ooi pts':>7} {'>5%':>4} {'>10%':>4} {'joined px':>10} "
          f"{'left px':>9} {'time s':>6}", flush=True)
    for name, ov in runs.items():
        t0 = time.perf_counter()
        r = segment(cap, cloud, make_config("ours", ov))
        dt = time.perf_counter() - t0
        masks[name] = r.masks
        if a.save:
            a.save.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(a.save / f"{name}.npz", **r.masks)
        c = change(masks["ours"], r.masks)
        print(f"{name:>10} {len(r.ooi_cloud):7d} {c['over5']:4d} {c['over10']:4d} "
              f"{c['joined']:10d} {c['left']:9d} {dt:6.0f}", flush=True)
        if a.figure and name == list(runs)[1]:
            figure(a.figure, cap, masks["ours"], r.masks, c["frac"], a.show)
    return 0


if __name__ == "__main__":
    sys.exit(main())
