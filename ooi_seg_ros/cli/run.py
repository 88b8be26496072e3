"""``ooi-seg run INPUT --out DIR``: the whole pipeline offline, SfM -> segmentation -> training.

The same core code the nodes use, on a capture bag or dataset folder. Writes ``DIR/sfm/``
(``ooi-seg sfm`` outputs; skipped when the input already carries a cloud, e.g. a COLMAP
dataset), ``DIR/segment/`` (``ooi-seg segment`` outputs: masks, OOI cloud, mesh, report) and
``DIR/train/`` (``ooi-seg train`` outputs: splats.ply, training.mcap, held-out renders,
report), and ``DIR/summary.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from ..core.types import InputError
from .segment import add_size_arguments, add_threads_argument, read_at_working_size


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="the whole pipeline: SfM -> segmentation -> splat training")
    p.add_argument("input", help="capture bag (.mcap / rosbag2 folder) or dataset folder")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--method", choices=("ours", "paper"), default=None,
                   help="segmentation preset (default: ours)")
    add_size_arguments(p)
    add_threads_argument(p)
    p.add_argument("--iterations", type=int, default=None, help="training iterations")
    p.add_argument("--max-gaussians", type=int, default=None, help="Gaussian budget (MCMC cap)")
    p.add_argument("--skip-train", action="store_true", help="stop after the masks")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from . import main as cli_main
    from ..capture_io import input_kind, read_capture_and_cloud
    from ..seg.pipeline import make_config, segment
    from ..seg.report import write_outputs
    from ..sfm.export import write_colmap_model, write_ply
    from ..sfm.pipeline import SfmConfig, reconstruct

    src = Path(args.input)
    if not src.exists():
        raise InputError(f"input {args.input} does not exist (a capture bag .mcap, a rosbag2 "
                         "folder or a dataset folder)")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary: dict = {"input": str(src.resolve()), "times_s": {}}
    est_model = None  # the mapping's model, when the photos came without poses
    t0 = time.perf_counter()

    print(f"[1/3] reading {src} ...", flush=True)
    kind = input_kind(str(src))
    capture, cloud, photos, gt_full, size_info = read_at_working_size(  # memory checked
        lambda f, lazy: read_capture_and_cloud(str(src), downscale=f, lazy_images=lazy),
        args.downscale, args.max_pixels, lazy_differs=kind == "bag")
    summary["downscale"] = size_info["downscale"]
    summary["views"] = len(capture.views)
    dropped = capture.meta.get("dropped")
    if dropped:
        summary["dropped"] = dropped
    if cloud is None or len(cloud) == 0:
        print(f"[1/3] SfM over {len(capture.views)} views ...", flush=True)
        t = time.perf_counter()
        cfg = SfmConfig()
        cfg.mapping.num_threads = args.threads
        summary["sfm_threads"] = args.threads
        sfm_cap, cloud, report = reconstruct(capture, cfg, work_dir=out / "sfm" / "mapping")
        if not capture.has_poses:
            capture = sfm_cap  # poses estimated by mapping
            # for the training step, which reloads the input from the segment folder
            est_model = sfm_cap.meta.get("sfm_model_dir")
        (out / "sfm").mkdir(parents=True, exist_ok=True)
        write_colmap_model(cloud, out / "sfm" / "sparse")
        write_ply(cloud.xyz, cloud.rgb, out / "sfm" / "sfm_points.ply")
        (out / "sfm" / "report.json").write_text(json.dumps(report, indent=1, default=str))
        summary["times_s"]["sfm"] = time.perf_counter() - t
        summary["sfm_points"] = len(cloud)
        print(f"      {len(cloud)} points -> {out / 'sfm'}", flush=True)
    else:
        summary["sfm_points"] = len(cloud)
        print(f"[1/3] the input carries an SfM cloud of {len(cloud)} points", flush=True)

    print("[2/3] segmenting the object of interest ...", flush=True)
    t = time.perf_counter()
    result = segment(capture, cloud, make_config(args.method))
    info = {"input": str(src.resolve()), "kind": "capture" if kind != "colmap" else kind,
            "method": args.method, "config": None, "seed": None, **size_info,
            "cloud": "sfm", "views": len(capture.views),
            "image_keys": [v.key for v in capture.views],
            "image_sources": [v.source for v in capture.views]}
    if est_model:
        info["cloud"] = "sfm (poses estimated by mapping)"
        info["sfm_model"] = str(Path(est_model).resolve())
    seg_dir = write_outputs(out / "segment", result, capture, info, photos=photos,
                            photo_gt=gt_full)
    summary["times_s"]["segment"] = time.perf_counter() - t
    summary["segment"] = {"counts": result.counts, "warnings": result.warnings,
                          "metrics": result.metrics["mean"] if result.metrics else None}
    m = summary["segment"]["metrics"]
    extra = (f", IoU {m['iou']:.3f} / recall {m['recall']:.3f} vs ground truth" if m else "")
    print(f"      {len(result.ooi_cloud)} OOI points, {len(result.masks)} masks{extra} -> "
          f"{seg_dir}", flush=True)
    for w in result.warnings:
        print(f"      warning: {w}", flush=True)

    rc = 0
    if not args.skip_train:
        print("[3/3] training object-only Gaussian splats ...", flush=True)
        t = time.perf_counter()
        targs = ["train", str(seg_dir), "--out", str(out / "train")]
        if args.iterations is not None:
            targs += ["--iterations", str(args.iterations)]
        if args.max_gaussians is not None:
            targs += ["--max-gaussians", str(args.max_gaussians)]
        rc = cli_main(targs)
        summary["times_s"]["train"] = time.perf_counter() - t
        rep = out / "train" / "report.json"
        if rep.exists():
            trep = json.loads(rep.read_text())
            summary["train"] = {k: trep.get(k) for k in (
                "heldout_psnr", "heldout_ssim", "heldout_psnr_gt_mask", "heldout_ssim_gt_mask",
                "heldout_spill", "heldout_spill_gt_mask",
                "n_gaussians", "iterations", "its_per_s",
                "seconds", "cpu_seconds", "backend", "nan_steps", "dropped_no_pose")}
    summary["times_s"]["total"] = time.perf_counter() - t0
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=str))
    print("\noutputs:")
    if (out / "sfm").exists():
        print(f"  SfM cloud:        {out / 'sfm' / 'sfm_points.ply'}")
    print(f"  object masks:     {seg_dir / 'masks'}/<key>.png")
    print(f"  OOI cloud / mesh: {seg_dir / 'ooi_points.ply'}, {seg_dir / 'ooi_mesh.ply'}")
    print(f"  segmentation:     {seg_dir / 'report.html'}")
    if not args.skip_train and rc != 0:
        print("  splats:           none -- training stopped (its error is above)")
    elif not args.skip_train:
        print(f"  splats:           {out / 'train' / 'splats.ply'}")
        print(f"  training bag:     {out / 'train' / 'training.mcap'}")
        print(f"  training report:  {out / 'train' / 'report.html'}")
    print(f"  summary:          {out / 'summary.json'}")
    return rc
