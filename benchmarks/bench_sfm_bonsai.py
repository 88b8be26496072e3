"""Benchmark: unknown-pose mapping (``ooi_seg_ros.sfm.mapping``) on the Mip-NeRF 360 bonsai photos.

Runs the full pycolmap route once (SIFT, sequential matching, incremental mapping) and prints it
side by side with the reference model shipped in ``/work/shared/data/mipnerf360-bonsai/sparse/0``:
registered images, points, mean track length, mean reprojection error, and the camera-centre
error after a similarity alignment onto the reference (as a fraction of the camera-orbit radius).
Slow (~25+ min on 2 cores): run it in the background with ``nice``.

    nice -n 10 .venv/bin/python benchmarks/bench_sfm_bonsai.py --out /tmp/bonsai_sfm \
        > /tmp/bonsai_sfm.log 2>&1 &

``--step K --runs N``: every K-th photo only (K=5: 58 photos, matched exhaustively), mapped N
times (pycolmap's multi-threaded mapping differs from run to run). When the exhaustive model's
cameras jump along the photo order, the mapping matches the photos sequentially too
(``MappingConfig.sequential_rematch``): both models of each run are compared with the
reference, side by side, and the one the mapping kept is marked.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "mipnerf360-bonsai"


def _centers(rec) -> dict[str, np.ndarray]:
    out = {}
    for im in rec.images.values():
        if im.has_pose:
            out[im.name] = np.asarray(im.projection_center())
    return out


def compare(ours_dir: Path, ref_dir: Path) -> dict:
    """Model statistics of both models and our camera-centre error after Sim(3) alignment."""
    import pycolmap

    ours = pycolmap.Reconstruction(str(ours_dir))
    ref = pycolmap.Reconstruction(str(ref_dir))
    res = {}
    for name, rec in (("ours", ours), ("reference", ref)):
        res[name] = {"registered_images": int(rec.num_reg_images()),
                     "points": int(rec.num_points3D()),
                     "mean_track_length": float(rec.compute_mean_track_length()),
                     "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error())}
    c_ref = _centers(ref)
    radius = float(np.median(np.linalg.norm(
        np.stack(list(c_ref.values())) - np.mean(np.stack(list(c_ref.values())), 0), axis=1)))
    sim = pycolmap.align_reconstructions_via_proj_centers(ours, ref, 0.1 * radius)
    if sim is None:
        res["alignment"] = "failed"
        return res
    c_ours = _centers(ours)
    common = sorted(set(c_ours) & set(c_ref))
    M = np.asarray(sim.matrix())
    err = np.array([np.linalg.norm(M[:, :3] @ c_ours[n] + M[:, 3] - c_ref[n]) for n in common])
    res["aligned_center_error"] = {
        "common_images": len(common), "orbit_radius_ref_units": radius,
        "median_frac_of_radius": float(np.median(err) / radius),
        "max_frac_of_radius": float(np.max(err) / radius)}
    return res


def _best_model(sparse: Path) -> Path:
    import pycolmap
    dirs = [p for p in sparse.iterdir() if p.is_dir()]
    return max(dirs, key=lambda p: pycolmap.Reconstruction(str(p)).num_reg_images())


def subset_runs(out: Path, step: int, runs: int, threads: int) -> int:
    """Map every ``step``-th photo ``runs`` times; compare each model with the reference."""
    from ooi_seg_ros.sfm.colmap_io import load_colmap_model
    from ooi_seg_ros.sfm.mapping import (MappingConfig, looking_away, map_image_folder,
                                         path_jump)
    photos = out / f"images_step{step}"
    photos.mkdir(parents=True, exist_ok=True)
    for k, p in enumerate(sorted((DATA / "images").iterdir())):
        if k % step == 0 and not (photos / p.name).exists():
            (photos / p.name).symlink_to(p)
    n = len(list(photos.iterdir()))
    rows = []
    for r in range(runs):
        work = out / f"step{step}_run{r}"
        t0 = time.perf_counter()
        capture, _, stats = map_image_folder(photos, work, MappingConfig(num_threads=threads))
        total = time.perf_counter() - t0
        kept = Path(capture.meta["sfm_model_dir"])
        for name in ("sparse", "sparse_sequential"):
            if not (work / name).is_dir():
                continue
            model = _best_model(work / name)
            res = compare(model, DATA / "sparse" / "0")
            cap, _ = load_colmap_model(model, photos)
            e = res.get("aligned_center_error", {})
            first = "exhaustive" if n <= MappingConfig().exhaustive_max_images else "sequential"
            rows.append({"run": r, "matching": first if name == "sparse" else
                         "sequential", "kept": model == kept,
                         "looking_away": len(looking_away(cap)),
                         "registered": res["ours"]["registered_images"],
                         "path_step_ratio": path_jump(cap)[0],
                         "median_err": e.get("median_frac_of_radius", float("nan")),
                         "max_err": e.get("max_frac_of_radius", float("nan")),
                         "total_s": total, "times_s": stats["times_s"]})
            print(json.dumps(rows[-1]), flush=True)
    print(f"\nevery {step}th photo ({n} photos), {runs} runs; camera-centre error after a "
          "similarity onto the reference, as a fraction of its orbit radius")
    print(f"{'run':>4s} {'matching':>11s} {'kept':>5s} {'registered':>10s} {'path step':>9s} "
          f"{'away':>5s} {'median err':>10s} {'max err':>8s} {'run s':>6s}")
    for w in rows:
        print(f"{w['run']:4d} {w['matching']:>11s} {'yes' if w['kept'] else '':>5s} "
              f"{w['registered']:10d} {w['path_step_ratio']:8.1f}x {w['looking_away']:5d} "
              f"{w['median_err']:10.4f} "
              f"{w['max_err']:8.3f} {w['total_s']:6.0f}")
    (out / f"bench_bonsai_step{step}.json").write_text(json.dumps(rows, indent=1))
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="/tmp/bonsai_sfm")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--compare-only", action="store_true",
                    help="skip mapping; compare an existing OUT/sparse/<k> model")
    ap.add_argument("--step", type=int, default=1, help="map every STEP-th photo only")
    ap.add_argument("--runs", type=int, default=1, help="with --step: mapping runs")
    args = ap.parse_args()
    out = Path(args.out)
    if args.step > 1:
        return subset_runs(out, args.step, args.runs, args.threads)
    stats = {}
    if not args.compare_only:
        from ooi_seg_ros.sfm.mapping import MappingConfig, map_image_folder
        t0 = time.perf_counter()
        capture, cloud, stats = map_image_folder(DATA / "images", out,
                                                 MappingConfig(num_threads=args.threads))
        stats["total_s"] = time.perf_counter() - t0
        model_dir = Path(capture.meta["sfm_model_dir"])
    else:
        model_dir = max((p for p in (out / "sparse").iterdir() if p.is_dir()),
                        key=lambda p: len(list(p.iterdir())))
    res = compare(model_dir, DATA / "sparse" / "0")
    res["run"] = stats
    print(json.dumps(res, indent=1))
    o, r = res["ours"], res["reference"]
    print(f"{'':28s}{'ours':>12s}{'reference':>12s}")
    for k in o:
        print(f"{k:28s}{o[k]:12.3f}{r[k]:12.3f}")
    (out / "bench_bonsai.json").write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
