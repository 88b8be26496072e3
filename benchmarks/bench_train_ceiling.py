"""How consistent are the simulator's images with any 3D model? A ceiling for held-out PSNR.

The simulator shades a pixel whose 2x2 sub-samples all hit the same part ONCE, at the mean
sub-sample point (``sim/render.py``: adaptive anti-aliasing): inside a part the texture is
point-sampled, one sample per pixel. Texture detail finer than a pixel (noise octaves, panel
lines a few cm wide seen from ~20 m) is then aliased: where the sample lands decides whether a
pixel sees a line or not, and that changes from view to view. No 3D model can reproduce such
per-view aliasing for a view it has not seen; the best it can do is the pixel-integrated
(band-limited) image.

For the held-out views (every 8th) this renders the object-only view (as
``SimCapture.object_truth``: the view's exposure, no sensor noise, over black) at 1x -- what the
training and held-out images are made of -- and at ``k`` x the resolution, box-averaged back
(k x k shading samples per pixel: the pixel-integrated image ``F``), and prints PSNR inside the
true mask and its 1-px-eroded interior:

- ``1x vs F``: how far the simulator's own image is from the pixel integral -- the error a
  model that renders ``F`` exactly makes against the object-only truth (the ceiling of
  ``bench_heldout_truth.py``'s figure up to the outline's 2x2 vs k x k coverage).
- ``photo vs F`` (interior): the same against the photo (adds sensor noise), the ceiling of
  ``bench_train.py``'s interior figure.
- ``F_k vs F_2k`` on the first held-out view: that ``F`` has converged.

    OMP_NUM_THREADS=1 nice -n 19 .venv/bin/python benchmarks/bench_train_ceiling.py \
        --scenes aircraft,tabletop [--factor 4] [--views 60] [--size 320x240] [--save DIR]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_erosion

from ooi_seg_ros.core.types import CameraIntrinsics
from ooi_seg_ros.sim import simulate_capture
from ooi_seg_ros.sim.capture import _view_rng
from ooi_seg_ros.sim.render import Renderer


def _psnr(a: np.ndarray, b: np.ndarray, m: np.ndarray) -> float:
    return float(-10 * np.log10(max(((a[m] - b[m]) ** 2).mean(), 1e-12)))


def _scaled(cam: CameraIntrinsics, k: int, shift: tuple[float, float] = (0.0, 0.0)
            ) -> CameraIntrinsics:
    """The camera whose k x k pixels tile each pixel of ``cam`` (pixel centres at integer
    coordinates: sub-pixel j of pixel i sits at i - 0.5 + (j + 0.5) / k), optionally moved by
    ``shift`` pixels of ``cam`` (x, y)."""
    return CameraIntrinsics(cam.width * k, cam.height * k, cam.fx * k, cam.fy * k,
                            k * (cam.cx + shift[0]) + (k - 1) / 2.0,
                            k * (cam.cy + shift[1]) + (k - 1) / 2.0)


def _render(ren: Renderer, cam: CameraIntrinsics, pose, k: int, exposure: float,
            ss: int, shift: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Object-only render (float 0..1, no noise) at k x the resolution, box-averaged to
    ``cam``'s size."""
    res = ren.render(_scaled(cam, k, shift), pose, ss, None, 0.0, exposure, object_only=True)
    img = res.rgb.astype(np.float32) / 255.0
    h, w = cam.height, cam.width
    return img.reshape(h, k, w, k, 3).mean((1, 3))


def pixel_integrated(sim, index: int, k: int = 4, cache: Path | None = Path("/tmp/ooi_F")
                     ) -> np.ndarray:
    """``F`` of view ``index`` of a SimCapture (float32 [H, W, 3]): the object-only render
    at k x the resolution with 2x2 sub-samples, box-averaged (cached as .npy in ``cache``)."""
    cfg = sim.config
    name = f"F_{cfg.scene}_{cfg.seed}_{cfg.n_views}_{cfg.width}x{cfg.height}_k{k}_{index}.npy"
    if cache is not None and (cache / name).exists():
        return np.load(cache / name)
    rng = _view_rng(cfg.seed, index)
    expo = float(np.clip(1.0 + rng.normal(0, cfg.exposure_jitter), 0.8, 1.2))
    v = sim.capture.views[index]
    f = _render(Renderer(sim.scene), v.camera, v.pose, k, expo, 2).astype(np.float32)
    if cache is not None:  # written under a temporary name, then renamed: runs share it
        cache.mkdir(parents=True, exist_ok=True)
        tmp = cache / f"{name}.{os.getpid()}.tmp.npy"
        np.save(tmp, f)
        os.replace(tmp, cache / name)
    return f


def _convergence(sim, ren: Renderer, scene: str) -> None:
    """PSNR of k x k shading samples per pixel (k = 1..4) against 8 x 8, first view."""
    cfg = sim.config
    v = sim.capture.views[0]
    rng = _view_rng(cfg.seed, 0)
    expo = float(np.clip(1.0 + rng.normal(0, cfg.exposure_jitter), 0.8, 1.2))
    ref = _render(ren, v.camera, v.pose, 8, expo, 1)
    m = v.gt_mask
    inner = binary_erosion(m)
    for kk in (1, 2, 3, 4):
        t = time.process_time()
        # 2x2 sub-samples at k x the resolution, coherent ones shaded once: k x k shading
        # samples per pixel (k = 1: exactly the simulator's image)
        img = _render(ren, v.camera, v.pose, kk, expo, 2)
        print(f"{scene:>10} view 0: {kk}x{kk} shading samples per pixel vs 8x8: "
              f"{_psnr(img, ref, m):.2f} dB mask, {_psnr(img, ref, inner):.2f} dB interior "
              f"({time.process_time() - t:.1f} CPU-s)", flush=True)


