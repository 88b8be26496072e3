"""Does the noise stage warn exactly when its OOI cloud holds a neighbouring object?

The point stages' OOI cloud can take a neighbour when the cloud is too sparse to show the
gap between them (``seg/noise.py``, ``warn_apart_share``). This runs the point stages (ROI,
floor, density, noise; no masks) of the improved default on simulator captures and scores
each OOI cloud against the simulator's geometry: its purity is the share of its points within
2% of the object's diagonal from the object's surface. A cloud under ``--impure`` purity (0.85)
holds something else; the table counts how often the stage's warning fires on such clouds and
on the others. (SfM clouds carry stray points near the surface: 0.88-0.99 on the quality
bench's 60-view clouds, the thin bicycle lowest; a neighbour taken in brings a cloud to 0.8
or under.)

Clouds: the depth-proxy cloud that ``ooi-seg segment sim:SCENE:SEED`` uses (160x120, as the
CLI's default; ``--views`` of them), and with ``--cache DIR`` the SfM clouds of
``bench_seg_quality.py`` cached there (60 views; no SfM is run here).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_noise_warning.py \
        --scenes toycar tabletop aircraft stool bicycle --views 6 8 12 20 30 \
        --seeds 0 1 2 3 4 5 6 7 --cache /tmp/ooi_seg_bench_cache_v2
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_seg_quality import _load  # noqa: E402

from ooi_seg_ros.seg.pipeline import (_point_stages, cameras_convergence_point,  # noqa: E402
                                      frame_radius, make_config)
from ooi_seg_ros.seg.proxy import depth_proxy_cloud  # noqa: E402
from ooi_seg_ros.sim import simulate_capture  # noqa: E402


def point_stages(capture, xyz: np.ndarray, over: dict | None = None
                 ) -> tuple[np.ndarray, dict]:
    """Indices of the OOI cloud the default point stages (with ``over``, overrides of ``ours``)
    keep, and the noise stage's params."""
    cfg = make_config("ours", over or {})
    views = capture.views
    poses = [v.pose for v in views]
    target = cameras_convergence_point(poses)
    centres = np.array([p.t for p in poses])
    up = -np.mean([p.R[:, 1] for p in poses], axis=0)
    sub = np.arange(len(xyz))
    p: dict = {}
    for _, fn in _point_stages(cfg, views, target, frame_radius(views, target), centres, up):
        keep, p = fn(xyz[sub])
        sub = sub[np.asarray(keep, np.int64)]
    return sub, p


def row(tag: str, capture, xyz: np.ndarray, scene, over: dict | None = None) -> dict:
    out = {}
    for key, ov in (("", None), ("set_", over)) if over is not None else (("", None),):
        sub, p = point_stages(capture, xyz, ov)
        on = scene.distance_to_ooi(xyz[sub]) < 0.02 * scene.ooi_diagonal
        out.update({f"{key}points": len(sub),
                    f"{key}purity": float(on.mean()) if len(sub) else 0.0,
                    f"{key}apart": 1.0 - p.get("main_share", 1.0),
                    f"{key}eps": p.get("eps_scale"), f"{key}refused": p.get("stopped_at_scale"),
                    f"{key}warned": "warning" in p,
                    # the share of the object's own points (within 2% of its diagonal) kept
                    f"{key}object_points": int(on.sum())})
    return {"tag": tag, **out}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["toycar", "tabletop", "aircraft"])
    ap.add_argument("--views", nargs="+", type=int, default=[6, 12, 30])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3])
    ap.add_argument("--cache", type=Path, default=None,
                    help="folder of bench_seg_quality.py's cached SfM clouds")
    ap.add_argument("--impure", type=float, default=0.85,
                    help="an OOI cloud under this purity holds something else")
    ap.add_argument("--set", type=json.loads, default=None,
                    help="overrides of ours (JSON): each cloud also run with them, side by side")
    args = ap.parse_args()
    rows = []
    print(f"{'cloud':38s} {'points':>6s} {'purity':>6s} {'apart':>6s} {'eps':>5s} "
          f"{'refused':>7s} warned" + ("   | with --set: points purity eps warned"
                                       if args.set is not None else ""))
    for scene in args.scenes:
        for n in args.views:
            for seed in args.seeds:
                sim = simulate_capture(scene, n_views=n, width=160, height=120, seed=seed)
                cloud = depth_proxy_cloud(sim, seed=seed)
                rows.append(row(f"sim:{scene}:{seed} --sim-views {n}", sim.capture, cloud.xyz,
                                sim.scene, args.set))
                _print(rows[-1])
    if args.cache is not None:
        for f in sorted(args.cache.glob("seg_bench_*_s*_v*.npz")):
            bits = f.stem.split("_")  # seg_bench_SCENE_sSEED_vN_WxH[_...]
            if bits[2] not in args.scenes or len(bits) != 6:
                continue
            capture, cloud = _load(f)
            sim = simulate_capture(bits[2], n_views=2, width=32, height=24,
                                   seed=int(bits[3][1:]))  # the scene's geometry only
            rows.append(row(f"SfM {f.stem[10:]}", capture, cloud.xyz, sim.scene, args.set))
            _print(rows[-1])
    bad = [r for r in rows if r["purity"] < args.impure]
    good = [r for r in rows if r["purity"] >= args.impure]
    print(f"\n{len(rows)} OOI clouds: {len(bad)} impure (purity < {args.impure}), "
          f"{sum(r['warned'] for r in bad)} of them warned; {len(good)} pure, "
          f"{sum(r['warned'] for r in good)} of them warned")
    for r in bad:
        if not r["warned"]:
            print(f"  impure, no warning: {r['tag']} (purity {r['purity']:.2f}, apart "
                  f"{r['apart']:.1%})")
    if args.set is not None:
        changed = [r for r in rows if r["set_points"] != r["points"]
                   or r["set_purity"] != r["purity"]]
        print(f"with --set: {sum(r['set_purity'] < args.impure for r in rows)} impure "
              f"({sum(r['set_warned'] for r in rows if r['set_purity'] < args.impure)} warned),"
              f" {len(changed)} of {len(rows)} clouds changed:")
        for r in changed:
            print(f"  {r['tag']}: purity {r['purity']:.3f} -> {r['set_purity']:.3f}, points "
                  f"{r['points']} -> {r['set_points']}, object points {r['object_points']} -> "
                  f"{r['set_object_points']}")


def _print(r: dict) -> None:
    extra = (f"   | {r['set_points']:6d} {r['set_purity']:6.3f} {r['set_eps']!s:>5s} "
             f"{'yes' if r['set_warned'] else ''}" if "set_points" in r else "")
    print(f"{r['tag']:38s} {r['points']:6d} {r['purity']:6.3f} {r['apart']:6.1%} "
          f"{r['eps']!s:>5s} {r['refused']!s:>7s} {'yes' if r['warned'] else '   '}" + extra,
          flush=True)


if __name__ == "__main__":
    main()
