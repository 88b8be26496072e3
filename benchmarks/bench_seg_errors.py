"""Where the default segmentation's mask error comes from: every wrong pixel split by cause.

Runs the default (``ours``) on the cached simulator captures of ``bench_seg_quality.py``
(same SfM clouds) and labels each false-negative and false-positive pixel with the first
cause that applies, from data the pipeline already has plus the simulator's truth:

FN (object pixel called background):
  ``outline``   within ``--outline`` px of the true outline (the simulator anti-aliases it:
                a 1-px error there is a rounding of the truth, not a segmentation fault)
  ``plane``     the plane check (``photo.py``) called the pixel floor, wall or background
                beyond the object: sure background
  ``no-seed``   outside the splatted silhouette of the OOI points: no point near it, GrabCut
                had to reach it by colour alone
  ``grabcut``   inside the silhouette, not floor: GrabCut's colour models said background
FP (background pixel called object):
  ``outline``   as above
  ``impure``    under the splat of an OOI point that is not on the object (a point is on the
                object when >= 90% of the GT masks of the views framing it contain it)
  ``halo``      inside the silhouette of the object's own points (disc halo GrabCut kept)
  ``leak``      outside every splat: GrabCut grew the mask there by colour
and, across those, how many FP pixels truly show the support plane (simulator depth: the
3D point under the pixel lies within ``--plane-tol`` x the OOI radius of the support
height) -- the pixels the plane check should have caught; and how many FN pixels lie inside a
hole of the mask (background it encloses: the spokes of a wheel between its rim and hub, what
``refine.bridges`` looks for; the truth draws a spoke 1-2 px wide, so most are ``outline``).

Prints pixels and share of the scene's total error (FN + FP) per cause, and writes an
overlay of the worst views per scene coloured by cause (``--figure``).

    OMP_NUM_THREADS=1 nice -n 19 .venv/bin/python benchmarks/bench_seg_errors.py \
        --scenes aircraft tabletop bicycle toycar --figure /tmp/seg_errors.png
    # the same on the session-5 default (before the shifted patch and the object keep)
    OMP_NUM_THREADS=1 nice -n 19 .venv/bin/python benchmarks/bench_seg_errors.py \
        --set '{"refine": {"plane_check": {"shifted": false, "object_keep": false}}}'
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_seg_quality import load_case  # noqa: E402

from ooi_seg_ros.seg import photo  # noqa: E402
from ooi_seg_ros.seg.masks import point_masks, point_radii, render_masks  # noqa: E402
from ooi_seg_ros.seg.pipeline import make_config, segment  # noqa: E402
from ooi_seg_ros.seg.refine import point_support  # noqa: E402

FN_CAUSES = ("outline", "plane", "no-seed", "grabcut")
FP_CAUSES = ("outline", "impure", "halo", "leak")
# overlay colours per cause (RGB)
COLOURS = {("fn", "plane"): (255, 200, 0), ("fn", "no-seed"): (0, 80, 255),
           ("fn", "grabcut"): (0, 220, 255), ("fn", "outline"): (120, 120, 255),
           ("fp", "impure"): (255, 0, 255), ("fp", "halo"): (255, 60, 0),
           ("fp", "leak"): (255, 0, 0), ("fp", "outline"): (255, 140, 140)}


def sim_depths(scene: str, seed: int, n_views: int, size: tuple[int, int], cache: Path,
               sim_set: Optional[dict] = None) -> tuple[np.ndarray, float, float]:
    """Simulator depth maps [V, H, W], support height and OOI radius (cached as npz)."""
    w, h = size
    tag = "".join(f"_{k}-{v}" for k, v in sorted((sim_set or {}).items()))
    path = cache / f"seg_errors_depth_{scene}_s{seed}_v{n_views}_{w}x{h}{tag}.npz"
    if path.exists():
        z = np.load(path)
        return z["depth"], float(z["support_z"]), float(z["radius"])
    from ooi_seg_ros.sim import simulate_capture
    sim = simulate_capture(scene, n_views=n_views, width=w, height=h, seed=seed,
                           **(sim_set or {}))
    summ = sim.scene.summary()
    depth = np.stack(sim.depths).astype(np.float32)
    cache.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, depth=depth, support_z=summ["support_z"],
                        radius=summ["ooi_radius"])
    return depth, float(summ["support_z"]), float(summ["ooi_radius"])


def support_pixels(view, depth: np.ndarray, support_z: float, tol: float) -> np.ndarray:
    """Bool [H, W]: the pixel's surface point lies within ``tol`` of the support height."""
    from ooi_seg_ros.seg.masks import undistorted_dirs
    c = view.camera
    d = undistorted_dirs(c)  # z = 1 camera rays: depth is the optical-axis distance
    z = depth.reshape(-1).astype(float)
    ok = np.isfinite(z) & (z > 0)
    X = view.pose.t + (d * np.where(ok, z, 0.0)[:, None]) @ view.pose.R.T
    return (ok & (np.abs(X[:, 2] - support_z) < tol)).reshape(c.height, c.width)


