"""``ooi-seg segment``: segment the object of interest and write masks for every view.

INPUT is a COLMAP model folder (``sparse/0`` + ``images``, or a sparse folder with
``--images``), a dataset folder or bag readable by ``ooi_seg_ros.capture_io`` (SfM runs when it
has no cloud; a folder of photos without poses is mapped by pycolmap, which estimates them, and
images it cannot register get no mask and a warning), or ``sim:SCENE[:SEED]`` (a simulator
capture with a depth-proxy cloud, for demos and tests).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Callable, Optional

from ..core.config import load_yaml
from ..core.types import InputError


def register(subparsers) -> None:
    p = subparsers.add_parser("segment", help="segment the OOI and render per-view masks",
                              description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", help="COLMAP folder, dataset folder, bag, or sim:SCENE[:SEED]")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--method", choices=("paper", "ours"), default=None,
                   help="paper = literal baseline; ours = improved default")
    p.add_argument("--config", help="YAML with SegmentationConfig overrides")
    p.add_argument("--seed", type=int, default=None, help="seed of every random step")
    p.add_argument("--images", help="image folder of a COLMAP sparse model")
    add_threads_argument(p)
    add_size_arguments(p)
    p.add_argument("--sim-views", type=int, default=30, help="views of a sim: input")
    p.add_argument("--sim-size", default="160x120", help="WxH of a sim: input")
    p.set_defaults(func=run)


def parse_downscale(text: str) -> Optional[float]:
    """``--downscale``: "auto" (None) or a factor >= 1."""
    if str(text).lower() == "auto":
        return None
    try:
        f = float(text)
    except ValueError:
        f = float("nan")
    if not (f >= 1.0 and f < float("inf")):
        raise argparse.ArgumentTypeError(f"{text!r}: give auto or a factor >= 1 (2 = half "
                                         "resolution)")
    return f


def add_threads_argument(p: argparse.ArgumentParser) -> None:
    """``--threads`` (sfm, segment and run): pycolmap's threads for mapping bare photos."""
    p.add_argument("--threads", type=int, default=-1,
                   help="pycolmap threads when photos without poses are mapped (-1 = all "
                        "cores; 1 = the same photos always give the same model, ~1.5x the "
                        "time: pycolmap's stages are not repeatable on several threads)")


def add_size_arguments(p: argparse.ArgumentParser) -> None:
    """``--downscale`` and ``--max-pixels`` (segment and run)."""
    from ..seg.pipeline import SEG_MAX_PIXELS
    p.add_argument("--downscale", type=parse_downscale, default=None, metavar="auto|F",
                   help="read the images at 1/F resolution (any input but sim:); auto "
                        "(default): the smallest integer F that brings every view to "
                        "--max-pixels and the run into the available memory. Masks are "
                        "written at the photos' size either way")
    p.add_argument("--max-pixels", type=int, default=SEG_MAX_PIXELS,
                   help=f"with --downscale auto: pixels per view to work at (default "
                        f"{SEG_MAX_PIXELS:,}; 0 = full size); the refinement's time grows "
                        "linearly with it")


