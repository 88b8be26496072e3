"""The segmentation pipeline: SfM cloud -> OOI cloud -> mesh -> per-view masks.

``method="paper"`` is the literal section-4 pipeline (the baseline). ``method="ours"`` (the
default) adds the signals an orbit gives for free: the camera-framing region of interest, a
camera-aware support-plane rule, the DBSCAN cluster the cameras look at, masks splatted from
the OOI points (no Poisson balloon), and a per-view GrabCut refinement seeded by the
projections of the OOI points (on a crop enlarged twice when the image is small, so that thin
parts survive the graph cut: ``refine.upsample``), in which every pixel that shows the support
plane, a background wall (plane-induced photo-consistency with nearby views, ``photo.py``) or
the background beyond the object (the same test at the depth of the nearest background SfM
point behind it) is sure background -- next to the object also when only a patch shifted off
the pixel matches and the pixel's own colour does -- while pixels whose colour the object's
depth explains and the plane's does not stay object (over the OOI points' discs, also where
they reach past the splatted silhouette: ``plane_check.keep_discs``); the refined outline then
takes the ring pixels whose colour is nearer the object's than the background's
(``refine.edge_matte``).
Before that, each view's mask takes the pixels whose rays meet the visual hull of all views'
refined masks (voxels that a majority of the views hold) and whose colour that view's
GrabCut object model explains better than its background model (``refine.hull_additions``):
thin parts with no SfM point that other views found; from the looser hull of the voxels more
than 30% of the views hold, only the pixels two neighbour views repeat at its depth and refute
at four depths off it (``hull_thin_agree``, ``hull_thin_distinct``: a spoke or a leaf only some
views' GrabCut kept, not a uniform wall that matches at any depth). Before the additions, what
GrabCut grew past the splatted silhouette leaves a view's mask where few views' masks hold it
(``hull_cut_grown``) and, where it runs out to an image side the silhouette does not
reach, where most views' masks miss it (``border_leak_hull``: nothing beyond the image's
edge stopped the cut there -- the wall above a crown that nears the top of the photo).
Both hulls leave out the voxels that two views saw past (an SfM feature observed more than 3
voxels beyond on the ray: ``hull_free``), so a uniform wall seen through a gap under the
crown, which every view's GrabCut kept and no silhouette carves, leaves the masks too.
After the additions, a pixel the neighbour views place past the object leaves the mask
(``behind_cut``: more of them repeat its colour at some depth beyond the looser hull than at
any depth inside it -- a chair or shelf seen between the leaves, kept by GrabCut for its
colour; ``behind_open``: only where a 2x2 square fits, not the lone pixels and 1-px streaks a
striped surface aliases into).
Last, thin straight parts that span a hole of a view's mask from one side to the other -- a
wheel's spokes between its rim and its hub -- join it (``refine.bridges``, ``thin.py``): a
line filter's response, thresholded against the hole's own texture, along a chord whose two
ends meet the mask.
Each stage is a function with a typed input and output and its own config dataclass, so
stages can be swapped by configuration.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field
from typing import Callable, Collection, Optional

import numpy as np

from ..core import config as cfgmod
from ..core.geometry import cameras_convergence_point
from ..core.types import Capture, InputError, SfmCloud, TriMesh
from .density import DensityConfig, density_filter, spacing
from .floor import FloorConfig, floor_filter
from .masks import MaskConfig, hull_carve, point_masks, point_radii, render_masks
from .mesh import MeshConfig, build_mesh
from .metrics import scene_metrics
from .noise import NoiseConfig, grow_selection, noise_filter
from .photo import background_planes
from .refine import RefineConfig, refine_masks
from .residual import ResidualConfig, colour_mismatch, colour_vote, residual_filter
from .roi import RoiConfig, frame_radius, framing_warning, roi_filter
from .stability import (StabilityConfig, centred_alternative, copies_choice,
                        stability_check, stability_warning)

METHODS = ("paper", "ours")


@dataclass
class SegmentationConfig:
    """Resolved options of the whole segmentation (written as config.yaml next to outputs)."""

    method: str = "ours"  # "paper" (literal baseline) or "ours" (improved default)
    seed: int = 0  # seed of every random step (subsets, RANSAC)
    min_points: int = 50  # fewer input points than this is an input error
    min_ooi_points: int = 30  # an OOI of fewer points is kept, with a warning: masks drawn
    # from so few points are unreliable (the bicycle from 30 views: 15-27 points, IoU 0.34-0.39;
    # 30 pose-free photos at 256x192: 7 points, IoU 0.03; every 60-view capture: >= 100)
    residual: ResidualConfig = field(default_factory=ResidualConfig)  # multi-view points
    # that fit their rays worse than the cloud's typical track: out of the OOI cloud the
    # point stages chose and out of the background's seeds
    roi: RoiConfig = field(default_factory=RoiConfig)  # camera-framing region of interest
    density: DensityConfig = field(default_factory=DensityConfig)  # 4.1 Monte Carlo KDE
    floor: FloorConfig = field(default_factory=FloorConfig)  # 4.2 floor removal
    noise: NoiseConfig = field(default_factory=NoiseConfig)  # 4.3 noise removal
    stability: StabilityConfig = field(default_factory=StabilityConfig)  # re-runs of the
    # point stages on copies with points left out: a warning when the OOI choice flips
    mesh: MeshConfig = field(default_factory=MeshConfig)  # 4.4 meshing
    masks: MaskConfig = field(default_factory=MaskConfig)  # 4.5 masks
    refine: RefineConfig = field(default_factory=RefineConfig)  # per-view GrabCut refinement


def preset(method: str) -> dict:
    """Stage options that define ``method`` (user overrides are applied on top)."""
    if method == "paper":
        return {"method": "paper", "residual": {"enabled": False}, "roi": {"enabled": False},
                "density": {"drop_fraction": 0.3, "first_peak": True},
                "floor": {"mode": "paper"}, "noise": {"method": "dbscan", "select": "largest"},
                "mesh": {"method": "poisson"},
                "masks": {"mode": "mesh", "closing_kernel": 5, "fill_holes": False,
                          "hull_consistency": False},
                "refine": {"enabled": False}, "stability": {"draws": 0}}
    if method == "ours":
        return {"method": "ours", "roi": {"enabled": True},
                "density": {"drop_fraction": 0.0, "relative_cut": 0.1, "first_peak": False,
                            "sparse_share": 0.05, "sparse_seeds": False},
                "floor": {"mode": "support", "support_select": "nearest",
                          "band_interior": True, "support_min_of": "remaining",
                          "band_local": 4, "max_under_density": 0.1},
                "noise": {"method": "dbscan", "select": "central", "eps_scale": 1.0,
                          "eps_step": 0.25, "eps_max_scale": 4.0, "settle_change": 0.15,
                          "max_extent_growth": 1.25, "merge_reach_scale": 1.2,
                          "part_above": 0.25, "retreat": True,
                          "widen_unclustered": True, "central_weight": "standing",
                          "rebase_on_switch": True, "central_inner": True,
                          "lookahead": True, "centre_absolute": True,
                          "retreat_centring": False},
                "mesh": {"method": "poisson"},
                "masks": {"mode": "points", "closing_kernel": 5, "fill_holes": True,
                          "splat_scale": 0.6, "hull_consistency": False,
                          "hull_carve": False},
                "refine": {"enabled": True, "fg_seeds": "projections", "edge_window": 7,
                           "max_side": 400, "band_gaps": 3.0, "seed_cover": 0.5625,
                           "hull_add": True,
                           "upsample": 2, "hull_cut_grown": True, "hull_free": 2,
                           "border_leak_hull": True, "hull_thin_agree": 0.3,
                           "hull_thin_distinct": 4, "behind_cut": "mask",
                           "behind_open": True, "outline_vote": True, "grown_open": 1,
                           "bridges": {"enabled": True},
                           "plane_check": {"enabled": True, "over_seeds": True,
                                           "extra_planes": 3, "behind": True,
                                           "shifted": True, "object_keep": True,
                                           "behind_window": 3, "neighbours": 8,
                                           "max_deg": 35.0, "rank": 3,
                                           "keep_discs": True, "object_guard": True,
                                           "pixel_votes": True, "pixel_reach": 1,
                                           "pixel_reach_density": 0.2,
                                           "pixel_reach_ground": 0.8,
                                           "adapt_noise": 2.0, "exposure_auto": True}}}
    raise InputError(f"unknown segmentation method {method!r}; choose one of {METHODS}")


def _merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def make_config(method: Optional[str] = None, overrides: Optional[dict] = None
                ) -> SegmentationConfig:
    """Config of ``method`` (or overrides['method'], default "ours") with ``overrides`` on top."""
    overrides = dict(overrides or {})
    m = method or overrides.get("method") or "ours"
    data = _merge(preset(m), overrides)
    data["method"] = m
    try:
        cfg = cfgmod.from_dict(SegmentationConfig, data)
    except (ValueError, TypeError) as exc:
        raise InputError(f"bad segmentation config: {exc}") from None
    # checked here: a stage's ValueError while it runs reads as "no OOI" (_run_point_stages)
    d = cfg.density
    if not 0.0 <= float(d.drop_fraction) < 1.0:
        raise InputError(f"bad segmentation config: density.drop_fraction={d.drop_fraction}; "
                         f"it is a share of the points in [0, 1)")
    if not 0.0 <= float(d.relative_cut) <= 1.0:
        raise InputError(f"bad segmentation config: density.relative_cut={d.relative_cut}; it "
                         f"is a fraction of the median density in [0, 1] (0 = off)")
    if not 0.0 <= float(d.sparse_share) < 1.0:
        raise InputError(f"bad segmentation config: density.sparse_share={d.sparse_share}; "
                         f"it is a share of the points in [0, 1) (0 = off)")
    if not float(cfg.noise.grow_local) >= 0.0:
        raise InputError(f"bad segmentation config: noise.grow_local={cfg.noise.grow_local}; "
                         f"it is a number of median mask disc radii >= 0 (0 = off)")
    for sub in (cfg.density, cfg.floor, cfg.refine):
        sub.seed = cfg.seed
    return cfg


@dataclass
class SegmentationResult:
    """Everything the segmentation produced."""

    ooi_cloud: SfmCloud  # the OOI's points (with observations)
    mesh: TriMesh  # surface of the OOI (may be empty)
    masks: dict  # {view.key: bool [H, W]} for every input view
    counts: dict  # points left after each stage
    params: dict  # parameters actually used per stage
    timings: dict  # seconds per stage
    warnings: list  # human-readable warnings
    config: SegmentationConfig
    metrics: Optional[dict] = None  # scene_metrics vs view.gt_mask when present
    stage_clouds: dict = field(default_factory=dict)  # {stage: ([N,3], [N,3] rgb)} (report)


def _needs_all_masks(cfg: SegmentationConfig) -> bool:
    """Whether a mask of one view depends on the masks of the other views (the voxel-hull
    options, the two-pass consistency seeds): a view subset then needs every view's mask."""
    return bool(cfg.masks.hull_consistency or cfg.masks.hull_carve
                or (cfg.refine.enabled and (cfg.refine.fg_seeds == "consistent"
                                            or cfg.refine.hull_add)))


