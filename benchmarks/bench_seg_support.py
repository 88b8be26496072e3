"""Which support plane the floor stage chooses, under the default and under variants.

For each case (the cached captures of ``bench_seg_quality.py``; SfM runs first where a case is
not cached) this runs the ROI and floor stages of ``ours`` only -- seconds per cloud -- and
prints every plane the support search fitted (inliers, the convergence point's height over
it, surround sectors, ``under_interior``, and ``under_density`` where a variant reads it) and
which one it chose, once per variant, so a change to the support search can be checked
against many clouds before the costly masks.
A case is ``SCENE@SEED[@VIEWS[@SIMSET_JSON[@WxH]]]``.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_seg_support.py \\
        --set 'cloudshare={"floor": {"support_min_of": "cloud"}}' \\
        stool@0 stool@1 'stool@0@60@{"hfov_deg": 90}@544x408'
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_seg_quality import load_case  # noqa: E402

from ooi_seg_ros.core.geometry import cameras_convergence_point  # noqa: E402
from ooi_seg_ros.seg.floor import floor_filter  # noqa: E402
from ooi_seg_ros.seg.pipeline import make_config  # noqa: E402
from ooi_seg_ros.seg.roi import roi_filter  # noqa: E402


def planes(case: str, over: dict, cache: Path) -> tuple[int, list, int]:
    """(ROI points, planes tried, index of the chosen one or -1) of one case."""
    c = case.split("@", 4)
    views = int(c[2]) if len(c) > 2 and c[2] else 60
    sim_set = json.loads(c[3]) if len(c) > 3 and c[3] else None
    size = tuple(int(v) for v in (c[4] if len(c) > 4 else "320x240").split("x"))
    cap, cloud, _ = load_case(c[0], int(c[1]), views, size, "sfm", cache, sim_set=sim_set)
    cfg = make_config("ours", over)
    poses = [v.pose for v in cap.views]
    target = cameras_convergence_point(poses)
    centers = np.array([p.t for p in poses])
    up = -np.mean([p.R[:, 1] for p in poses], axis=0)
    xyz = cloud.xyz[np.isfinite(cloud.xyz).all(axis=1)]
    keep, _ = roi_filter(xyz, cap.views, target, cfg.roi)
    _, p = floor_filter(xyz[keep], cfg.floor, centers, up, target)
    tried = p.get("planes_tried", [])
    chosen = [i for i, t in enumerate(tried) if t["plane"] == p.get("support_plane")]
    return len(keep), tried, chosen[0] if chosen else -1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cases", nargs="+", help="SCENE@SEED[@VIEWS[@SIMSET_JSON[@WxH]]]")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=JSON",
                    help="a variant: overrides of ours (repeatable)")
    ap.add_argument("--cache", default="/tmp/ooi_seg_bench_cache_v2")
    args = ap.parse_args()
    variants = [("ours", {})] + [(s.split("=", 1)[0], json.loads(s.split("=", 1)[1]))
                                 for s in args.set]
    for case in args.cases:
        chosen = []
        for name, over in variants:
            n, tried, k = planes(case, over, Path(args.cache))
            chosen.append(tried[k]["plane"] if k >= 0 else None)
            cells = [f"{t['inliers']} pts h {t['target_height']:.3g}"
                     + (f" sect {t['surround_sectors']} under {t['under_interior']:.3g}"
                        if "surround_sectors" in t else "")
                     + (f" density {t['under_density']:.3g}"
                        if t.get("under_density") is not None else "") for t in tried]
            print(f"{case} {name}: ROI {n}, chose #{k} | " + "; ".join(cells), flush=True)
        same = all(c == chosen[0] for c in chosen)
        print(f"{case}: " + ("the same plane under every variant" if same
                             else "THE CHOSEN PLANE DIFFERS between variants"), flush=True)


if __name__ == "__main__":
    main()