def _ablate(sim, scene: str, k: int) -> None:
    """1x vs F (interior, PSNR of the mean MSE over views 0, 24, 48) with one texture feature
    of every material removed (a copy of the scene; the simulator is not changed)."""
    import copy
    from dataclasses import replace

    cfg = sim.config
    variants = {"as simulated": {}, "no panel-line grid": {"grid": None},
                "no decals": {"decals": ()}, "no spots": {"spot_frac": 0.0},
                "noise octaves <= 4": {"octaves": 4},
                "none of these": {"grid": None, "decals": (), "spot_frac": 0.0, "octaves": 4}}
    for label, change in variants.items():
        sc = copy.copy(sim.scene)
        sc.materials = {n: replace(m, **{key: (min(m.octaves, val) if key == "octaves" else val)
                                         for key, val in change.items()})
                        for n, m in sim.scene.materials.items()}
        ren = Renderer(sc)
        mse = []
        for i in (0, 24, 48):
            v = sim.capture.views[i]
            rng = _view_rng(cfg.seed, i)
            expo = float(np.clip(1.0 + rng.normal(0, cfg.exposure_jitter), 0.8, 1.2))
            one = _render(ren, v.camera, v.pose, 1, expo, cfg.supersample)
            f = _render(ren, v.camera, v.pose, k, expo, 2)
            inner = binary_erosion(v.gt_mask)
            mse.append(float(((one[inner] - f[inner]) ** 2).mean()))
        print(f"{scene:>10} {label:>20}: 1x vs F interior {-10 * np.log10(np.mean(mse)):.2f} dB",
              flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="aircraft,tabletop")
    ap.add_argument("--views", type=int, default=60)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--factor", type=int, default=4, help="supersampling factor of F per side")
    ap.add_argument("--convergence", action="store_true",
                    help="only: the first held-out view shaded at k x k samples per pixel "
                    "(k = 1..4; k = 1 is the simulator's image) against 8 x 8, with the CPU "
                    "seconds of each render -- what a simulator fix would cost and give")
    ap.add_argument("--ablate", action="store_true",
                    help="only: 1x vs F on views 0, 24, 48 with one texture feature of the "
                    "object's materials removed at a time (panel-line grid, decals, spots, "
                    "noise octaves above 4) -- which feature the aliasing comes from")
    ap.add_argument("--save", type=Path, default=None,
                    help="write 1x | F | 4x|1x - F| strips of the held-out views here (PNG)")
    a = ap.parse_args()
    w, h = (int(x) for x in a.size.split("x"))
    k = a.factor
    print(f"{'scene':>10} {'view':>5} {'1x vs F (mask)':>14} {'1x vs F (int)':>13} "
          f"{'photo vs F (int)':>16} {'photo vs 1x (int)':>17}")
    for scene in a.scenes.split(","):
        t0 = time.process_time()
        sim = simulate_capture(scene, n_views=a.views, width=w, height=h, seed=0)
        ren = Renderer(sim.scene)
        cfg = sim.config
        if a.convergence:
            _convergence(sim, ren, scene)
            continue
        if a.ablate:
            _ablate(sim, scene, k)
            continue
        rows = []
        for i, v in enumerate(sim.capture.views):
            if i % 8:
                continue
            rng = _view_rng(cfg.seed, i)
            expo = float(np.clip(1.0 + rng.normal(0, cfg.exposure_jitter), 0.8, 1.2))
            one = sim.object_truth(i)
            f = pixel_integrated(sim, i, k)
            m = v.gt_mask
            inner = binary_erosion(m)
            photo = v.image.astype(np.float32) / 255.0
            r = (_psnr(one, f, m), _psnr(one, f, inner), _psnr(photo, f, inner),
                 _psnr(photo, one, inner))
            rows.append(r)
            print(f"{scene:>10} {i:>5} {r[0]:>14.2f} {r[1]:>13.2f} {r[2]:>16.2f} {r[3]:>17.2f}",
                  flush=True)
            if i == 0:
                f2 = _render(ren, v.camera, v.pose, 2 * k, expo, 1)
                print(f"{scene:>10} view 0: F_{k} vs F_{2 * k} (interior) "
                      f"{_psnr(f, f2, inner):.2f} dB (F has converged when this is high)",
                      flush=True)
            if a.save is not None:
                from PIL import Image

                a.save.mkdir(parents=True, exist_ok=True)
                err = np.clip(4 * np.abs(one - f) * m[..., None], 0, 1)
                strip = np.concatenate([one, f, err], 1)
                Image.fromarray((strip * 255 + 0.5).astype(np.uint8)).save(
                    a.save / f"ceiling_{scene}_{i:02d}.png")
        t = np.array(rows)
        mse = lambda c: float(-10 * np.log10(np.mean(10 ** (-t[:, c] / 10))))  # noqa: E731
        print(f"{scene:>10} {'mean':>5} {t[:, 0].mean():>14.2f} {t[:, 1].mean():>13.2f} "
              f"{t[:, 2].mean():>16.2f} {t[:, 3].mean():>17.2f}   (PSNR of the mean MSE: "
              f"{mse(0):.2f} {mse(1):.2f} {mse(2):.2f}; {time.process_time() - t0:.0f} CPU-s)",
              flush=True)


if __name__ == "__main__":
    main()