def _only_hull_add(cfg: SegmentationConfig) -> bool:
    """Whether the hull additions are the only reason a mask needs the other views' masks."""
    return bool(cfg.refine.enabled and cfg.refine.hull_add and not (
        cfg.masks.hull_consistency or cfg.masks.hull_carve
        or cfg.refine.fg_seeds == "consistent"))


def _point_stages(cfg: SegmentationConfig, views: list, target: np.ndarray, radius: float,
                  cam_centers: np.ndarray, cam_up: np.ndarray) -> list:
    """The point stages of ``cfg`` in order: [(name, fn(xyz) -> (kept indices, params))]."""
    stages = []
    if cfg.roi.enabled:
        stages.append(("roi", lambda x: roi_filter(x, views, target, cfg.roi)))
    order = ["floor", "density"] if cfg.method == "ours" else ["density", "floor"]
    found: dict = {}  # the support plane of the current run, for the noise stage

    def floor(x):
        keep, p = floor_filter(x, cfg.floor, cam_centers, cam_up, target)
        found["plane"] = p.get("support_plane")
        return keep, p

    for name in order:
        if name == "density":
            stages.append(("density", lambda x: density_filter(x, cfg.density)))
        else:
            stages.append(("floor", floor))
    stages.append(("noise", lambda x: noise_filter(x, cfg.noise, target, radius,
                                                   found.get("plane"))))
    return stages


