"""Forward+backward throughput of the CPU tile rasteriser next to the brute-force reference.

Random Gaussians filling a sphere in front of the camera (a dense object-like footprint), SH
degree --sh-degree (3: what training runs at after its first ~1000 steps).
Prints it/s in the same run for: the tile rasteriser with the compiled kernel (projection, SH
colour and compositing, the default), the same with the projection and SH colour under torch
autograd (the default until session 5), the rasteriser on its pure-torch path, and the
brute-force reference (only where its dense
[N, H*W] tensors fit in --ref-max-elems). The torch path is skipped where it would exceed
--torch-max-pairs tile pairs (it takes tens of seconds per iteration there).

Rates are iterations per second of this process's CPU time (one thread), best of --reps: on a
shared machine wall-clock rates mostly measure the other jobs; the wall-clock rate of the
kernel path is printed as well.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_raster.py [--sizes 320x240,640x480]
        [--counts 10000,50000,200000] [--reps 3] [--threads 1] [--sh-degree 3]
"""

from __future__ import annotations

import argparse
import functools
import time

import numpy as np
import torch

from ooi_seg_ros.core.geometry import look_at
from ooi_seg_ros.core.types import CameraIntrinsics
from ooi_seg_ros.train import raster_cpu, raster_kernel, raster_reference
from ooi_seg_ros.train.gaussians import init_from_points
from ooi_seg_ros.train.raster_common import RasterCamera, project


def _kernel_torch_projection(model, cam, bg):
    """Compiled compositing after the torch-autograd projection (the pre-session-5 default)."""
    pr = project(model.means, model.log_scales, model.quats, model.logit_opacities,
                 model.sh_dc, model.sh_rest, cam, model.sh_degree)
    return raster_cpu.rasterize(pr, cam, bg, kernel=True)


def _time(fn, model, cam, reps: int) -> tuple[float, int, float]:
    """(it/s by CPU time, tile pairs, it/s by wall time), best of ``reps``."""
    bg = torch.zeros(3)
    best, best_wall, inter = float("inf"), float("inf"), 0
    for _ in range(reps):
        for p in model.params().values():
            p.grad = None
        t, tw = time.process_time(), time.perf_counter()
        out = fn(model, cam, bg)
        out.image.sum().backward()
        best = min(best, time.process_time() - t)
        best_wall = min(best_wall, time.perf_counter() - tw)
        inter = out.n_intersections
    return 1.0 / max(best, 1e-6), inter, 1.0 / max(best_wall, 1e-6)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="320x240,640x480")
    ap.add_argument("--counts", default="10000,50000,200000")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--ref-max-elems", type=float, default=3e8)
    ap.add_argument("--torch-max-pairs", type=float, default=3e5)
    ap.add_argument("--sh-degree", type=int, default=3)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    if not raster_kernel.available():
        print(f"kernel unavailable: {raster_kernel.unavailable_reason()}")
        return
    rng = np.random.default_rng(0)
    kern = functools.partial(raster_cpu.render, kernel=True)
    torch_path = functools.partial(raster_cpu.render, kernel=False)
    print(f"{'size':>8} {'N':>7} {'pairs':>9} {'kernel it/s':>12} {'k+torch proj':>13} "
          f"{'torch it/s':>11} {'reference it/s':>15} {'kernel wall it/s':>17}")
    for size in a.sizes.split(","):
        w, h = (int(x) for x in size.split("x"))
        cam = CameraIntrinsics(width=w, height=h, fx=0.9 * w, fy=0.9 * w, cx=(w - 1) / 2,
                               cy=(h - 1) / 2)
        rc = RasterCamera.from_view(cam, look_at(np.array([3.0, 0.0, 1.0]), np.zeros(3)))
        for n in (int(c) for c in a.counts.split(",")):
            d = rng.normal(size=(n, 3))
            pts = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.5, 1.0, (n, 1))
            m = init_from_points(pts, rng.integers(0, 255, (n, 3)), 0.5)
            m.sh_degree = a.sh_degree
            with torch.no_grad():
                m.sh_rest.normal_(0.0, 0.1, generator=torch.Generator().manual_seed(n))
            m.requires_grad_(True)
            tile, pairs, wall = _time(kern, m, rc, a.reps)
            ktp = _time(_kernel_torch_projection, m, rc, a.reps)[0]
            tor = "skipped"
            if pairs <= a.torch_max_pairs:
                tor = f"{_time(torch_path, m, rc, a.reps)[0]:.3f}"
            ref = "n/a (memory)"
            if n * w * h <= a.ref_max_elems:
                ref = f"{_time(raster_reference.render, m, rc, 1)[0]:.3f}"
            print(f"{size:>8} {n:>7} {pairs:>9} {tile:>12.3f} {ktp:>13.3f} {tor:>11} {ref:>15} "
                  f"{wall:>17.3f}", flush=True)


if __name__ == "__main__":
    main()
