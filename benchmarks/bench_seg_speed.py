"""Per-stage segmentation time vs cloud size, and mask rendering cost, next to naive baselines.

Synthetic clouds of N points (a textured-floor plane, an object shell, background clutter) seen
by a 60-camera orbit at 640x480. Each stage runs on the full N-point cloud. Baselines: a plain
scikit-learn Gaussian KDE fitted to and scored on the whole cloud (O(N^2); measured at small N
and extrapolated quadratically, marked "~"), and per-pixel brute-force mask rendering (every
pixel tested against every projected point disc, no acceleration; measured on one view).
The noise stage runs with the default ("ours") options, eps widening included.

``--pipeline SCENE:WxH ...`` also times the whole default ``segment()`` per stage (ROI ...
refinement with the plane check) on the quality bench's cached SfM captures (60 views; run
bench_seg_quality.py once to fill the cache). Wall times are printed with the process CPU
time and the load average: run it under ``flock /tmp/ooi_timing.lock`` on a shared box.

    OMP_NUM_THREADS=1 flock /tmp/ooi_timing.lock .venv/bin/python benchmarks/bench_seg_speed.py \
        --sizes 10000 100000 --pipeline aircraft:320x240 aircraft:640x360

``--pipeline-set NAME=JSON`` times a variant (overrides of ``ours``) right after the default
on each capture, ``--repeats`` times in turn; ``--sizes`` with no value skips the clouds:

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_seg_speed.py --sizes \
        --pipeline aircraft:320x240 --pipeline-set 'it2={"refine": {"iterations": 2}}'
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np

from ooi_seg_ros.core.geometry import look_at
from ooi_seg_ros.core.types import CameraIntrinsics, SfmCloud, View
from ooi_seg_ros.seg.density import DensityConfig, density_filter
from ooi_seg_ros.seg.floor import FloorConfig, floor_filter
from ooi_seg_ros.seg.masks import MaskConfig, mesh_masks, point_masks, point_radii
from ooi_seg_ros.seg.mesh import MeshConfig, build_mesh
from ooi_seg_ros.seg.noise import noise_filter
from ooi_seg_ros.seg.pipeline import make_config, segment
from ooi_seg_ros.seg.roi import RoiConfig, roi_filter


def make_cloud(n: int, seed: int = 0) -> np.ndarray:
    """[n,3]: 60% floor plane, 15% object shell (radius 1 at z=1), 25% clutter."""
    rng = np.random.default_rng(seed)
    nf, no = int(0.6 * n), int(0.15 * n)
    floor = np.c_[rng.uniform(-10, 10, (nf, 2)), rng.normal(0, 0.005, nf)]
    s = rng.normal(size=(no, 3))
    obj = s / np.linalg.norm(s, axis=1, keepdims=True) + [0, 0, 1.05]
    clutter = rng.uniform([-10, -10, 0], [10, 10, 4], (n - nf - no, 3))
    return np.vstack([floor, obj, clutter])


def make_views(n: int, w: int = 640, h: int = 480) -> list[View]:
    cam = CameraIntrinsics(w, h, 0.8 * w, 0.8 * w, (w - 1) / 2, (h - 1) / 2)
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        eye = np.array([6 * np.cos(a), 6 * np.sin(a), 3.0])
        out.append(View(f"v{k}", k, cam, look_at(eye, np.array([0, 0, 1.0]))))
    return out


def load_note() -> str:
    """Load average and this process's CPU seconds so far (timings on a shared box)."""
    la = os.getloadavg()
    return f"load {la[0]:.2f}/{la[1]:.2f}, process CPU {time.process_time():.0f} s"


def pipeline_timings(cases: list[str], cache: str, variants: Optional[dict] = None,
                     repeats: int = 1) -> None:
    """Per-stage seconds of the default segment() on cached SfM captures; with ``variants``
    ({name: overrides of ``ours``}) each variant runs right after the default on the same
    capture, ``repeats`` times in turn (alternating, so load drifts hit both alike)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_seg_quality import load_case
    stages = ["roi", "floor", "density", "noise", "mesh", "masks", "refine"]
    runs = {"default": {}, **(variants or {})}
    print("\nwhole segment(), 60 views (seconds per stage; plane check inside refine)")
    print(f"{'case':>18} {'variant':>10} " + " ".join(f"{s:>8}" for s in stages)
          + f" {'plane':>7} {'total':>7} {'CPU s':>7}  load   IoU")
    for case in cases:
        scene, size = case.split(":")
        w, h = (int(x) for x in size.split("x"))
        cap, cloud, _ = load_case(scene, 0, 60, (w, h), "sfm", Path(cache))
        for _ in range(max(1, repeats)):
            for name, over in runs.items():
                cpu0 = time.process_time()
                r, t = timed(lambda: segment(cap, cloud, make_config("ours", over)))
                cpu = time.process_time() - cpu0
                plane = r.params.get("refine", {}).get("plane_check_s", float("nan"))
                la = os.getloadavg()
                iou = (r.metrics or {}).get("mean", {}).get("iou", float("nan"))
                print(f"{case:>18} {name:>10} "
                      + " ".join(f"{r.timings.get(s, float('nan')):8.2f}" for s in stages)
                      + f" {plane:7.2f} {t:7.2f} {cpu:7.2f}  {la[0]:.2f}  {iou:.3f}",
                      flush=True)


CPU: list[float] = []  # CPU seconds of each timed() call, in call order


def timed(fn):
    """(result, wall seconds); the call's process CPU seconds are appended to ``CPU``."""
    c0, t0 = time.process_time(), time.perf_counter()
    res = fn()
    CPU.append(time.process_time() - c0)
    return res, time.perf_counter() - t0


