"""End-to-end object-only training on a tiny simulated capture, edge cases, CLI and export."""

import json
import re
from argparse import Namespace

import numpy as np
import pytest
import torch

from ooi_seg_ros.cli import export as export_cli
from ooi_seg_ros.cli import train as train_cli
from ooi_seg_ros.core.types import InputError
from ooi_seg_ros.train.gaussians import load_ply, read_ply_header
from ooi_seg_ros.train.trainer import TrainConfig, train

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def sim():
    from ooi_seg_ros.sim import simulate_capture
    return simulate_capture("aircraft", n_views=10, width=48, height=36, seed=0,
                            supersample=1).capture


def _cfg(**kw):
    base = dict(iterations=30, max_gaussians=600, refine_every=10, refine_start=10,
                eval_every=10, snapshot_every=10, sh_degree_interval=10)
    base.update(kw)
    return TrainConfig(**base)


def test_train_holdout_counts_and_improves(sim):
    masks = {v.key: v.gt_mask for v in sim.views}
    pts = sim.gt_ooi_points[::40]
    r = train(sim, masks, pts, _cfg())
    keys = [v.key for v in sim.views]
    assert r.heldout_keys == [keys[0], keys[8]]  # every 8th from the first
    assert not set(r.heldout_keys) & set(r.train_keys)
    assert len(r.model) <= 600 and r.model.sh_degree == 2
    assert r.history[-1]["loss"] < r.history[0]["loss"]
    assert len(r.snapshots) == 3 and r.heldout and np.isfinite(r.heldout[0].psnr)
    # renders are black outside the object: Gaussians were not spent on background
    h = r.heldout[0]
    assert h.render[~h.mask].mean() < h.render[h.mask].mean()


def test_heldout_is_also_scored_in_the_ground_truth_mask(sim):
    """A computed mask's false positives are scored against the photo (background an
    object-only model does not render); with the capture's own truth the report says how
    good the object is. Same render, two masks; no truth -> no second figure."""
    from dataclasses import replace

    from scipy.ndimage import binary_dilation
    pts = sim.gt_ooi_points[::40]
    wide = {v.key: binary_dilation(v.gt_mask, iterations=3) for v in sim.views}
    r = train(sim, wide, pts, _cfg(iterations=10, eval_every=0))
    for h in r.heldout:
        assert h.psnr_gt is not None and h.ssim_gt is not None
        assert h.psnr_gt != h.psnr
    m = r.metrics()
    assert m["heldout_psnr_gt_mask"] == pytest.approx(np.mean([h.psnr_gt for h in r.heldout]))
    # opacity spilled past the mask: a wider mask leaves less of the render outside it
    assert all(0.0 <= h.spill <= h.spill_gt <= 1.0 for h in r.heldout)
    assert m["heldout_spill_gt_mask"] == pytest.approx(np.mean([h.spill_gt for h in r.heldout]))
    exact = train(sim, {v.key: v.gt_mask for v in sim.views}, pts,
                  _cfg(iterations=5, eval_every=0))
    assert all(h.psnr_gt == pytest.approx(h.psnr) for h in exact.heldout)
    assert all(h.spill_gt == pytest.approx(h.spill) for h in exact.heldout)
    bare = replace(sim, views=[replace(v, gt_mask=None) for v in sim.views])
    r = train(bare, wide, pts, _cfg(iterations=5, eval_every=0))
    assert all(h.psnr_gt is None and h.spill_gt is None for h in r.heldout)
    assert r.metrics()["heldout_psnr_gt_mask"] is None
    assert r.metrics()["heldout_spill"] is not None


def test_spill_is_the_opacity_share_past_the_mask_margin():
    from ooi_seg_ros.train.trainer import _spill

    mask = torch.zeros(20, 20, dtype=torch.bool)
    mask[5:10, 5:10] = True
    alpha = torch.zeros(20, 20)
    alpha[5:10, 5:10] = 1.0  # 25 inside
    alpha[11, 7] = 1.0  # 2 px out: outline blur, not counted
    alpha[15, 15] = 0.5  # far out
    assert _spill(alpha, mask) == pytest.approx(0.5 / 26.5)
    assert _spill(torch.zeros(20, 20), mask) == 0.0


