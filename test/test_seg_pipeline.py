"""End-to-end segmentation on a small simulator capture, the CLI, and bad-input handling."""

import json

import numpy as np
import pytest

from ooi_seg_ros.cli import main
from ooi_seg_ros.core.geometry import look_at
from ooi_seg_ros.core.types import Capture, InputError, SfmCloud
from ooi_seg_ros.seg.pipeline import make_config, segment
from ooi_seg_ros.seg.proxy import depth_proxy_cloud
from ooi_seg_ros.sim import simulate_capture


@pytest.fixture(scope="module")
def aircraft():
    sim = simulate_capture("aircraft", n_views=12, width=128, height=96, seed=0)
    return sim, depth_proxy_cloud(sim, 300, seed=0)


def test_ours_beats_paper_on_sim(aircraft):
    sim, cloud = aircraft
    paper = segment(sim.capture, cloud, make_config("paper"))
    ours = segment(sim.capture, cloud, make_config("ours"))
    keys = {v.key for v in sim.capture.views}
    assert set(ours.masks) == keys and set(paper.masks) == keys
    assert ours.metrics["mean"]["iou"] > paper.metrics["mean"]["iou"] + 0.1
    assert ours.metrics["mean"]["iou"] > 0.7
    assert ours.counts["noise"] == len(ours.ooi_cloud) > 50
    assert not ours.warnings


def test_on_cloud_sees_the_final_ooi_cloud_before_the_masks(aircraft):
    sim, cloud = aircraft
    seen = []
    res = segment(sim.capture, cloud, make_config("ours", {"refine": {"enabled": False}}),
                  on_cloud=lambda c: seen.append(c.xyz.copy()))
    assert len(seen) == 1
    np.testing.assert_array_equal(seen[0], res.ooi_cloud.xyz)


def test_deterministic(aircraft):
    sim, cloud = aircraft
    a = segment(sim.capture, cloud, make_config("ours", {"seed": 3}))
    b = segment(sim.capture, cloud, make_config("ours", {"seed": 3}))
    assert a.counts == b.counts
    assert all((a.masks[k] == b.masks[k]).all() for k in a.masks)


def test_bad_inputs(aircraft):
    sim, cloud = aircraft
    with pytest.raises(InputError, match="min_points"):
        segment(sim.capture, SfmCloud.empty(sim.capture.views))
    with pytest.raises(InputError, match="unknown segmentation method"):
        make_config("magic")
    with pytest.raises(InputError, match="bad segmentation config"):
        make_config("ours", {"density": {"no_such_option": 1}})
    # NaN points are dropped, counted and reported
    bad = cloud.subset(np.arange(len(cloud)))
    bad.xyz = bad.xyz.copy()
    bad.xyz[:25] = np.nan
    r = segment(sim.capture, bad, make_config("ours"))
    assert r.counts["finite"] == len(cloud) - 25 and any("NaN" in w for w in r.warnings)
    # views without poses
    nopose = Capture([type(v)(v.key, v.stamp_ns, v.camera, None, v.image)
                      for v in sim.capture.views])
    with pytest.raises(InputError, match="pose"):
        segment(nopose, cloud)


def test_all_one_plane_is_an_error_not_a_white_mask(aircraft):
    sim, _ = aircraft
    rng = np.random.default_rng(0)
    plane = SfmCloud.from_points(np.c_[rng.uniform(-20, 20, (3000, 2)), np.zeros(3000)])
    for method in ("ours", "paper"):
        try:
            r = segment(sim.capture, plane, make_config(method))
        except InputError as exc:
            assert "stage" in str(exc)
        else:
            assert r.warnings, "a plane-only cloud must not pass silently"


def test_cameras_that_see_nothing_warn(aircraft):
    sim, cloud = aircraft
    views = []
    for v in sim.capture.views:
        away = v.pose.t + (v.pose.t - cloud.xyz.mean(axis=0))
        views.append(type(v)(v.key, v.stamp_ns, v.camera, look_at(v.pose.t, away), v.image))
    r = segment(sim.capture, cloud, make_config("ours"))
    r2 = segment(Capture(views), cloud.subset(np.arange(len(cloud))),
                 make_config("ours", {"roi": {"enabled": False}, "refine": {"enabled": False}}))
    assert not r.warnings
    assert any("see nothing" in w for w in r2.warnings)


def test_cli_segment_and_eval(tmp_path, capsys):
    out = tmp_path / "seg"
    args = ["segment", "sim:aircraft:0", "--out", str(out), "--sim-views", "6",
            "--sim-size", "96x72"]
    assert main(args) == 0
    for f in ("ooi_points.ply", "ooi_mesh.ply", "report.json", "report.html", "config.yaml",
              "input.json"):
        assert (out / f).is_file(), f
    assert len(list((out / "masks").glob("*.png"))) == 6
    rep = json.loads((out / "report.json").read_text())
    assert rep["metrics"]["mean"]["iou"] > 0.5 and "noise" in rep["counts"]
    capsys.readouterr()
    assert main(["eval", "--pred", str(out / "masks"), "--gt", "sim:aircraft:0",
                 "--sim-views", "6", "--sim-size", "96x72", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["views"] == 6 and res["mean"]["iou"] == pytest.approx(
        rep["metrics"]["mean"]["iou"])
    assert main(["segment", str(tmp_path / "missing"), "--out", str(out)]) == 1
    assert main(["eval", "--pred", str(tmp_path), "--gt", str(out / "masks")]) == 1
