"""Mask quality of the segmentation, paper mode vs the improved default, on real SfM clouds.

For every scene and seed: a simulated orbit capture with exact GT masks and the package's own
known-pose SfM (``sfm.pipeline.reconstruct``, every view a keyframe) -- both cached under
``--cache`` (keyed by scene / seed / views / size) so reruns only pay the segmentation. Each
variant then runs on the same cloud. ``--cloud proxy`` uses the old depth-proxy cloud
(``seg.proxy``) instead. ``demo`` as a scene is the bundled bag ``bags/demo.mcap`` with the
default SfM (keyframe selection on), as ``ooi-seg segment bags/demo.mcap`` runs it.
Prints per-run and per-scene mean IoU / precision / recall / Dice side by side.
``--sfm-set JSON`` runs the SfM with ``IncrementalConfig`` overrides (its clouds cached apart,
under a name made from the overrides), e.g. ``'{"epipolar_band_matching": false}'``.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_seg_quality.py \
        --scenes aircraft tabletop bicycle toycar demo --seeds 0 --views 60 --size 320x240
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Optional

import numpy as np

from ooi_seg_ros.core.types import CameraIntrinsics, Capture, Pose, SfmCloud, View
from ooi_seg_ros.seg.pipeline import make_config, segment

ROOT = Path(__file__).resolve().parents[1]

VARIANTS = {
    "paper": ("paper", {}),
    "ours": ("ours", {}),
    "ours-no-refine": ("ours", {"refine": {"enabled": False}}),
    "ours-paper-floor": ("ours", {"floor": {"mode": "paper"}}),
    "ours-no-roi": ("ours", {"roi": {"enabled": False}}),
    "ours-mesh-masks": ("ours", {"masks": {"mode": "mesh"}, "refine": {"enabled": False}}),
    "ours+hull": ("ours", {"masks": {"hull_consistency": True}}),
    "ours+carve": ("ours", {"masks": {"hull_carve": True}}),
    "ours-no-plane": ("ours", {"refine": {"plane_check": {"enabled": False}}}),
    "ours-no-walls": ("ours", {"refine": {"plane_check": {"extra_planes": 0}}}),
    "ours-consistent": ("ours", {"refine": {"fg_seeds": "consistent", "consistency": 0.5}}),
    "ours-obs-seeds": ("ours", {"refine": {"fg_seeds": "observations"}}),
    # the default before the plane check (commit a025e30): two GrabCut passes seeded by the
    # points >= 70% of the first-pass masks hold, then the voxel-hull carve
    "ours-prev": ("ours", {"masks": {"hull_carve": True},
                           "refine": {"fg_seeds": "consistent", "consistency": 0.7,
                                      "plane_check": {"enabled": False}}}),
    "ours-grow": ("ours", {"noise": {"grow_scale": 2.0}}),
    # one DBSCAN eps of 1.5 spacings (the default until the eps widening, this round)
    "ours-single-eps": ("ours", {"noise": {"eps_scale": 1.5, "eps_max_scale": 0.0,
                                           "merge_reach_scale": 1.0}}),
    # eps widening, clusters merged only within the main cluster's own reach (x1.0)
    "ours-reach1": ("ours", {"noise": {"merge_reach_scale": 1.0}}),
    # the default of session 4 (before the behind-the-object test and the outline matting)
    "ours-s4": ("ours", {"refine": {"edge_window": 0, "max_side": 256,
                                    "plane_check": {"behind": False, "shifted": False,
                                                    "object_keep": False}}}),
    "ours-no-behind": ("ours", {"refine": {"plane_check": {"behind": False}}}),
    "ours-no-matte": ("ours", {"refine": {"edge_window": 0}}),
    # session 6 (two engineers): the shifted-patch floor test and the object-keep map; the
    # behind test's 3-px patches, GrabCut on crops up to 400 px, matting at coverage 0.4.
    # "ours-s5" = the session-5 default; the others = the new default less one change
    "ours-s5": ("ours", {"refine": {"edge_alpha": 0.5, "max_side": 256,
                                    "plane_check": {"shifted": False, "object_keep": False,
                                                    "behind_window": 0}}}),
    "ours-no-shifted": ("ours", {"refine": {"plane_check": {"shifted": False}}}),
    "ours-no-keep": ("ours", {"refine": {"plane_check": {"object_keep": False}}}),
    # session 22: the default before the plane check's object guard
    "ours-no-guard": ("ours", {"refine": {"plane_check": {"object_guard": False}}}),
    # session 23: the default before the per-pixel floor votes; the looser vote tried first
    "ours-no-pixel-votes": ("ours", {"refine": {"plane_check": {"pixel_votes": False}}}),
    "ours-pv-loose": ("ours", {"refine": {"plane_check": {"pixel_strict": False}}}),
    # session 24: no chroma-subsampling measure (unflagged JPEG pixels then get no graph cut)
    "ours-no-blend": ("ours", {"refine": {"blend_detect": False}}),
    # GrabCut at the image's own size (the default before session 25)
    "ours-up1": ("ours", {"refine": {"upsample": 1}}),
    # session 24: splat shapes that hug thin parts; radii of stray points (both trade recall)
    "ours-ellipse": ("ours", {"masks": {"splat_shape": "ellipse"}}),
    "ours-local-radii": ("ours", {"masks": {"splat_local": True}}),
    "ours+band": ("ours", {"refine": {"band_fraction": 0.3}}),
    "ours-bw5": ("ours", {"refine": {"plane_check": {"behind_window": 0}}}),
    "ours-ms256": ("ours", {"refine": {"max_side": 256}}),
    "ours-ms320": ("ours", {"refine": {"max_side": 320}}),
    "ours-a5": ("ours", {"refine": {"edge_alpha": 0.5}}),
    # S1's and S2's changes measured separately (each on top of the session-5 default)
    "ours-s6-plane": ("ours", {"refine": {"edge_alpha": 0.5, "max_side": 256,
                                          "plane_check": {"behind_window": 0}}}),
    "ours-s6-behind": ("ours", {"refine": {"plane_check": {"shifted": False,
                                                           "object_keep": False}}}),
    # session 7: the session-6 default, before the multi-view hull additions
    "ours-s6": ("ours", {"refine": {"hull_add": False}}),
    # session 7's point stage: eps widening from 1.5 spacings in steps of 0.5, the extent
    # at the first eps as the reference (no persistence test)
    "ours-s7": ("ours", {"noise": {"eps_scale": 1.5, "eps_step": 0.5, "settle_change": 0.0,
                                   "max_extent_growth": 1.5}}),
    "ours+hull-cut": ("ours", {"refine": {"hull_cut": True}}),
    "ours-hull-specks": ("ours", {"refine": {"hull_connected": False}}),
    "ours+hull-photo": ("ours", {"refine": {"hull_photo": True}}),
    # session 9: the plane check's neighbours before (4 nearest within 25 deg, 2 must match)
    "ours-s8": ("ours", {"refine": {"plane_check": {"neighbours": 4, "max_deg": 25.0,
                                                    "rank": 2}}}),
    "ours-n8r2": ("ours", {"refine": {"plane_check": {"rank": 2}}}),
}


def _save(path: Path, cap: Capture, cloud: SfmCloud) -> None:
    """Views (images, GT masks, cameras, poses) and the cloud as one npz."""
    vs = cap.views
    c = vs[0].camera
    view_index = {v.key: i for i, v in enumerate(vs)}
    cloud_views = np.array([view_index[v.key] for v in cloud.views], np.int64)
    np.savez_compressed(
        path, keys=np.array([v.key for v in vs]), stamps=np.array([v.stamp_ns for v in vs]),
        images=np.stack([v.get_image() for v in vs]),
        gt=np.stack([v.gt_mask for v in vs]) if vs[0].gt_mask is not None else np.zeros(0),
        R=np.stack([v.pose.R for v in vs]), t=np.stack([v.pose.t for v in vs]),
        cam=np.array([c.width, c.height, c.fx, c.fy, c.cx, c.cy], float),
        dist_model=np.array(c.distortion_model), dist=np.asarray(c.dist, float),
        xyz=cloud.xyz, rgb=cloud.rgb, error=cloud.error, obs_ptr=cloud.obs_ptr,
        obs_view=cloud.obs_view, obs_xy=cloud.obs_xy, cloud_views=cloud_views)


def _load(path: Path, compressed: bool = False) -> tuple[Capture, SfmCloud]:
    """Capture and cloud saved by ``_save``; ``compressed`` marks the images as JPEG'd."""
    z = np.load(path, allow_pickle=False)
    w, h, fx, fy, cx, cy = z["cam"]
    cam = CameraIntrinsics(int(w), int(h), fx, fy, cx, cy, str(z["dist_model"]), z["dist"])
    gt = z["gt"]
    rows = zip(z["keys"], z["stamps"], z["R"], z["t"], z["images"])
    views = [View(str(k), int(s), cam, Pose(R, t), img, gt[i] if len(gt) else None,
                  compressed=compressed) for i, (k, s, R, t, img) in enumerate(rows)]
    cloud = SfmCloud(z["xyz"], z["rgb"], z["error"], z["obs_ptr"], z["obs_view"], z["obs_xy"],
                     [views[i] for i in z["cloud_views"]])
    return Capture(views), cloud


