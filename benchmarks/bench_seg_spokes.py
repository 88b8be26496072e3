"""Where a thin-structured object's missed pixels lie, and what ``refine.bridges`` (or a line
search, an experiment kept here, not in the package) adds inside the holes of the masks.

Runs the default (``ours``) with ``refine.bridges`` off on ``bench_seg_quality.py``'s cached
simulator capture (same SfM clouds, every ``--view-step``-th view scored), keeps those final
masks (``--cache``, so variants can be compared without segmenting again) and then, per
variant, adds what it finds inside the holes of each mask and prints, pooled over the scored
views:

- IoU / recall after the addition (pooled, so IoU differs slightly from the per-view mean that
  ``bench_seg_quality.py`` prints);
- added pixels that are right (on the truth), adjacent (one pixel off it) or far;
- object pixels missed inside holes of the masks before and after.

Variants: ``none``; ``pass`` (``refine.bridges`` with its options, ``--set`` JSON overrides of
``BridgeConfig``); ``line`` (a search per hole over every angle and offset of a straight chord
from the mask to the mask, each chord scored by its mean line response against the other
chords at its angle: median + ``--k-mad`` MADs; session 67); ``union`` (both).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_seg_spokes.py --scene bicycle --seed 0 \\
        --size 320x240 --variants none pass line union
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_seg_quality import load_case  # noqa: E402
from ooi_seg_ros.seg.pipeline import make_config, segment  # noqa: E402
from ooi_seg_ros.seg.thin import BridgeConfig, line_response, thin_bridges  # noqa: E402


def line_search(img: np.ndarray, mask: np.ndarray, k_mad: float = 8.0, n_dir: int = 12,
                angles: int = 90, step: float = 0.5, min_len: float = 16.0,
                floor: float = 10.0, min_hole: int = 81, nms_share: float = 0.3
                ) -> np.ndarray:
    """Pixels of straight chords across the holes of ``mask`` found by an exhaustive search.

    Per hole: every line at ``angles`` directions over 180 degrees and offsets ``step`` px
    apart through the hole's box; each run of the line inside the hole that starts and ends
    at the mask and is at least ``min_len`` px long is a chord, scored by the mean line
    response (``thin.line_response``, the direction interpolated between its bins, the
    position bilinearly) along it, 1 px in from each end. A chord is kept when its score
    exceeds the median of the chords at its angle by ``k_mad`` scaled MADs (and ``floor``);
    the best first, a chord whose pixels mostly touch a kept one is dropped, and each kept
    chord is drawn one pixel per step, every pixel moved to the best response of the three
    across it (the ridge).
    """
    mask = np.asarray(mask, bool)
    h, w = mask.shape
    added = np.zeros_like(mask)
    holes = ndimage.binary_fill_holes(mask) & ~mask
    lab, n = ndimage.label(holes)
    if n == 0:
        return added
    area = np.bincount(lab.ravel())
    rs = line_response(img, 9, 2, n_dir)
    taken = np.zeros_like(mask)
    for hole, sl in enumerate(ndimage.find_objects(lab), start=1):
        if area[hole] < min_hole:
            continue
        ho = lab == hole
        cy = (sl[0].start + sl[0].stop - 1) / 2.0
        cx = (sl[1].start + sl[1].stop - 1) / 2.0
        rad = 0.5 * np.hypot(sl[0].stop - sl[0].start, sl[1].stop - sl[1].start) + 2
        ts = np.arange(-rad, rad + 1e-9, step)
        rhos = np.arange(-rad, rad + 1e-9, step)
        chords = []  # (angle index, rho, t0, t1, score)
        for k in range(angles):
            th = np.pi * k / angles
            u = np.array([np.cos(th), np.sin(th)])
            nv = np.array([-u[1], u[0]])
            X = cx + rhos[:, None] * nv[0] + ts[None, :] * u[0]
            Y = cy + rhos[:, None] * nv[1] + ts[None, :] * u[1]
            xi, yi = np.rint(X).astype(int), np.rint(Y).astype(int)
            inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
            xc, yc = np.clip(xi, 0, w - 1), np.clip(yi, 0, h - 1)
            inh = inside & ho[yc, xc]
            inm = inside & mask[yc, xc]
            b = th / np.pi * n_dir
            b0 = int(np.floor(b)) % n_dir
            wb = b - np.floor(b)
            Xc, Yc = np.clip(X, 0, w - 1.001), np.clip(Y, 0, h - 1.001)
            xf, yf = np.floor(Xc).astype(int), np.floor(Yc).astype(int)
            ax, ay = Xc - xf, Yc - yf

            def bil(r: np.ndarray) -> np.ndarray:
                return ((1 - ax) * (1 - ay) * r[yf, xf] + ax * (1 - ay) * r[yf, xf + 1]
                        + (1 - ax) * ay * r[yf + 1, xf] + ax * ay * r[yf + 1, xf + 1])
            val = (1 - wb) * bil(rs[b0]) + wb * bil(rs[(b0 + 1) % n_dir])
            skip = int(round(1.0 / step))
            for p in np.nonzero(inh.any(1))[0]:
                d = np.diff(np.concatenate([[0], inh[p].astype(np.int8), [0]]))
                for a, e in zip(np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]):
                    if (e - a) * step < min_len or a == 0 or e >= len(ts):
                        continue
                    if not (inm[p, a - 1] and inm[p, e]):
                        continue  # a chord runs from the mask to the mask
                    v = val[p, a + skip:e - skip]
                    if len(v) >= 3:
                        chords.append((k, rhos[p], ts[a], ts[e - 1], float(v.mean())))
        if not chords:
            continue
        c = np.array(chords)
        thr = np.full(len(c), np.inf)
        for k in range(angles):
            sel = c[:, 0] == k
            if sel.sum() >= 5:
                s = c[sel, 4]
                med = np.median(s)
                thr[sel] = max(med + k_mad * 1.4826 * np.median(np.abs(s - med)), floor)
        idx = np.nonzero(c[:, 4] > thr)[0]
        for i in idx[np.argsort(-(c[idx, 4] - thr[idx]))]:
            th = np.pi * c[i, 0] / angles
            u = np.array([np.cos(th), np.sin(th)])
            nv = np.array([-u[1], u[0]])
            t = np.arange(c[i, 2], c[i, 3] + 1e-9, max(abs(u[0]), abs(u[1])))
            px = np.rint(cx + c[i, 1] * nv[0] + t * u[0]).astype(int)
            py = np.rint(cy + c[i, 1] * nv[1] + t * u[1]).astype(int)
            ok = (px >= 0) & (px < w) & (py >= 0) & (py < h)
            px, py = px[ok], py[ok]
            if not len(px):
                continue
            best = np.maximum.reduce([rs[(int(np.rint(th / np.pi * n_dir)) + d) % n_dir]
                                      for d in (-1, 0, 1)])
            sx, sy = int(np.rint(nv[0])), int(np.rint(nv[1]))
            cxs = np.stack([np.clip(px + j * sx, 0, w - 1) for j in (-1, 0, 1)])
            cys = np.stack([np.clip(py + j * sy, 0, h - 1) for j in (-1, 0, 1)])
            kk = best[cys, cxs].argmax(0)
            px, py = cxs[kk, np.arange(len(kk))], cys[kk, np.arange(len(kk))]
            if taken[py, px].mean() > nms_share:
                continue
            added[py, px] = True
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    taken[np.clip(py + dy, 0, h - 1), np.clip(px + dx, 0, w - 1)] = True
    return added & holes


def final_masks(args) -> dict:
    """{key: (image, mask with the bridges off, truth)} of the scored views (cached)."""
    w, h = (int(x) for x in args.size.split("x"))
    path = Path(args.cache) / f"spokes_{args.scene}_s{args.seed}_{w}x{h}_step{args.view_step}.npz"
    cap, cloud, _ = load_case(args.scene, args.seed, args.views, (w, h), "sfm", Path(args.cache))
    views = cap.views
    keys = [v.key for v in views[::args.view_step]]
    if path.exists():
        z = np.load(path)
        masks = {k: z[k] for k in keys}
    else:
        cfg = make_config("ours", {"seed": args.seed, "refine": {"bridges": {"enabled": False}}})
        r = segment(cap, cloud, cfg, mask_keys=keys)
        masks = r.masks
        np.savez_compressed(path, **masks)
    return {v.key: (v.get_image(), masks[v.key], v.gt_mask) for v in views if v.key in masks}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="bicycle")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--views", type=int, default=60)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--view-step", type=int, default=2)
    ap.add_argument("--cache", default="/tmp/ooi_seg_bench_cache_v2")
    ap.add_argument("--variants", nargs="+", default=["none", "pass", "line", "union"],
                    choices=["none", "pass", "line", "union"])
    ap.add_argument("--set", type=json.loads, default={}, metavar="JSON",
                    help="BridgeConfig overrides for pass/union, e.g. '{\"q_high\": 94}'")
    ap.add_argument("--k-mad", type=float, default=8.0, help="line: MADs over the median")
    args = ap.parse_args()
    t0 = time.perf_counter()
    data = final_masks(args)
    print(f"{args.scene} seed {args.seed} {args.size}: {len(data)} views scored, masks in "
          f"{time.perf_counter() - t0:.0f} s (bridges off)")
    cfg = BridgeConfig(**dict({"enabled": True}, **args.set))
    print("variant | IoU | recall | added right / adjacent / far | missed in holes | s")
    for name in args.variants:
        t0 = time.perf_counter()
        tp = fp = fn = right = adj = far = miss_h = 0
        for img, m, g in data.values():
            add = np.zeros_like(m)
            if name in ("pass", "union"):
                add |= thin_bridges(img, m, cfg)[0]
            if name in ("line", "union"):
                add |= line_search(img, m, args.k_mad)
            m2 = m | add
            near = ndimage.binary_dilation(g, np.ones((3, 3), bool))
            tp += int((m2 & g).sum())
            fp += int((m2 & ~g).sum())
            fn += int((~m2 & g).sum())
            right += int((add & g).sum())
            adj += int((add & ~g & near).sum())
            far += int((add & ~near).sum())
            miss_h += int((g & ~m2 & ndimage.binary_fill_holes(m)).sum())
        print(f"{name} | {tp / (tp + fp + fn):.4f} | {tp / (tp + fn):.4f} | "
              f"{right} / {adj} / {far} | {miss_h} | {time.perf_counter() - t0:.0f}")


if __name__ == "__main__":
    main()
