"""Object-only training with the gsplat (CUDA) back-end, side by side with the CPU back-end.

Two steps, because the GPU machine has no simulator dependencies (open3d) and no network:

    # here: simulate the scenes and pack what training needs (images, GT masks, poses, K,
    # true surface points) into one .npz per scene
    .venv/bin/python benchmarks/bench_train_gpu.py export --scenes aircraft,tabletop,bicycle \
        --out .gpu
    # on the CUDA machine (gsplat installed): train object-only and full-image with the same
    # Gaussian cap for the same number of steps, and time the CPU back-end on the same scene
    python3 benchmarks/bench_train_gpu.py run --data .gpu --budget 120

Scores are the held-out views (every 8th, never trained on), PSNR and SSIM inside the true
object mask, the final model rendered by the *CPU* rasteriser, so that a model trained with
gsplat is scored by the other back-end (a mismatch between them would show as a drop).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from ooi_seg_ros.core.types import CameraIntrinsics, Capture, Pose, View
from ooi_seg_ros.train.trainer import TrainConfig, train


def export(scenes: list[str], out: Path, views: int, size: str, shade: bool = False) -> None:
    """Simulate each scene and write OUT/<scene>.npz (OUT/<scene>_ss.npz with ``shade``: the
    texture integrated over each pixel, the simulator's ``shade_subsamples``)."""
    from ooi_seg_ros.sim import simulate_capture
    w, h = (int(x) for x in size.split("x"))
    out.mkdir(parents=True, exist_ok=True)
    for scene in scenes:
        opts = {"shade_subsamples": True} if shade else {}
        cap = simulate_capture(scene, n_views=views, width=w, height=h, seed=0, **opts).capture
        c = cap.views[0].camera
        name = f"{scene}_ss" if shade else scene
        np.savez_compressed(
            out / f"{name}.npz", images=np.stack([v.get_image() for v in cap.views]),
            masks=np.stack([v.gt_mask for v in cap.views]),
            poses=np.stack([v.pose.matrix() for v in cap.views]),
            keys=np.array([v.key for v in cap.views]),
            stamps=np.array([v.stamp_ns for v in cap.views]),
            K=np.array([c.width, c.height, c.fx, c.fy, c.cx, c.cy]), ooi=cap.gt_ooi_points)
        print(f"{name}: {len(cap.views)} views -> {out / (name + '.npz')}", flush=True)


def load(path: Path) -> Capture:
    d = np.load(path)
    w, h, fx, fy, cx, cy = d["K"]
    cam = CameraIntrinsics(int(w), int(h), float(fx), float(fy), float(cx), float(cy))
    views = [View(str(k), int(s), cam, Pose.from_matrix(p), image=img, gt_mask=m)
             for k, s, p, img, m in zip(d["keys"], d["stamps"], d["poses"], d["images"],
                                        d["masks"])]
    return Capture(views, source=str(path), gt_ooi_points=d["ooi"])


def score(model, capture: Capture, keys: list[str], lowpass: float
          ) -> tuple[float, float, float, float]:
    """Held-out PSNR / SSIM in the true mask, PSNR in the mask eroded by one pixel and that
    interior PSNR after a per-channel gain per view (``bench_train._score``), rendered by the
    CPU rasteriser with the low-pass the model was trained with (rendering a model at another
    one blurs or sharpens it). The interior figure is the fair one between object-only and
    full-image models: on the outline a full-image model paints the photo's blend of object
    and background, which the in-mask PSNR rewards, and outside the mask it paints background
    where the masked target is black, which the in-mask SSIM's windows punish."""
    from bench_train import _score
    return _score(model.to("cpu"), capture, keys, lowpass)


def run(data: Path, budget: float, cap_n: int, cpu_steps: int, out: Path | None,
        scenes: list[str] | None = None, iterations: int = 0,
        modes: tuple[str, ...] = ("object-only", "full-image")) -> None:
    rows = []
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)  # the render and the JSON go there
    print(f"{'scene':>9} {'backend':>7} {'mode':>11} {'steps':>6} {'it/s':>7} {'N':>6} "
          f"{'PSNR(mask)':>10} {'SSIM(mask)':>10} {'interior':>8} {'gain-fit':>8}  (the "
          f"trainer's own figure: in the mask, over the whole image for full-image)", flush=True)
    for path in sorted(data.glob("*.npz")):
        if scenes and path.stem not in scenes:
            continue
        cap = load(path)
        rng = np.random.default_rng(0)
        pts = cap.gt_ooi_points
        pts = pts[rng.choice(len(pts), min(5000, len(pts)), replace=False)]
        masks = {v.key: v.gt_mask for v in cap.views}
        # speed probe with each back-end on the same scene, same start
        probe = {"cpu": 0.0, "gsplat": 0.0}
        for backend, steps in (("cpu", cpu_steps), ("gsplat", 200)) if not iterations else ():
            cfg = TrainConfig(iterations=steps, max_gaussians=cap_n, backend=backend,
                              eval_every=0, snapshot_every=0, threads=0)
            t0 = time.time()
            r = train(cap, masks, pts, cfg)
            probe[backend] = r.its_per_s
            rows.append({"scene": path.stem, "backend": backend, "mode": "probe",
                         "steps": steps, "its_per_s": r.its_per_s, "wall": time.time() - t0})
            print(f"{path.stem:>9} {backend:>7} {'probe':>11} {steps:>6} {r.its_per_s:>7.2f}",
                  flush=True)
        iters = iterations or max(500, int(probe["gsplat"] * budget * 0.9))
        for mode in modes:
            cfg = TrainConfig(iterations=iters, max_gaussians=cap_n, backend="gsplat",
                              full_image=mode == "full-image", eval_every=0,
                              snapshot_every=0, threads=0,
                              sh_degree_interval=max(300, iters // 10),
                              refine_every=100)
            r = train(cap, None if cfg.full_image else masks, pts, cfg)
            p, s, pin, pgain = score(r.model, cap, r.heldout_keys, cfg.lowpass)
            own = r.metrics()
            rows.append({"scene": path.stem, "backend": "gsplat", "mode": mode, "steps":
                         r.iterations_done, "its_per_s": r.its_per_s, "n": len(r.model),
                         "psnr_cpu_scored": p, "ssim_cpu_scored": s,
                         "psnr_interior": pin, "psnr_interior_gain_fit": pgain,
                         "psnr_gsplat_scored": own["heldout_psnr"],
                         "ssim_gsplat_scored": own["heldout_ssim"], "seconds": r.seconds})
            print(f"{path.stem:>9} {'gsplat':>7} {mode:>11} {r.iterations_done:>6} "
                  f"{r.its_per_s:>7.2f} {len(r.model):>6} {p:>10.2f} {s:>10.3f} {pin:>8.2f} "
                  f"{pgain:>8.2f}  (gsplat-scored {own['heldout_psnr']:.2f}/"
                  f"{own['heldout_ssim']:.3f}, "
                  f"{r.seconds:.0f} s)", flush=True)
            if out is not None and mode == "object-only":
                from PIL import Image
                h = r.heldout[1 % len(r.heldout)]
                Image.fromarray(np.concatenate([h.gt, h.render], 1)).save(
                    out / f"{path.stem}_{iters}_{h.key}.png")
        if out is not None:
            (out / f"bench_train_gpu_{'_'.join(scenes or ['all'])}.json").write_text(
                json.dumps(rows, indent=1))
        if iterations:
            continue
        print(f"{path.stem:>9} speed ratio gsplat/cpu = "
              f"{probe['gsplat'] / max(probe['cpu'], 1e-9):.1f}x", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("export")
    e.add_argument("--scenes", default="aircraft,tabletop,bicycle")
    e.add_argument("--out", default=".gpu")
    e.add_argument("--views", type=int, default=60)
    e.add_argument("--size", default="320x240")
    e.add_argument("--shade-subsamples", action="store_true",
                   help="texture integrated over each pixel (written as <scene>_ss.npz)")
    r = sub.add_parser("run")
    r.add_argument("--data", default=".gpu")
    r.add_argument("--budget", type=float, default=120.0, help="seconds per gsplat run")
    r.add_argument("--max-gaussians", type=int, default=20000)
    r.add_argument("--cpu-steps", type=int, default=30, help="steps of the CPU speed probe")
    r.add_argument("--out", default=None, help="folder for JSON rows and sample renders")
    r.add_argument("--scenes", default="", help="comma list (default: every .npz in --data)")
    r.add_argument("--iterations", type=int, default=0,
                   help="fixed step count instead of --budget (skips the speed probes)")
    r.add_argument("--modes", default="object-only,full-image")
    a = ap.parse_args()
    if a.cmd == "export":
        export(a.scenes.split(","), Path(a.out), a.views, a.size, a.shade_subsamples)
    else:
        run(Path(a.data), a.budget, a.max_gaussians, a.cpu_steps,
            Path(a.out) if a.out else None, [x for x in a.scenes.split(",") if x],
            a.iterations, tuple(a.modes.split(",")))


if __name__ == "__main__":
    main()
