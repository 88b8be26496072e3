"""The OOI point set on the real bonsai photos with fewer views, one setting against another.

A drone orbit keeps 30-100 keyframes, not the 289 photos of the Mip-NeRF 360 capture. For each
``--steps`` k this keeps every k-th registered image of the reference COLMAP model in
``../shared/data/mipnerf360-bonsai`` (``pycolmap.Reconstruction.deregister_frame``: the other
images' observations leave the tracks, and points seen by fewer than two kept images go), then
runs the point stages of ``ours`` (with the stability check) under the default and under each
``--set`` override, and prints the points left after the density and noise stages, the noise
stage's widening (where it settled, stopped, joined parts), and the stability check's flips.
No ground truth exists there: a set near the density stage's count holds the whole tree, pot
and stand region; a small one is a fragment (look at the masks: ``ooi-seg segment DIR``).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_seg_bonsai_views.py \\
        --steps 1 3 4 5 6 8 10 --set 'pa0={"noise": {"part_above": 0.0}}'
    # other subsets of the same sizes: --steps 4 5 6 8 --offsets 1 2 3
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

BONSAI = ROOT.parent / "shared" / "data" / "mipnerf360-bonsai"


def subset_model(src: Path, dst: Path, step: int, offset: int = 0) -> int:
    """Write ``dst`` (images/ as links, sparse/0) keeping every ``step``-th registered image
    by name, from the ``offset``-th on; returns the number kept."""
    import pycolmap
    rec = pycolmap.Reconstruction(str(src / "sparse" / "0"))
    ids = sorted((i for i in rec.images if rec.images[i].has_pose),
                 key=lambda i: rec.images[i].name)
    keep = set(ids[offset::step])
    for i in ids:
        if i not in keep:
            rec.deregister_frame(rec.images[i].frame_id)
    (dst / "sparse" / "0").mkdir(parents=True, exist_ok=True)
    (dst / "images").mkdir(parents=True, exist_ok=True)
    rec.write(str(dst / "sparse" / "0"))
    for i in keep:
        name = rec.images[i].name
        link = dst / "images" / name
        if not link.exists():
            os.symlink(src / "images" / name, link)
    return len(keep)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=BONSAI)
    ap.add_argument("--steps", type=int, nargs="+", default=[1, 3, 4, 5, 6, 8, 10])
    ap.add_argument("--offsets", type=int, nargs="+", default=[0],
                    help="first photo kept (0..step-1): other subsets of the same size")
    ap.add_argument("--set", action="append", default=[],
                    help='extra variant "name={json overrides of ours}" (repeatable)')
    args = ap.parse_args(argv)
    if not (args.data / "sparse" / "0").is_dir():
        print(f"no COLMAP model under {args.data}/sparse/0", file=sys.stderr)
        return 2
    from ooi_seg_ros.capture_io import read_capture_and_cloud
    from ooi_seg_ros.seg.pipeline import make_config, segment
    variants = [("default", {})]
    for s in args.set:
        name, _, js = s.partition("=")
        variants.append((name, json.loads(js)))
    print(f"{'views':>5} {'first':>5} {'variant':>10} {'density':>7} {'noise':>6} {'OOI':>6} "
          f"{'settled':>7} {'stopped':>7} {'joined':>12} {'held up':>8} {'flips':>5} "
          f"{'copies (points)':>18} {'s':>5} warnings")
    with tempfile.TemporaryDirectory() as tmp:
        for step, off in [(st, o) for st in args.steps for o in args.offsets if o < st]:
            d = Path(tmp) / f"every{step}_{off}"
            n = subset_model(args.data, d, step, off)
            cap, cloud = read_capture_and_cloud(d, downscale=4)
            for name, over in variants:
                cfg = make_config("ours", over)
                cfg.refine.enabled = False  # point stages (and the check) only
                cfg.masks.mode = "points"
                t0 = time.perf_counter()
                r = segment(cap, cloud, cfg, mask_keys=[cap.views[0].key])
                dt = time.perf_counter() - t0
                p, st = r.params["noise"], r.params.get("stability", {})
                sizes = st.get("sizes") or [0]
                print(f"{n:>5} {off:>5} {name:>10} {r.counts['density']:>7} "
                      f"{r.counts['noise']:>6} {len(r.ooi_cloud):>6} "
                      f"{str(p.get('settled_at_scale', '-')):>7} "
                      f"{str(p.get('stopped_at_scale', '-')):>7} "
                      f"{str(p.get('parts_joined_at', '-')):>12} "
                      f"{str(p.get('parts_held_up_at', '-')):>8} {st.get('flips', 0):>5} "
                      f"{f'{min(sizes)}-{max(sizes)}':>18} {dt:>5.1f} "
                      f"{'; '.join(w.split(':')[0] for w in r.warnings) or '-'}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