def _run_point_stages(stages: list, xyz: np.ndarray, idx: np.ndarray
                      ) -> tuple[np.ndarray, dict]:
    """Indices (into ``xyz``) of the OOI set the point stages choose from the points ``idx``
    and the last stage's parameters; the set is empty when a stage leaves fewer than 4 points
    or finds the input degenerate."""
    sub = np.asarray(idx, np.int64)
    none = np.zeros(0, np.int64)
    p: dict = {}
    for _, fn in stages:
        if len(sub) < 4:
            return none, {}
        try:
            keep, p = fn(xyz[sub])
        except (InputError, ValueError, np.linalg.LinAlgError):
            return none, {}
        sub = sub[np.asarray(keep, np.int64)]
    return (sub, p) if len(sub) >= 4 else (none, {})


def segment(capture: Capture, cloud: SfmCloud, config: Optional[SegmentationConfig] = None,
            on_cloud: Optional[Callable[[SfmCloud], None]] = None,
            mask_keys: Optional[Collection[str]] = None,
            context_masks: Optional[dict] = None) -> SegmentationResult:
    """Segment the OOI of ``capture`` from ``cloud`` and render a mask for every view.

    ``on_cloud`` (optional) is called with the OOI cloud as soon as the point stages are done,
    before the mesh and the per-view masks (the costly part), so that a live node can publish
    the OOI cloud early. An exception it raises propagates.

    ``mask_keys`` (optional): render and refine masks only for the views with these keys
    (``result.masks`` and the metrics hold only them). The point stages, the planes and the
    mesh still use the whole capture, and every view stays available as context (neighbours
    of the plane check), so each of these masks equals the full run's mask of that view.
    Options that make one view's mask depend on the others' (voxel hull, consistency seeds)
    render every mask and keep the subset (same masks, no saving). A key not in the capture
    is an input error.

    ``context_masks`` (optional, with ``mask_keys``): {key: mask} of the other views, made
    earlier. When the hull additions (``refine.hull_add``) are the only option that needs
    the other views' masks and these cover every other view, they stand in for those views
    in the hull, and only the ``mask_keys`` views are refined (a live node's incremental
    runs: its older keyframes' final masks). The masks then differ from a full run's by as
    much as the older masks differ from what a full run would make of those views now.
    """
    # a copy: a fallback below (masks from points when the mesh is empty) must not stay in
    # the caller's config (a live node reuses one config for every run)
    cfg = copy.deepcopy(config) if config is not None else make_config()
    views = capture.views
    if not views:
        raise InputError("capture has no views")
    if not capture.has_poses:
        raise InputError("every view needs a pose for segmentation; run SfM or add poses")
    wanted: Optional[set] = None
    if mask_keys is not None:
        if isinstance(mask_keys, str):
            mask_keys = [mask_keys]
        wanted = set(mask_keys)
        unknown = wanted - {v.key for v in views}
        if unknown:
            raise InputError(f"mask_keys holds {len(unknown)} key(s) not in the capture, e.g. "
                             f"{sorted(unknown)[0]!r}; pass keys of the capture's views")
    # the views whose masks are rendered (all of them when a mask needs the others')
    needs_all = wanted is not None and _needs_all_masks(cfg)
    context: Optional[dict] = None
    if needs_all and context_masks is not None and _only_hull_add(cfg):
        # the hull additions need every view's mask: masks of the other views made earlier
        # (a node's final masks of its older keyframes) stand in for refining them again
        others = [v for v in views if v.key not in wanted]
        if all(v.key in context_masks and np.shape(context_masks[v.key])
               == (v.camera.height, v.camera.width) for v in others):
            context = {v.key: np.asarray(context_masks[v.key], bool) for v in others}
            needs_all = False
    mask_views = views if wanted is None or needs_all else [
        v for v in views if v.key in wanted]
    warnings: list[str] = []
    counts: dict = {"input": int(len(cloud))}
    params: dict = {}
    timings: dict = {}
    stage_clouds: dict = {}
    finite = np.isfinite(cloud.xyz).all(axis=1)
    if not finite.all():
        warnings.append(f"dropped {int((~finite).sum())} points with NaN/inf coordinates")
        cloud = cloud.subset(finite)
    counts["finite"] = int(len(cloud))
    if len(cloud) < cfg.min_points:
        raise InputError(f"the cloud has {len(cloud)} valid points, fewer than min_points="
                         f"{cfg.min_points}; check the SfM output (too few views/features?)")
    if not cloud.views:
        cloud.views = views
    poses = [v.pose for v in views]
    target = cameras_convergence_point(poses)
    cam_centers = np.array([p.t for p in poses])
    cam_up = -np.mean([p.R[:, 1] for p in poses], axis=0)
    radius = frame_radius(views, target)
    params["orbit"] = {"convergence_point": target.tolist(), "frame_radius": radius}
    stage_clouds["input"] = (cloud.xyz, cloud.rgb)
    full = cloud
    sel = np.arange(len(cloud))
    small_disc = np.zeros(len(full), bool)  # points whose mask discs are capped (density)
    grown_pts = np.zeros(0, np.int64)  # points noise.grow_scale added

    def run(name: str, fn) -> None:
        nonlocal cloud, sel
        t0 = time.perf_counter()
        keep, p = fn(cloud.xyz)
        timings[name] = time.perf_counter() - t0
        keep = np.asarray(keep, np.int64)
        if "sparse" in p:  # density.sparse_share: kept points whose discs are capped
            p = dict(p)
            small_disc[sel[keep[p.pop("sparse")]]] = True
            p["sparse_points"] = int(small_disc.sum())
        params[name] = p
        if "warning" in p:
            warnings.append(f"{name}: {p['warning']}")
        sel = sel[keep]
        cloud = cloud.subset(keep)
        counts[name] = int(len(cloud))
        stage_clouds[name] = (cloud.xyz, cloud.rgb)
        if len(cloud) < 4:
            raise InputError(f"no dense region left after the {name} stage ({len(cloud)} "
                             f"points); the cloud may be all one plane or pure noise -- "
                             f"check the input or try the other --method")

    stages = _point_stages(cfg, views, target, radius, cam_centers, cam_up)
    noise_in = sel
    for name, fn in stages:
        if name == "noise":
            noise_in = sel.copy()
        run(name, fn)
    if cfg.stability.draws > 0:
        t0 = time.perf_counter()
        flipped: list = []
        st = stability_check(len(full), sel, lambda idx: _run_point_stages(stages, full.xyz, idx),
                             cfg.stability, cfg.seed, flipped)
        params["stability"] = st
        w = stability_warning(st, len(cloud))
        if (w and cfg.stability.resolve and (st["flip_scales"] or flipped)
                and cfg.noise.method == "dbscan"):
            local = np.nonzero(np.isin(noise_in, sel))[0]
            copies = [np.nonzero(np.isin(noise_in, c))[0] for c in
                      copies_choice(len(full), flipped, cfg.stability.min_jaccard,
                                    min_copies=(cfg.stability.draws + 1) // 2)]
            k, st["resolved"] = centred_alternative(
                full.xyz[noise_in], local, st["flip_scales"], cfg.noise, target, radius,
                rgb=full.rgb[noise_in] if full.rgb is not None else None,
                alike=cfg.stability.alike_colour,
                copies=copies if cfg.stability.copies else None,
                max_growth=cfg.noise.max_extent_growth if cfg.stability.extent_guard else 0.0,
                up_plane=(params.get("floor") or {}).get("support_plane"))
            cands = st["resolved"]["candidates"]
            chosen = st["resolved"]["chosen_scale"]
            if chosen is not None:
                sel = noise_in[k]
                cloud = full.subset(sel)
                stage_clouds["stability"] = (cloud.xyz, cloud.rgb)
                why = ("its further points look like this one's: the rest of the object"
                       if cands[0][3] != "-" else "better centred on the cameras' "
                       "convergence point")
                how = ("the re-runs' own choice" if chosen == "copies"
                       else f"the noise stage at eps {chosen} spacings")
                w += (f"; kept instead the choice of a re-run ({len(cloud)} points, {how}; "
                      f"{why})")
            elif st["resolved"].get("too_wide"):
                w += (f"; kept this one (the re-runs' larger choice reaches more than "
                      f"{cfg.noise.max_extent_growth:g}x as far from the convergence point: "
                      f"a neighbour joining, the step the noise stage itself refuses)")
            elif any(c[3] is None for c in cands[1:]):
                w += ("; kept this one (a re-run chose a part of it whose colours match the "
                      "rest)")
            else:
                w += "; kept this one (better centred on the cameras' convergence point)"
        counts["stability"] = int(len(cloud))
        timings["stability"] = time.perf_counter() - t0
        if w:
            warnings.append(f"stability: {w}")
    if cfg.noise.grow_scale > 0 and cfg.noise.method == "dbscan" and len(sel):
        # an option (off in ours): one hop of grow_scale spacings from the chosen OOI set
        # back into the noise stage's input (an object's lone points past eps: an aircraft's
        # landing-gear wheels), once, after the tie-break chose the set
        t0 = time.perf_counter()
        sub = full.xyz[noise_in]
        local = np.nonzero(np.isin(noise_in, sel))[0]
        eps = params.get("noise", {}).get("eps") if cfg.noise.grow_unclustered_only else None
        grown = grow_selection(sub, local, cfg.noise, spacing(sub, cfg.noise.min_samples), eps)
        added = noise_in[np.setdiff1d(grown, local)]
        if cfg.noise.grow_colour_vote > 0 and len(added):
            # only points whose pixels look like the object in most views framing them
            rest = np.ones(len(full), bool)
            rest[sel] = False
            rest[added] = False
            vote = colour_vote(full.xyz[added], full.rgb[sel], full.rgb[rest], views,
                               seed=cfg.seed)
            ok = np.nan_to_num(vote, nan=0.0) >= cfg.noise.grow_colour_vote
            params.setdefault("noise", {})["grow_refused"] = int((~ok).sum())
            added = added[ok]
        params.setdefault("noise", {})["grown"] = int(len(added))
        grown_pts = np.sort(added)
        if len(added):
            if cfg.noise.grow_sparse:
                small_disc[added] = True
            sel = np.union1d(sel, added)
            cloud = full.subset(sel)
            stage_clouds["grow"] = (cloud.xyz, cloud.rgb)
        counts["grow"] = int(len(cloud))
        timings["grow"] = time.perf_counter() - t0
    if cfg.residual.ooi_colour_vote > 0 and len(sel) > 4:
        # an option (off in ours): OOI points whose pixels look like the rest of the cloud's
        # colours in most views framing them leave the OOI cloud (not to the background seeds)
        t0 = time.perf_counter()
        rest = np.ones(len(full), bool)
        rest[sel] = False
        vote = colour_vote(full.xyz[sel], full.rgb[sel], full.rgb[rest], views, seed=cfg.seed)
        ok = ~(np.nan_to_num(vote, nan=1.0) < cfg.residual.ooi_colour_vote)
        if cfg.residual.ooi_colour_vote_mismatch > 0 and not ok.all():
            # only where its pixels disagree with its own colour too (photo-inconsistent)
            mm = colour_mismatch(full.xyz[sel], full.rgb[sel], views)
            if np.isfinite(mm).any():
                lim = cfg.residual.ooi_colour_vote_mismatch * np.nanmedian(mm)
                ok |= ~(np.nan_to_num(mm, nan=0.0) > lim)
        params["ooi_colour_vote"] = {"dropped": int((~ok).sum())}
        if cfg.residual.ooi_colour_vote_sparse:
            small_disc[sel[~ok]] = True
            params["ooi_colour_vote"] = {"flagged": int((~ok).sum())}
        elif ok.sum() >= 4 and not ok.all():
            sel = sel[ok]
            cloud = full.subset(sel)
            stage_clouds["colour_vote"] = (cloud.xyz, cloud.rgb)
        counts["colour_vote"] = int(len(cloud))
        timings["colour_vote"] = time.perf_counter() - t0
    # an option (off in ours): points that belong to neither side -- multi-view points whose
    # rays agree worse than the cloud's typical track (``residual.py``) -- leave the OOI cloud
    # (its masks' splats and sure seeds) and the background's seeds, after the point stages
    # chose the OOI from the whole cloud (thinning the cloud first moved their close choices)
    neither = np.zeros(len(full), bool)
    if cfg.residual.enabled:
        t0 = time.perf_counter()
        keep, params["residual"] = residual_filter(full, cfg.residual)
        neither[:] = True
        neither[keep] = False
        ok = ~neither[sel]
        if cfg.residual.colour_factor > 0 and (~ok).any() and ok.sum() >= 4:
            mis = colour_mismatch(full.xyz[sel], full.rgb[sel], views)
            ref = float(np.nanmedian(mis[ok])) if np.isfinite(mis[ok]).any() else np.nan
            if np.isfinite(ref):
                stay = ~ok & ~(mis > cfg.residual.colour_factor * ref)  # NaN stays
                ok |= stay
                neither[sel[stay]] = False
                params["residual"].update({"colour_median": ref,
                                           "kept_consistent": int(stay.sum())})
        params["residual"]["dropped_ooi"] = int((~ok).sum())
        if ok.sum() >= 4 and not ok.all():
            sel = sel[ok]
            cloud = full.subset(sel)
        counts["residual"] = int(len(cloud))
        timings["residual"] = time.perf_counter() - t0
        stage_clouds["residual"] = (cloud.xyz, cloud.rgb)
    framing = framing_warning(cloud.xyz, views, cfg.roi) if cfg.roi.enabled else None
    if framing:
        warnings.append(f"roi: {framing}")
    if len(cloud) < cfg.min_ooi_points:
        warnings.append(f"only {len(cloud)} SfM points form the OOI (fewer than "
                        f"{cfg.min_ooi_points}): masks drawn from so few points are unreliable "
                        f"-- capture more views or larger images, or check that the SfM found "
                        f"points on the object (report.html shows the cloud after each stage)")
    if on_cloud is not None:
        on_cloud(cloud)
    def masks_of(sel_: np.ndarray, cloud_: SfmCloud, params_: dict, timings_: dict,
                 warnings_: list) -> tuple[TriMesh, dict]:
        """Mesh, masks, refinement and carving of the OOI points ``sel_`` (``cloud_``)."""
        t0 = time.perf_counter()
        try:
            mesh, params_["mesh"] = build_mesh(cloud_, cfg.mesh)
        except RuntimeError as exc:
            mesh = TriMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int32))
            warnings_.append(f"mesh: reconstruction failed ({exc}); mesh left empty")
        timings_["mesh"] = time.perf_counter() - t0
        if cfg.masks.mode == "mesh" and mesh.is_empty:
            warnings_.append("mesh is empty; masks fall back to point splats")
            cfg.masks.mode = "points"
        t0 = time.perf_counter()
        masks, params_["masks"] = render_masks(mask_views, cfg.masks, mesh, cloud_.xyz,
                                               small_disc[sel_] if small_disc.any() else None)
        timings_["masks"] = time.perf_counter() - t0
        if cfg.refine.enabled:
            t0 = time.perf_counter()
            removed = ~neither
            removed[sel_] = False
            fp = params.get("floor", {})
            plane = None
            if fp.get("support_plane") is not None and "band_inliers" in fp:
                # points in the layer between the inliers' band and the floor's measured
                # thickness may be the object's foot (a pot's base, a tyre): not background
                plane = np.asarray(fp["support_plane"])
                h = full.xyz @ plane[:3] + plane[3]
                removed &= ~((h > fp["band_inliers"]) & (h <= fp["band"]))
            pcfg = cfg.refine.plane_check
            if plane is not None and pcfg.enabled and pcfg.extra_planes > 0:
                extra = background_planes(full.xyz[removed], cloud_.xyz, cam_centers,
                                          float(fp.get("threshold", 0.0)), pcfg.extra_planes,
                                          cfg.seed)
                params_["background_planes"] = extra.tolist()
                plane = np.vstack([plane[None], extra])
            try:
                seeds = (~small_disc[sel_] if small_disc.any() and not cfg.density.sparse_seeds
                         else None)
                masks, params_["refine"] = refine_masks(masks, views, cloud_,
                                                        full.subset(removed), cfg.refine,
                                                        plane, target, context, seeds,
                                                        fp.get("band_inliers"))
            except ImportError:
                warnings_.append("refine: opencv-python-headless is not installed; masks are "
                                 "the unrefined point silhouettes")
            timings_["refine"] = time.perf_counter() - t0
        if cfg.masks.hull_carve:
            t0 = time.perf_counter()
            masks, params_["hull_carve"] = hull_carve(masks, views, cloud_.xyz, cfg.masks)
            timings_["hull_carve"] = time.perf_counter() - t0
        return mesh, masks

    mesh, masks = masks_of(sel, cloud, params, timings, warnings)
    grown_in = np.intersect1d(grown_pts, sel)
    if cfg.noise.grow_local > 0 and len(grown_in) and len(grown_in) < len(sel):
        # the grown points may add pixels only near their own discs: the masks made without
        # them (as if grow_scale were off), plus what the masks with them add within
        # grow_local median disc radii of a grown point (elsewhere a grown point moves the
        # hull steps' and GrabCut's choices, in views that never see it near there)
        t0 = time.perf_counter()
        base_sel = np.setdiff1d(sel, grown_in)
        base = masks_of(base_sel, full.subset(base_sel), {}, {}, [])[1]
        pos = np.searchsorted(sel, grown_in)
        r = cfg.noise.grow_local * float(params.get("masks", {}).get("median_radius", 0.0)
                                         or np.median(point_radii(cloud.xyz, cfg.masks.splat_k,
                                                                  cfg.masks.splat_scale)))
        # (a disc wider than the image's sides covers all of it: no wider box to draw)
        cap = min(cfg.masks.max_splat_px * cfg.noise.grow_local,
                  max(v.camera.width + v.camera.height for v in mask_views))
        near = point_masks(cloud.xyz[pos], np.full(len(pos), r), mask_views,
                           MaskConfig(closing_kernel=1, fill_holes=False, max_splat_px=cap),
                           finish=False)
        added_px = 0
        for k in masks:
            nb = near.get(k)
            m = base[k] | (masks[k] & nb) if nb is not None and nb.shape == base[k].shape \
                else base[k]
            added_px += int((m & ~base[k]).sum())
            masks[k] = m
        params.setdefault("noise", {})["grow_local"] = {"radius": r, "added_px": added_px}
        timings["grow_local"] = time.perf_counter() - t0
    if wanted is not None:
        masks = {k: m for k, m in masks.items() if k in wanted}
        params["mask_keys"] = len(masks)
    cover = np.array([m.mean() for m in masks.values()])
    n_empty = int((cover == 0).sum())
    if n_empty:
        warnings.append(f"{n_empty} of {len(masks)} views see nothing of the OOI (empty mask)")
    if masks and n_empty == len(masks):
        warnings.append("every mask is empty: the cameras see nothing of the segmented OOI")
    n_full = int((cover > 0.95).sum())
    if n_full:
        warnings.append(f"{n_full} masks cover >95% of their image: the segmentation likely "
                        f"kept background; do not trust these masks")
    metrics = None
    if capture.has_gt_masks and masks:
        metrics = scene_metrics(masks, {v.key: v.gt_mask for v in views if v.key in masks})
    return SegmentationResult(cloud, mesh, masks, counts, params, timings, warnings, cfg,
                              metrics, stage_clouds)