def test_sparse_cloud_is_filled_near_the_visual_hull_surface(sim):
    """A bare OOI cloud (an SfM cloud misses plain panels) is topped up to init_fill with
    points inside every mask that sees them, near a mask's outline; off with init_fill 0."""
    from ooi_seg_ros.train import mcmc
    from ooi_seg_ros.train.trainer import TrainResult, _hull_surface_points, _prepare
    masks = {v.key: v.gt_mask for v in sim.views}
    cfg = _cfg(iterations=1, eval_every=0, init_fill=300)
    frames, _ = _prepare(sim, masks, cfg, TrainResult(model=None, config=cfg))
    few = sim.gt_ooi_points[::400]
    extra = _hull_surface_points(frames, 300, few, 1.5, torch.Generator().manual_seed(0))
    assert 200 <= len(extra) <= 300
    frac, seen = mcmc.outside_mask_fraction(torch.from_numpy(extra).float(),
                                            [f.cam for f in frames], [f.mask for f in frames])
    assert float(frac.max()) == 0.0 and int(seen.min()) >= len(frames) // 4
    # near the object's surface: within a few true-surface spacings of it
    d = np.linalg.norm(extra[:, None] - sim.gt_ooi_points[None, ::4], axis=2).min(1)
    span = np.ptp(sim.gt_ooi_points, axis=0).max()
    assert np.median(d) < 0.05 * span
    r = train(sim, masks, few, cfg)
    assert r.init_filled == 300 - len(few) and r.metrics()["init_filled"] == r.init_filled
    r = train(sim, masks, few, _cfg(iterations=1, eval_every=0, init_fill=0))
    assert r.init_filled == 0


def test_drops_and_skips_are_counted(sim):
    from dataclasses import replace
    views = list(sim.views)
    views[1] = replace(views[1], pose=None)
    masks = {v.key: v.gt_mask for v in views}
    masks[views[2].key] = np.zeros_like(views[2].gt_mask)
    cap = replace(sim, views=views)
    r = train(cap, masks, sim.gt_ooi_points[::40], _cfg(iterations=3, eval_every=0))
    assert r.dropped_no_pose == 1 and r.skipped_empty_mask == 1
    assert len(r.train_keys) == 6


def test_empty_cloud_uses_visual_hull_and_errors(sim):
    masks = {v.key: v.gt_mask for v in sim.views}
    r = train(sim, masks, np.zeros((0, 3)), _cfg(iterations=2, eval_every=0))
    assert r.init == "visual_hull" and len(r.model) > 10
    with pytest.raises(InputError, match="max-gaussians"):
        train(sim, masks, sim.gt_ooi_points[::40], _cfg(max_gaussians=10 ** 10))
    with pytest.raises(InputError, match="mask"):
        train(sim, {}, sim.gt_ooi_points[::40], _cfg(iterations=2))


def test_nan_step_is_skipped(sim):
    masks = {v.key: v.gt_mask for v in sim.views}
    calls = {"n": 0}
    from ooi_seg_ros.train import trainer as tr
    orig = tr.photometric_loss

    def flaky(*a, **k):
        calls["n"] += 1
        out = orig(*a, **k)
        return out * float("nan") if calls["n"] == 2 else out

    tr.photometric_loss = flaky
    try:
        r = train(sim, masks, sim.gt_ooi_points[::40], _cfg(iterations=5, eval_every=0))
    finally:
        tr.photometric_loss = orig
    assert r.nan_steps == 1 and len(r.history) == 4
    assert all(torch.isfinite(t).all() for t in r.model.params().values())


def test_full_image_option(sim):
    cfg = _cfg(iterations=3, full_image=True, eval_every=0)
    r = train(sim, None, sim.gt_ooi_points[::40], cfg)
    assert r.heldout and r.heldout[0].mask.all()