def read_at_working_size(read: Callable[[float, bool], tuple], downscale: Optional[float],
                         max_pixels: int, lazy_differs: bool = False) -> tuple:
    """(capture, cloud, photo views by key or None, full-size ground-truth masks by key or
    None, info) for ``read(downscale, lazy) -> (capture, cloud)``: the input is opened at full
    size (lazily) to learn its photos' sizes, then read at ``downscale`` (None: the factor
    ``working_downscale`` picks) -- every view in memory at the size the run works at. The
    photo views (images loaded on demand) come back when that size is smaller, for writing
    the masks at the photos' size. A capture too large for the memory even so is refused
    (``check_memory``). ``lazy_differs``: a lazy read keeps images out of memory (a bag), so
    the input is read again even at full size."""
    from ..seg.pipeline import check_memory, working_downscale
    probe, cloud = read(1.0, True)
    sizes = [(v.camera.width, v.camera.height) for v in probe.views]
    f = (float(working_downscale(sizes, max_pixels)) if downscale is None
         else float(downscale))
    photos = gt_full = None
    if f != 1.0:
        photos = {v.key: v for v in probe.views}
        if probe.has_gt_masks:
            gt_full = {v.key: v.gt_mask for v in probe.views}
    if f != 1.0 or lazy_differs:
        cap, cloud = read(f, False)
    else:
        cap = probe
    check_memory(cap, downscale=f)  # before the run, not killed part way
    photo = sorted(set(sizes))
    info = {"downscale": f, "downscale_auto": downscale is None,
            "max_pixels": max_pixels if downscale is None else None,
            "photo_size": list(photo[-1]) if len(photo) == 1 else [list(s) for s in photo],
            "working_size": [cap.views[0].camera.width, cap.views[0].camera.height]
            if cap.views else None}
    return cap, cloud, photos, gt_full, info


def _colmap_dirs(path: Path, images: str | None) -> tuple[Path, Path] | None:
    """(sparse dir, images dir) if ``path`` is a COLMAP model folder, else None."""
    for sparse in (path / "sparse" / "0", path / "sparse", path):
        if any((sparse / f"cameras.{e}").exists() for e in ("bin", "txt")):
            img = Path(images) if images else None
            if img is None:
                for cand in (path / "images", sparse.parent.parent / "images",
                             sparse.parent / "images"):
                    if cand.is_dir():
                        img = cand
                        break
            if img is None:
                raise InputError(f"found a COLMAP model in {sparse} but no images folder; "
                                 f"pass --images DIR")
            return sparse, img
    return None