# the segmentation's peak memory, measured (``/usr/bin/time -v ooi-seg segment`` on the real
# bonsai's 289 views, BENCHMARKS, Segmentation > Session 34): 1.43 GiB at 400x266 and 2.49 GiB
# at 800x533 -- about 1.15 GB of libraries and cloud, and 12.3 bytes per pixel of every view
# (the images stay loaded; masks, GrabCut and plane-check buffers)
SEG_MEMORY_PER_PIXEL = 12.3


def estimate_memory_bytes(capture: Capture) -> int:
    """About how many bytes ``segment`` adds to what a process holds once its libraries are
    loaded, for ``capture``: ``SEG_MEMORY_PER_PIXEL`` per pixel of every view."""
    px = sum(int(v.camera.width) * int(v.camera.height) for v in capture.views)
    return int(SEG_MEMORY_PER_PIXEL * px)


# the most pixels per view ``ooi-seg segment`` / ``run`` work at when no --downscale is given:
# the refinement's time is linear in pixels (the real bonsai: 0.43 MP x 289 views 14 min, on
# 2 cores), so photos above about 1 MP are read smaller and the masks scaled back up to them
SEG_MAX_PIXELS = 1_000_000


def working_downscale(sizes: list[tuple[int, int]], max_pixels: int = SEG_MAX_PIXELS,
                      available: Optional[int] = None) -> int:
    """The integer factor to read views of ``sizes`` ((width, height) each) at when the user
    gave none: the smallest f >= 1 that brings every view to at most ``max_pixels`` pixels
    (``<= 0``: no limit) and the run's estimated memory (``estimate_memory_bytes``) within
    ``available`` bytes (default: what the machine has available now). Sizes as
    ``CameraIntrinsics.scaled(1 / f)`` gives them; a view is never made smaller than 16 px on
    its short side for the pixel limit."""
    if not sizes:
        return 1
    if available is None:
        from ..core.resources import available_memory
        available = available_memory()

    def px(f: int) -> list[int]:
        return [int(round(w / f)) * int(round(h / f)) for w, h in sizes]

    short = min(min(w, h) for w, h in sizes)
    f = 1
    while f < 64:
        p = px(f)
        over_px = max_pixels > 0 and max(p) > max_pixels and short / (f + 1) >= 16
        if not over_px and SEG_MEMORY_PER_PIXEL * sum(p) <= available:
            break
        f += 1
    return f