CACHE_BASELINE = {"epipolar_band_matching": False}  # SfM defaults of the v2 cache's clouds


def load_case(scene: str, seed: int, n_views: int, size: tuple[int, int], source: str,
              cache: Path, refresh: bool = False,
              sfm_set: Optional[dict] = None, jpeg: int = 0, sim_set: Optional[dict] = None
              ) -> tuple[Capture, SfmCloud, dict]:
    """(capture with GT masks, cloud, info) of one case; SfM clouds are cached in ``cache``.

    ``sfm_set``: ``IncrementalConfig`` overrides (cached apart, under a name made from them).
    ``sim_set``: further ``SimConfig`` options of the simulated capture (cached apart).
    ``jpeg`` > 0: every image goes through JPEG at this quality first (as a camera or a
    ``/compressed`` image topic delivers it), for the SfM and the segmentation alike.
    """
    from ooi_seg_ros.sfm.pipeline import SfmConfig, reconstruct
    from ooi_seg_ros.sfm.incremental import IncrementalConfig
    # cache names record how the effective SfM options differ from those the v2 cache was
    # made with (band matching off then), so a changed default never reads stale clouds
    from dataclasses import asdict
    eff = asdict(IncrementalConfig(**(sfm_set or {})))
    base = dict(asdict(IncrementalConfig()), **CACHE_BASELINE)
    diff = {k: v for k, v in eff.items() if base.get(k) != v}
    tag = "_" + "_".join(f"{k}-{v}" for k, v in sorted(diff.items())) if diff else ""
    tag += f"_jpeg{int(jpeg)}" if jpeg else ""
    tag += "".join(f"_{k}-{v}" for k, v in sorted((sim_set or {}).items()))

    def sfm_config(**kw) -> SfmConfig:
        return SfmConfig(incremental=IncrementalConfig(**(sfm_set or {})), progress=False, **kw)
    w, h = size
    if scene == "demo":
        path = cache / f"seg_bench_demo{tag}.npz"
        if path.exists() and not refresh:
            cap, cloud = _load(path, compressed=jpeg > 0)
            return cap, cloud, {"cached": True}
        from ooi_seg_ros.capture_io import read_capture_and_cloud
        cap, _ = read_capture_and_cloud(ROOT / "bags" / "demo.mcap")
        cap = _jpeg(cap, jpeg)
        t0 = time.perf_counter()
        _, cloud, _ = reconstruct(cap, sfm_config())
        cache.mkdir(parents=True, exist_ok=True)
        _save(path, cap, cloud)
        return cap, cloud, {"cached": False, "sfm_s": time.perf_counter() - t0}
    from ooi_seg_ros.sim import simulate_capture
    if source == "proxy":
        from ooi_seg_ros.seg.proxy import depth_proxy_cloud
        sim = simulate_capture(scene, n_views=n_views, width=w, height=h, seed=seed)
        return sim.capture, depth_proxy_cloud(sim, 300, seed=seed), {"cached": False}
    path = cache / f"seg_bench_{scene}_s{seed}_v{n_views}_{w}x{h}{tag}.npz"
    if path.exists() and not refresh:
        cap, cloud = _load(path, compressed=jpeg > 0)
        return cap, cloud, {"cached": True}
    sim = simulate_capture(scene, n_views=n_views, width=w, height=h, seed=seed,
                           **(sim_set or {}))
    cap = _jpeg(sim.capture, jpeg)
    t0 = time.perf_counter()
    _, cloud, _ = reconstruct(cap, sfm_config(use_all_frames=True))
    cache.mkdir(parents=True, exist_ok=True)
    _save(path, cap, cloud)
    return cap, cloud, {"cached": False, "sfm_s": time.perf_counter() - t0}


