"""Mask quality under other camera layouts than the scenes' own three-ring orbits.

The quality bench flies every scene's own three rings with a 60 deg lens. A drone crew flies
what the site allows: one ring, half an orbit beside a wall, farther out, or a wider lens.
For each scene and ``--layouts`` entry this simulates that capture (cached by
``bench_seg_quality.load_case``, SfM included), runs the default (``ours``) and every ``--set``
variant on the same cloud, and prints IoU / precision / recall side by side.

Layouts (``SimConfig`` options; ring distances in OOI radii):
  ``orbit``     the scene's own rings (the quality bench's capture)
  ``one-ring``  the scene's middle ring only
  ``half-arc``  every ring over 180 deg of azimuth (``arc_deg``)
  ``far``       the scene's rings 1.6x farther out (the object a third of the size in frame)
  ``wide``      a 90 deg lens at 544x408: the object as many pixels across as in ``orbit``,
                but 3x the room around it in every frame
  ``wide-low``  a 90 deg lens at 320x240 (the object 0.6x as wide in pixels)
  ``barrel``    the scene's rings through its own 60 deg lens with barrel distortion
                (plumb_bob k1 -0.12, k2 0.03: a small drone camera's, uncorrected)
  ``loose-aim`` the scene's rings, each view aimed 0.3 OOI radii off the object's centre
                (std; the default capture's is 0.05): a pilot or gimbal that frames loosely
  ``noisy``     the scene's rings in poor light: sensor noise 6 (of 255; default 1.5) and
                10% exposure swings (default 3%)
  ``vignette``  the scene's rings through a lens whose corners get 60% of the centre's light
                (``vignetting`` 0.4: gain 1 - 0.4 r^2, r over the half diagonal), uncorrected
  ``field``     all of it at once, milder: barrel distortion as ``barrel``, vignetting 0.3,
                sensor noise 4, 8% exposure swings, views aimed 0.15 OOI radii off (a cheap
                drone on an overcast day)
  ``bayer``     the scene's rings through a camera's optics and Bayer sensor: the lens's
                low-pass (Gaussian 0.6 px), one colour per pixel (RGGB), the
                image demosaiced (OpenCV edge-aware), its noise correlated between
                neighbouring pixels as a real camera's (``demosaic``)
  ``bayer-noisy`` ``noisy`` on that sensor (the noise 6 drawn on the mosaic)

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_seg_layouts.py \\
        --scenes aircraft tabletop toycar stool bicycle --layouts one-ring half-arc wide \\
        --set 'cloudshare={"floor": {"support_min_of": "cloud"}}'
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_seg_quality import load_case  # noqa: E402

from ooi_seg_ros.seg.pipeline import make_config, segment  # noqa: E402
from ooi_seg_ros.sim import make_scene  # noqa: E402

LAYOUTS = ("orbit", "one-ring", "half-arc", "far", "wide", "wide-low", "barrel", "loose-aim",
           "noisy", "vignette", "field", "bayer", "bayer-noisy")


def layout(scene: str, name: str, seed: int) -> tuple[dict, tuple[int, int]]:
    """(SimConfig options, image size) of layout ``name`` for ``scene``."""
    rings = [[r.elevation_deg, r.distance] for r in make_scene(scene, seed).rings]
    if name == "orbit":
        return {}, (320, 240)
    if name == "one-ring":
        return {"rings": [rings[len(rings) // 2]]}, (320, 240)
    if name == "half-arc":
        return {"arc_deg": 180.0}, (320, 240)
    if name == "far":
        return {"rings": [[e, round(1.6 * d, 3)] for e, d in rings]}, (320, 240)
    if name == "wide":
        return {"hfov_deg": 90.0}, (544, 408)
    if name == "wide-low":
        return {"hfov_deg": 90.0}, (320, 240)
    if name == "barrel":
        return {"distortion": [-0.12, 0.03, 0.0, 0.0, 0.0]}, (320, 240)
    if name == "loose-aim":
        return {"aim_jitter": 0.3}, (320, 240)
    if name == "noisy":
        return {"sensor_noise": 6.0, "exposure_jitter": 0.1}, (320, 240)
    if name == "vignette":
        return {"vignetting": 0.4}, (320, 240)
    if name == "field":
        return {"distortion": [-0.12, 0.03, 0.0, 0.0, 0.0], "vignetting": 0.3,
                "sensor_noise": 4.0, "exposure_jitter": 0.08, "aim_jitter": 0.15}, (320, 240)
    if name == "bayer":  # a real camera's sensor: one colour per pixel, demosaiced
        return {"demosaic": True}, (320, 240)
    if name == "bayer-noisy":  # "noisy" on that sensor (the noise drawn before demosaicing)
        return {"demosaic": True, "sensor_noise": 6.0, "exposure_jitter": 0.1}, (320, 240)
    raise ValueError(f"unknown layout {name!r}; choose from {', '.join(LAYOUTS)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+",
                    default=["aircraft", "tabletop", "toycar", "stool", "bicycle"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--layouts", nargs="+", default=["one-ring", "half-arc", "wide"],
                    choices=LAYOUTS)
    ap.add_argument("--views", type=int, default=60)
    ap.add_argument("--view-step", type=int, default=2, help="score every k-th view")
    ap.add_argument("--cache", default="/tmp/ooi_seg_bench_cache_v2")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=JSON",
                    help="a variant: overrides of ours (repeatable)")
    args = ap.parse_args()
    variants = [("ours", {})] + [(s.split("=", 1)[0], json.loads(s.split("=", 1)[1]))
                                 for s in args.set]
    print(f"{'scene':>9} {'seed':>4} {'layout':>9} {'variant':>12} {'IoU':>6} {'prec':>6} "
          f"{'recall':>6} {'minIoU':>6} {'ooi pts':>7} {'warn':>4} {'time s':>6}", flush=True)
    rows = []
    for scene in args.scenes:
        for seed in args.seeds:
            for lay in args.layouts:
                sim_set, size = layout(scene, lay, seed)
                cap, cloud, _ = load_case(scene, seed, args.views, size, "sfm",
                                          Path(args.cache), sim_set=sim_set or None)
                keys = [v.key for v in cap.views[::max(1, args.view_step)]]
                for name, over in variants:
                    t0 = time.perf_counter()
                    r = segment(cap, cloud, make_config("ours", dict(over, seed=seed)),
                                mask_keys=keys)
                    m = r.metrics["mean"]
                    worst = min(pv["iou"] for pv in r.metrics["per_view"].values())
                    rows.append((scene, lay, name, m))
                    print(f"{scene:>9} {seed:>4} {lay:>9} {name:>12} {m['iou']:6.3f} "
                          f"{m['precision']:6.3f} {m['recall']:6.3f} {worst:6.3f} "
                          f"{len(r.ooi_cloud):7d} {len(r.warnings):4d} "
                          f"{time.perf_counter() - t0:6.1f}", flush=True)
    print("\nmeans over seeds, IoU / recall")
    for name, _ in variants:
        for lay in args.layouts:
            cells = []
            for scene in args.scenes:
                ms = [r[3] for r in rows if r[0] == scene and r[1] == lay and r[2] == name]
                cells.append(f"{scene} {np.mean([m['iou'] for m in ms]):.3f} / "
                             f"{np.mean([m['recall'] for m in ms]):.3f}")
            print(f"{name:>12} {lay:>9}: " + ", ".join(cells))


if __name__ == "__main__":
    main()