def check_memory(capture: Capture, available: Optional[int] = None,
                 downscale: float = 1.0) -> None:
    """Raise ``InputError`` before a run that clearly cannot fit in memory (the system would
    kill it part way): how much it needs, how much there is, and the ``--downscale`` that
    fits. ``available``: bytes (default: what the machine has available now);
    ``downscale``: the factor the images were already read at (the advice multiplies it).
    The libraries' own share is left out of the estimate, so a run is never refused that
    might fit."""
    if available is None:
        from ..core.resources import available_memory
        available = available_memory()
    need = estimate_memory_bytes(capture)
    if need <= available or not capture.views:
        return
    f = 2
    while need / f ** 2 > available and f < 64:
        f += 1
    sizes = sorted({(v.camera.width, v.camera.height) for v in capture.views})
    size = "x".join(map(str, sizes[-1])) + (" and smaller" if len(sizes) > 1 else "")
    raise InputError(f"segmenting {len(capture.views)} views of {size} needs about "
                     f"{need / 2 ** 30:.1f} GiB of memory and {available / 2 ** 30:.1f} GiB "
                     f"is available; read the images smaller: --downscale {f * downscale:g} "
                     f"(about {need / f ** 2 / 2 ** 30:.1f} GiB)")


def cloud_change(prev_xyz: np.ndarray, new_xyz: np.ndarray,
                 tol: Optional[float] = None) -> dict:
    """How much an OOI cloud changed between two segmentations (e.g. whether a live node
    should re-render its masks): ``added`` = share of the new points farther than ``tol``
    from every previous point, ``removed`` = share of the previous points farther than
    ``tol`` from every new point, ``changed`` = the larger of the two (0 = same surface).

    ``tol`` defaults to twice the new cloud's median nearest-neighbour spacing, so it follows
    the cloud's scale and density.
    """
    from scipy.spatial import cKDTree
    a = np.asarray(prev_xyz, float).reshape(-1, 3)
    b = np.asarray(new_xyz, float).reshape(-1, 3)
    if len(a) == 0 or len(b) == 0:
        same = len(a) == len(b)
        return {"added": 0.0 if same else float(len(b) > 0),
                "removed": 0.0 if same else float(len(a) > 0),
                "changed": 0.0 if same else 1.0, "tol": 0.0}
    tb = cKDTree(b)
    if tol is None:
        d, _ = tb.query(b, k=2) if len(b) > 1 else (np.zeros((1, 2)), None)
        tol = 2.0 * float(np.median(d[:, 1]))
    added = float(np.mean(cKDTree(a).query(b)[0] > tol))
    removed = float(np.mean(tb.query(a)[0] > tol))
    return {"added": added, "removed": removed, "changed": max(added, removed),
            "tol": float(tol)}