def test_cli_train_and_export(sim, tmp_path):
    from ooi_seg_ros.capture_io import write_capture
    from PIL import Image
    cap_dir = tmp_path / "cap"
    write_capture(sim, cap_dir)
    mdir = tmp_path / "masks"
    mdir.mkdir()
    for v in sim.views:
        Image.fromarray(v.gt_mask.astype(np.uint8) * 255).save(mdir / f"{v.key}.png")
    out = tmp_path / "out"
    cfg_yaml = tmp_path / "c.yaml"
    cfg_yaml.write_text("max_gaussians: 400\nsnapshot_every: 5\neval_every: 5\n")
    args = Namespace(input=str(cap_dir), out=str(out), iterations=10, max_gaussians=None,
                     masks=str(mdir), init=None, full_image=False, sh_degree=None, seed=None,
                     backend="cpu", config=str(cfg_yaml), sim_views=60, sim_size="320x240",
                     quiet=True)
    assert train_cli.run(args) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["init"] == "visual_hull" and rep["n_heldout"] == 2
    assert rep["lpips"].startswith("unavailable")
    assert sorted(p.stem for p in (out / "heldout").iterdir()) == sorted(
        [sim.views[0].key, sim.views[8].key])
    page = (out / "report.html").read_text()
    assert page.count("<img") == 2
    page = re.sub(r"data:image/png;base64,[A-Za-z0-9+/=]*", "", page)
    assert "None" not in page and "heldout_psnr_gt_mask: " in page
    assert "lpips: unavailable" in page
    names, count, _, _ = read_ply_header(out / "splats.ply")
    assert count == rep["n_gaussians"] and len(names) == 62
    from ooi_seg_ros.bag import BagReader
    topics = BagReader(out / "training.mcap").topics()
    assert {"/train/splats", "/train/loss", "/train/psnr", "/train/masks",
            "/train/preview/v0"} <= set(topics)
    ply = tmp_path / "e.ply"
    assert export_cli.run(Namespace(bag=str(out / "training.mcap"), out=str(ply), index=-1,
                                    topic="/train/splats")) == 0
    a, b = load_ply(ply), load_ply(out / "splats.ply")
    assert torch.allclose(a.means, b.means) and torch.allclose(a.sh_rest, b.sh_rest)
    with pytest.raises(InputError, match="out of range"):
        export_cli.run(Namespace(bag=str(out / "training.mcap"), out=str(ply), index=99,
                                 topic="/train/splats"))


def test_schedule_follows_time_budget():
    """With a time budget the schedules run on elapsed time when that is further along."""
    from ooi_seg_ros.train.trainer import _progress
    cfg = TrainConfig(iterations=1000)
    assert _progress(1, cfg, 50.0) == 0.0 and abs(_progress(1000, cfg, 0.0) - 1.0) < 1e-12
    cfg = TrainConfig(iterations=100000, time_budget_s=100.0)
    assert abs(_progress(10, cfg, 50.0) - 0.5) < 1e-9
    assert _progress(10, cfg, 500.0) == 1.0


def test_cpu_clock_budget_stops_and_reports(sim):
    """A CPU-time budget stops training like a wall-clock one; both times are reported."""
    masks = {v.key: v.gt_mask for v in sim.views}
    r = train(sim, masks, sim.gt_ooi_points[::40],
              _cfg(iterations=100000, time_budget_s=0.5, budget_clock="cpu"))
    assert 0 < r.iterations_done < 100000
    m = r.metrics()
    assert m["cpu_seconds"] > 0.4 and m["seconds"] > 0
    with pytest.raises(InputError, match="budget_clock"):
        train(sim, masks, sim.gt_ooi_points[::40], _cfg(budget_clock="gpu"))


def test_scene_scale_follows_the_camera_orbit():
    """Position lr scale: 1.1 x the camera spread (3DGS), never below the cloud's radius."""
    from ooi_seg_ros.core.geometry import look_at
    from ooi_seg_ros.core.types import CameraIntrinsics
    from ooi_seg_ros.train.raster_common import RasterCamera
    from ooi_seg_ros.train.trainer import _Frame, _scene_scale
    cam = CameraIntrinsics(width=8, height=6, fx=8.0, fy=8.0, cx=3.5, cy=2.5)

    def frame(eye):
        rc = RasterCamera.from_view(cam, look_at(np.asarray(eye, float), np.zeros(3)))
        return _Frame("k", rc, torch.zeros(6, 8, 3), torch.ones(6, 8, dtype=torch.bool))

    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    orbit = [frame([5 * np.cos(a), 5 * np.sin(a), 1.0]) for a in angles]
    pts = np.random.default_rng(0).normal(size=(100, 3)) * 0.3
    assert abs(_scene_scale(pts, orbit) - 5.5) < 0.1
    assert _scene_scale(pts * 100, orbit) == pytest.approx(
        float(np.linalg.norm(pts * 100 - (pts * 100).mean(0), axis=1).max()))
    assert _scene_scale(pts[:1], [frame([0.0, 5.0, 1.0])]) == 1.0  # degenerate: unit scale