def load_input(args) -> tuple:
    """(capture, cloud, input_info, photo views or None, full-size ground-truth masks or None)
    for INPUT (see module doc), read at the working size (``read_at_working_size``). A
    capture too large for the memory available is refused here, with the ``--downscale``
    that fits."""
    src = str(args.input)
    info = {"input": src, "method": args.method, "config": args.config, "seed": args.seed}
    if src.startswith("sim:"):
        from ..seg.proxy import depth_proxy_cloud
        from ..sim import simulate_capture
        bits = src.split(":")
        try:
            w, h = (int(x) for x in args.sim_size.lower().split("x"))
            seed = int(bits[2]) if len(bits) > 2 else 0
        except ValueError:
            raise InputError(f"bad sim input {src!r} / --sim-size {args.sim_size!r}; use "
                             f"sim:SCENE[:SEED] and WxH") from None
        sim = simulate_capture(bits[1], n_views=args.sim_views, width=w, height=h, seed=seed)
        info.update({"kind": "sim", "scene": bits[1], "sim_seed": seed, "size": [w, h],
                     "views": args.sim_views, "cloud": "depth proxy (seg.proxy)",
                     "downscale": 1.0})
        return sim.capture, depth_proxy_cloud(sim, seed=seed), info, None, None
    path = Path(src)
    if not path.exists():
        raise InputError(f"input {src} does not exist")
    dirs = _colmap_dirs(path, args.images) if path.is_dir() else None
    if dirs is not None:
        from ..sfm.colmap_io import load_colmap_model
        cap, cloud, photos, gt_full, size_info = read_at_working_size(
            lambda f, _lazy: load_colmap_model(dirs[0], dirs[1], f), args.downscale,
            args.max_pixels)
        info.update(size_info)
        info.update({"kind": "colmap", "sparse": str(dirs[0].resolve()),
                     "images": str(dirs[1].resolve())})
        return cap, cloud, info, photos, gt_full
    try:
        from ..capture_io import input_kind, read_capture_and_cloud
    except ImportError:
        raise InputError(f"{src} is not a COLMAP model folder, and reading datasets/bags "
                         f"(ooi_seg_ros.capture_io) is not available in this build") from None
    # `train` reads this input again from input.json at the same downscale
    cap, cloud, photos, gt_full, size_info = read_at_working_size(
        lambda f, lazy: read_capture_and_cloud(path, downscale=f, lazy_images=lazy),
        args.downscale, args.max_pixels, lazy_differs=input_kind(path) == "bag")
    info.update(size_info)
    info["kind"] = "capture"
    dropped = {k: n for k, n in (cap.meta.get("dropped") or {}).items() if n}
    if dropped:  # counted and logged by the reader; said again where the user looks
        info["dropped"] = dropped
        names = cap.meta.get("unreadable") or []
        info.setdefault("warnings", []).append(
            f"input: dropped {sum(dropped.values())} image(s) ({dropped})"
            + (f": {', '.join(names[:5])}{', ...' if len(names) > 5 else ''}" if names else ""))
    if cap.meta.get("exif_turned"):
        info["exif_turned"] = cap.meta["exif_turned"]
    if cloud is None or len(cloud) == 0:
        try:
            from ..sfm.pipeline import reconstruct
        except ImportError:
            raise InputError(f"{src} has no SfM cloud and the SfM module cannot run here; "
                             f"run `ooi-seg sfm` first") from None
        # photos without poses: the estimated cameras are kept in OUT/sparse so that
        # `ooi-seg train OUT` finds the poses (the photos themselves carry none)
        keep = None if cap.has_poses else Path(args.out) / "sparse"
        from ..sfm.pipeline import SfmConfig
        sfm_cfg = SfmConfig()
        sfm_cfg.mapping.num_threads = getattr(args, "threads", -1)
        sfm_cap, cloud, sfm_report = reconstruct(cap, sfm_cfg, keep_model=keep)
        info["cloud"] = "sfm"
        if sfm_report.get("warning"):
            info.setdefault("warnings", []).append(f"sfm: {sfm_report['warning']}")
        if not cap.has_poses:
            # photos without poses: the mapping estimated them, for the views it registered
            missing = sorted({v.key for v in cap.views} - {v.key for v in sfm_cap.views})
            info["cloud"] = "sfm (poses estimated by mapping)"
            info["sfm_model"] = str(keep.resolve())
            mapping = sfm_report.get("mapping", {})
            info["mapping"] = {k: mapping[k] for k in (
                "images", "registered_images", "points", "matching", "rematch", "cameras",
                "mean_reprojection_error_px", "times_s") if k in mapping}
            info["mapping"]["camera_path_max_step_ratio"] = sfm_report.get(
                "camera_path_max_step_ratio")
            info["mapping"]["num_threads"] = sfm_cfg.mapping.num_threads
            if missing:
                info["views_not_registered"] = missing
                info["warnings"] = info.get("warnings", []) + [
                    f"input: {len(missing)} of {len(cap.views)} images were not registered "
                    f"by the mapping and get no mask ({', '.join(missing[:5])}"
                    f"{', ...' if len(missing) > 5 else ''})"]
            cap = sfm_cap
    return cap, cloud, info, photos, gt_full


def run(args) -> int:
    from ..seg.pipeline import make_config, segment
    from ..seg.report import write_outputs
    overrides = load_yaml(args.config) if args.config else {}
    if args.seed is not None:
        overrides["seed"] = args.seed
    cfg = make_config(args.method, overrides)
    t0 = time.perf_counter()
    cap, cloud, info, photos, gt_full = load_input(args)
    t_load = time.perf_counter() - t0
    result = segment(cap, cloud, cfg)
    result.timings["load"] = t_load
    result.warnings[:0] = info.pop("warnings", [])
    info["views"] = len(cap.views)
    info["image_keys"] = [v.key for v in cap.views]
    info["image_sources"] = [v.source for v in cap.views]
    out = write_outputs(args.out, result, cap, info, photos=photos, photo_gt=gt_full)
    mean = result.metrics["mean"] if result.metrics else None
    print(json.dumps({"out": str(out), "counts": result.counts, "metrics": mean,
                      "warnings": result.warnings}))
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    return 0
