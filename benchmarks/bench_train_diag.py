"""Where a trained model's held-out error comes from: training-view vs held-out PSNR, the score
against the pixel-integrated truth, the held-out curve, and error images.

Trains like ``bench_train.py`` (object-only, the capture's OOI surface points as the start,
ground-truth masks, CPU-time budget) -- or loads a model saved by an earlier run -- and prints,
inside the true masks:

- held-out views (every 8th, never trained on) against the photo: full mask and the 1-px
  eroded interior; against ``SimCapture.object_truth``; and against ``F``, the pixel-integrated
  object-only image (``bench_train_ceiling.py``: k x k shading samples per pixel);
- the same for ``--train-views`` training views: if those score far higher than the held-out
  ones, the model learned view-specific detail (overfitting); if both are low, it underfits;
- with ``--eval-every`` the held-out PSNR during training (the curve's shape);
- with ``--save-png DIR`` one strip per held-out view: photo | render | 4 x |error| (interior).

    OMP_NUM_THREADS=1 nice -n 19 .venv/bin/python benchmarks/bench_train_diag.py \
        --scene aircraft --budget 600 --max-gaussians 20000 [--variant NAME:key=value,...] \
        [--save-model FILE] [--load-model FILE] [--eval-every 1000] [--save-png DIR]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import binary_erosion

from ooi_seg_ros.train.gaussians import GaussianModel
from ooi_seg_ros.train.loss import masked_psnr, masked_ssim
from ooi_seg_ros.train.raster_common import LOWPASS, RasterCamera
from ooi_seg_ros.train.raster_cpu import render
from ooi_seg_ros.train.trainer import TrainConfig, train

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_train import _parse_variant  # noqa: E402
from bench_train_ceiling import pixel_integrated  # noqa: E402


def _scores(model: GaussianModel, sim, indices: list[int], with_f: bool, k: int,
            lowpass: float, png: Path | None = None, tag: str = "") -> dict:
    """Mean PSNR / SSIM of ``model`` on the views ``indices`` inside the true mask."""
    out: dict[str, list] = {"photo": [], "ssim": [], "interior": [], "truth": [], "F": [],
                            "F_int": []}
    with torch.no_grad():
        for i in indices:
            v = sim.capture.views[i]
            img = render(model, RasterCamera.from_view(v.camera, v.pose, lowpass=lowpass),
                         torch.zeros(3)).image.clamp(0, 1)
            m = torch.from_numpy(v.gt_mask)
            inner = torch.from_numpy(binary_erosion(v.gt_mask))
            photo = torch.from_numpy(v.image.astype(np.float32) / 255.0) * m[..., None]
            out["photo"].append(masked_psnr(img, photo, m))
            out["ssim"].append(masked_ssim(img, photo, m))
            out["interior"].append(masked_psnr(img, photo, inner))
            out["truth"].append(masked_psnr(img, torch.from_numpy(sim.object_truth(i)), m))
            if with_f:
                f = torch.from_numpy(pixel_integrated(sim, i, k))
                out["F"].append(masked_psnr(img, f, m))
                out["F_int"].append(masked_psnr(img, f, inner))
            if png is not None:
                from PIL import Image

                png.mkdir(parents=True, exist_ok=True)
                err = (4 * (img - photo).abs() * inner[..., None]).clamp(0, 1)
                strip = torch.cat([photo, img, err], 1).numpy()
                Image.fromarray((strip * 255 + 0.5).astype(np.uint8)).save(
                    png / f"diag_{tag}_{i:02d}.png")
    return {key: float(np.mean(val)) for key, val in out.items() if val}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="aircraft")
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--views", type=int, default=60)
    ap.add_argument("--budget", type=float, default=600.0, help="CPU seconds of training")
    ap.add_argument("--iterations", type=int, default=100000)
    ap.add_argument("--max-gaussians", type=int, default=20000)
    ap.add_argument("--init-points", type=int, default=5000)
    ap.add_argument("--variant", default="baseline", help="NAME:key=value,... TrainConfig")
    ap.add_argument("--eval-every", type=int, default=0)
    ap.add_argument("--train-views", type=int, default=8,
                    help="training views scored (evenly spread over the capture)")
    ap.add_argument("--factor", type=int, default=4, help="F's supersampling per side")
    ap.add_argument("--no-f", action="store_true", help="skip the pixel-integrated truth")
    ap.add_argument("--save-model", type=Path, default=None)
    ap.add_argument("--load-model", type=Path, default=None)
    ap.add_argument("--save-png", type=Path, default=None)
    a = ap.parse_args()
    torch.set_num_threads(1)
    from ooi_seg_ros.sim import simulate_capture

    w, h = (int(x) for x in a.size.split("x"))
    sim = simulate_capture(a.scene, n_views=a.views, width=w, height=h, seed=0)
    cap = sim.capture
    name, extra = _parse_variant(a.variant)
    if a.load_model is not None:
        d = torch.load(a.load_model)
        model = GaussianModel(**d["params"], sh_degree=d["sh_degree"])
        steps, cpu = d["steps"], d["cpu"]
        evals = d.get("evals", [])
        lowpass = d.get("lowpass", LOWPASS)
    else:
        rng = np.random.default_rng(0)
        pts = cap.gt_ooi_points
        pts = pts[rng.choice(len(pts), min(a.init_points, len(pts)), replace=False)]
        masks = {v.key: v.gt_mask for v in cap.views}
        kw = dict(iterations=a.iterations, max_gaussians=a.max_gaussians,
                  time_budget_s=a.budget, budget_clock="cpu", eval_every=a.eval_every,
                  snapshot_every=0)
        kw.update(extra)
        r = train(cap, masks, pts, TrainConfig(**kw))
        model, steps, cpu, evals = r.model, r.iterations_done, r.cpu_seconds, r.evals
        lowpass = r.config.lowpass
        if a.save_model is not None:
            a.save_model.parent.mkdir(parents=True, exist_ok=True)
            torch.save({"params": model.params(), "sh_degree": model.sh_degree,
                        "steps": steps, "cpu": cpu, "evals": evals, "variant": a.variant,
                        "lowpass": lowpass},
                       a.save_model)
    held = [i for i in range(len(cap.views)) if i % 8 == 0]
    rest = [i for i in range(len(cap.views)) if i % 8]
    pick = np.linspace(0, len(rest) - 1, min(a.train_views, len(rest))).round().astype(int)
    trn = [rest[j] for j in pick]
    sh = _scores(model, sim, held, not a.no_f, a.factor, lowpass, a.save_png,
                 f"{a.scene}_{name}")
    st = _scores(model, sim, trn, not a.no_f, a.factor, lowpass)
    print(f"{a.scene} {name}: {steps} steps, {len(model)} Gaussians, {cpu:.0f} CPU-s")
    print(f"{'views':>10} {'photo mask':>10} {'SSIM':>6} {'interior':>8} {'obj truth':>9} "
          f"{'F mask':>7} {'F int':>7}")
    for label, s in (("held-out", sh), ("training", st)):
        print(f"{label:>10} {s['photo']:>10.2f} {s['ssim']:>6.3f} {s['interior']:>8.2f} "
              f"{s['truth']:>9.2f} {s.get('F', float('nan')):>7.2f} "
              f"{s.get('F_int', float('nan')):>7.2f}")
    if evals:
        print("held-out curve (photo, mask): " + ", ".join(
            f"{e['it']}: {e['psnr']:.2f}/{e['ssim']:.3f}" for e in evals))


if __name__ == "__main__":
    main()
