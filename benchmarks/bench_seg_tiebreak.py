"""The stability check's tie-break, scored against the simulator's truth, with and without an
option.

For each cached capture of ``bench_seg_quality.py`` this runs the point stages with the
stability check (``seg/stability.py``: re-runs on copies with 10% of the points left out, and
the tie-break ``resolve`` after a flip) on the whole SfM cloud and on ``--draws`` copies of it
with ``--drop`` of its points left out at random (seeds 1000, 1001, ...: the truth-scored draws
of ``bench_seg_stability.py``). Each resulting OOI cloud is scored by purity (share of its
points on the object: at least 90% of the GT masks of the views framing a point hold it) and
completeness (share of the on-object points of the cloud it was chosen from). A cloud is
*wrong* when its completeness is under 0.85 or its purity more than 0.1 below the best purity
any of the capture's clouds reached with completeness >= 0.9 (the definition of sessions
14-15). Every variant (``--variant NAME=JSON`` of segmentation overrides; ``default`` is always
run) sees the same clouds in the same process.

Prints per capture the clouds the check flagged and, per variant, how many are wrong and which
the tie-break changed; then the totals and every cloud on which the variants disagree.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_seg_tiebreak.py \\
        --scenes tabletop toycar --seeds 0 1 2 3 4 5 6 7 --draws 10 \\
        --variant 'no_guard={"stability": {"extent_guard": false}}'
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_seg_quality import load_case  # noqa: E402

from ooi_seg_ros.seg.pipeline import make_config, segment  # noqa: E402
from ooi_seg_ros.seg.refine import point_support  # noqa: E402


def ooi_with_check(cap, cloud, seed: int, overrides: dict):
    """(OOI points, the stability check's record) after the point stages with the check."""
    cfg = make_config("ours", dict(overrides, seed=seed))
    cfg.refine.enabled = False
    cfg.masks.mode = "points"
    r = segment(cap, cloud, cfg, mask_keys=[cap.views[0].key])
    return r.ooi_cloud.xyz, r.params.get("stability") or {}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["tabletop", "toycar"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4, 5, 6, 7])
    ap.add_argument("--views", type=int, default=60)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--cache", default="/tmp/ooi_seg_bench_cache_v2")
    ap.add_argument("--sfm-set", type=json.loads, default=None, metavar="JSON",
                    help="IncrementalConfig overrides (as bench_seg_quality.py)")
    ap.add_argument("--draws", type=int, default=10)
    ap.add_argument("--drop", type=float, default=0.1)
    ap.add_argument("--variant", action="append", default=[], metavar="NAME=JSON",
                    help="segmentation overrides to compare with the default (repeatable)")
    ap.add_argument("--json", help="write every cloud's figures here")
    args = ap.parse_args()
    w, h = (int(x) for x in args.size.split("x"))
    variants = {"default": {}}
    for v in args.variant:
        name, _, js = v.partition("=")
        variants[name] = json.loads(js)
    names = list(variants)
    rows = []
    for scene in args.scenes:
        for seed in ([0] if scene == "demo" else args.seeds):
            cap, cloud, _ = load_case(scene, seed, args.views, (w, h), "sfm", Path(args.cache),
                                      sfm_set=args.sfm_set)
            gts = {v.key: v.gt_mask for v in cap.views}
            on = point_support(cloud.xyz, gts, cap.views) >= 0.9
            index = {tuple(p): i for i, p in enumerate(cloud.xyz)}
            recs = []
            for d in range(args.draws + 1):
                keep = (np.ones(len(cloud), bool) if d == 0 else
                        np.random.default_rng(1000 + d - 1).random(len(cloud)) >= args.drop)
                sub = cloud if d == 0 else cloud.subset(keep)
                n_on = max(int(on[keep].sum()), 1)
                per = {}
                for name in names:
                    xyz, st = ooi_with_check(cap, sub, seed, variants[name])
                    ids = np.array([index[tuple(p)] for p in xyz], int)
                    k = int(on[ids].sum()) if len(ids) else 0
                    res = st.get("resolved") or {}
                    per[name] = {"n": len(ids), "purity": k / max(len(ids), 1),
                                 "completeness": k / n_on, "flips": int(st.get("flips", 0)),
                                 "changed": res.get("chosen_scale") is not None,
                                 "too_wide": res.get("too_wide", [])}
                recs.append(per)
            best = max([r[nm]["purity"] for r in recs for nm in names
                        if r[nm]["completeness"] >= 0.9] or [0.0])
            for r in recs:
                for nm in names:
                    x = r[nm]
                    x["wrong"] = bool(x["completeness"] < 0.85 or x["purity"] < best - 0.1)
            rows.append({"scene": scene, "seed": seed, "best_purity": best, "clouds": recs})
            cells = []
            for nm in names:
                wrong = sum(r[nm]["wrong"] for r in recs)
                flagged = sum(r[nm]["flips"] > 0 for r in recs)
                changed = sum(r[nm]["changed"] for r in recs)
                cells.append(f"{nm}: wrong {wrong} flagged {flagged} changed {changed}")
            print(f"{scene:>9} {seed:>2} (best purity {best:.3f}) | " + " | ".join(cells),
                  flush=True)
    print()
    n_clouds = sum(len(r["clouds"]) for r in rows)
    for nm in names:
        wrong = sum(c[nm]["wrong"] for r in rows for c in r["clouds"])
        whole = sum(r["clouds"][0][nm]["wrong"] for r in rows)
        flagged = sum(c[nm]["flips"] > 0 for r in rows for c in r["clouds"])
        changed = sum(c[nm]["changed"] for r in rows for c in r["clouds"])
        print(f"{nm:>12}: wrong {wrong} of {n_clouds} clouds ({whole} of {len(rows)} whole "
              f"clouds); flagged {flagged}; tie-break changed {changed}")
    for r in rows:
        for d, c in enumerate(r["clouds"]):
            if len({(c[nm]["n"], c[nm]["wrong"]) for nm in names}) > 1:
                print(f"  differ: {r['scene']} {r['seed']} "
                      f"{'whole' if d == 0 else f'copy {d - 1}'}: " + "; ".join(
                          f"{nm} {c[nm]['n']} pts purity {c[nm]['purity']:.3f} compl "
                          f"{c[nm]['completeness']:.3f}{' WRONG' if c[nm]['wrong'] else ''}"
                          f"{' too wide ' + str(c[nm]['too_wide']) if c[nm]['too_wide'] else ''}"
                          for nm in names))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