def test_exposure_compensation_learns_per_view_gains(sim):
    """Training views brightened / darkened by known gains: the learned centred log-gains
    follow them, offsets stay out in "gain" mode, and a bad mode name is an InputError."""
    from dataclasses import replace
    from ooi_seg_ros.train.trainer import _apply_exposure
    gains = np.where(np.arange(len(sim.views)) % 2 == 0, 0.8, 1.15)
    views = [replace(v, image=np.clip(v.get_image() * g, 0, 255).astype(np.uint8))
             for v, g in zip(sim.views, gains)]
    cap = replace(sim, views=views)
    masks = {v.key: v.gt_mask for v in views}
    r = train(cap, masks, sim.gt_ooi_points[::40],
              _cfg(iterations=80, eval_every=0, exposure="gain", lr_exposure=0.03))
    learned = r.exposure.mean(1)  # [V] mean log-gain of the training views
    assert r.exposure.shape == (len(r.train_keys), 3)
    assert abs(float(learned.mean())) < 1e-6  # centred: held-out views get the mean exposure
    applied = np.log([gains[i] for i, v in enumerate(views) if v.key in r.train_keys])
    assert np.corrcoef(learned, applied)[0, 1] > 0.5
    # the gain scales the object only, never the background it is composited over
    img, alpha, bg = torch.full((2, 2, 3), 0.3), torch.tensor([[1.0, 0.0], [0.5, 0.0]]), \
        torch.full((3,), 0.3)
    e = torch.tensor([[np.log(2.0)] * 3, [-np.log(2.0)] * 3], dtype=torch.float32)
    out = _apply_exposure(img, alpha, bg, e, 0)  # centred: log-gain ln 2 for view 0
    assert torch.allclose(out[0, 0], torch.full((3,), 0.6)) and torch.allclose(out[0, 1], bg)
    with pytest.raises(InputError, match="exposure"):
        train(sim, masks, sim.gt_ooi_points[::40], _cfg(iterations=2, exposure="curves"))


def test_crop_and_half_size_targets(sim):
    """A training view's crop camera renders exactly that window of the full render (background
    composite included), and the half-size camera renders the 2x2 average of the full image."""
    from ooi_seg_ros.train.gaussians import init_from_points
    from ooi_seg_ros.train.raster_common import RasterCamera
    from ooi_seg_ros.train.raster_cpu import render
    from ooi_seg_ros.train.trainer import _Frame, _half_camera, _levels

    v = sim.views[3]
    model = init_from_points(sim.gt_ooi_points[::20], None, 0.7)
    cam = RasterCamera.from_view(v.camera, v.pose)
    bg = torch.tensor([0.2, 0.5, 0.8])
    full = render(model, cam, bg).image
    img = torch.from_numpy(v.image.astype(np.float32) / 255)
    mask = torch.from_numpy(v.gt_mask)
    lv = _levels(_Frame(v.key, cam, img, mask), TrainConfig(coarse_frac=0.5))
    tg = lv[0]
    x0, y0 = int(cam.cx - tg.cam.cx), int(cam.cy - tg.cam.cy)
    assert tg.cam.width * tg.cam.height < 48 * 36
    window = full[y0:y0 + tg.cam.height, x0:x0 + tg.cam.width]
    crop = render(model, tg.cam, bg).image
    assert crop.shape == window.shape and crop.shape[:2] == tg.mask.shape
    assert int(tg.mask.sum()) == int(mask.sum())  # every mask pixel is inside the crop
    assert torch.allclose(crop, window, atol=2e-3)  # tiles start at the crop's corner
    assert torch.equal(tg.image, img[y0:y0 + tg.cam.height, x0:x0 + tg.cam.width])
    # half size: the rendered silhouette's centroid maps to (full - 0.5) / 2
    half = render(model, _half_camera(cam), torch.zeros(3)).alpha
    fa = render(model, cam, torch.zeros(3)).alpha
    ys, xs = torch.meshgrid(torch.arange(36.0), torch.arange(48.0), indexing="ij")
    hy, hx = torch.meshgrid(torch.arange(18.0), torch.arange(24.0), indexing="ij")
    c_full = torch.stack([(fa * xs).sum(), (fa * ys).sum()]) / fa.sum()
    c_half = torch.stack([(half * hx).sum(), (half * hy).sum()]) / half.sum()
    assert torch.allclose((c_full - 0.5) / 2, c_half, atol=0.3)
    assert lv[1].image.shape[:2] == lv[1].mask.shape and bool(lv[1].mask.any())


def test_lowpass_reaches_training_and_heldout_cameras(sim):
    """TrainConfig.lowpass is the dilation of every camera the trainer renders with: the
    full, mask-cropped and half-size training targets and the held-out views (whose renders
    are then the model's renders at that value)."""
    from ooi_seg_ros.train.raster_common import RasterCamera
    from ooi_seg_ros.train.raster_cpu import render
    from ooi_seg_ros.train.trainer import TrainResult, _prepare

    masks = {v.key: v.gt_mask for v in sim.views}
    cfg = _cfg(lowpass=0.05, coarse_frac=0.5)
    tr, held = _prepare(sim, masks, cfg, TrainResult(model=None, config=cfg))
    assert {f.cam.lowpass for f in tr + held} == {0.05}
    assert {t.cam.lowpass for f in tr for t in f.levels} == {0.05}
    assert TrainConfig().lowpass == 0.1
    r = train(sim, masks, sim.gt_ooi_points[::40], _cfg(lowpass=0.05, iterations=10))
    v = sim.views[0]
    with torch.no_grad():
        img = render(r.model, RasterCamera.from_view(v.camera, v.pose, lowpass=0.05),
                     torch.zeros(3)).image.clamp(0, 1)
    assert np.abs((img.numpy() * 255 + 0.5).astype(np.uint8).astype(int)
                  - r.heldout[0].render.astype(int)).max() <= 1