def outline_band(gt: np.ndarray, width: float) -> np.ndarray:
    """Pixels within ``width`` px of the boundary between object and background."""
    din = ndimage.distance_transform_edt(gt)
    dout = ndimage.distance_transform_edt(~gt)
    return (gt & (din <= width)) | (~gt & (dout <= width))


def attribute(scene: str, args) -> dict:
    """Run the default on ``scene`` and split its error pixels by cause."""
    w, h = (int(x) for x in args.size.split("x"))
    cap, cloud, _ = load_case(scene, args.seed, args.views, (w, h), "sfm", Path(args.cache),
                              jpeg=args.jpeg, sim_set=args.sim_set)
    views = cap.views
    idx = {v.key: i for i, v in enumerate(views)}
    floors: dict[int, np.ndarray] = {}
    orig = photo.PlaneConsistency.floor_maps

    def record(self, i, box, shape=None):  # the floor map of each refined crop, full frame
        fl, soft = orig(self, i, box, shape)
        y0, y1, x0, x1 = box
        full = floors.setdefault(i, np.zeros((h, w), bool))
        if fl.shape != (y1 - y0, x1 - x0):
            import cv2
            fl2 = cv2.resize(fl.astype(np.uint8), (x1 - x0, y1 - y0),
                             interpolation=cv2.INTER_NEAREST).astype(bool)
        else:
            fl2 = fl
        full[y0:y1, x0:x1] |= fl2
        return fl, soft

    keys = [v.key for v in views[::args.view_step]] if args.view_step > 1 else None
    photo.PlaneConsistency.floor_maps = record
    try:
        cfg = make_config("ours", dict(json.loads(args.set or "{}"), seed=args.seed))
        t0 = time.perf_counter()
        r = segment(cap, cloud, cfg, mask_keys=keys)
        dt = time.perf_counter() - t0
    finally:
        photo.PlaneConsistency.floor_maps = orig
    mviews = [v for v in views if v.key in r.masks]
    xyz = r.ooi_cloud.xyz
    gts = {v.key: v.gt_mask for v in views}
    on_obj = point_support(xyz, gts, views) >= 0.9
    splat, _ = render_masks(mviews, cfg.masks, r.mesh, xyz)
    # the impure points' discs with the radii the pipeline gave them (spacing in the whole
    # OOI cloud), so "under an impure point" means the same disc that seeded the silhouette
    radii = point_radii(xyz, cfg.masks.splat_k, cfg.masks.splat_scale)
    splat_bad = point_masks(xyz[~on_obj], radii[~on_obj], mviews, cfg.masks)
    depth, support_z, radius = sim_depths(scene, args.seed, args.views, (w, h),
                                          Path(args.cache), args.sim_set)
    fn = {c: 0 for c in FN_CAUSES}
    fp = {c: 0 for c in FP_CAUSES}
    fp_plane = 0
    fn_band2 = fp_band2 = 0
    fn_holes = 0
    per_view = []
    for v in mviews:
        pred, gt = r.masks[v.key], v.gt_mask
        i = idx[v.key]
        band = outline_band(gt, args.outline)
        band2 = outline_band(gt, 2.0)
        fl = floors.get(i, np.zeros_like(gt))
        S = splat[v.key]
        lab = np.zeros(gt.shape, np.uint8)  # cause index + 1 for the overlay
        miss = gt & ~pred
        left = miss.copy()
        for k, (c, m) in enumerate((("outline", band), ("plane", fl), ("no-seed", ~S),
                                    ("grabcut", np.ones_like(gt)))):
            sel = left & m
            fn[c] += int(sel.sum())
            lab[sel] = 1 + k
            left &= ~sel
        extra = pred & ~gt
        left = extra.copy()
        for k, (c, m) in enumerate((("outline", band), ("impure", splat_bad[v.key]),
                                    ("halo", S), ("leak", np.ones_like(gt)))):
            sel = left & m
            fp[c] += int(sel.sum())
            lab[sel] = 5 + k
            left &= ~sel
        sup = support_pixels(v, depth[i], support_z, args.plane_tol * radius)
        fp_plane += int((extra & sup & ~band).sum())
        fn_band2 += int((miss & band2).sum())
        # object pixels inside a hole of the mask (background it encloses): thin parts across
        # a hole, a wheel's spokes -- what ``refine.bridges`` looks for
        fn_holes += int((miss & ndimage.binary_fill_holes(pred)).sum())
        fp_band2 += int((extra & band2).sum())
        iou = r.metrics["per_view"][v.key]["iou"]
        per_view.append((iou, v.key, lab))
    per_view.sort(key=lambda t: t[0])
    return {"scene": scene, "metrics": r.metrics["mean"], "fn": fn, "fp": fp,
            "fp_support_plane": fp_plane, "fn_band2": fn_band2, "fp_band2": fp_band2,
            "fn_holes": fn_holes, "ooi_points": int(len(xyz)), "object_points": int(on_obj.sum()),
            "seconds": dt, "worst": per_view[:args.worst], "views": {v.key: v for v in mviews},
            "masks": r.masks}


