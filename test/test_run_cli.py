"""`ooi-seg run` on the bundled bag -- what `make demo` calls -- with a short training run."""

import json
from pathlib import Path

import pytest

from ooi_seg_ros.cli import main

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_run_on_the_demo_bag_writes_every_stage(tmp_path):
    out = tmp_path / "demo"
    assert main(["run", str(ROOT / "bags" / "demo.mcap"), "--out", str(out),
                 "--iterations", "30"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["views"] == 60 and summary["sfm_points"] > 1000
    seg = summary["segment"]
    assert not seg["warnings"]
    # the demo bag carries ground-truth masks: the segmentation is scored against them
    assert seg["metrics"]["iou"] > 0.7, seg["metrics"]
    assert len(list((out / "segment" / "masks").glob("*.png"))) == 60
    train = summary["train"]
    assert train["iterations"] == 30 and train["n_gaussians"] > 0
    assert train["heldout_psnr"] > 10 and train["nan_steps"] == 0
    for f in ("sfm/sfm_points.ply", "segment/ooi_points.ply", "train/splats.ply",
              "train/training.mcap", "train/report.html"):
        assert (out / f).stat().st_size > 0, f
    assert set(summary["times_s"]) == {"sfm", "segment", "train", "total"}
