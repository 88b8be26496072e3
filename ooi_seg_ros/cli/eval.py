"""``ooi-seg eval``: IoU / precision / recall / Dice of predicted masks against ground truth."""

from __future__ import annotations

import json
from pathlib import Path

from ..core.types import InputError


def register(subparsers) -> None:
    p = subparsers.add_parser("eval", help="mask metrics against ground-truth masks")
    p.add_argument("--pred", required=True, help="folder of predicted <key>.png masks")
    p.add_argument("--gt", required=True,
                   help="folder of ground-truth <key>.png masks, a bag/dataset with GT masks, "
                        "or sim:SCENE[:SEED] (with --sim-views/--sim-size as used to segment)")
    p.add_argument("--sim-views", type=int, default=30)
    p.add_argument("--sim-size", default="160x120")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=run)


def load_gt(src: str, sim_views: int, sim_size: str) -> dict:
    """{key: bool mask} from a PNG folder, a simulator spec, or a capture with GT masks."""
    from ..seg.metrics import load_mask_dir
    if src.startswith("sim:"):
        from ..sim import simulate_capture
        bits = src.split(":")
        w, h = (int(x) for x in sim_size.lower().split("x"))
        sim = simulate_capture(bits[1], n_views=sim_views, width=w, height=h,
                               seed=int(bits[2]) if len(bits) > 2 else 0)
        return {v.key: v.gt_mask for v in sim.capture.views}
    p = Path(src)
    if p.is_dir() and any(p.glob("*.png")):
        return load_mask_dir(p)
    try:
        from ..capture_io import read_capture_and_cloud
    except ImportError:
        raise InputError(f"{src} is not a folder of PNG masks") from None
    cap, _ = read_capture_and_cloud(p)
    if not cap.has_gt_masks:
        raise InputError(f"{src} has no ground-truth masks")
    return {v.key: v.gt_mask for v in cap.views}


def run(args) -> int:
    from ..seg.metrics import format_table, load_mask_dir, scene_metrics
    pred = load_mask_dir(args.pred)
    gt = load_gt(args.gt, args.sim_views, args.sim_size)
    res = scene_metrics(pred, gt)
    if args.json:
        print(json.dumps({"mean": res["mean"], "views": res["views"],
                          "missing_predictions": res["missing_predictions"]}))
    else:
        print(format_table(res))
        if res["missing_predictions"]:
            print(f"{len(res['missing_predictions'])} ground-truth views have no prediction")
    return 0
