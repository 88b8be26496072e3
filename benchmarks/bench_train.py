"""Object-only vs full-image training under the same CPU budget and Gaussian cap.

For each simulator scene: a capture (default 60 views, 320x240), the OOI surface points as
initial cloud, ground-truth masks; then (a) object-only training (loss inside the masks, random
background, mask-aware MCMC) and (b) the same training on the full image without masks. Both
are scored on the held-out views (every 8th) by PSNR/SSIM inside the true object mask.

The budget is CPU time of the training process by default (``--clock cpu``, one thread): on a
shared machine a wall-clock budget mostly measures the other jobs. Wall and CPU seconds of
every run are printed.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_train.py --budget 600
        [--scenes aircraft,tabletop] [--size 320x240] [--views 60] [--max-gaussians 20000]
        [--clock cpu|wall] [--modes object-only,full-image]
        [--variant NAME:key=value,key=value ...]   # object-only TrainConfig variants
    .venv/bin/python benchmarks/bench_train.py --silhouette-cap --scenes aircraft,tabletop
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from ooi_seg_ros.train.loss import masked_psnr, masked_ssim
from ooi_seg_ros.train.raster_common import LOWPASS, RasterCamera
from ooi_seg_ros.train.raster_cpu import render
from ooi_seg_ros.train.trainer import TrainConfig, train


def _score_truth(model, sim, keys, lowpass: float = LOWPASS) -> tuple[float, float]:
    """Mean held-out (PSNR, SSIM) inside the true mask against the simulator's object-only
    truth (``SimCapture.object_truth``: outline pixels hold the object's share only, the
    view's exposure, no sensor noise) instead of the photo: what an exact object-only model
    would reach 100 dB on."""
    ps, ss = [], []
    index = {v.key: i for i, v in enumerate(sim.capture.views)}
    with torch.no_grad():
        for k in keys:
            v = sim.capture.views[index[k]]
            img = render(model, RasterCamera.from_view(v.camera, v.pose, lowpass=lowpass),
                         torch.zeros(3)).image
            m = torch.from_numpy(v.gt_mask)
            gt = torch.from_numpy(sim.object_truth(index[k])) * m[..., None]
            ps.append(masked_psnr(img, gt, m))
            ss.append(masked_ssim(img, gt, m))
    return float(np.mean(ps)), float(np.mean(ss))


def _score(model, capture, keys, lowpass: float = LOWPASS) -> tuple[float, float, float, float]:
    """Mean held-out (PSNR, SSIM) inside the true mask, PSNR inside the mask eroded by one
    pixel, and that interior PSNR after a per-channel gain fitted to each held-out view.

    The simulator anti-aliases silhouettes, so a mask pixel on the outline holds up to half
    background colour that an object-only model cannot render (see _silhouette_cap). It also
    varies the exposure per frame (3% gain), which no model can know for an unseen view; the
    last figure fits 3 gains per view by least squares inside the interior (as colour-corrected
    metrics do), to show how much of the error is that exposure.
    """
    from scipy.ndimage import binary_erosion

    ps, ss, pi, pg = [], [], [], []
    views = {v.key: v for v in capture.views}
    with torch.no_grad():
        for k in keys:
            v = views[k]
            img = render(model, RasterCamera.from_view(v.camera, v.pose, lowpass=lowpass),
                         torch.zeros(3)).image
            m = torch.from_numpy(v.gt_mask)
            gt = torch.from_numpy(v.image.astype(np.float32) / 255.0) * m[..., None]
            ps.append(masked_psnr(img, gt, m))
            ss.append(masked_ssim(img, gt, m))
            inner = torch.from_numpy(binary_erosion(v.gt_mask))
            pi.append(masked_psnr(img, gt, inner))
            r, g = img.clamp(0, 1)[inner], gt[inner]
            gain = (r * g).sum(0) / (r * r).sum(0).clamp_min(1e-12)
            pg.append(masked_psnr((img.clamp(0, 1) * gain).clamp(0, 1), gt, inner))
    return float(np.mean(ps)), float(np.mean(ss)), float(np.mean(pi)), float(np.mean(pg))


def _silhouette_cap(sim, keys) -> tuple[float, float]:
    """(share of mask pixels that are partly background, PSNR in mask of a perfect object-only
    render) on the held-out views.

    The simulator shades 2x2 sub-samples per pixel and puts a pixel in the mask when >= 2 of
    them hit the object, so an outline pixel's colour is c x object + (1 - c) x background
    (coverage c = 0.5 or 0.75). A perfect object-only model renders c x object over black, so
    it is off by (1 - c) x background there (taken from the nearest pixel no sub-sample of
    which hits the object). A model can beat this only by painting some average background
    colour into the outline, which differs from view to view.
    """
    import open3d as o3d
    from scipy import ndimage

    from ooi_seg_ros.core.types import Pose
    from ooi_seg_ros.sim.render import Renderer, camera_rays

    ren = Renderer(sim.scene)
    ss = sim.config.supersample
    views = {v.key: v for v in sim.capture.views}
    frac, caps = [], []
    for k in keys:
        v = views[k]
        dc, _ = camera_rays(v.camera, Pose.identity(), ss)
        d = dc.reshape(-1, 3).astype(np.float32) @ np.asarray(v.pose.R, np.float32).T
        o = np.broadcast_to(np.asarray(v.pose.t, np.float32), d.shape)
        ans = ren.rs.cast_rays(o3d.core.Tensor(np.ascontiguousarray(np.concatenate([o, d], 1))))
        hit = np.isfinite(ans["t_hit"].numpy())
        prim = np.where(hit, ans["primitive_ids"].numpy().astype(np.int64), 0)
        h, w = v.gt_mask.shape
        c = (hit & ren.tri_ooi[prim]).reshape(h, w, ss * ss).mean(-1)
        m = v.gt_mask
        img = v.image.astype(np.float32) / 255.0
        near = ndimage.distance_transform_edt(c > 0, return_distances=False, return_indices=True)
        err = (1.0 - c)[..., None] * img[near[0], near[1]]
        frac.append(float(((c < 1) & m).sum() / max(1, m.sum())))
        caps.append(float(-10 * np.log10(max((err[m] ** 2).mean(), 1e-12))))
    return float(np.mean(frac)), float(np.mean(caps))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="aircraft")
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--views", type=int, default=60)
    ap.add_argument("--budget", type=float, default=600.0, help="seconds per training run")
    ap.add_argument("--iterations", type=int, default=100000)
    ap.add_argument("--max-gaussians", type=int, default=20000)
    ap.add_argument("--init-points", type=int, default=5000)
    ap.add_argument("--clock", default="cpu", choices=("cpu", "wall"))
    ap.add_argument("--modes", default="object-only,full-image")
    ap.add_argument("--variant", action="append", default=[],
                    help="NAME:key=value,... an object-only run with these TrainConfig values "
                    "(repeatable; replaces the object-only mode); NAME alone = defaults")
    ap.add_argument("--sim-shade-subsamples", action="store_true",
                    help="simulate with every 2x2 sub-sample shaded (texture integrated over "
                         "the pixel) instead of the default point-sampled texture")
    ap.add_argument("--silhouette-cap", action="store_true",
                    help="only print the PSNR cap a perfect object-only model has (no training)")
    a = ap.parse_args()
    torch.set_num_threads(1)
    from ooi_seg_ros.sim import simulate_capture
    w, h = (int(x) for x in a.size.split("x"))
    if not a.silhouette_cap:
        print(f"{'scene':>10} {'mode':>11} {'its':>6} {'N':>6} {'PSNR(mask)':>10} "
              f"{'SSIM(mask)':>10} {'PSNR(interior)':>14} {'gain-fit':>8} "
              f"{'PSNR/SSIM(obj truth)':>20} {'cpu s':>7} {'wall s':>7}")
    for scene in a.scenes.split(","):
        sim = simulate_capture(scene, n_views=a.views, width=w, height=h, seed=0,
                               shade_subsamples=a.sim_shade_subsamples)
        cap = sim.capture
        if a.silhouette_cap:
            held = [v.key for i, v in enumerate(cap.views) if i % 8 == 0]
            frac, cap_db = _silhouette_cap(sim, held)
            print(f"{scene:>10} partly-background mask pixels {frac:.3f}, PSNR cap of a perfect "
                  f"object-only render {cap_db:.2f} dB", flush=True)
            continue
        rng = np.random.default_rng(0)
        pts = cap.gt_ooi_points
        pts = pts[rng.choice(len(pts), min(a.init_points, len(pts)), replace=False)]
        masks = {v.key: v.gt_mask for v in cap.views}
        runs = []
        for mode in a.modes.split(","):
            if mode == "object-only" and a.variant:
                runs += [_parse_variant(v) for v in a.variant]
            else:
                runs.append((mode, {"full_image": mode == "full-image"}))
        for name, extra in runs:
            kw = dict(iterations=a.iterations, max_gaussians=a.max_gaussians,
                      time_budget_s=a.budget, budget_clock=a.clock, eval_every=0,
                      snapshot_every=0)
            kw.update(extra)
            cfg = TrainConfig(**kw)
            r = train(cap, None if cfg.full_image else masks, pts, cfg)
            p, s, pi, pg = _score(r.model, cap, r.heldout_keys, cfg.lowpass)
            pt, st = _score_truth(r.model, sim, r.heldout_keys, cfg.lowpass)
            print(f"{scene:>10} {name:>11} {r.iterations_done:>6} {len(r.model):>6} "
                  f"{p:>10.2f} {s:>10.3f} {pi:>14.2f} {pg:>8.2f} "
                  f"{f'{pt:.2f} / {st:.3f}':>20} {r.cpu_seconds:>7.0f} {r.seconds:>7.0f}",
                  flush=True)


def _parse_variant(text: str) -> tuple[str, dict]:
    """"name:key=value,key=value" -> (name, {key: value}) with values typed like the
    TrainConfig field they set."""
    from dataclasses import fields

    name, _, rest = text.partition(":")
    types = {f.name: type(f.default) for f in fields(TrainConfig)}
    out: dict = {}
    for item in filter(None, rest.split(",")):
        key, _, val = item.partition("=")
        if key not in types:
            raise SystemExit(f"unknown TrainConfig field {key!r} in --variant {text!r}")
        typ = types[key]
        out[key] = (val.lower() in ("1", "true", "yes")) if typ is bool else typ(val)
    return name, out


if __name__ == "__main__":
    main()
