"""Simulator benchmark: render cost and how SfM-friendly the rendered captures are.

For every scene: time to render a 60-view 320x240 capture with adaptive 2x2 anti-aliasing,
next to the baseline of one sample per pixel; SIFT features per image (pycolmap) on the OOI and
on the background; mutual-nearest-neighbour SIFT matches between neighbouring orbit views that
the true geometry confirms (< 3 px). With ``--sfm`` also a full pycolmap reconstruction
(pose-free, exhaustive matching) per scene: registered views, points, camera error after a
similarity alignment, and the fraction of points on the OOI / near the support (this takes
~20-40 s per scene).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_sim.py [--views 60] [--sfm]
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ooi_seg_ros.core.geometry import project  # noqa: E402
from ooi_seg_ros.sim import SCENES, make_scene, simulate_capture  # noqa: E402


def sift_features(images: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
    import pycolmap

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        sift = pycolmap.Sift(pycolmap.FeatureExtractionOptions(), pycolmap.Device.cpu)
    out = []
    for img in images:
        g = img.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32) / 255.0
        kp, desc = sift.extract(np.ascontiguousarray(g))
        out.append((kp[:, :2] - 0.5, np.asarray(desc, np.float32)))  # ROS pixel centres
    return out


def verified_matches(fa, fb, va, vb, depth_a) -> int:
    """Mutual-NN + ratio-test matches whose true reprojection error is below 3 px."""
    sim = fa[1] @ fb[1].T
    if sim.shape[0] < 2 or sim.shape[1] < 2:
        return 0
    ab, ba = np.argmax(sim, 1), np.argmax(sim, 0)
    srt = np.sort(sim, 1)
    ratio = np.arccos(np.clip(srt[:, -1], -1, 1)) < 0.8 * np.arccos(np.clip(srt[:, -2], -1, 1))
    ia = np.nonzero((ba[ab] == np.arange(len(ab))) & ratio)[0]
    ib = ab[ia]
    cam = va.camera
    uv = fa[0][ia]
    px = np.clip(np.round(uv).astype(int), 0, [cam.width - 1, cam.height - 1])
    d = depth_a[px[:, 1], px[:, 0]]
    xc = np.stack([(uv[:, 0] - cam.cx) / cam.fx * d, (uv[:, 1] - cam.cy) / cam.fy * d, d], 1)
    pb, _ = project(xc @ va.pose.R.T + va.pose.t, cam, vb.pose)
    err = np.linalg.norm(pb - fb[0][ib], axis=1)
    return int(np.sum(np.isfinite(err) & (err < 3.0)))


def run_sfm(sim) -> dict:
    import pycolmap
    from PIL import Image

    root = Path(tempfile.mkdtemp(prefix="bench_sim_"))
    try:
        (root / "images").mkdir()
        for v in sim.capture.views:
            Image.fromarray(v.image).save(root / "images" / f"{v.key}.png")
        db = root / "db.db"
        t0 = time.monotonic()
        pycolmap.extract_features(db, root / "images", camera_mode=pycolmap.CameraMode.SINGLE)
        pycolmap.match_exhaustive(db)
        recs = pycolmap.incremental_mapping(db, root / "images", root / "sparse")
        dt = time.monotonic() - t0
        if not recs:
            return {"sfm_s": dt, "registered": 0}
        rec = max(recs.values(), key=lambda r: r.num_reg_images())
        poses = {v.key: v.pose for v in sim.capture.views}
        src, dst = [], []
        for im in rec.images.values():
            src.append(np.asarray(im.projection_center()))
            dst.append(poses[Path(im.name).stem].t)
        src, dst = np.array(src), np.array(dst)
        ms, md = src.mean(0), dst.mean(0)
        A, B = src - ms, dst - md
        U, S, Vt = np.linalg.svd(B.T @ A)
        D = np.eye(3)
        D[2, 2] = np.sign(np.linalg.det(U @ Vt))
        R = U @ D @ Vt
        s = np.trace(np.diag(S) @ D) / (A ** 2).sum()
        cam_err = np.sqrt(((s * A @ R.T - B) ** 2).sum(1).mean())
        X = np.array([p.xyz for p in rec.points3D.values()])
        Xw = s * (X - ms) @ R.T + md
        diag = sim.scene.ooi_diagonal
        on_ooi = sim.scene.distance_to_ooi(Xw) < 0.01 * diag
        support = np.abs(Xw[:, 2] - sim.scene.support_z) < 0.01 * diag
        return {"sfm_s": dt, "registered": rec.num_reg_images(), "points": len(X),
                "cam_err_rel": cam_err / diag, "on_ooi": float(on_ooi.mean()),
                "on_support": float(support.mean()),
                "med_err_rel": float(np.median(sim.scene.distance_to_surface(Xw)) / diag)}
    finally:
        shutil.rmtree(root, ignore_errors=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=60)
    ap.add_argument("--sfm", action="store_true", help="also run pycolmap SfM per scene")
    ap.add_argument("--scenes", nargs="*", default=list(SCENES))
    args = ap.parse_args()
    print(f"threads OMP={os.environ.get('OMP_NUM_THREADS', 'unset')}, views={args.views}, "
          "320x240, seed 0")
    hdr = (f"{'scene':9s} {'OOI diag m':>10s} {'render ss=1 s':>13s} {'render AA2x2 s':>14s} "
           f"{'OOI cover %':>11s} {'SIFT/img':>8s} {'SIFT/kpx OOI':>12s} {'SIFT/kpx bg':>11s} "
           f"{'verified matches/pair':>21s}")
    print(hdr)
    rows = []
    for name in args.scenes:
        make_scene(name, 0)._build()
        t0 = time.monotonic()
        simulate_capture(name, args.views, 320, 240, seed=0, supersample=1)
        t1 = time.monotonic()
        sim = simulate_capture(name, args.views, 320, 240, seed=0, supersample=2)
        t2 = time.monotonic()
        views = sim.capture.views
        feats = sift_features([v.image for v in views])
        n_on = n_off = a_on = a_off = 0
        for v, f in zip(views, feats):
            px = np.clip(np.round(f[0]).astype(int), 0, [319, 239])
            m = v.gt_mask[px[:, 1], px[:, 0]]
            n_on += int(m.sum())
            n_off += int((~m).sum())
            a_on += int(v.gt_mask.sum())
            a_off += int((~v.gt_mask).sum())
        pairs = [k for k in range(len(views) - 1)][:: max(1, len(views) // 10)]
        good = [verified_matches(feats[k], feats[k + 1], views[k], views[k + 1], sim.depths[k])
                for k in pairs]
        cover = 100 * np.mean([v.gt_mask.mean() for v in views])
        print(f"{name:9s} {sim.scene.ooi_diagonal:10.3g} {t1 - t0:13.1f} {t2 - t1:14.1f} "
              f"{cover:11.1f} {np.mean([len(f[0]) for f in feats]):8.0f} "
              f"{1000 * n_on / max(a_on, 1):12.1f} {1000 * n_off / max(a_off, 1):11.1f} "
              f"{np.mean(good):21.0f}", flush=True)
        rows.append((name, sim))
    if args.sfm:
        print(f"\n{'scene':9s} {'SfM s':>6s} {'registered':>10s} {'points':>7s} "
              f"{'cam err/diag':>12s} {'median err/diag':>15s} {'on OOI %':>8s} "
              f"{'on support %':>12s}")
        for name, sim in rows:
            r = run_sfm(sim)
            if r.get("registered", 0) == 0:
                print(f"{name:9s} {r['sfm_s']:6.1f} {'0':>10s}")
                continue
            print(f"{name:9s} {r['sfm_s']:6.1f} {r['registered']:10d} {r['points']:7d} "
                  f"{r['cam_err_rel']:12.2e} {r['med_err_rel']:15.2e} "
                  f"{100 * r['on_ooi']:8.1f} {100 * r['on_support']:12.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
