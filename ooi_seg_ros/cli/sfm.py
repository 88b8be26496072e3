"""``ooi-seg sfm``: an SfM cloud of a capture bag, a COLMAP dataset folder or an image folder.

Posed input (bag, COLMAP dataset, nerfstudio folder) goes through keyframe selection and the
known-pose incremental SfM; an image folder without poses through pycolmap mapping. Writes
``OUT/sfm_points.ply`` (xyz + rgb), ``OUT/sparse/`` (COLMAP binary model) and
``OUT/report.json`` (keyframes used/dropped and why, points, mean track length, median
reprojection error, time per step).
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from .segment import add_threads_argument


def register(subparsers) -> None:
    p = subparsers.add_parser("sfm", help="build the SfM cloud of a capture",
                              description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", help="capture bag (.mcap / rosbag2 folder), COLMAP dataset folder, "
                                 "nerfstudio folder, or image folder")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--downscale", type=float, default=1.0,
                   help="read images at 1/downscale resolution (COLMAP images_N when present)")
    p.add_argument("--max-keyframes", type=int, default=0, help="stop after N keyframes (0 = all)")
    p.add_argument("--all-frames", action="store_true",
                   help="use every posed frame as a keyframe (no motion/blur selection)")
    p.add_argument("--ba", action="store_true", help="bundle-adjust the points (poses fixed)")
    p.add_argument("--refine-poses", action="store_true", help="with --ba: refine poses too")
    p.add_argument("--reuse", action="store_true",
                   help="COLMAP dataset with a model: load it instead of recomputing")
    p.add_argument("--config", help="YAML with SfmConfig overrides")
    add_threads_argument(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..capture_io import input_kind, read_capture_and_cloud
    from ..core.config import from_dict, load_yaml, to_dict
    from ..core.types import InputError
    from ..sfm.export import write_colmap_model, write_ply
    from ..sfm.pipeline import SfmConfig, reconstruct, summarize

    cfg = from_dict(SfmConfig, load_yaml(args.config)) if args.config else SfmConfig()
    if args.max_keyframes < 0:
        raise InputError("--max-keyframes must be >= 0")
    cfg.keyframes.max_keyframes = args.max_keyframes
    cfg.use_all_frames = cfg.use_all_frames or args.all_frames
    cfg.bundle_adjust = cfg.bundle_adjust or args.ba
    cfg.refine_poses = cfg.refine_poses or args.refine_poses
    cfg.mapping.num_threads = args.threads
    cfg.progress = not args.quiet
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    kind = input_kind(args.input)
    capture, cloud = read_capture_and_cloud(args.input, downscale=args.downscale)
    t_read = time.perf_counter() - t0
    if args.reuse:
        if kind != "colmap" or cloud is None or len(cloud) == 0:
            raise InputError(f"--reuse needs a COLMAP dataset folder with a model; {args.input} "
                             f"is a {kind} input without one")
        report = {"reused_model": True, "input_views": len(capture.views), "times_s": {}}
        report.update(summarize(cloud))
    else:
        capture, cloud, report = reconstruct(capture, cfg, work_dir=out / "mapping")
    report["input"] = str(args.input)
    report["input_kind"] = kind
    report["times_s"]["read_s"] = t_read
    t1 = time.perf_counter()
    sparse = out / "sparse"
    if sparse.exists():
        shutil.rmtree(sparse)
    write_colmap_model(cloud, sparse)
    write_ply(cloud.xyz, cloud.rgb, out / "sfm_points.ply")
    report["times_s"]["export_s"] = time.perf_counter() - t1
    report["times_s"]["total_s"] = time.perf_counter() - t0
    report["config"] = to_dict(cfg)
    (out / "report.json").write_text(json.dumps(report, indent=1, default=str))
    print(f"sfm: {report['points']} points from {report.get('keyframes_used')} keyframes, "
          f"mean track {report['mean_track_length']:.2f}, median reprojection "
          f"{report['median_reprojection_px']:.3f} px -> {out}")
    return 0