def naive_mask(xyz: np.ndarray, radii: np.ndarray, view: View) -> np.ndarray:
    """Every pixel against every projected disc (no acceleration)."""
    from ooi_seg_ros.core.geometry import project
    c = view.camera
    uv, z = project(xyz, c, view.pose)
    r = radii * c.fx / z
    uu, vv = np.meshgrid(np.arange(c.width, dtype=np.float32), np.arange(c.height,
                                                                         dtype=np.float32))
    pix = np.c_[uu.ravel(), vv.ravel()]
    hit = np.zeros(len(pix), bool)
    for s in range(0, len(pix), 4096):
        d2 = ((pix[s:s + 4096, None, :] - uv[None].astype(np.float32)) ** 2).sum(-1)
        hit[s:s + 4096] = (d2 <= (r ** 2)[None]).any(1)
    return hit.reshape(c.height, c.width)


def primitives(repeats: int = 200) -> None:
    """The refinement's hottest numpy primitives next to the form they replaced, same inputs,
    same process: the rigid transform of a crop's points (``to_camera`` vs ``[N, 3] @ R.T +
    t``) and the plane check's box means (``cv2.boxFilter`` vs ``ndimage.uniform_filter``,
    float32), session 26; the plane check's remap coordinates of a crop's points in a
    neighbour (float32 from a ``PointSet`` vs float64 ``project_distorted``), session 27
    (max |diff| in px); the hull additions' voxel grid voted on by a view's mask, the same
    two ways, session 28 (max change of a vote: 0 = the same votes)."""
    import cv2
    from scipy import ndimage

    from ooi_seg_ros.core.geometry import to_camera
    rng = np.random.default_rng(0)
    pose = make_views(1)[0].pose
    r_cw, t_cw = pose.world_to_cam()
    print(f"\n{'primitive':<34} {'before ms':>10} {'now ms':>8} {'ratio':>6} {'max |diff|':>11}")
    for n in (5000, 50000, 1000000):
        x = rng.random((n, 3))
        before = (lambda: x @ r_cw.T + t_cw)
        _row(f"camera frame, N={n}", before, lambda: to_camera(x, pose),
             repeats if n < 500000 else 10, lambda: np.stack(to_camera(x, pose), 1))
    for h, w, win in ((240, 320, 5), (400, 400, 5), (240, 320, 3)):
        a = (rng.random((h, w)) * 255).astype(np.float32)
        _row(f"box mean {w}x{h}, window {win}",
             lambda: ndimage.uniform_filter(a, win, mode="nearest"),
             lambda: cv2.boxFilter(a, -1, (win, win), borderType=cv2.BORDER_REPLICATE),
             repeats)
    # session 27: the plane check's remap coordinates of a crop's 3D points in a neighbour,
    # float64 (``project_distorted``, then cast) vs float32 from a prepared ``PointSet``
    import dataclasses
    from ooi_seg_ros.seg.masks import project_distorted
    from ooi_seg_ros.seg.photo import PointSet
    views = make_views(2)
    cam_i, pose_j = views[0].camera, views[1].pose
    for n, dist in ((50000, (0.0,) * 5), (90000, (0.0,) * 5),
                    (90000, (-0.1, 0.02, 0.0, 0.0, 0.0))):
        cam = dataclasses.replace(cam_i, dist=np.array(dist), distortion_model="plumb_bob")
        # points near the object the cameras orbit, as the crops' plane / depth points are
        X = np.array([0.0, 0.0, 1.0]) + rng.normal(0.0, 0.5, (n, 3))
        hit = rng.random(n) > 0.05

        def old_maps():
            uv, z = project_distorted(X, cam, pose_j)
            ok = hit & (z > 0) & np.isfinite(uv[:, 0]) & np.isfinite(uv[:, 1])
            ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1)
            ok &= (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height - 1)
            return np.where(ok, uv[:, 0], -1.0).astype(np.float32), ok

        pts = PointSet(X, hit)

        def new_maps():
            u, v, z = pts.project(cam, pose_j)
            with np.errstate(invalid="ignore"):
                ok = pts.hit & (z > 0) & (u >= 0) & (u <= cam.width - 1)
                ok &= (v >= 0) & (v <= cam.height - 1)
            u[~ok] = -1.0
            v[~ok] = -1.0
            return u, ok
        tag = "distorted" if any(dist) else "pinhole"
        _row(f"sample coords N={n // 1000}k {tag}", lambda: old_maps()[0],
             lambda: new_maps()[0], max(10, repeats // 10))
        t0 = time.perf_counter()
        for _ in range(10):
            PointSet(X, hit)
        once = (time.perf_counter() - t0) * 100
        print(f"{'  + PointSet, once per crop':<34} {'':>10} {once:>8.3f}"
              f"   (shared by the crop's ~8 neighbours)")
    # session 28: the hull additions' voxel grid (up to ``hull_max_voxels`` centres) voted
    # on by every view's mask: float64 ``project_distorted`` vs float32 from a ``PointSet``
    # made once per capture; the row's diff is the largest change of a voxel's vote
    cam = views[0].camera
    mask = np.zeros((cam.height, cam.width), bool)
    mask[cam.height // 4:3 * cam.height // 4, cam.width // 4:3 * cam.width // 4] = True
    for side in (50, 100):
        ax = np.linspace(-0.6, 0.6, side)
        grid = np.stack(np.meshgrid(ax, ax, ax + 1.0, indexing="ij"), -1).reshape(-1, 3)

        def votes(u, w, z):
            ui, vi = np.rint(u), np.rint(w)
            with np.errstate(invalid="ignore"):
                ok = (z > 1e-9) & (ui >= 0) & (ui < cam.width) & (vi >= 0) & (vi < cam.height)
            out = np.full(len(grid), -1, np.int8)
            out[ok] = mask[vi[ok].astype(int), ui[ok].astype(int)]
            return out

        def old_votes():
            uv, z = project_distorted(grid, cam, pose_j)
            return votes(uv[:, 0], uv[:, 1], z)
        cells = PointSet(grid, np.ones(len(grid), bool))
        _row(f"hull grid votes, {side ** 3 // 1000}k voxels", old_votes,
             lambda: votes(*cells.project(cam, pose_j)), max(5, repeats // 40))


def _row(name: str, before, now, repeats: int, now_array=None) -> None:
    times = []
    for fn in (before, now, before, now):  # interleaved: load changes hit both
        fn()
        t0 = time.perf_counter()
        for _ in range(repeats):
            fn()
        times.append((time.perf_counter() - t0) / repeats * 1e3)
    tb, tn = min(times[0], times[2]), min(times[1], times[3])
    diff = float(np.abs(np.asarray(before()) - np.asarray((now_array or now)())).max())
    print(f"{name:<34} {tb:>10.3f} {tn:>8.3f} {tb / tn:>5.1f}x {diff:>11.2e}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--primitives", action="store_true",
                    help="only time the refinement's numpy primitives against their old form")
    ap.add_argument("--sizes", nargs="*", type=int, default=[10000, 100000, 1000000],
                    help="cloud sizes of the per-stage table (none: only --pipeline)")
    ap.add_argument("--sklearn-sizes", nargs="+", type=int, default=[5000, 10000, 20000])
    ap.add_argument("--mask-views", type=int, default=300)
    ap.add_argument("--pipeline", nargs="*", default=[], metavar="SCENE:WxH",
                    help="also time the whole default segment() on these cached captures")
    ap.add_argument("--pipeline-set", action="append", default=[], metavar="NAME=JSON",
                    help="--pipeline: also time this variant (overrides of ours) next to the "
                         "default on each capture (repeatable)")
    ap.add_argument("--repeats", type=int, default=1,
                    help="--pipeline: runs of the default and each variant, in turn")
    ap.add_argument("--cache", default="/tmp/ooi_seg_bench_cache_v2",
                    help="bench_seg_quality.py's SfM cache")
    args = ap.parse_args()
    if args.primitives:
        primitives()
        return
    variants = {}
    for item in args.pipeline_set:
        name, _, js = item.partition("=")
        variants[name] = json.loads(js)
    if not args.sizes:
        pipeline_timings(args.pipeline, args.cache, variants, args.repeats)
        return
    noise_cfg = make_config("ours").noise
    print(load_note())
    views = make_views(60)
    centers = np.array([v.pose.t for v in views])
    up = np.array([0, 0, 1.0])
    target = np.array([0, 0, 1.0])
    print("baseline: plain sklearn KDE over the whole cloud")
    sk = {}
    for n in args.sklearn_sizes:
        x = make_cloud(n)
        _, t = timed(lambda: density_filter(x, DensityConfig(method="sklearn", n_subsets=1,
                                                             subset_fraction=1.0)))
        sk[n] = t
        print(f"  N={n:>8}  {t:8.2f} s")
    n0 = max(sk)
    print(f"\n{'N':>8} {'roi':>7} {'floor/p':>8} {'floor/s':>8} {'density':>8} {'sklearnKDE':>11} "
          f"{'noise':>7} {'mesh':>7}  (seconds; ~ = extrapolated N^2)")
    ooi = None
    cpu_rows = []
    for n in args.sizes:
        x = make_cloud(n)
        CPU.clear()
        _, t_roi = timed(lambda: roi_filter(x, views, target, RoiConfig()))
        _, t_fp = timed(lambda: floor_filter(x, FloorConfig(mode="paper"), centers, up, target))
        (keep, _), t_fs = timed(lambda: floor_filter(x, FloorConfig(mode="support"), centers,
                                                     up, target))
        _, t_d = timed(lambda: density_filter(x, DensityConfig()))
        xs = x[keep]
        (k2, pn), t_n = timed(lambda: noise_filter(xs, noise_cfg, target, 3.0))
        cloud = SfmCloud.from_points(xs[k2])
        cloud.views = views
        (mesh, _), t_m = timed(lambda: build_mesh(cloud, MeshConfig(poisson_depth=8)))
        sk_est = sk[n] if n in sk else sk[n0] * (n / n0) ** 2
        mark = "" if n in sk else "~"
        print(f"{n:>8} {t_roi:7.2f} {t_fp:8.2f} {t_fs:8.2f} {t_d:8.2f} {mark:>1}{sk_est:10.1f} "
              f"{t_n:7.2f} {t_m:7.2f}   [{load_note()}; DBSCAN {pn.get('dbscan')}]", flush=True)
        cpu_rows.append((n, list(CPU)))
        if ooi is None or n == 100000:
            ooi, ooi_mesh = cloud.xyz, mesh
    # CPU seconds do not depend on the load of a shared box: the scaling is read from these
    print(f"\n{'N':>8} {'roi':>7} {'floor/p':>8} {'floor/s':>8} {'density':>8} {'noise':>7} "
          f"{'mesh':>7}  (process CPU seconds; growth vs the previous N, N log N in brackets)")
    prev = None
    for n, c in cpu_rows:
        line = f"{n:>8} " + " ".join(f"{v:7.2f}" for v in c)
        if prev is not None:
            nlogn = (n * np.log(n)) / (prev[0] * np.log(prev[0]))
            line += "   x" + " x".join(f"{a / max(b, 1e-9):.1f}" for a, b in zip(c, prev[1]))
            line += f"   [N log N: x{nlogn:.1f}]"
        print(line)
        prev = (n, c)
    mv = make_views(args.mask_views)
    sub = ooi[np.random.default_rng(0).choice(len(ooi), min(len(ooi), 5000), replace=False)]
    radii = point_radii(sub, 4, 0.6)
    cfg = MaskConfig(closing_kernel=5)
    _, t_mesh = timed(lambda: mesh_masks(ooi_mesh, mv, cfg))
    _, t_pts = timed(lambda: point_masks(sub, radii, mv, cfg))
    m_naive, t_naive = timed(lambda: naive_mask(sub, radii, mv[0]))
    m_fast = point_masks(sub, radii, mv[:1], MaskConfig(closing_kernel=1))["v0"]
    agree = (m_naive == m_fast).mean()
    print(f"\nmasks for {len(mv)} views at 640x480 ({len(sub)} OOI points, mesh with "
          f"{len(ooi_mesh.triangles)} triangles):")
    for name, t in (("mesh ray-cast (open3d)", t_mesh), ("point splat (EDT per radius)", t_pts)):
        print(f"  {name:<29} {t:8.2f} s  ({1000 * t / len(mv):.1f} ms/view)")
    print(f"  naive per-pixel (baseline)   ~{t_naive * len(mv):8.1f} s  ({1000 * t_naive:.0f} "
          f"ms/view measured on 1 view; pixel agreement with splat {agree:.4f})")
    print(f"  [{load_note()}]")
    if args.pipeline:
        pipeline_timings(args.pipeline, args.cache, variants, args.repeats)


if __name__ == "__main__":
    main()