def _jpeg(cap: Capture, quality: int) -> Capture:
    """``cap`` with every image through a JPEG encode / decode at ``quality`` (0: as is)."""
    if not quality:
        return cap
    import dataclasses
    import io
    from PIL import Image
    views = []
    for v in cap.views:
        bio = io.BytesIO()
        Image.fromarray(v.get_image()).save(bio, format="JPEG", quality=int(quality))
        bio.seek(0)
        img = np.asarray(Image.open(bio).convert("RGB"))
        views.append(dataclasses.replace(v, image=img, loader=None, compressed=True))
    return dataclasses.replace(cap, views=views)


def _at_scale(cap: Capture, cloud: SfmCloud, f: int) -> tuple[Capture, SfmCloud]:
    """``cap`` and ``cloud`` as a reader gives them at ``--downscale f``: images averaged
    down (box), intrinsics scaled, ground truth averaged and kept >= 0.5, the cloud's
    observations scaled (ROS pixel centres)."""
    from ooi_seg_ros.capture_io import _resize_mask, _resize_rgb
    s = 1.0 / f
    views = []
    for v in cap.views:
        cam = v.camera.scaled(s)
        size = (cam.width, cam.height)
        views.append(View(v.key, v.stamp_ns, cam, v.pose, _resize_rgb(v.get_image(), size),
                          _resize_mask(v.gt_mask, size) if v.gt_mask is not None else None,
                          compressed=v.compressed))
    idx = {v.key: i for i, v in enumerate(cap.views)}
    xy = ((cloud.obs_xy.astype(np.float64) + 0.5) * s - 0.5).astype(np.float32)
    return Capture(views), SfmCloud(cloud.xyz, cloud.rgb, cloud.error, cloud.obs_ptr,
                                    cloud.obs_view, xy, [views[idx[v.key]] for v in cloud.views])


