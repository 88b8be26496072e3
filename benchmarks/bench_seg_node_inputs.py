"""Replay the segmentation node's own inputs offline, under other settings, and score them.

Reads the pickle ``node_inputs_plugin.py`` wrote during the node integration test (the
keyframes and the SfM cloud the running nodes built from ``bags/demo.mcap``) and runs
``seg.pipeline.segment`` on it with the node's own config, then with each ``--set`` variant
(JSON overrides on top of the node's config, as ``seg.*`` parameters would be). Scored against
the bag's ``/ground_truth/mask``: mean IoU (min), recall, OOI points, the Jaccard of the OOI set
with the first variant's, the points only the first (``-``) or only the variant (``+``) kept,
and with them the share of the views framing each point whose true mask holds it ("gt
support": about 1 on the object, near 0 off it). With the node's config the first line
reproduces the test's own figure (0.922 / 0.972 at b13a059).

    .venv/bin/python benchmarks/bench_seg_node_inputs.py --inputs /tmp/node_inputs.pkl \\
        --set 'ring0={"floor": {"band_local": 0}}' --set 'd0={"density": {"drop_fraction": 0}}'

``--points`` runs the point stages only (no masks; seconds instead of minutes).
"""

from __future__ import annotations

import argparse
import copy
import json
import pickle
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ooi_seg_ros import msgconv  # noqa: E402
from ooi_seg_ros.bag.mcap_bag import BagReader  # noqa: E402
from ooi_seg_ros.core import config as cfgmod  # noqa: E402
from ooi_seg_ros.core.types import Capture  # noqa: E402
from ooi_seg_ros.seg.pipeline import SegmentationConfig, _merge, segment  # noqa: E402
from ooi_seg_ros.seg.refine import point_support  # noqa: E402


def ground_truth(bag: Path) -> dict:
    r = BagReader(str(bag))
    out = {}
    for _topic, ty, _t, data in r.messages(topics=["/ground_truth/mask"]):
        m = r.decode(ty, data)
        out[msgconv.stamp_to_ns(m.header.stamp)] = msgconv.image_to_mask(m)
    return out


def _key_set(xyz: np.ndarray) -> dict:
    return {tuple(p): i for i, p in enumerate(np.round(xyz, 6))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--inputs", default="/tmp/node_inputs.pkl")
    ap.add_argument("--bag", default=str(ROOT / "bags" / "demo.mcap"))
    ap.add_argument("--set", action="append", default=[], metavar="NAME=JSON")
    ap.add_argument("--points", action="store_true", help="point stages only")
    ap.add_argument("--list", type=int, default=12, help="differing points listed per variant")
    a = ap.parse_args()
    if not Path(a.inputs).is_file():
        sys.exit(f"{a.inputs}: no such file. Write it first by running the node integration "
                 f"test with the plugin: OOI_DUMP_NODE_INPUTS={a.inputs} PYTHONPATH=benchmarks "
                 f".venv/bin/python -m pytest -p node_inputs_plugin -q -s "
                 f"test/test_nodes_pipeline.py::test_nodes_on_demo_bag")
    with open(a.inputs, "rb") as f:
        d = pickle.load(f)
    gt = ground_truth(Path(a.bag))
    base = cfgmod.to_dict(d["cfg"])
    variants = [("node", {})] + [(s.split("=", 1)[0], json.loads(s.split("=", 1)[1]))
                                 for s in a.set]
    views0 = d["views"]
    gtk = {v.key: gt[v.stamp_ns] for v in views0 if v.stamp_ns in gt}
    first = None
    for name, over in variants:
        cfg = cfgmod.from_dict(SegmentationConfig, _merge(base, over))
        views = copy.deepcopy(views0)
        res = segment(Capture(views=views, source="ros"), copy.deepcopy(d["cloud"]), cfg,
                      mask_keys=[views[0].key] if a.points else None)
        xyz = np.asarray(res.ooi_cloud.xyz)
        keys = _key_set(xyz)
        line = f"{name:>8}: {len(xyz)} OOI points, counts {res.counts}"
        if not a.points:
            ious, recs = [], []
            for v in views:
                p, g = res.masks[v.key] > 0, gt[v.stamp_ns]
                ious.append((p & g).sum() / max((p | g).sum(), 1))
                recs.append((p & g).sum() / max(g.sum(), 1))
            line += (f"; IoU {np.mean(ious):.3f} (min {np.min(ious):.3f}), recall "
                     f"{np.mean(recs):.3f} over {len(views)} keyframes")
        if first is None:
            first = (keys, xyz)
            print(line, flush=True)
            continue
        fk, fxyz = first
        union = len(set(fk) | set(keys))
        line += f"; Jaccard with node {len(set(fk) & set(keys)) / max(union, 1):.3f}"
        print(line, flush=True)
        for sign, src, other in (("-", fxyz, keys), ("+", xyz, fk)):
            diff = np.array([p for p in src if tuple(np.round(p, 6)) not in other])
            if not len(diff):
                continue
            sup = point_support(diff, gtk, views0)
            print(f"   {sign} {len(diff)} points, gt support "
                  f"{' '.join(f'{s:.2f}' for s in sup[:a.list])}", flush=True)


if __name__ == "__main__":
    main()
