"""``ooi-seg train``: object-only Gaussian splat training from a segmentation folder or capture.

INPUT is either the output folder of ``ooi-seg segment`` (input.json, masks/, ooi_points.ply)
or a capture (bag, COLMAP/nerfstudio/image folder, ``sim:SCENE[:SEED]``) together with
``--masks DIR`` (the paper's naive baseline: user-given masks) or ground-truth masks carried
by the capture (simulator). Writes splats.ply, training.mcap, heldout/<key>.png, report.json,
report.html and config.yaml into --out.
"""

from __future__ import annotations

import argparse
import base64
import dataclasses
import html
import io
import json
from pathlib import Path
from typing import Optional

import numpy as np

from ..core import config as cfgmod
from ..core.types import Capture, InputError
from ..train.trainer import TrainConfig, TrainResult


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "train", help="train object-only Gaussian splats (paper 4.6)",
        description="Train a 3D Gaussian splat model of the object only: loss inside the "
                    "object masks, MCMC densification under a cap, every 8th view held out.")
    p.add_argument("input", help="ooi-seg segment output folder, or a capture with --masks")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--iterations", type=int, default=None,
                   help=f"training steps (default {TrainConfig.iterations})")
    p.add_argument("--max-gaussians", type=int, default=None,
                   help="hard cap on the number of Gaussians "
                        f"(default {TrainConfig.max_gaussians})")
    p.add_argument("--masks", default=None,
                   help="folder of <key>.png object masks (overrides the segmentation's)")
    p.add_argument("--init", default=None, help="PLY point cloud to start from "
                   "(default: the segmentation's ooi_points.ply)")
    p.add_argument("--full-image", action="store_true",
                   help="no masks: loss over all pixels (baseline for comparison)")
    p.add_argument("--sh-degree", type=int, default=None, help="final SH degree (default 3)")
    p.add_argument("--seed", type=int, default=None, help="random seed (default 0)")
    p.add_argument("--backend", default=None, choices=["auto", "cpu", "gsplat"],
                   help="rasteriser (default auto: gsplat on CUDA, else CPU)")
    p.add_argument("--config", default=None, help="YAML file with TrainConfig fields")
    p.add_argument("--sim-views", type=int, default=60, help="views for sim: inputs")
    p.add_argument("--sim-size", default="320x240", help="image size for sim: inputs")
    p.add_argument("--lpips-weights", default=None,
                   help="local state-dict file of the LPIPS network (nothing is downloaded; "
                        "without it LPIPS is reported as unavailable)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _config(args: argparse.Namespace) -> TrainConfig:
    data = cfgmod.load_yaml(args.config) if args.config else {}
    cfg = cfgmod.from_dict(TrainConfig, data)
    for flag, name in (("iterations", "iterations"), ("max_gaussians", "max_gaussians"),
                       ("sh_degree", "sh_degree"), ("seed", "seed"), ("backend", "backend")):
        val = getattr(args, flag)
        if val is not None:
            setattr(cfg, name, val)
    if args.full_image:
        cfg.full_image = True
    return cfg


def _load_capture(src: str, sim_views: int, sim_size: str, downscale: float = 1.0) -> Capture:
    if src.startswith("sim:"):
        from ..sim import simulate_capture
        bits = src.split(":")
        try:
            w, h = (int(x) for x in sim_size.lower().split("x"))
            seed = int(bits[2]) if len(bits) > 2 else 0
        except ValueError:
            raise InputError(f"bad sim input {src!r} / size {sim_size!r}; use sim:SCENE[:SEED] "
                             "and WxH") from None
        return simulate_capture(bits[1], n_views=sim_views, width=w, height=h, seed=seed).capture
    from ..capture_io import read_capture
    if not Path(src).exists():
        raise InputError(f"input {src} does not exist")
    return read_capture(src, downscale=downscale)


def load_inputs(args: argparse.Namespace) -> tuple[Capture, Optional[dict], Optional[np.ndarray],
                                                   Optional[np.ndarray]]:
    """(capture, masks by key or None, init points or None, init colours or None)."""
    from ..capture_io import _load_mask

    src = Path(args.input)
    masks_dir: Optional[Path] = Path(args.masks) if args.masks else None
    init_ply: Optional[Path] = Path(args.init) if args.init else None
    if (src / "input.json").is_file():
        info = json.loads((src / "input.json").read_text())
        kind = info.get("kind")
        if kind == "sim":
            size = info.get("size", [320, 240])
            capture = _load_capture(f"sim:{info['scene']}:{info.get('sim_seed', 0)}",
                                    int(info.get("views", 60)), f"{size[0]}x{size[1]}")
        elif kind == "colmap":
            from ..sfm.colmap_io import load_colmap_model
            capture, _ = load_colmap_model(info["sparse"], info["images"],
                                           float(info.get("downscale", 1.0)))
        else:
            capture = _load_capture(str(info["input"]), args.sim_views, args.sim_size,
                                    float(info.get("downscale", 1.0) or 1.0))
            if info.get("sfm_model"):  # photos without poses: the cameras segment estimated
                capture = _with_model_poses(capture, Path(info["sfm_model"]))
        masks_dir = masks_dir or src / "masks"
        if init_ply is None and (src / "ooi_points.ply").is_file():
            init_ply = src / "ooi_points.ply"
    else:
        capture = _load_capture(str(args.input), args.sim_views, args.sim_size)
    masks: Optional[dict] = None
    if args.full_image:
        masks = None
    elif masks_dir is not None:
        if not masks_dir.is_dir():
            raise InputError(f"masks folder {masks_dir} does not exist")
        masks = {}
        for v in capture.views:
            p = masks_dir / f"{v.key}.png"
            if p.is_file():
                masks[v.key] = _mask_for_view(_load_mask(p), v, p)
        if not masks:
            raise InputError(f"no <key>.png masks in {masks_dir} match the capture's view keys "
                             f"(e.g. {capture.views[0].key}.png)")
        for v in capture.views:  # views without a mask file: treated as empty (skipped)
            if v.key not in masks:
                masks[v.key] = np.zeros((v.camera.height, v.camera.width), dtype=bool)
    elif capture.has_gt_masks:
        masks = {v.key: v.gt_mask for v in capture.views}
    else:
        raise InputError("no object masks: pass an ooi-seg segment folder, --masks DIR, or "
                         "--full-image")
    pts, cols = None, None
    if init_ply is not None:
        pts, cols = _read_points(init_ply)
    return capture, masks, pts, cols


def _mask_for_view(mask: np.ndarray, view, path: Path) -> np.ndarray:
    """``mask`` at ``view``'s size: masks are written at the photo's size (``segment``) and
    training may read the photos smaller (``--downscale``); a mask of another shape than its
    photo is an error, not stretched."""
    from ..seg.masks import mask_at_size
    w, h = view.camera.width, view.camera.height
    mh, mw = mask.shape
    if (mw, mh) == (w, h):
        return mask
    if abs(mw / mh - w / h) > 0.02 * w / h:
        raise InputError(f"mask {path} is {mw}x{mh} but its image is {w}x{h} (another shape); "
                         "give masks made for these images")
    return mask_at_size(mask, (w, h))


def _with_model_poses(capture: Capture, model_dir: Path) -> Capture:
    """``capture``'s views with the cameras and poses of the COLMAP model ``ooi-seg segment``
    estimated for them (matched by key = the model image name's stem); views the model did
    not register keep no pose (training drops and counts them)."""
    from ..core.types import View
    from ..sfm.colmap_io import load_colmap_model
    if not model_dir.is_dir():
        raise InputError(f"the segment folder's estimated cameras ({model_dir}) are missing; "
                         "run `ooi-seg segment` again")
    model, _ = load_colmap_model(model_dir)
    by_key = {v.key: v for v in model.views}
    views = []
    for v in capture.views:
        m = by_key.get(v.key)
        if m is None:
            views.append(View(v.key, v.stamp_ns, v.camera, None, v.image, v.gt_mask, v.loader,
                              v.source))
            continue
        h, w = v.get_image().shape[:2]
        if (m.camera.width, m.camera.height) != (w, h):
            raise InputError(f"image {v.key} is {w}x{h} but the segment folder's camera for "
                             f"it is {m.camera.width}x{m.camera.height}; use the same "
                             "--downscale as the segment run")
        views.append(View(v.key, v.stamp_ns, m.camera, m.pose, v.image, v.gt_mask, v.loader,
                          v.source))
    return dataclasses.replace(capture, views=views)


def _read_points(path: Path) -> tuple[np.ndarray, Optional[np.ndarray]]:
    import open3d as o3d
    if not path.is_file():
        raise InputError(f"initial point cloud {path} does not exist")
    pc = o3d.io.read_point_cloud(str(path))
    xyz = np.asarray(pc.points, dtype=np.float64)
    cols = (np.asarray(pc.colors) * 255).astype(np.uint8) if pc.has_colors() else None
    return xyz, cols


def _png_b64(rgb: np.ndarray) -> str:
    from PIL import Image
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG")
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _lpips(result: TrainResult, weights: Optional[str]):
    """Mean masked LPIPS over the held-out views, or the reason it is unavailable."""
    import torch

    from ..train.loss import load_lpips
    net = load_lpips(weights)
    if net is None:
        return "unavailable (no local weights file)"
    with torch.no_grad():
        vals = [float(net(torch.from_numpy(h.render / 255.0).float(),
                          torch.from_numpy(h.gt / 255.0).float(), torch.from_numpy(h.mask)))
                for h in result.heldout]
    return float(np.mean(vals)) if vals else None


def _summary_lines(metrics: dict, lpips) -> list[str]:
    """The report page's summary, readable: units, sensible digits, and what a missing
    figure means (no ground-truth masks, no LPIPS weights) instead of ``None``."""
    lines = []
    for k, v in metrics.items():
        if v is None:
            why = ("no ground-truth masks in the capture (scored in the computed masks only)"
                   if k.endswith("_gt_mask") else "not measured")
            lines.append(f"{k}: n/a -- {why}")
        elif isinstance(v, float) and "psnr" in k:
            lines.append(f"{k}: {v:.2f} dB")
        elif isinstance(v, float) and "spill" in k:
            lines.append(f"{k}: {100 * v:.1f}% of the render's opacity outside the mask")
        elif isinstance(v, float):
            lines.append(f"{k}: {v:.3f}" if "ssim" in k else f"{k}: {v:.1f}")
        else:
            lines.append(f"{k}: {v}")
    lines.append(f"lpips: {lpips:.3f}" if isinstance(lpips, float)
                 else f"lpips: {lpips}; give --lpips-weights FILE")
    return lines


def write_outputs(result: TrainResult, masks: Optional[dict], out: Path,
                  extra: Optional[dict] = None, lpips_weights: Optional[str] = None) -> dict:
    """splats.ply, training.mcap, heldout/*.png, report.json/html, config.yaml; the report."""
    from PIL import Image

    from ..train.gaussians import save_ply

    out.mkdir(parents=True, exist_ok=True)
    save_ply(result.model, out / "splats.ply")
    (out / "heldout").mkdir(exist_ok=True)
    for h in result.heldout:
        Image.fromarray(h.render).save(out / "heldout" / f"{h.key}.png")
    write_training_bag(out / "training.mcap", result, masks)
    rep = result.metrics()
    rep["heldout"] = [{"key": h.key, "psnr": h.psnr, "ssim": h.ssim, "spill": h.spill,
                       "psnr_gt_mask": h.psnr_gt, "ssim_gt_mask": h.ssim_gt,
                       "spill_gt_mask": h.spill_gt} for h in result.heldout]
    rep["evals"] = result.evals
    rep["lpips"] = _lpips(result, lpips_weights)
    rep.update(extra or {})
    (out / "report.json").write_text(json.dumps(rep, indent=1))
    cfgmod.write_yaml(result.config, out / "config.yaml")
    rows = "".join(
        f"<tr><td>{html.escape(h.key)}<br>PSNR {h.psnr:.2f} dB<br>SSIM {h.ssim:.3f}"
        + ("" if h.psnr_gt is None else
           f"<br>in the ground-truth mask:<br>PSNR {h.psnr_gt:.2f} dB<br>SSIM {h.ssim_gt:.3f}")
        + ("" if h.spill is None else f"<br>opacity outside the mask: {100 * h.spill:.1f}%")
        + "</td>"
        f"<td><img src='data:image/png;base64,{_png_b64(np.concatenate([h.gt, h.render], 1))}'>"
        "</td></tr>" for h in result.heldout)
    summary = "".join(f"<li>{html.escape(line)}</li>"
                      for line in _summary_lines(result.metrics(), rep["lpips"]))
    (out / "report.html").write_text(
        "<!doctype html><html><head><meta charset='utf-8'><title>ooi-seg train</title></head>"
        f"<body><h1>Object-only splat training</h1><ul>{summary}</ul>"
        "<h2>Held-out views: ground truth (object only) | render</h2>"
        f"<table>{rows}</table></body></html>")
    return rep


SPLAT_TOPIC = "/train/splats"
T0_NS = 1_700_000_000_000_000_000  # bag time of iteration 0 (iteration k at T0 + k ms)


def splat_fields(model) -> dict[str, np.ndarray]:
    """PointCloud2 columns of a model, in 3DGS PLY order without the normals."""
    from ..train.gaussians import PLY_FIELDS, to_ply_array
    arr = to_ply_array(model)
    return {name: arr[:, j] for j, name in enumerate(PLY_FIELDS)
            if name not in ("nx", "ny", "nz")}


def write_training_bag(path: Path, result: TrainResult, masks: Optional[dict]) -> None:
    """training.mcap: splat snapshots, preview renders, masks and the loss/PSNR curves."""
    from ..bag import BagWriter, message_class
    from ..msgconv import fields_to_pointcloud2, mask_to_image, ns_to_stamp, rgb_to_image

    f32 = message_class("std_msgs/msg/Float32")
    with BagWriter(path) as bag:
        bag.add_topic(SPLAT_TOPIC, "sensor_msgs/msg/PointCloud2")
        for topic in ("/train/loss", "/train/psnr", "/train/heldout_psnr",
                      "/train/heldout_ssim", "/train/num_gaussians"):
            bag.add_topic(topic, "std_msgs/msg/Float32")
        if masks:
            bag.add_topic("/train/masks", "sensor_msgs/msg/Image")
            for k, key in enumerate(sorted(masks)):
                bag.write("/train/masks", mask_to_image(masks[key], ns_to_stamp(T0_NS + k),
                                                        frame_id=str(key)), T0_NS + k)
        for h in result.history:
            t = T0_NS + int(h["it"]) * 1_000_000
            bag.write("/train/loss", f32(data=float(h["loss"])), t)
            bag.write("/train/psnr", f32(data=float(h["psnr"])), t)
            bag.write("/train/num_gaussians", f32(data=float(h["n"])), t)
        for e in result.evals:
            t = T0_NS + int(e["it"]) * 1_000_000
            bag.write("/train/heldout_psnr", f32(data=float(e["psnr"])), t)
            bag.write("/train/heldout_ssim", f32(data=float(e["ssim"])), t)
        for it, model in result.snapshots:
            t = T0_NS + int(it) * 1_000_000
            bag.write(SPLAT_TOPIC, fields_to_pointcloud2(splat_fields(model), ns_to_stamp(t)), t)
        keys = sorted({key for _, key, _ in result.previews})
        for key in keys:
            bag.add_topic(f"/train/preview/v{keys.index(key)}", "sensor_msgs/msg/Image")
        for it, key, rgb in result.previews:
            t = T0_NS + int(it) * 1_000_000
            bag.write(f"/train/preview/v{keys.index(key)}",
                      rgb_to_image(rgb, ns_to_stamp(t), frame_id=str(key)), t)


def run(args: argparse.Namespace) -> int:
    from ..train.trainer import train

    cfg = _config(args)
    capture, masks, pts, cols = load_inputs(args)
    result = train(capture, masks, pts, cfg, init_colors=cols, show_progress=not args.quiet)
    rep = write_outputs(result, masks, Path(args.out),
                        lpips_weights=getattr(args, "lpips_weights", None))
    psnr, ssim = rep["heldout_psnr"], rep["heldout_ssim"]
    psnr_s = "n/a" if psnr is None else f"{psnr:.2f} dB"
    ssim_s = "n/a" if ssim is None else f"{ssim:.3f}"
    gt_s = ""
    if rep.get("heldout_psnr_gt_mask") is not None:
        gt_s = (f" (in the ground-truth masks: {rep['heldout_psnr_gt_mask']:.2f} dB, SSIM "
                f"{rep['heldout_ssim_gt_mask']:.3f})")
    print(f"wrote {args.out}: {rep['n_gaussians']} Gaussians, held-out masked PSNR {psnr_s}, "
          f"SSIM {ssim_s}{gt_s}, {rep['its_per_s']:.2f} it/s")
    return 0