def _enlarged_rows(r, cap: Capture, name: str, f: int) -> list[tuple[str, dict, float]]:
    """(variant name, mean metrics, worst IoU) of ``r``'s working-size masks enlarged to
    ``cap``'s size against its ground truth: bilinear, and placed by the photo (the CLI's)."""
    from ooi_seg_ros.seg.masks import mask_at_size
    from ooi_seg_ros.seg.metrics import scene_metrics
    views = {v.key: v for v in cap.views}
    gt = {k: views[k].gt_mask for k in r.masks}
    out = []
    for tag, guided in (("bl", False), ("g", True)):
        pred = {k: mask_at_size(m, (views[k].camera.width, views[k].camera.height),
                                guide=views[k].get_image() if guided else None)
                for k, m in r.masks.items()}
        sm = scene_metrics(pred, gt)
        out.append((f"{name}/{f}{tag}", sm["mean"],
                    min(pv["iou"] for pv in sm["per_view"].values())))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+",
                    default=["aircraft", "tabletop", "bicycle", "toycar", "stool", "demo"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--views", type=int, default=60)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--cloud", choices=("sfm", "proxy"), default="sfm",
                    help="sfm = the package's known-pose SfM (cached); proxy = depth proxy")
    ap.add_argument("--cache", default="/tmp/ooi_seg_bench_cache_v2",
                    help="SfM cache folder (v2: clouds of the SfM since commit 118fd9a)")
    ap.add_argument("--refresh", action="store_true", help="recompute cached SfM clouds")
    ap.add_argument("--variants", nargs="*", default=["paper", "ours"], choices=list(VARIANTS),
                    help="named variants (may be empty when --set gives the variants)")
    ap.add_argument("--set", action="append", default=[], metavar="JSON",
                    help='extra variant "name={json overrides of ours}" (repeatable)')
    ap.add_argument("--view-step", type=int, default=1,
                    help="mask every k-th view only (quick experiments; the point stages and "
                         "the plane check still see every view, via segment(mask_keys=...))")
    ap.add_argument("--sfm-set", type=json.loads, default=None, metavar="JSON",
                    help="IncrementalConfig overrides for the SfM (its clouds cached apart)")
    ap.add_argument("--json", help="write all per-run metrics here")
    ap.add_argument("--jpeg", type=int, default=0, metavar="Q",
                    help="images through JPEG at quality Q first (SfM cached apart)")
    ap.add_argument("--unflagged", action="store_true",
                    help="with --jpeg: clear the views' compressed flag, as for JPEG (or video) "
                    "frames a driver decodes and publishes as raw Images")
    ap.add_argument("--sim-set", type=json.loads, default=None, metavar="JSON",
                    help='SimConfig options of the captures, e.g. \'{"shade_subsamples": true}\''
                         " (cached apart)")
    ap.add_argument("--work-downscale", type=int, default=0, metavar="F",
                    help="also segment every case at 1/F of its size (as `ooi-seg segment "
                         "--downscale F` reads it) and score the masks enlarged back to the "
                         "capture's size: NAME/Fbl bilinear, NAME/Fg placed by the photo")
    args = ap.parse_args()
    w, h = (int(x) for x in args.size.split("x"))
    variants = {n: VARIANTS[n] for n in args.variants}
    for s in args.set:
        name, js = s.split("=", 1)
        variants[name] = ("ours", json.loads(js))
    rows = []
    print(f"{'scene':>9} {'seed':>4} {'variant':>17} {'IoU':>6} {'prec':>6} {'recall':>6} "
          f"{'Dice':>6} {'minIoU':>6} {'ooi pts':>7} {'time s':>6}")
    for scene in args.scenes:
        seeds = [0] if scene == "demo" else args.seeds
        for seed in seeds:
            cap, cloud, info = load_case(scene, seed, args.views, (w, h), args.cloud,
                                         Path(args.cache), args.refresh, args.sfm_set,
                                         args.jpeg, args.sim_set)
            if args.unflagged:
                import dataclasses
                cap = dataclasses.replace(cap, views=[dataclasses.replace(v, compressed=False)
                                                      for v in cap.views])
            keys = None
            if args.view_step > 1:
                keys = [v.key for v in cap.views[::args.view_step]]
            if not info["cached"]:
                print(f"# {scene} seed {seed}: {len(cloud)} SfM points in "
                      f"{info.get('sfm_s', 0):.0f} s (cached now)", flush=True)
            for name, (method, ov) in variants.items():
                t0 = time.perf_counter()
                try:
                    r = segment(cap, cloud, make_config(method, dict(ov, seed=seed)),
                                mask_keys=keys)
                    m, n = r.metrics["mean"], len(r.ooi_cloud)
                    worst = min(pv["iou"] for pv in r.metrics["per_view"].values())
                except Exception as exc:  # noqa: BLE001 -- a failed run scores zero, reported
                    print(f"{scene:>9} {seed:>4} {name:>17} failed: {exc}")
                    m, n, worst = {"iou": 0.0, "precision": 0.0, "recall": 0.0, "dice": 0.0}, 0, 0
                dt = time.perf_counter() - t0
                rows.append((scene, seed, name, m))
                print(f"{scene:>9} {seed:>4} {name:>17} {m['iou']:6.3f} {m['precision']:6.3f} "
                      f"{m['recall']:6.3f} {m['dice']:6.3f} {worst:6.3f} {n:7d} {dt:6.1f}",
                      flush=True)
                if args.work_downscale > 1:
                    t0 = time.perf_counter()
                    scap, scloud = _at_scale(cap, cloud, args.work_downscale)
                    r = segment(scap, scloud, make_config(method, dict(ov, seed=seed)),
                                mask_keys=keys)
                    dt = time.perf_counter() - t0
                    for vname, m, worst in _enlarged_rows(r, cap, name, args.work_downscale):
                        rows.append((scene, seed, vname, m))
                        print(f"{scene:>9} {seed:>4} {vname:>17} {m['iou']:6.3f} "
                              f"{m['precision']:6.3f} {m['recall']:6.3f} {m['dice']:6.3f} "
                              f"{worst:6.3f} {len(r.ooi_cloud):7d} {dt:6.1f}", flush=True)
    print("\nper-scene means over seeds (IoU / precision / recall / Dice)")
    print(f"{'variant':>17} " + " ".join(f"{s:>27}" for s in args.scenes)
          + f" {'mean IoU':>9} {'mean rec':>9}")
    names = list(dict.fromkeys(r[2] for r in rows))
    for name in names:
        cells, ious, recs = [], [], []
        for scene in args.scenes:
            ms = [r[3] for r in rows if r[0] == scene and r[2] == name]
            mm = {k: float(np.mean([m[k] for m in ms])) for k in ms[0]}
            ious.append(mm["iou"])
            recs.append(mm["recall"])
            cells.append(f"{mm['iou']:.3f}/{mm['precision']:.3f}/{mm['recall']:.3f}/"
                         f"{mm['dice']:.3f}")
        print(f"{name:>17} " + " ".join(f"{c:>27}" for c in cells)
              + f" {np.mean(ious):9.3f} {np.mean(recs):9.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps(
            [{"scene": r[0], "seed": r[1], "variant": r[2], **r[3]} for r in rows], indent=1))


if __name__ == "__main__":
    main()
