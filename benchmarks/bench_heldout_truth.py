"""Scores a training run's held-out renders against the photo and the object-only truth.

    .venv/bin/python benchmarks/bench_heldout_truth.py out/demo/train \\
        --scene aircraft --views 60 --size 320x240 --seed 0

``DIR/heldout/<key>.png`` (renders over black, as ``ooi-seg train`` writes them) are compared,
inside the simulator's ground-truth mask, with the captured photo and with
``SimCapture.object_truth`` -- the view as an exact object-only model would render it (outline
pixels scaled by the object's coverage instead of mixed with the background behind) -- and
with the photo in the mask's interior (eroded by one pixel, as ``bench_train.py`` does). The
capture is re-simulated from its parameters (the demo bag is aircraft, 60 views, 320x240,
seed 0), so both are exact.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.ndimage import binary_erosion

from ooi_seg_ros.sim import simulate_capture


def _psnr(a: np.ndarray, b: np.ndarray, m: np.ndarray) -> float:
    return float(-10 * np.log10(max(((a[m] - b[m]) ** 2).mean(), 1e-12)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("train_dir", type=Path)
    ap.add_argument("--scene", default="aircraft")
    ap.add_argument("--views", type=int, default=60)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    w, h = (int(x) for x in a.size.split("x"))
    sim = simulate_capture(a.scene, n_views=a.views, width=w, height=h, seed=a.seed)
    index = {v.key: i for i, v in enumerate(sim.capture.views)}
    rows = []
    for p in sorted((a.train_dir / "heldout").glob("*.png")):
        if p.stem not in index:
            raise SystemExit(f"{p.name}: no view with that key in the simulated capture; "
                             "check --scene/--views/--size/--seed")
        i = index[p.stem]
        v = sim.capture.views[i]
        r = np.asarray(Image.open(p).convert("RGB"), np.float32) / 255.0
        photo = v.image.astype(np.float32) / 255.0
        rows.append((_psnr(r, photo, v.gt_mask), _psnr(r, sim.object_truth(i), v.gt_mask),
                     _psnr(r, photo, binary_erosion(v.gt_mask))))
    if not rows:
        raise SystemExit(f"no held-out renders in {a.train_dir / 'heldout'}")
    t = np.array(rows)
    print(f"{len(t)} held-out views, PSNR inside the ground-truth mask:")
    print(f"  vs the photo              {t[:, 0].mean():6.2f} dB")
    print(f"  vs the object-only truth  {t[:, 1].mean():6.2f} dB")
    print(f"  vs the photo, interior    {t[:, 2].mean():6.2f} dB (mask eroded by 1 px)")


if __name__ == "__main__":
    main()