def figure(results: list[dict], out: str) -> None:
    """Worst views per scene (rows), each pixel error coloured by its cause."""
    from PIL import Image
    rows = []
    for res in results:
        tiles = []
        for iou, key, lab in res["worst"]:
            img = res["views"][key].get_image().astype(float) * 0.45
            for k, c in enumerate(FN_CAUSES):
                img[lab == 1 + k] = COLOURS[("fn", c)]
            for k, c in enumerate(FP_CAUSES):
                img[lab == 5 + k] = COLOURS[("fp", c)]
            tiles.append(np.clip(img, 0, 255).astype(np.uint8))
        rows.append(np.concatenate(tiles, 1))
    wmax = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, wmax - r.shape[1]), (0, 0))) for r in rows]
    Image.fromarray(np.concatenate(rows, 0)).save(out)
    print("wrote", out, "(FN: yellow plane, blue no-seed, cyan grabcut, lilac outline; "
          "FP: magenta impure, orange halo, red leak, pink outline)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["aircraft", "tabletop", "bicycle", "toycar"])
    ap.add_argument("--seed", type=int, default=0, help="simulator seed of the captures")
    ap.add_argument("--views", type=int, default=60)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--cache", default="/tmp/ooi_seg_bench_cache_v2")
    ap.add_argument("--view-step", type=int, default=1, help="score every k-th view only")
    ap.add_argument("--jpeg", type=int, default=0, metavar="Q",
                    help="the captures through JPEG at quality Q (bench_seg_quality's cache)")
    ap.add_argument("--outline", type=float, default=1.0,
                    help="outline band half-width in px (the anti-aliased edge)")
    ap.add_argument("--plane-tol", type=float, default=0.01,
                    help="support-plane pixels: surface within this x the OOI radius of it")
    ap.add_argument("--worst", type=int, default=3, help="views per scene in the figure")
    ap.add_argument("--figure", help="write the cause overlay of the worst views here")
    ap.add_argument("--json", help="write the counts here")
    ap.add_argument("--sim-set", type=json.loads, default=None, metavar="JSON",
                    help="SimConfig options of the captures, as bench_seg_quality.py's "
                         "(e.g. '{\"hfov_deg\": 90}'; cached apart)")
    ap.add_argument("--set", metavar="JSON",
                    help='overrides of the default, e.g. the session-5 default: \'{"refine": '
                         '{"plane_check": {"shifted": false, "object_keep": false}}}\'')
    args = ap.parse_args()
    results = [attribute(s, args) for s in args.scenes]
    print(f"\nerror pixels by cause, `ours` {args.set or '(default)'}, {args.size}, "
          f"{args.views} views"
          f"{'' if args.view_step == 1 else f' (every {args.view_step}th scored)'}; "
          f"share = of the scene's FN+FP pixels")
    head = (["scene", "IoU", "recall", "FN+FP"] + [f"FN {c}" for c in FN_CAUSES]
            + [f"FP {c}" for c in FP_CAUSES] + ["FP on plane", "FN in holes", "in 2px band"])
    print(" | ".join(head))
    for res in results:
        tot = sum(res["fn"].values()) + sum(res["fp"].values())
        cell = [res["scene"], f"{res['metrics']['iou']:.3f}", f"{res['metrics']['recall']:.3f}",
                f"{tot}"]
        cell += [f"{res['fn'][c]} ({res['fn'][c] / tot:.0%})" for c in FN_CAUSES]
        cell += [f"{res['fp'][c]} ({res['fp'][c] / tot:.0%})" for c in FP_CAUSES]
        cell += [f"{res['fp_support_plane']} ({res['fp_support_plane'] / tot:.0%})",
                 f"{res['fn_holes']} ({res['fn_holes'] / tot:.0%})",
                 f"{(res['fn_band2'] + res['fp_band2']) / tot:.0%}"]
        print(" | ".join(cell))
        print(f"    OOI points {res['ooi_points']}, on the object {res['object_points']}; "
              f"worst views {[(k, round(i, 3)) for i, k, _ in res['worst']]}; "
              f"{res['seconds']:.0f} s")
    if args.figure:
        figure(results, args.figure)
    if args.json:
        Path(args.json).write_text(json.dumps(
            [{k: res[k] for k in ("scene", "metrics", "fn", "fp", "fp_support_plane",
                                  "fn_band2", "fp_band2", "fn_holes", "ooi_points",
                                  "object_points")}
             for res in results], indent=1))


if __name__ == "__main__":
    main()