def test_edge_background_is_the_local_background_on_the_outline(sim):
    """The outline option: ring = mask pixels touching background; its colour = the mean of the
    pixels >= 2 px outside the mask nearby (the mixed pixel just outside is not used); the
    training targets carry the ring cropped with the image, and training runs with it."""
    from ooi_seg_ros.train.raster_common import RasterCamera
    from ooi_seg_ros.train.trainer import _Frame, _levels, edge_background

    img = torch.zeros(12, 12, 3)
    img[..., 1] = 1.0  # green background
    mask = torch.zeros(12, 12, dtype=torch.bool)
    mask[4:8, 4:8] = True
    img[4:8, 4:8] = torch.tensor([1.0, 0.0, 0.0])
    img[3, 4:8] = torch.tensor([0.5, 0.5, 0.0])  # a mixed pixel just outside the mask
    edge, bg = edge_background(img, mask)
    ring = mask.clone()
    ring[5:7, 5:7] = False
    assert torch.equal(edge, ring)
    assert torch.allclose(bg[edge], torch.tensor([0.0, 1.0, 0.0]).expand(12, 3))
    assert float(bg[~edge].abs().max()) == 0.0
    v = sim.views[3]
    frame = _Frame(v.key, RasterCamera.from_view(v.camera, v.pose),
                   torch.from_numpy(v.image.astype(np.float32) / 255),
                   torch.from_numpy(v.gt_mask))
    for tg in _levels(frame, TrainConfig(edge_background=True, coarse_frac=0.5)):
        assert tg.edge.shape == tg.mask.shape and bool(tg.edge.any())
        assert not bool((tg.edge & ~tg.mask).any())
    assert _levels(frame, TrainConfig())[0].edge is None
    masks = {v.key: v.gt_mask for v in sim.views}
    r = train(sim, masks, sim.gt_ooi_points[::40], _cfg(edge_background=True))
    assert r.history[-1]["loss"] < r.history[0]["loss"] and np.isfinite(r.heldout[0].psnr)


def test_background_penalty_spares_a_margin_past_the_mask():
    from ooi_seg_ros.train.loss import mask_crop
    from ooi_seg_ros.train.raster_common import RasterCamera
    from ooi_seg_ros.train.trainer import _far_from_mask, _target

    mask = torch.zeros(40, 50, dtype=torch.bool)
    mask[18:22, 20:30] = True
    far = _far_from_mask(mask, 2)
    assert not bool((far & mask).any())
    assert not bool(far[16, 18]) and not bool(far[23, 31])  # 2 px out: spared
    assert bool(far[15, 20]) and bool(far[20, 32])  # 3 px out: penalised
    cam = RasterCamera(torch.eye(3), torch.zeros(3), 40.0, 40.0, 25.0, 20.0, 50, 40)
    image = torch.rand(40, 50, 3)
    tg = _target(cam, image, mask, crop=True, far_margin=2)
    rows, cols = mask_crop(mask, 5)
    assert tg.far is not None and torch.equal(tg.far, far[rows, cols])
    assert _target(cam, image, mask, crop=True).far is None


def test_report_summary_says_what_a_missing_figure_means():
    lines = train_cli._summary_lines({"heldout_psnr": 21.1349, "heldout_ssim": 0.75043,
                                      "heldout_psnr_gt_mask": None, "heldout_spill": 0.0188,
                                      "n_gaussians": 10000}, "unavailable (no local weights file)")
    assert lines[:4] == ["heldout_psnr: 21.13 dB", "heldout_ssim: 0.750",
                         "heldout_psnr_gt_mask: n/a -- no ground-truth masks in the capture "
                         "(scored in the computed masks only)",
                         "heldout_spill: 1.9% of the render's opacity outside the mask"]
    assert lines[4] == "n_gaussians: 10000" and lines[-1].startswith("lpips: unavailable")
    assert train_cli._summary_lines({}, 0.1234) == ["lpips: 0.123"]
