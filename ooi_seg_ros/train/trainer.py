"""Object-only Gaussian splat training (paper 4.6) on the CPU (or gsplat on CUDA).

Inputs: a Capture (images + camera-to-world poses), one boolean object mask per view key, and
the OOI point cloud for initialisation. Loss only on object pixels, renders over a random
background colour each step (so Gaussians cannot stand in for background), MCMC densification
under a hard cap with mask-aware relocation. Every 8th view (capture order, starting with the
first) is held out and never trained on.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
import torch

from ..core.resources import available_memory
from ..core.types import CameraIntrinsics, Capture, InputError
from . import mcmc
from .gaussians import GaussianModel, MAX_SH_DEGREE, init_from_points
from .loss import SSIM_SIZE, mask_crop, masked_psnr, masked_ssim, photometric_loss
from .raster_common import RasterCamera


@dataclass
class TrainConfig:
    """Options of object-only splat training (defaults: 3DGS-MCMC, scaled to a CPU budget)."""

    iterations: int = 6000  # optimisation steps (one view per step). The issue allows ~10 min
    # for a 60-view 320x240 capture on a 2-core CPU: 6000 steps took 276 CPU-s on the demo bag
    # (held-out 20.12 dB / SSIM 0.773; 3000 steps: 106 CPU-s, 19.36 / 0.713; session 7)
    max_gaussians: int = 10000  # MCMC hard cap on the number of Gaussians
    sh_degree: int = 3  # final spherical-harmonics degree
    sh_degree_interval: int = 300  # raise the active SH degree every this many steps
    lr_means: float = 1.6e-4  # position lr, times the scene scale, decays x0.01 to the end
    lr_sh_dc: float = 2.5e-3  # base colour lr
    lr_sh_rest: float = 1.25e-4  # higher SH bands lr
    lr_opacity: float = 0.05  # logit-opacity lr
    lr_scales: float = 5e-3  # log-scale lr
    lr_quats: float = 1e-3  # rotation lr
    lambda_dssim: float = 0.2  # weight of D-SSIM in the photometric loss
    opacity_reg: float = 0.01  # MCMC L1 opacity penalty
    scale_reg: float = 0.01  # MCMC L1 scale penalty
    bg_alpha_reg: float = 0.1  # penalty on opacity outside the mask (haze, streaks, fog)
    bg_alpha_margin_px: int = 2  # ... only on pixels more than this many pixels outside the
    # mask: a computed mask's outline is uncertain by a pixel or two (recall ~0.97), and the
    # object's own pixels just past it should not be pushed transparent. Without it nothing
    # stops Gaussians from spilling opacity where the loss sees no pixel: on the real bonsai
    # photos half of each held-out render's opacity lay outside the mask (0.48 -> 0.02 with
    # it); on four simulator captures it takes 55-90% of the haze away. Cost: -0.04 dB on
    # the tabletop with true masks at equal steps, -0.03..-0.21 dB in the true mask on the
    # product path (outline pixels), more in computed masks whose false positives the haze
    # had been painting (BENCHMARKS, Training, sessions 57-59). 0 = off.
    noise_lr: float = 5e5  # MCMC SGLD noise scale (times the position lr)
    refine_every: int = 100  # relocate / add Gaussians every this many steps
    refine_start: int = 100  # first refinement step
    refine_stop_frac: float = 0.8  # no refinement in the last 20% of the steps
    grow_rate: float = 0.1  # add up to this fraction of the current count per refinement
    outside_mask_limit: float = 0.5  # relocate Gaussians outside the mask in > this fraction
    seed: int = 0  # view order, backgrounds, MCMC sampling and noise
    background: str = "random"  # "random" per step, or "black"/"white" (evaluation is black)
    full_image: bool = False  # ignore masks: loss over all pixels (paper Fig. 1 baseline)
    holdout_every: int = 8  # every n-th view (from the first) is held out; 0 = none
    eval_every: int = 500  # held-out PSNR/SSIM every this many steps (0 = only at the end)
    snapshot_every: int = 500  # keep a copy of the splats every this many steps (0 = end only)
    initial_opacity: float = 0.5  # opacity of the initial Gaussians
    max_memory_fraction: float = 0.7  # refuse to start above this share of available RAM
    backend: str = "auto"  # "cpu", "gsplat" (CUDA) or "auto"
    time_budget_s: float = 0.0  # stop after this many seconds of training (0 = none); the
    # schedules (position lr decay, refinement window) then follow the larger of the step and
    # time fractions, so a run cut by the budget still anneals instead of stopping mid-schedule
    budget_clock: str = "wall"  # "wall", or "cpu" (this process's CPU time: on a shared machine
    # the same budget then buys the same work whatever else runs)
    threads: int = 1  # torch CPU threads (0 = torch default); >1 collapses on a loaded box
    exposure: str = "none"  # per-training-view colour compensation learned with the splats:
    # "gain" (3 per-channel gains), "affine" (gains + offsets) or "none". Centred over the
    # training views, so a held-out view (identity) is rendered at their mean exposure
    lr_exposure: float = 5e-3  # learning rate of the per-view log-gains / offsets
    crop_to_mask: bool = True  # render and score only each training view's mask bounding box
    # grown by the SSIM window's half size: the loss is the same (pixels outside the mask carry
    # none), the renders cost less. The composite over the background holds inside the crop
    lowpass: float = 0.1  # pixel^2 added to each Gaussian's 2D covariance when rendering
    # (3DGS: 0.3, the renderer's default; 0.1 ~ a pixel's own box filter, 1/12 px^2, as in
    # Mip-Splatting's 2D filter). 0.3 -> 0.1 gave +1.0-1.2 dB held-out on aircraft and
    # tabletop (BENCHMARKS.md, Training, session 6). 0.03 gave another +0.5-0.7 dB there, but
    # that gain comes from the simulator's point-sampled texture (one shading sample per
    # pixel); a real camera integrates over the pixel, so the default stays at the
    # pixel-footprint value. The trainer's held-out renders and the gsplat back-end use it;
    # PLY viewers render with 0.3 (slightly softer)
    coarse_frac: float = 0.0  # train on 2x2-averaged views (a quarter of the pixels) for this
    # fraction of the schedule, then at full resolution
    init_fill: int = 5000  # when the OOI cloud has fewer points, add points near the surface of
    # the training masks' visual hull up to this many (capped at max_gaussians; 0 = off): an
    # SfM cloud is dense on texture and bare on plain panels, and Gaussians grown from far away
    # reach those late. On the demo bag (634 SfM points) +0.65 dB / +0.024 SSIM held-out in
    # the true masks, the same as starting from 5,000 true surface points; the stool (66
    # points) +4.5 dB (BENCHMARKS, Training, sessions 57-58)
    init_fill_band_px: float = 1.5  # "near the surface": within this many pixels of a mask's
    # outline in at least one training view (inside every mask that sees the point)
    edge_background: bool = False  # on the mask's inner ring (mask pixels next to background),
    # composite the render over the photo's own local background (mean of the pixels 2-3 px
    # outside the mask) instead of the step's random colour: an outline pixel of the photo
    # mixes the object with what lies behind it, and this lets the splats explain that pixel
    # with partial coverage rather than with a background-tinted colour


@dataclass
class HeldOutResult:
    """Evaluation of one held-out view."""

    key: str
    psnr: float
    ssim: float
    render: np.ndarray  # [H, W, 3] uint8, over black
    gt: np.ndarray  # [H, W, 3] uint8, object only (background black)
    mask: np.ndarray  # [H, W] bool
    psnr_gt: Optional[float] = None  # the same render scored inside the capture's own
    ssim_gt: Optional[float] = None  # ground-truth mask (simulator bags), when it has one
    spill: Optional[float] = None  # share of the render's opacity outside the mask grown by
    # SPILL_MARGIN_PX: haze and floaters an object-only model should not have
    spill_gt: Optional[float] = None  # the same outside the ground-truth mask, when there is one


@dataclass
class TrainResult:
    """What training produced and counted."""

    model: GaussianModel
    config: TrainConfig
    history: list[dict] = field(default_factory=list)  # {"it", "loss", "psnr", "n"}
    evals: list[dict] = field(default_factory=list)  # {"it", "psnr", "ssim"} on held-out views
    heldout: list[HeldOutResult] = field(default_factory=list)
    snapshots: list[tuple[int, GaussianModel]] = field(default_factory=list)
    previews: list[tuple[int, str, np.ndarray]] = field(default_factory=list)  # it, key, rgb
    train_keys: list[str] = field(default_factory=list)
    heldout_keys: list[str] = field(default_factory=list)
    dropped_no_pose: int = 0
    skipped_empty_mask: int = 0
    nan_steps: int = 0
    iterations_done: int = 0  # less than config.iterations when the time budget ran out
    init: str = "points"  # "points" or "visual_hull"
    init_filled: int = 0  # points added near the masks' visual hull surface (init_fill)
    seconds: float = 0.0  # wall-clock training time (without the final evaluation)
    cpu_seconds: float = 0.0  # CPU time of this process over the same span
    its_per_s: float = 0.0
    backend: str = "cpu"
    exposure: Optional[np.ndarray] = None  # [V, 3|6] learned per-view log-gain (, offset)

    def metrics(self) -> dict:
        """Mean held-out masked PSNR/SSIM and counts (report.json)."""
        ps = [h.psnr for h in self.heldout if math.isfinite(h.psnr)]
        ss = [h.ssim for h in self.heldout]
        pg = [h.psnr_gt for h in self.heldout if h.psnr_gt is not None
              and math.isfinite(h.psnr_gt)]
        sg = [h.ssim_gt for h in self.heldout if h.ssim_gt is not None]
        sp = [h.spill for h in self.heldout if h.spill is not None]
        spg = [h.spill_gt for h in self.heldout if h.spill_gt is not None]
        return {"heldout_psnr": float(np.mean(ps)) if ps else None,
                "heldout_ssim": float(np.mean(ss)) if ss else None,
                "heldout_psnr_gt_mask": float(np.mean(pg)) if pg else None,
                "heldout_ssim_gt_mask": float(np.mean(sg)) if sg else None,
                "heldout_spill": float(np.mean(sp)) if sp else None,
                "heldout_spill_gt_mask": float(np.mean(spg)) if spg else None,
                "n_heldout": len(self.heldout), "n_train": len(self.train_keys),
                "n_gaussians": len(self.model), "seconds": self.seconds,
                "cpu_seconds": self.cpu_seconds,
                "its_per_s": self.its_per_s, "iterations": self.iterations_done,
                "dropped_no_pose": self.dropped_no_pose,
                "skipped_empty_mask": self.skipped_empty_mask, "nan_steps": self.nan_steps,
                "init": self.init, "init_filled": self.init_filled, "backend": self.backend}


# --------------------------------------------------------------------------- data preparation


def _undistort_maps(cam: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel of the ideal pinhole image, where to sample the distorted image."""
    if cam.distortion_model not in ("plumb_bob", "rational_polynomial"):
        raise InputError(f"cannot undistort camera model {cam.distortion_model!r}; "
                         "rectify the images first or use plumb_bob")
    d = np.zeros(8)
    d[:min(8, len(cam.dist))] = np.asarray(cam.dist, dtype=np.float64)[:8]
    k1, k2, p1, p2, k3, k4, k5, k6 = d
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    x = (u - cam.cx) / cam.fx
    y = (v - cam.cy) / cam.fy
    r2 = x * x + y * y
    radial = ((1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3)
              / (1 + k4 * r2 + k5 * r2 ** 2 + k6 * r2 ** 3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return yd * cam.fy + cam.cy, xd * cam.fx + cam.cx


def undistort(image: np.ndarray, mask: Optional[np.ndarray],
              cam: CameraIntrinsics) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Resample a distorted image (bilinear) and mask (nearest) onto the ideal pinhole grid."""
    from scipy.ndimage import map_coordinates

    rows, cols = _undistort_maps(cam)
    out = np.stack([map_coordinates(image[..., c].astype(np.float32), [rows, cols], order=1,
                                    mode="nearest") for c in range(image.shape[2])], -1)
    out_mask = None
    if mask is not None:
        out_mask = map_coordinates(mask.astype(np.uint8), [rows, cols], order=0,
                                   mode="constant", cval=0).astype(bool)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8), out_mask


@dataclass
class _Target:
    """What one training step renders and scores: a camera and its image and mask."""

    cam: RasterCamera
    image: torch.Tensor  # [h, w, 3] float in [0, 1]
    mask: torch.Tensor  # [h, w] bool
    edge: Optional[torch.Tensor] = None  # [h, w] bool: outline pixels with a local background
    edge_bg: Optional[torch.Tensor] = None  # [h, w, 3] that background (zero off ``edge``)
    far: Optional[torch.Tensor] = None  # [h, w] bool: pixels the background-opacity penalty
    # covers (outside the mask by more than ``bg_alpha_margin_px``); None = outside the mask


@dataclass
class _Frame:
    key: str
    cam: RasterCamera
    image: torch.Tensor  # [H, W, 3] float in [0, 1]
    mask: torch.Tensor  # [H, W] bool
    levels: list[_Target] = field(default_factory=list)  # training targets: full, half size
    gt_mask: Optional[torch.Tensor] = None  # held-out views: the capture's ground-truth mask


def _crop_camera(cam: RasterCamera, rows: slice, cols: slice) -> RasterCamera:
    """The camera of the window ``rows`` x ``cols`` of ``cam``'s image (principal point moved,
    same pixel grid), so a render of it equals that window of the full render."""
    return RasterCamera(cam.R, cam.t, cam.fx, cam.fy, cam.cx - cols.start, cam.cy - rows.start,
                        cols.stop - cols.start, rows.stop - rows.start, cam.lowpass)


def _half_camera(cam: RasterCamera) -> RasterCamera:
    """The camera of the 2x2-averaged image: pixel i covers full pixels 2i and 2i + 1, whose
    centres average to 2i + 0.5 (pixel centres at integer coordinates)."""
    return RasterCamera(cam.R, cam.t, cam.fx / 2, cam.fy / 2, (cam.cx - 0.5) / 2,
                        (cam.cy - 0.5) / 2, cam.width // 2, cam.height // 2, cam.lowpass)


def edge_background(image: torch.Tensor, mask: torch.Tensor, reach: int = 3
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """The mask's inner ring and the photo's local background colour there.

    Ring: mask pixels with a non-mask 8-neighbour. Background: the mean colour of the pixels
    at least 2 px outside the mask (the pixel just outside is itself a mix) within the
    ``(2 reach + 1)``-square window around the ring pixel. Returns ``edge`` [h, w] bool (ring
    pixels that have such background) and ``edge_bg`` [h, w, 3] (zero off ``edge``).
    """
    m = mask.to(image.dtype)[None, None]
    near = torch.nn.functional.max_pool2d(m, 3, 1, 1)[0, 0] > 0
    ring = mask & (torch.nn.functional.max_pool2d(1.0 - m, 3, 1, 1)[0, 0] > 0)
    far = (~near).to(image.dtype)
    win = 2 * reach + 1

    def box_sum(x: torch.Tensor) -> torch.Tensor:  # [h, w, c] -> window sums
        y = torch.nn.functional.avg_pool2d(x.permute(2, 0, 1)[None], win, 1, reach,
                                           count_include_pad=True)
        return y[0].permute(1, 2, 0) * (win * win)

    cnt = box_sum(far[..., None])[..., 0]
    edge = ring & (cnt > 0.5)
    bg = box_sum(image * far[..., None]) / cnt.clamp_min(1.0)[..., None]
    return edge, bg * edge[..., None].to(image.dtype)


def _far_from_mask(mask: torch.Tensor, margin: int) -> torch.Tensor:
    """Pixels more than ``margin`` pixels (chessboard distance) outside ``mask``."""
    m = mask.float()[None, None]
    grown = torch.nn.functional.max_pool2d(m, 2 * margin + 1, 1, margin)[0, 0] > 0
    return ~grown


def _target(cam: RasterCamera, image: torch.Tensor, mask: torch.Tensor,
            crop: bool, edges: bool = False, far_margin: int = 0) -> _Target:
    """A training target, cut to the mask's bounding box grown by the SSIM window's half size
    when ``crop`` (the loss sees no pixel outside that box; ``photometric_loss`` crops the
    same box); with ``edges``, the outline's local background (``edge_background``); with
    ``far_margin`` > 0, the pixels the background-opacity penalty covers."""
    edge, edge_bg = edge_background(image, mask) if edges else (None, None)
    far = _far_from_mask(mask, far_margin) if far_margin > 0 else None
    if not crop:
        return _Target(cam, image, mask, edge, edge_bg, far)
    rows, cols = mask_crop(mask, SSIM_SIZE // 2)
    cut = (lambda t: None if t is None else t[rows, cols].contiguous())
    return _Target(_crop_camera(cam, rows, cols), image[rows, cols].contiguous(),
                   mask[rows, cols].contiguous(), cut(edge), cut(edge_bg), cut(far))


def _levels(f: _Frame, cfg: TrainConfig) -> list[_Target]:
    """Full-size and half-size training targets of a frame (the half-size mask keeps pixels
    at least half covered by the full-size mask)."""
    crop = cfg.crop_to_mask and not cfg.full_image
    edges = cfg.edge_background and not cfg.full_image
    margin = cfg.bg_alpha_margin_px if cfg.bg_alpha_reg > 0 and not cfg.full_image else 0
    out = [_target(f.cam, f.image, f.mask, crop, edges, margin)]
    if cfg.coarse_frac > 0:
        h2, w2 = f.cam.height // 2, f.cam.width // 2
        img = f.image[:2 * h2, :2 * w2].reshape(h2, 2, w2, 2, 3).mean((1, 3))
        cover = f.mask[:2 * h2, :2 * w2].float().reshape(h2, 2, w2, 2).mean((1, 3))
        mask = cover >= 0.5
        if not bool(mask.any()):
            mask = cover > 0
        out.append(_target(_half_camera(f.cam), img, mask, crop, edges, (margin + 1) // 2))
    return out


def _prepare(capture: Capture, masks: Optional[dict[str, np.ndarray]], cfg: TrainConfig,
             result: TrainResult) -> tuple[list[_Frame], list[_Frame]]:
    train, held = [], []
    for idx, view in enumerate(capture.views):
        if view.pose is None:
            result.dropped_no_pose += 1
            continue
        image = view.get_image()
        if cfg.full_image:
            mask = np.ones(image.shape[:2], dtype=bool)
        else:
            mask = None if masks is None else masks.get(view.key)
            if mask is None:
                raise InputError(f"no object mask for view {view.key!r}; pass a masks folder "
                                 "with <key>.png for every view (or --full-image)")
            mask = np.asarray(mask).astype(bool)
            if mask.shape != image.shape[:2]:
                raise InputError(f"mask of view {view.key!r} is {mask.shape[1]}x"
                                 f"{mask.shape[0]}, image is {image.shape[1]}x"
                                 f"{image.shape[0]}; masks must match the images")
        cam = view.camera
        if cam.has_distortion:
            image, mask = undistort(image, mask, cam)
        if not mask.any():
            result.skipped_empty_mask += 1
            continue
        frame = _Frame(view.key, RasterCamera.from_view(cam, view.pose, lowpass=cfg.lowpass),
                       torch.from_numpy(image.astype(np.float32) / 255.0), torch.from_numpy(mask))
        is_held = cfg.holdout_every > 0 and idx % cfg.holdout_every == 0
        if not is_held:
            frame.levels = _levels(frame, cfg)
        elif view.gt_mask is not None and not cfg.full_image:
            gm = np.asarray(view.gt_mask).astype(bool)
            if gm.shape == image.shape[:2] and gm.any():
                if cam.has_distortion:
                    gm = undistort(view.get_image(), gm, cam)[1]
                frame.gt_mask = torch.from_numpy(gm)
        (held if is_held else train).append(frame)
    if not train:
        raise InputError("no usable training views (all held out, without pose or with empty "
                         "masks); capture more views or check the masks")
    return train, held


def _visual_hull_points(frames: list[_Frame], n: int, gen: torch.Generator) -> np.ndarray:
    """Random points inside the masks' visual hull (init when the OOI cloud is empty/tiny).

    Samples a box around the point the cameras look at (half size: half the median camera
    distance) and keeps points inside the mask in every view that sees them.
    """
    from ..core.geometry import cameras_convergence_point
    from ..core.types import Pose

    poses = []
    for f in frames:
        R, t = f.cam.R.double().numpy(), f.cam.t.double().numpy()
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, t
        poses.append(Pose.from_matrix(np.linalg.inv(w2c)))
    center = cameras_convergence_point(poses)
    dist = np.median([np.linalg.norm(p.center - center) for p in poses])
    cand = (torch.rand((n * 40, 3), generator=gen, dtype=torch.float64) - 0.5) * dist
    cand = cand + torch.from_numpy(center)
    frac, seen = mcmc.outside_mask_fraction(cand.float(), [f.cam for f in frames],
                                            [f.mask for f in frames])
    keep = (frac == 0) & (seen >= max(1, len(frames) // 4))
    pts = cand[keep][:n].numpy()
    if len(pts) < 4:
        raise InputError("could not initialise: the OOI cloud is empty and no point lies in "
                         "the masks' visual hull; check that masks and poses belong together")
    return pts


def _hull_surface_points(frames: list[_Frame], n: int, near: np.ndarray, band_px: float,
                         gen: torch.Generator, rounds: int = 8, per_round: int = 400_000
                         ) -> np.ndarray:
    """Up to ``n`` random points near the surface of the masks' visual hull.

    Candidates are drawn in the box of ``near`` (the OOI cloud) grown by a quarter of its
    size on each side; a candidate survives when it falls inside the mask of every view that
    sees it (and at least a quarter of the views see it), and it is "near the surface" when
    in some view it lands within ``band_px`` of the mask's outline. Views carve in turn, so
    later views only project the survivors.
    """
    from scipy.ndimage import distance_transform_edt

    lo, hi = near.min(0), near.max(0)
    pad = 0.25 * np.maximum(hi - lo, 1e-6)
    lo_t = torch.from_numpy(lo - pad).float()
    span = torch.from_numpy(hi - lo + 2 * pad).float()
    inner = [torch.from_numpy(distance_transform_edt(f.mask.numpy())).float() for f in frames]
    need_seen = max(1, len(frames) // 4)
    found: list[torch.Tensor] = []
    total = 0
    for _ in range(rounds):
        cand = lo_t + torch.rand((per_round, 3), generator=gen) * span
        idx = torch.arange(per_round)
        seen = torch.zeros(per_round, dtype=torch.int32)
        edge = torch.full((per_round,), float("inf"))
        for f, dist in zip(frames, inner):
            p = cand[idx]
            pc = p @ f.cam.R.T.float() + f.cam.t.float()
            z = pc[:, 2]
            u = torch.round(f.cam.fx * pc[:, 0] / z.clamp_min(1e-6) + f.cam.cx).long()
            v = torch.round(f.cam.fy * pc[:, 1] / z.clamp_min(1e-6) + f.cam.cy).long()
            ok = (z > 0) & (u >= 0) & (u < f.cam.width) & (v >= 0) & (v < f.cam.height)
            d = torch.zeros(len(idx))
            d[ok] = dist[v[ok], u[ok]]
            seen[idx[ok]] += 1
            inside = ~ok | (d > 0)
            edge[idx[ok & inside]] = torch.minimum(edge[idx[ok & inside]], d[ok & inside])
            idx = idx[inside]
            if len(idx) == 0:
                break
        keep = idx[(seen[idx] >= need_seen) & (edge[idx] <= band_px)]
        found.append(cand[keep])
        total += len(keep)
        if total >= n:
            break
    pts = torch.cat(found) if found else torch.zeros((0, 3))
    if len(pts) > n:
        pts = pts[torch.randperm(len(pts), generator=gen)[:n]]
    return pts.double().numpy()


def _colors_from_views(pts: np.ndarray, frames: list[_Frame], max_views: int = 16) -> np.ndarray:
    """[N, 3] uint8 initial colours: mean of the pixels the points project to inside the masks.

    Without colours every Gaussian would start grey and spend hundreds of steps on its base
    colour; occlusion is ignored (a point's back-side pixels average in), which is fine for a
    starting value.
    """
    p = torch.from_numpy(pts).float()
    acc = torch.zeros(len(p), 3)
    cnt = torch.zeros(len(p))
    step = max(1, len(frames) // max_views)
    for f in frames[::step]:
        pc = p @ f.cam.R.T.float() + f.cam.t.float()
        z = pc[:, 2].clamp_min(1e-6)
        u = torch.round(f.cam.fx * pc[:, 0] / z + f.cam.cx).long()
        v = torch.round(f.cam.fy * pc[:, 1] / z + f.cam.cy).long()
        ok = (pc[:, 2] > 0) & (u >= 0) & (u < f.cam.width) & (v >= 0) & (v < f.cam.height)
        ok[ok.clone()] = f.mask[v[ok], u[ok]]
        acc[ok] += f.image[v[ok], u[ok]]
        cnt[ok] += 1
    col = torch.where(cnt[:, None] > 0, acc / cnt.clamp_min(1)[:, None], torch.full_like(acc, 0.5))
    return (col.numpy() * 255 + 0.5).astype(np.uint8)


# ------------------------------------------------------------------------------------ training


def choose_backend(name: str) -> str:
    """Resolve "auto" to "gsplat" when gsplat and CUDA are usable, else "cpu"."""
    if name not in ("auto", "cpu", "gsplat"):
        raise InputError(f"unknown backend {name!r}; use auto, cpu or gsplat")
    if name == "cpu":
        return "cpu"
    from .raster_gsplat import gsplat_available

    if gsplat_available():
        return "gsplat"
    if name == "gsplat":
        raise InputError("backend gsplat needs the gsplat package and a CUDA GPU; "
                         "install gsplat or use --backend cpu")
    return "cpu"


def _renderer(backend: str) -> Callable:
    if backend == "gsplat":
        from .raster_gsplat import render
    else:
        from .raster_cpu import render
    return render


def estimate_memory_bytes(max_gaussians: int, width: int, height: int) -> int:
    """Rough peak memory of one training step on the CPU back-end.

    Per Gaussian: 59 parameters x (value, grad, 2 Adam moments) + projection temporaries;
    per pixel the dense per-tile batches keep ~10 float tensors of tiles x K x 256 for the
    backward pass, with K bounded by the number of Gaussians overlapping a tile (taken as 2%
    of the cap, at least 64, a generous figure for an object in the frame).
    """
    per_gauss = 59 * 4 * 4 + 400
    k = max(64, int(0.02 * max_gaussians))
    raster = 10 * 4 * width * height * k // 4
    return max_gaussians * per_gauss + raster + 200 * 2 ** 20


class _Progress:
    """A one-line progress bar on stderr (iterations, loss, PSNR, Gaussians, it/s)."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.total, self.enabled, self.t0, self.last = total, enabled, time.time(), 0.0

    def update(self, it: int, loss: float, psnr: float, n: int, force: bool = False) -> None:
        now = time.time()
        if not self.enabled or (not force and now - self.last < 0.5):
            return
        self.last = now
        frac = it / max(1, self.total)
        bar = "#" * int(30 * frac)
        rate = it / max(1e-9, now - self.t0)
        sys.stderr.write(f"\rtrain [{bar:<30}] {it}/{self.total} loss {loss:.4f} "
                         f"psnr {psnr:5.2f} n {n} {rate:.1f} it/s")
        if force:
            sys.stderr.write("\n")
        sys.stderr.flush()


SPILL_MARGIN_PX = 2  # the spill figure ignores opacity this close to the mask (outline blur)


def _spill(alpha: torch.Tensor, mask: torch.Tensor) -> float:
    """Share of a render's opacity that lies more than SPILL_MARGIN_PX outside ``mask``."""
    total = float(alpha.sum())
    if total <= 0:
        return 0.0
    return float(alpha[_far_from_mask(mask, SPILL_MARGIN_PX)].sum()) / total


def _evaluate(model: GaussianModel, frames: list[_Frame], render: Callable,
              full_image: bool) -> list[HeldOutResult]:
    out = []
    black = torch.zeros(3)
    with torch.no_grad():
        for f in frames:
            o = render(model, f.cam, black)
            r = o.image.clamp(0, 1).cpu()
            alpha = o.alpha.detach().clamp(0, 1).cpu()
            m = None if full_image else f.mask
            gt = f.image if full_image else f.image * f.mask[..., None]
            h = HeldOutResult(f.key, masked_psnr(r, gt, f.mask), masked_ssim(r, gt, f.mask),
                              (r.numpy() * 255 + 0.5).astype(np.uint8),
                              (gt.numpy() * 255 + 0.5).astype(np.uint8), f.mask.numpy().copy())
            if not full_image:
                h.spill = _spill(alpha, f.mask)
            if f.gt_mask is not None:
                # a computed mask's background pixels (its false positives) are scored against
                # the photo, which an object-only model cannot render: the truth's mask says
                # how good the object itself is
                g = f.image * f.gt_mask[..., None]
                h.psnr_gt = masked_psnr(r, g, f.gt_mask)
                h.ssim_gt = masked_ssim(r, g, f.gt_mask)
                h.spill_gt = _spill(alpha, f.gt_mask)
            out.append(h)
            del m
    return out


def train(capture: Capture, masks: Optional[dict[str, np.ndarray]],
          init_points: Optional[np.ndarray], config: Optional[TrainConfig] = None,
          init_colors: Optional[np.ndarray] = None,
          progress: Optional[Callable[[int, float, float, int], None]] = None,
          show_progress: bool = False) -> TrainResult:
    """Train object-only Gaussians; see the module doc. ``masks`` maps view key -> [H, W] bool.

    ``init_points`` [N, 3] is the OOI cloud (with ``init_colors`` [N, 3] uint8, optional); with
    fewer than 4 points the Gaussians start at random points inside the masks' visual hull.
    """
    cfg = config or TrainConfig()
    if cfg.iterations < 1:
        raise InputError(f"iterations={cfg.iterations} must be >= 1")
    if cfg.max_gaussians < 1:
        raise InputError(f"max_gaussians={cfg.max_gaussians} must be >= 1")
    if not 0 <= cfg.sh_degree <= MAX_SH_DEGREE:
        raise InputError(f"sh_degree={cfg.sh_degree} must be within 0..{MAX_SH_DEGREE}")
    if len(capture.views) == 0:
        raise InputError("the capture has no views")
    if cfg.budget_clock not in ("wall", "cpu"):
        raise InputError(f"budget_clock={cfg.budget_clock!r}; use wall or cpu")
    clock = time.process_time if cfg.budget_clock == "cpu" else time.time
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    backend = choose_backend(cfg.backend)
    render = _renderer(backend)
    result = TrainResult(model=None, config=cfg, backend=backend)  # type: ignore[arg-type]
    train_frames, held_frames = _prepare(capture, masks, cfg, result)
    w = max(f.cam.width for f in train_frames)
    h = max(f.cam.height for f in train_frames)
    need, have = estimate_memory_bytes(cfg.max_gaussians, w, h), available_memory()
    if need > cfg.max_memory_fraction * have:
        raise InputError(f"max_gaussians={cfg.max_gaussians} at {w}x{h} needs about "
                         f"{need / 2**30:.1f} GiB, only {have / 2**30:.1f} GiB available; "
                         "lower --max-gaussians")
    gen = torch.Generator().manual_seed(int(cfg.seed))
    torch.manual_seed(int(cfg.seed))
    pts = None if init_points is None else np.asarray(init_points, dtype=np.float64).reshape(-1, 3)
    if pts is None or len(pts) < 4:
        pts = _visual_hull_points(train_frames, min(cfg.max_gaussians, 5000), gen)
        init_colors, result.init = None, "visual_hull"
    fill_to = min(cfg.init_fill, cfg.max_gaussians)
    if result.init == "points" and len(pts) < fill_to:
        extra = _hull_surface_points(train_frames, fill_to - len(pts), pts,
                                     cfg.init_fill_band_px, gen)
        result.init_filled = len(extra)
        if len(extra):
            if init_colors is not None:
                init_colors = np.concatenate([np.asarray(init_colors, dtype=np.uint8).reshape(
                    -1, 3), _colors_from_views(extra, train_frames)])
            pts = np.concatenate([pts, extra])
    if len(pts) > cfg.max_gaussians:
        sel = torch.randperm(len(pts), generator=gen)[:cfg.max_gaussians].numpy()
        pts = pts[sel]
        init_colors = None if init_colors is None else np.asarray(init_colors)[sel]
    if init_colors is None:
        init_colors = _colors_from_views(pts, train_frames)
    model = init_from_points(pts, init_colors, cfg.initial_opacity).requires_grad_(True)
    scene_scale = _scene_scale(pts, train_frames)
    lr_means0 = cfg.lr_means * scene_scale
    opt = _adam([
        {"params": [model.means], "lr": lr_means0, "name": "means"},
        {"params": [model.log_scales], "lr": cfg.lr_scales, "name": "log_scales"},
        {"params": [model.quats], "lr": cfg.lr_quats, "name": "quats"},
        {"params": [model.logit_opacities], "lr": cfg.lr_opacity, "name": "logit_opacities"},
        {"params": [model.sh_dc], "lr": cfg.lr_sh_dc, "name": "sh_dc"},
        {"params": [model.sh_rest], "lr": cfg.lr_sh_rest, "name": "sh_rest"},
    ])
    expo, opt_expo = _exposure_params(cfg, len(train_frames))
    bar = _Progress(cfg.iterations, show_progress)
    good = model.detached()
    order: list[int] = []
    preview_frames = (held_frames or train_frames)[:2]
    t0, t0_wall, t0_cpu = clock(), time.time(), time.process_time()
    loss_v, psnr_v = float("nan"), 0.0
    done = cfg.iterations
    for it in range(1, cfg.iterations + 1):
        if cfg.time_budget_s > 0 and clock() - t0 > cfg.time_budget_s:
            done = it - 1
            break
        model.sh_degree = min(cfg.sh_degree, (it - 1) // max(1, cfg.sh_degree_interval))
        frac = _progress(it, cfg, clock() - t0)
        lr_m = lr_means0 * 0.01 ** frac
        opt.param_groups[0]["lr"] = lr_m
        if not order:
            order = torch.randperm(len(train_frames), generator=gen).tolist()
        fi = order.pop()
        f = train_frames[fi]
        tg = f.levels[1 if cfg.coarse_frac > 0 and frac < cfg.coarse_frac else 0]
        if cfg.full_image or cfg.background == "black":
            bg = torch.zeros(3)
        elif cfg.background == "white":
            bg = torch.ones(3)
        else:
            bg = torch.rand(3, generator=gen)
        out = render(model, tg.cam, bg)
        image = out.image if expo is None else _apply_exposure(out.image, out.alpha, bg, expo, fi)
        if tg.edge is not None:  # the outline over the photo's own background there
            image = image + (1.0 - out.alpha)[..., None] * (tg.edge_bg - bg) * tg.edge[..., None]
        if cfg.full_image:
            gt, mask = tg.image, None
        else:
            m3 = tg.mask[..., None].to(tg.image.dtype)
            gt, mask = tg.image * m3 + bg * (1 - m3), tg.mask
        loss = photometric_loss(image, gt, mask, cfg.lambda_dssim)
        total = loss + mcmc.regularisation(model, cfg.opacity_reg, cfg.scale_reg)
        if mask is not None and cfg.bg_alpha_reg > 0:
            # background pixels carry no photometric loss, so nothing else stops Gaussians
            # from spilling opacity there: keep the object's silhouette inside the mask
            # (inside the rendered window: the mask's box when crop_to_mask)
            outside = ~mask if tg.far is None else tg.far
            if bool(outside.any()):
                total = total + cfg.bg_alpha_reg * out.alpha[outside].mean()
        opt.zero_grad(set_to_none=True)
        if opt_expo is not None:
            opt_expo.zero_grad(set_to_none=True)
        if not torch.isfinite(total):
            result.nan_steps += 1
            _restore(model, good)
            continue
        total.backward()
        opt.step()
        if opt_expo is not None:
            opt_expo.step()
        mcmc.inject_noise(model, lr_m, cfg.noise_lr)
        if not _all_finite(model):
            result.nan_steps += 1
            _restore(model, good)
            continue
        loss_v = float(loss.detach())
        with torch.no_grad():
            psnr_v = masked_psnr(image.detach(), gt, mask)
        result.history.append({"it": it, "loss": loss_v, "psnr": psnr_v, "n": len(model)})
        if (cfg.refine_every > 0 and cfg.refine_start <= it and frac <= cfg.refine_stop_frac
                and it % cfg.refine_every == 0):
            _refine(model, opt, cfg, train_frames, gen)
            good = model.detached()
        if cfg.eval_every > 0 and it % cfg.eval_every == 0 and it < cfg.iterations and held_frames:
            ev = _evaluate(model, held_frames, render, cfg.full_image)
            result.evals.append({"it": it, "psnr": float(np.mean([e.psnr for e in ev])),
                                 "ssim": float(np.mean([e.ssim for e in ev]))})
        if cfg.snapshot_every > 0 and it % cfg.snapshot_every == 0 and it < cfg.iterations:
            _snapshot(result, model, it, preview_frames, render)
        if progress is not None:
            progress(it, loss_v, psnr_v, len(model))
        bar.update(it, loss_v, psnr_v, len(model))
    result.seconds = time.time() - t0_wall
    result.cpu_seconds = time.process_time() - t0_cpu
    result.its_per_s = done / max(result.seconds, 1e-9)
    result.iterations_done = done
    bar.update(done, loss_v, psnr_v, len(model), force=True)
    model.requires_grad_(False)
    result.model = model.detached()
    _snapshot(result, result.model, done, preview_frames, render)
    result.heldout = _evaluate(result.model, held_frames, render, cfg.full_image)
    if result.heldout:
        result.evals.append({"it": done,
                             "psnr": float(np.mean([e.psnr for e in result.heldout])),
                             "ssim": float(np.mean([e.ssim for e in result.heldout]))})
    result.train_keys = [f.key for f in train_frames]
    if expo is not None:
        result.exposure = _centred(expo.detach()).numpy().copy()
    result.heldout_keys = [f.key for f in held_frames]
    return result


@torch.no_grad()
def _all_finite(model: GaussianModel) -> bool:
    """True when no parameter holds a NaN or an infinity, from one sum per tensor (a sum is
    finite only if every element is, barring an overflow of float32, which would be as bad):
    ~0.1 ms per step at 20k Gaussians instead of ~4 ms for element-wise tests."""
    return all(math.isfinite(float(p.sum())) for p in model.params().values())


def _adam(groups: list) -> torch.optim.Optimizer:
    """Adam with its fused implementation where torch has one for the device (on the CPU it
    is ~8x faster than the default per-parameter loop, ~5% of a training step), else the loop.
    """
    try:
        return torch.optim.Adam(groups, eps=1e-15, fused=True)
    except (RuntimeError, TypeError, ValueError):
        return torch.optim.Adam(groups, eps=1e-15)


def _exposure_params(cfg: TrainConfig, n_views: int
                     ) -> tuple[Optional[torch.Tensor], Optional[torch.optim.Optimizer]]:
    """Per-training-view [V, 3] log-gains (+ [V, 3] offsets for "affine") and their own
    optimiser, or (None, None).

    Kept out of the splats' optimiser: MCMC resizes and resets that one per Gaussian.
    """
    if cfg.exposure not in ("none", "gain", "affine"):
        raise InputError(f"exposure={cfg.exposure!r}; use none, gain or affine")
    if cfg.exposure == "none" or cfg.full_image:
        return None, None
    expo = torch.zeros((n_views, 6 if cfg.exposure == "affine" else 3), requires_grad=True)
    return expo, _adam([{"params": [expo], "lr": cfg.lr_exposure}])


def _centred(expo: torch.Tensor) -> torch.Tensor:
    """Exposure parameters minus their mean over the views: the splats' colours then hold the
    mean exposure (a global gain could otherwise drift between the splats and every view)."""
    return expo - expo.mean(0, keepdim=True)


def _apply_exposure(image: torch.Tensor, alpha: torch.Tensor, bg: torch.Tensor,
                    expo: torch.Tensor, view: int) -> torch.Tensor:
    """The render with view ``view``'s gain/offset applied to the object only (not to the
    background it is composited over): gain x colour + offset x alpha + (1 - alpha) x bg."""
    e = _centred(expo)[view]
    a = alpha[..., None]
    obj = image - (1.0 - a) * bg
    out = obj * torch.exp(e[:3]) + (1.0 - a) * bg
    return out + a * e[3:] if len(e) > 3 else out


def _scene_scale(pts: np.ndarray, frames: list[_Frame]) -> float:
    """Length the position learning rate is relative to, as in 3DGS: 1.1 x the largest distance
    of a training camera from the cameras' mean, and at least the initial cloud's radius.

    For an orbit that is about the orbit radius (2-3 object radii). Scaling by the object's
    own radius instead made the position steps 2-3x smaller than 3DGS's, too slow for a
    budget of a few thousand steps (measured: BENCHMARKS.md, Training).
    """
    extent = float(np.linalg.norm(pts - pts.mean(0), axis=1).max()) if len(pts) > 1 else 0.0
    centres = np.stack([f.cam.center.double().numpy() for f in frames])
    cams = 1.1 * float(np.linalg.norm(centres - centres.mean(0), axis=1).max())
    scale = max(extent, cams)
    return scale if math.isfinite(scale) and scale > 1e-3 else 1.0


def _progress(it: int, cfg: TrainConfig, elapsed: float) -> float:
    """How far through the run step ``it`` is, in [0, 1]: by steps, or by time if budgeted."""
    frac = (it - 1) / max(1, cfg.iterations - 1)
    if cfg.time_budget_s > 0:
        frac = max(frac, elapsed / cfg.time_budget_s)
    return min(1.0, frac)


@torch.no_grad()
def _restore(model: GaussianModel, good: GaussianModel) -> None:
    """Copy the last good parameters back (sizes match: ``good`` is taken after growth)."""
    for name, t in model.params().items():
        src = getattr(good, name)
        if src.shape == t.shape:
            t.copy_(src)


def _snapshot(result: TrainResult, model: GaussianModel, it: int, frames: list[_Frame],
              render: Callable) -> None:
    snap = model.detached()
    result.snapshots.append((it, snap))
    with torch.no_grad():
        for f in frames:
            img = render(snap, f.cam, torch.zeros(3)).image.clamp(0, 1)
            result.previews.append((it, f.key, (img.numpy() * 255 + 0.5).astype(np.uint8)))


def _refine(model: GaussianModel, opt: torch.optim.Optimizer, cfg: TrainConfig,
            frames: list[_Frame], gen: torch.Generator) -> None:
    """MCMC step: relocate dead / outside-mask Gaussians, then grow towards the cap."""
    outside = None
    if not cfg.full_image:
        outside, _ = mcmc.outside_mask_fraction(model.means.detach(), [f.cam for f in frames],
                                                [f.mask for f in frames])
    dead = mcmc.dead_mask(model, 0.005, outside, cfg.outside_mask_limit)
    if bool(dead.all()):
        return
    mcmc.relocate(model, opt, dead, gen)
    n = len(model)
    n_add = min(cfg.max_gaussians, int(n * (1 + cfg.grow_rate))) - n
    mcmc.add_new(model, opt, max(0, n_add), gen)
