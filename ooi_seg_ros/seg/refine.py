"""Improved-mode stage: per-view refinement of the masks against the image (GrabCut).

The splatted silhouette of the OOI points is right in the large but has a halo of a disc
radius around it and misses what no SfM point covers. Every view also knows *where* SfM
features were seen: the 2D observations of OOI points are object pixels, the observations of
the points the earlier stages removed (floor, background) are background pixels. These seeds,
plus the silhouette as "probably object" and a band around it as "probably background",
initialise GrabCut (colour models + graph cut) on a crop around the object. A refinement that
changes the area beyond ``max_area_change`` is rejected and the silhouette kept (counted).

``upsample`` (2 in ``ours``): a crop smaller than ``max_side`` is cut on a grid enlarged that
many times (labels nearest, image bicubic) and each pixel is object when at least half its
sub-pixels are -- the truth's own convention for an outline pixel. The graph cut's smoothness
term charges each boundary edge; enlarged k times, a part's data terms grow with its area
(k^2) and its boundary edges only k times, so a part 1-4 px wide (a tube, a leaf) is cut
away for the length of its boundary less often, and the outline is placed to a sub-pixel
(measured, BENCHMARKS session 25: thin scenes gain recall and precision, solid ones stay
within +-0.005 IoU; the refinement costs about twice the time).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from scipy import ndimage

from ..core.geometry import finite_rows
from ..core.types import SfmCloud, View
from .masks import (MaskConfig, fill_small_holes, outline_vote, point_masks,
                    project_distorted)
from .photo import (PlaneCheckConfig, PlaneConsistency, PointSet, capture_noise,
                    view_exposures)
from .thin import BridgeConfig, check_config, thin_bridges


@dataclass
class RefineConfig:
    """Options of the GrabCut refinement."""

    enabled: bool = False  # run the refinement (needs opencv-python-headless)
    iterations: int = 4  # GrabCut iterations per view
    band_fraction: float = 0.15  # "probably background" band width, fraction of the mask size
    band_gaps: float = 0.0  # the band is at least this many mean gaps between the view's object
    # seeds (sqrt(silhouette area / seeds in it)): where the OOI cloud is sparse, parts no point
    # lies on reach further past the silhouette; 0 = the fraction alone (see ``_band_px``).
    # 3 in ``ours`` since session 39 (BENCHMARKS, Segmentation > Session 39: stool 8 seeds
    # 0.890 / 0.960 -> 0.900 / 0.976; the dense scenes' bands are not widened)
    seed_cover: float = 0.0  # where the discs of the view's sure object seeds would cover more
    # than this share of the image around them, each is drawn with the probability that brings
    # it down to the share (``_thin_seeds``); 0 = every seed. 0.5625 in ``ours`` since session
    # 40 (BENCHMARKS, Segmentation > Session 40: each stray OOI point seeds a false blob; 120
    # views aircraft 0.887 / 0.896 -> 0.899 / 0.907, tabletop 0.899 / 0.899 -> 0.909 / 0.910)
    seed_radius: int = 1  # radius in px of the sure seeds drawn at observations
    seed_colour: float = 0.0  # > 0 (with fg_seeds "projections"): a projected object seed whose
    # pixel differs from its point's SfM colour by more than this many times the view's median
    # difference is dropped (a point on a thin part that projects beside it seeds background).
    # Session 51, 3.0 against the default: IoU +0.002..+0.008 on most captures, recall
    # -0.001..-0.008 (aircraft 0-5 0.928 / 0.975 -> 0.934 / 0.972), so an option, off: the
    # aircraft's recall sits at the bar (BENCHMARKS, Segmentation > Session 51)
    max_side: int = 256  # crops larger than this are refined at reduced resolution
    max_area_change: float = 0.5  # reject results that grow/shrink the mask by more than this
    hole_max_fraction: float = 0.02  # fill holes smaller than this x the mask area
    fg_seeds: str = "observations"  # sure-object seeds: "observations" (the 2D features
    # matched in this view) | "projections" (every OOI point projected: whatever hides it from
    # this view is, on an orbit, the object itself, so its pixel is object either way) |
    # "consistent" (projections of the points the first-pass masks agree on; two passes)
    second_init: str = "splat"  # consistent: probable-object region of the second pass:
    # "splat" (the splatted silhouette) | "first" (the first pass's result)
    consistency: float = 0.7  # consistent: min share of views whose first-pass mask holds a point
    voronoi: bool = False  # silhouette pixels nearer a background than an object observation
    # start as probably-background instead of probably-object
    opening: int = 1  # iterations of the binary opening that removes specks from the result
    grown_open: int = 0  # > 0: what GrabCut grew past the splatted silhouette is also opened
    # with a square of side 2 r + 1 (a painted floor line, 2-3 px wide and diagonal, survives
    # the 3x3 cross of ``opening``; GrabCut follows white lines from a white wing tip)
    upsample: int = 1  # GrabCut on the crop enlarged this many times (labels nearest, image
    # bicubic) when the crop is below max_side, its result averaged back (>= half the sub-
    # pixels object): a thin part 2 px wide is 4 px wide to the graph cut's smoothness term
    enlarged_iterations: int = -1  # upsample > 1: how many of the ``iterations`` run on the
    # enlarged crop, the others first on the crop at its own size (a quarter of the pixels;
    # the colour models and labels they leave carry over): -1 = all of them (session 25);
    # 0 = none: one graph cut on the enlarged crop with the models learnt on the crop frozen
    # (the enlarged grid matters to the smoothness term; see ``_grabcut_pass``)
    edge_window: int = 0  # outline matting: a pixel just outside the mask joins it when its
    # colour is nearer the mean of the object pixels than of the background pixels within this
    # window (px) around it; 0 = off (see ``edge_matte``)
    edge_alpha: float = 0.5  # outline matting: the ring pixel joins when its estimated object
    # coverage (its colour's position between the two local means) is at least this. 0.5 is
    # the truth's own rule (a pixel at least half covered is object); ``ours`` used 0.4,
    # read off the simulator, until the outline vote (session 36: 0.5 then scored as well)
    outline_vote: bool = False  # last: every outline pixel decided again by the joint
    # bilateral vote of the pixels around it (``masks.outline_vote``: colour width half the
    # view's median colour step across the outline)
    seed: int = 0  # seed of OpenCV's RNG (GrabCut's colour-model initialisation)
    hull_add: bool = False  # multi-view recovery (``hull_additions``): a pixel outside a view's
    # refined mask joins it when its ray meets a voxel that most views' masks hold (the visual
    # hull of the refined masks) *and* that view's GrabCut colour models call its colour object
    # -- parts with no SfM point that other views found (a tyre arc, a top tube, a wing tip).
    # Needs every view's refined mask: ``segment(mask_keys=...)`` then refines all views
    hull_agree: float = 0.5  # hull_add: a voxel is in the hull when the masks of more than this
    # share of the views that frame it hold it (0.5 = a majority of the views)
    hull_voxel_px: float = 1.0  # hull_add: voxel edge in pixels at the object's median depth
    # (the grid follows the images' resolution: one voxel ~ one pixel's footprint)
    hull_thin_agree: float = 0.0  # hull_add: > 0 also adds pixels the looser hull of the
    # voxels held by more than this share of the framing views reaches (a leaf or spoke only
    # some views' GrabCut found), colour-tested as the others and, with the plane check's
    # neighbours, photo-consistent: two neighbour views repeat the pixel's colour at one depth
    # inside the looser hull. 0.3 in ``ours`` since session 31, with ``hull_thin_distinct``
    # 4 (alone it also added the real bonsai's wall and cloth: BENCHMARKS, Segmentation >
    # Sessions 30 and 31)
    hull_thin_distinct: int = 0  # hull_thin_agree: > 0: the looser hull's pixel must also be
    # refuted -- fewer than two of the neighbours that see the point repeat its colour -- at
    # this many of the 4 depths ``OFF_HULL`` off the looser hull's interval along its ray: a
    # uniform wall or cloth is consistent at every depth (it says nothing about where the
    # pixel lies), a spoke or leaf seen against a varied background only at its own. 4 in
    # ``ours``: 2 still added 9,462 px of the real bonsai's wall, 4 adds 1,959 px
    hull_cut: bool = False  # hull_add: also drop the mask pixels whose rays miss that hull (a
    # blob only a minority of the views hold); off: it costs the aircraft's thin tips (recall)
    hull_cut_grown: bool = False  # hull_add: drop the mask pixels that GrabCut grew past the
    # splatted silhouette (no OOI point's disc covers them) whose rays miss the hull of
    # ``hull_cut_agree``: a leak along a background edge of the object's colour (a fence rail
    # and a tree trunk behind a saddle) is held by this view alone, a part no SfM point
    # covers but other views' masks hold too stays. On in ``ours`` since session 29
    # (BENCHMARKS, Segmentation > Session 29): bicycle +0.012 IoU with its recall; it also
    # cuts leaf tips only one view's GrabCut found (stool at 320x240: -0.001 IoU and recall)
    hull_cut_agree: float = 0.25  # hull_cut_grown: the hull it tests against holds the voxels
    # more than this share of the framing views hold (0.5, the additions' majority, also cut
    # true outline pixels of the aircraft and the bicycle: recall -0.0001 to -0.0025)
    border_leak: bool = False  # a region GrabCut grew past the splatted silhouette out to an
    # image side the silhouette does not reach leaves the mask: the crop has no background
    # margin beyond the image's edge, so nothing stopped the cut there (a bright window above
    # a crown that nears the top of the photo); the hull additions may bring back what other
    # views' masks hold
    border_leak_hull: bool = False  # hull_add: as ``border_leak``, but the pixels of such a
    # region are dropped only where their rays miss the hull of the masks (``hull_agree``):
    # an object part out to the image side that most views framing it hold (a wing tip that
    # leaves the frame, found in the views that see all of it) stays. On in ``ours`` since
    # session 30 (BENCHMARKS, Segmentation > Session 30): the real bonsai loses 11,311 px of
    # wall and window above its crown in 19 views; the simulator scenes move by <= 0.0004
    behind_cut: str = "off"  # hull_add: drop the mask pixels that the plane check's neighbours
    # place past the object (``_photo_behind``, a winner-take-all depth vote along the pixel's
    # ray: more neighbours repeat its colour at a depth beyond the looser hull than at any
    # depth inside it) -- background seen between leaves or through a frame, kept by GrabCut
    # for its colour. "mask": every mask pixel ("mask" in ``ours`` since session 33:
    # BENCHMARKS, Segmentation > Session 33); "grown": only those outside the splatted
    # silhouette (the leaves' gaps lie inside it); "off"
    behind_margin: int = 3  # behind_cut: neighbours by which the best depth behind must win
    behind_max_in: int = 3  # behind_cut: a pixel more neighbours repeat inside the hull stays
    behind_step_px: float = 4.0  # behind_cut: the depth sweeps' step, in pixels of parallax
    # in the farthest neighbour (4 since session 34: the same masks as 1 px within 0.001
    # IoU / recall on every simulator scene and the real bonsai, 0.7-0.8x the time; the
    # nearer neighbours are sampled finer, and a surface's colour changes little in 2 px)
    behind_open: bool = False  # behind_cut: cut only what a 2x2 square fits in: no lone pixels
    # or 1-px streaks (the real bonsai's striped stand matched at a wrong depth there); on in
    # ``ours``: it keeps every simulator scene's recall, at about half the plants' IoU gain
    hull_connected: bool = True  # hull_add: keep only the added pixels 8-connected to the mask
    # (through other added pixels): a lone apron speck of the fuselage's grey is not a part
    hull_photo: bool = False  # hull_add: an added pixel must also be photo-consistent: at some
    # depth where its ray crosses the hull, its colour is within plane_check.max_diff of what
    # at least one of the plane check's neighbour views sees there (background seen through
    # the hull lands elsewhere in the neighbours)
    hull_photo_depths: int = 8  # hull_photo: depths sampled across the ray's hull interval
    hull_graph: str = "compressed"  # hull_add on lossy-compressed images: "compressed" (only
    # views whose ``View.compressed`` is set) | "on" | "off". The colour test's verdict on an
    # added pixel must also survive a graph cut (GrabCut's frozen models, the contrast-weighted
    # smoothness) -- after JPEG the pixel just outside the outline has a colour blended with
    # the object's, which the per-pixel test calls object (a 1-2 px halo all round); the cut
    # leaves that halo out. Not on lossless images: there the added ring pixels are mostly
    # true outline, and the cut costs recall (session 21, BENCHMARKS)
    blend_detect: bool = True  # hull_graph "compressed" also acts on a capture whose colour
    # is blurred wider than its brightness (``capture_chroma_sharpness`` under ``blend_max``):
    # JPEG or video frames a driver decoded and publishes as raw ``Image``s, or saved as PNG
    # -- the same blended outline colours, with no flag to say so (``View.compressed``)
    blend_max: float = 0.9  # blend_detect: chroma this much smoother than luma counts as
    # subsampled (full-resolution colour ~1: its edges are the luma's; 4:2:0 JPEG 0.6-0.8)
    hull_graph_thin_px: float = 3.0  # hull_graph: where no mask pixel within this many pixels
    # lies this deep inside the mask (a thin part, a part the mask missed) the per-pixel test
    # decides alone: the cut's smoothness removes thin parts, which the additions bring back
    hull_max_voxels: int = 1_000_000  # hull_add: coarser voxels when the grid would be larger
    hull_free: int = 0  # hull_add: > 0: a voxel leaves every hull when at least this many views
    # observed an SfM feature (object or background) beyond it on the ray through it -- the
    # camera saw past it, so it is free space (space carving by the features: the gap under a
    # crown or between a trunk and a pot, which no silhouette carves when every view's GrabCut
    # kept the uniform wall seen through it); 0: off
    hull_free_margin: float = 3.0  # hull_free: the feature lies more than this many voxel edges
    # beyond the voxel's depth in that view (a voxel just in front of a surface stays)
    hull_free_dilate: int = 1  # hull_free: each feature's depth holds over a (2r+1)^2 window
    # (features are sparse: ~2% of the pixels); 0: the feature's own pixel only
    # (its cost: one projection of the grid per view; 1M and 4M gave the same masks +-0.001)
    bridges: BridgeConfig = field(default_factory=BridgeConfig)  # last: thin straight parts
    # (spokes, struts) that span a hole of the mask from one side to the other join it
    # (``thin.thin_bridges``; GrabCut's smoothness cuts a part ~1 px wide whatever its colour)
    plane_check: PlaneCheckConfig = field(default_factory=PlaneCheckConfig)  # pixels whose
    # colour the support plane explains (photo-consistent with nearby views) are background


def _obs_by_view(cloud: SfmCloud, views: list[View]) -> list[np.ndarray]:
    """Observation pixel coordinates [k,2] of ``cloud``'s points in each of ``views``.

    ``obs_view`` indexes ``cloud.views`` (the SfM keyframes), which may be a subset or a
    reordering of the views being masked, so observations are matched by view key.
    """
    out = [np.zeros((0, 2), np.float32) for _ in range(len(views))]
    if len(cloud.obs_view) == 0:
        return out
    src = cloud.views if cloud.views else views
    where = {v.key: j for j, v in enumerate(views)}
    order = np.argsort(cloud.obs_view, kind="stable")
    ov = cloud.obs_view[order]
    xy = cloud.obs_xy[order]
    bounds = np.searchsorted(ov, np.arange(len(src) + 1))
    for i, v in enumerate(src):
        j = where.get(v.key)
        if j is not None:
            out[j] = xy[bounds[i]:bounds[i + 1]]
    return out


def _obs_ids_by_view(clouds: list[SfmCloud], views: list[View]
                     ) -> list[tuple[np.ndarray, np.ndarray]]:
    """(point ids, pixel xy) of the observations of ``clouds``' points in each of ``views``
    (matched by key, as ``_obs_by_view``); ids are unique over the clouds together."""
    where = {v.key: j for j, v in enumerate(views)}
    ids: list[list] = [[] for _ in views]
    xys: list[list] = [[] for _ in views]
    base = 0
    for c in clouds:
        src = c.views if c.views else views
        vj = np.array([where.get(v.key, -1) for v in src], np.int64)
        if len(c.obs_view):
            jv = vj[c.obs_view]
            pid = np.repeat(np.arange(len(c), dtype=np.int64), np.diff(c.obs_ptr)) + base
            order = np.argsort(jv, kind="stable")
            jv, pid, xy = jv[order], pid[order], c.obs_xy[order]
            bounds = np.searchsorted(jv, np.arange(len(views) + 1))
            for j in range(len(views)):
                ids[j].append(pid[bounds[j]:bounds[j + 1]])
                xys[j].append(xy[bounds[j]:bounds[j + 1]])
        base += len(c)
    return [(np.concatenate(i) if i else np.zeros(0, np.int64),
             np.concatenate(x) if x else np.zeros((0, 2), np.float32)) for i, x in zip(ids, xys)]


def _obs_depths(clouds: list[SfmCloud], views: list[View]) -> list[tuple]:
    """(pixel columns, rows, depths) of every observed feature of ``clouds`` in each of
    ``views`` (matched by key, as ``_obs_by_view``): where that view saw a surface."""
    parts: list[list] = [[] for _ in views]
    where = {v.key: j for j, v in enumerate(views)}
    for cloud in clouds:
        if len(cloud.obs_view) == 0:
            continue
        src = cloud.views if cloud.views else views
        pid = np.repeat(np.arange(len(cloud.xyz)), np.diff(cloud.obs_ptr))
        for i, sv in enumerate(src):
            j = where.get(sv.key)
            sel = np.nonzero(cloud.obs_view == i)[0]
            if j is None or not len(sel):
                continue
            v = views[j]
            _, z = project_distorted(cloud.xyz[pid[sel]], v.camera, v.pose)
            xy = cloud.obs_xy[sel]
            u, w = np.rint(xy[:, 0]), np.rint(xy[:, 1])
            ok = ((z > 1e-9) & np.isfinite(z) & (u >= 0) & (u < v.camera.width) & (w >= 0)
                  & (w < v.camera.height))
            parts[j].append((u[ok].astype(int), w[ok].astype(int), z[ok].astype(np.float32)))
    out = []
    for p in parts:
        if not p:
            out.append((np.zeros(0, int), np.zeros(0, int), np.zeros(0, np.float32)))
        else:
            out.append(tuple(np.concatenate(a) for a in zip(*p)))
    return out


def _seen_depth(obs: tuple, h: int, w: int, dilate: int) -> np.ndarray:
    """[h, w] the farthest observed feature's depth at each pixel (0: none), over a
    (2 ``dilate`` + 1)^2 window."""
    d = np.zeros((h, w), np.float32)
    u, v, z = obs
    if len(z):
        np.maximum.at(d, (v, u), z)
        if dilate > 0:
            d = ndimage.grey_dilation(d, size=(2 * dilate + 1, 2 * dilate + 1))
    return d


def _in_frame(proj: tuple[np.ndarray, np.ndarray], v: View) -> np.ndarray:
    """Projected pixels [k,2] in front of the camera and inside its image."""
    uv, z = proj
    c = v.camera
    ok = (z > 1e-9) & finite_rows(uv)
    ok &= (uv[:, 0] > -0.5) & (uv[:, 0] < c.width - 0.5)
    ok &= (uv[:, 1] > -0.5) & (uv[:, 1] < c.height - 0.5)
    return uv[ok].astype(np.float32)


def _colour_seeds(xyz: np.ndarray, rgb: np.ndarray, views: list[View], masks: dict,
                  factor: float) -> tuple[list[np.ndarray], int]:
    """Projected object seeds per view, without those whose pixel's colour is far from their
    point's own (SfM) colour: further than ``factor`` x the view's median distance."""
    out, dropped = [], 0
    for v in views:
        if v.key not in masks:
            out.append(np.zeros((0, 2), np.float32))
            continue
        uv, z = project_distorted(xyz, v.camera, v.pose)
        c = v.camera
        ok = (z > 1e-9) & finite_rows(uv)
        ok &= (uv[:, 0] > -0.5) & (uv[:, 0] < c.width - 0.5)
        ok &= (uv[:, 1] > -0.5) & (uv[:, 1] < c.height - 0.5)
        xy = uv[ok].astype(np.float32)
        if len(xy) >= 8:
            img = v.get_image()
            u = np.clip(np.rint(xy[:, 0]).astype(int), 0, c.width - 1)
            w = np.clip(np.rint(xy[:, 1]).astype(int), 0, c.height - 1)
            d = np.linalg.norm(img[w, u].astype(np.float32) - rgb[ok], axis=1)
            keep = d <= factor * max(float(np.median(d)), 1.0)
            dropped += int((~keep).sum())
            xy = xy[keep]
        out.append(xy)
    return out, dropped


def _draw(seed: np.ndarray, xy: np.ndarray, r: int, box: tuple, scale: float) -> None:
    y0, x0 = box[0], box[2]
    h, w = seed.shape
    u = np.rint((xy[:, 0] - x0) * scale).astype(int)
    v = np.rint((xy[:, 1] - y0) * scale).astype(int)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            uu, vv = u + dx, v + dy
            ok = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
            seed[vv[ok], uu[ok]] = True


def _band_px(m: np.ndarray, fg_xy: np.ndarray, cfg: RefineConfig) -> tuple[int, bool]:
    """Width in px of the "probably background" band around the silhouette ``m``, and
    whether ``band_gaps`` widened it.

    ``band_fraction`` of the silhouette's larger side, and with ``band_gaps`` > 0 at least that
    many mean gaps between the object seeds inside the silhouette: a silhouette splatted from a
    few points misses parts (a frond, a handle) that lie between or beyond its samples, about a
    gap or more from the nearest one, and GrabCut can only add pixels inside the band. The gap
    is a property of the cloud's density in this view, so dense clouds keep the fraction.
    """
    ys, xs = np.nonzero(m)
    size = max(np.ptp(ys), np.ptp(xs)) + 1
    band = base = max(3, int(cfg.band_fraction * size))
    if cfg.band_gaps > 0 and len(fg_xy):
        u = np.rint(fg_xy[:, 0]).astype(int)
        v = np.rint(fg_xy[:, 1]).astype(int)
        H, W = m.shape
        ok = (u >= 0) & (u < W) & (v >= 0) & (v < H)
        n = int(m[v[ok], u[ok]].sum())
        if n:
            band = max(band, int(round(cfg.band_gaps * np.sqrt(len(ys) / n))))
    return band, band > base


def _thin_seeds(xy: np.ndarray, m: np.ndarray, cover: float, radius: int, seed: int
                ) -> np.ndarray:
    """The object seeds ``xy`` [k,2] to draw in a view with silhouette ``m``: where their
    discs (side 2 ``radius`` + 1) would cover more than ``cover`` of the image around them,
    each is drawn with the probability that brings the cover there down to ``cover``. The
    local cover is counted within two target gaps of the seed (target gap = side /
    sqrt(cover)), so sparse parts (a dark stand with few features) keep every seed; seeds
    outside the silhouette are all kept.

    Each OOI point that is not on the object seeds a false blob of its own, while the true
    points' discs overlap: once the seeds are dense enough to cover much of the silhouette,
    more of them add stray blobs and no object (BENCHMARKS, Segmentation > Session 40).
    Random, not spatial, thinning: a stray point is alone where it lies and would survive a
    per-cell pick."""
    if cover <= 0 or not len(xy):
        return xy
    from scipy.spatial import cKDTree
    H, W = m.shape
    u = np.rint(xy[:, 0]).astype(int)
    v = np.rint(xy[:, 1]).astype(int)
    ok = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    inside = np.zeros(len(xy), bool)
    inside[ok] = m[v[ok], u[ok]]
    idx = np.nonzero(inside)[0]
    if len(idx) < 2:
        return xy
    side = 2 * int(radius) + 1
    gap = side / np.sqrt(cover)
    r = 2.0 * gap
    pts = xy[idx]
    count = cKDTree(pts).query_ball_point(pts, r, return_length=True)
    p = np.minimum(1.0, np.pi * r * r / (np.maximum(count, 1) * gap * gap))
    drop = idx[np.random.default_rng(seed).random(len(idx)) >= p]
    if not len(drop):
        return xy
    sel = np.ones(len(xy), bool)
    sel[drop] = False
    return xy[sel]


def _grabcut_pass(masks: dict[str, np.ndarray], views: list[View], fg_xy: list[np.ndarray],
                  bg_xy: list[np.ndarray], cfg: RefineConfig,
                  floor: Optional[PlaneConsistency] = None, floor_cache: Optional[dict] = None,
                  models: Optional[dict] = None, stats: Optional[dict] = None
                  ) -> tuple[dict, int, int]:
    """One GrabCut pass over every view with the given seed pixels; (masks, refined, rejected).

    ``floor`` (optional) marks the crop's pixels that show the support plane as sure
    background; ``floor_cache`` keeps those maps between passes (keyed by view and crop).
    ``models`` (optional) receives, per view GrabCut ran on, its colour models and where the
    plane check found background: {key: (bgd [1,65], fgd [1,65], full-frame bool [H,W])}.
    ``stats`` (optional) receives ``band_widened``: the views whose band ``band_gaps`` widened,
    and ``seeds_thinned``: the views whose object seeds ``seed_cover`` thinned.
    """
    import cv2
    out, refined, rejected = {}, 0, 0
    widened = thinned = 0
    floor_cache = {} if floor_cache is None else floor_cache
    for j, v in enumerate(views):
        if v.key not in masks:  # a context view only (neighbour of the plane check)
            continue
        m = masks[v.key]
        if m.sum() < 16:
            out[v.key] = m
            continue
        ys, xs = np.nonzero(m)
        band, wider = _band_px(m, np.asarray(fg_xy[j], float).reshape(-1, 2), cfg)
        widened += wider
        H, W = m.shape
        box = (max(0, ys.min() - band), min(H, ys.max() + band + 1),
               max(0, xs.min() - band), min(W, xs.max() + band + 1))
        crop = m[box[0]:box[1], box[2]:box[3]]
        img = v.get_image()[box[0]:box[1], box[2]:box[3]]
        scale = min(1.0, cfg.max_side / max(crop.shape))
        if scale < 1.0:
            dsize = (max(1, int(crop.shape[1] * scale)), max(1, int(crop.shape[0] * scale)))
            img = cv2.resize(img, dsize, interpolation=cv2.INTER_AREA)
            crop_s = cv2.resize(crop.astype(np.uint8), dsize,
                                interpolation=cv2.INTER_NEAREST).astype(bool)
        else:
            crop_s = crop
        bs = max(2, int(band * scale))
        near = ndimage.binary_dilation(crop_s, iterations=bs)
        gc = np.full(crop_s.shape, cv2.GC_BGD, np.uint8)
        gc[near] = cv2.GC_PR_BGD
        gc[crop_s] = cv2.GC_PR_FGD
        bg_seed = np.zeros(crop_s.shape, bool)
        fg_seed = np.zeros(crop_s.shape, bool)
        _draw(bg_seed, bg_xy[j], cfg.seed_radius, box, scale)
        fxy = np.asarray(fg_xy[j], float).reshape(-1, 2)
        if cfg.seed_cover > 0:
            n0 = len(fxy)
            fxy = _thin_seeds(fxy, m, cfg.seed_cover, cfg.seed_radius,
                              int(cfg.seed) * 100003 + j)
            thinned += len(fxy) < n0
        _draw(fg_seed, fxy, cfg.seed_radius, box, scale)
        if cfg.voronoi and fg_seed.any() and bg_seed.any():
            # silhouette pixels nearer a background observation than any object seed start
            # as "probably background": the discs' halo over the floor does not train the
            # object's colour model
            d_fg = ndimage.distance_transform_edt(~fg_seed)
            d_bg = ndimage.distance_transform_edt(~bg_seed)
            gc[crop_s & (d_bg < d_fg)] = cv2.GC_PR_BGD
        gc[bg_seed & ~fg_seed] = cv2.GC_BGD
        fallback = m  # kept when GrabCut fails or changes the area too much
        ref_area = crop.sum()
        fl_full = None
        if floor is not None:
            fkey = (j, box)
            if fkey not in floor_cache:
                # on the (possibly reduced) grid GrabCut works on: its cost is bounded too
                floor_cache[fkey] = floor.floor_maps(j, box, crop_s.shape)
            fl, fl_obj = floor_cache[fkey]
            fl_full = fl if scale >= 1.0 else cv2.resize(
                fl.astype(np.uint8), (crop.shape[1], crop.shape[0]),
                interpolation=cv2.INTER_NEAREST).astype(bool)
            # the floor pixels are known background: the silhouette without them is both the
            # fallback and the reference of the area check
            fallback = m.copy()
            fallback[box[0]:box[1], box[2]:box[3]] &= ~fl_full
            ref_area = (crop & ~fl_full).sum()
            gc[fl & ~fg_seed] = cv2.GC_BGD
        gc[fg_seed & ~bg_seed] = cv2.GC_FGD
        if floor is not None and floor.cfg.over_seeds:
            gc[fl] = cv2.GC_BGD
        if not (gc == cv2.GC_FGD).any() and not (gc == cv2.GC_PR_FGD).any():
            out[v.key] = fallback
            continue
        bgd, fgd = np.zeros((1, 65)), np.zeros((1, 65))
        cv2.setRNGSeed(int(cfg.seed) * 100003 + j)
        up = int(cfg.upsample) if scale >= 1.0 and max(crop.shape) < cfg.max_side else 1
        try:
            if up > 1:
                hh, ww = gc.shape
                gcu = cv2.resize(gc, (ww * up, hh * up), interpolation=cv2.INTER_NEAREST)
                bgr = np.ascontiguousarray(img[..., ::-1])
                imu = cv2.resize(bgr, (ww * up, hh * up), interpolation=cv2.INTER_CUBIC)
                k = int(cfg.enlarged_iterations)
                n_it = int(cfg.iterations)
                if 0 <= k < n_it:
                    # the colour models and labels of the first iterations need no sub-
                    # pixels: learn them on the crop, then continue on the enlarged crop
                    # from its labels (k > 0) or cut it once with the models frozen (k = 0)
                    g1 = gc.copy()
                    cv2.grabCut(bgr, g1, None, bgd, fgd, n_it - k, cv2.GC_INIT_WITH_MASK)
                    if k > 0:
                        gcu = cv2.resize(g1, (ww * up, hh * up),
                                         interpolation=cv2.INTER_NEAREST)
                        cv2.grabCut(imu, gcu, None, bgd, fgd, k, cv2.GC_EVAL)
                    else:
                        cv2.grabCut(imu, gcu, None, bgd, fgd, 1, cv2.GC_EVAL_FREEZE_MODEL)
                else:
                    cv2.grabCut(imu, gcu, None, bgd, fgd, n_it, cv2.GC_INIT_WITH_MASK)
                fgu = (gcu == cv2.GC_FGD) | (gcu == cv2.GC_PR_FGD)
                share = fgu.reshape(hh, up, ww, up).mean(axis=(1, 3))
                gc = np.where(share >= 0.5, cv2.GC_PR_FGD, cv2.GC_PR_BGD).astype(np.uint8)
            else:
                cv2.grabCut(np.ascontiguousarray(img[..., ::-1]), gc, None, bgd, fgd,
                            int(cfg.iterations), cv2.GC_INIT_WITH_MASK)
        except cv2.error:
            rejected += 1
            out[v.key] = fallback
            continue
        if models is not None:
            sure_bg = np.zeros_like(m)
            if fl_full is not None:
                sure_bg[box[0]:box[1], box[2]:box[3]] = fl_full
            models[v.key] = (bgd.copy(), fgd.copy(), sure_bg)
        res = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
        if scale < 1.0:
            res = cv2.resize(res.astype(np.uint8), (crop.shape[1], crop.shape[0]),
                             interpolation=cv2.INTER_NEAREST).astype(bool)
        if cfg.opening > 0:
            res = ndimage.binary_opening(res, iterations=int(cfg.opening))
        if cfg.grown_open > 0:
            r = int(cfg.grown_open)
            body = ndimage.binary_opening(res, np.ones((2 * r + 1, 2 * r + 1), bool))
            res &= crop | body
        if cfg.border_leak:
            res = _drop_border_leaks(res, crop, m, box)
        if floor is not None and fl_obj.any():
            # silhouette pixels the object's depth explains and the plane does not (after
            # the opening, which would take thin stems kept this way with it); with
            # keep_discs all the pixels the test covered (the discs reach past the silhouette)
            keep = fl_obj if floor.cfg.keep_discs else fl_obj & crop_s
            if keep.shape != res.shape:
                keep = cv2.resize(keep.astype(np.uint8), (res.shape[1], res.shape[0]),
                                  interpolation=cv2.INTER_NEAREST).astype(bool)
            if floor.cfg.keep_discs and (keep & ~crop).any():
                # past the silhouette the hue must also be the object's: clutter right beside
                # the object lies at the object's depth too, and the depth test alone keeps it
                # (measured: toy car); chromaticity, not GrabCut's RGB models, because the
                # object's own continuation past its last SfM point is often its shaded side
                # (measured: the aircraft's belly, which the RGB models give the apron)
                ext = keep & ~crop
                keep[ext] = chroma_vote(v.get_image()[box[0]:box[1], box[2]:box[3]], res,
                                        ~(res | keep), ext, j)
            if floor.cfg.keep_discs:
                # past the silhouette: what joins the object, or regions of at least the
                # plane check's min_region (no specks on the floor)
                lab, n = ndimage.label(res | keep, np.ones((3, 3), bool))
                hit = np.bincount(lab.ravel(), minlength=n + 1) >= floor.cfg.min_region
                hit[np.unique(lab[res])] = True
                hit[0] = False
                keep &= hit[lab] | crop  # inside the silhouette as without keep_discs
            res = res | keep
        res = fill_small_holes(res, cfg.hole_max_fraction)
        if floor is not None and floor.cfg.pixel_votes:
            res = _drop_pixel_floor(res, floor.pixel_floor.get((j, tuple(box))), fl_full,
                                    v.get_image()[box[0]:box[1], box[2]:box[3]], j,
                                    fg_seed & ~bg_seed, floor.cfg.min_region,
                                    floor.cfg.pixel_reach, floor.cfg.pixel_reach_density,
                                    floor.cfg.pixel_reach_ground)
        a0, a1 = ref_area, res.sum()
        if abs(a1 - a0) > cfg.max_area_change * a0:
            rejected += 1
            out[v.key] = fallback
            continue
        full = np.zeros_like(m)
        full[box[0]:box[1], box[2]:box[3]] = res
        out[v.key] = full
        refined += 1
    if stats is not None:
        stats["band_widened"] = int(widened)
        stats["seeds_thinned"] = int(thinned)
    return out, refined, rejected


def _drop_border_leaks(res: np.ndarray, crop: np.ndarray, m: np.ndarray, box: tuple
                       ) -> np.ndarray:
    """``res`` (a crop's GrabCut result) without the regions it grew past the silhouette
    ``crop`` that reach an image side the view's silhouette ``m`` does not reach."""
    return res & ~_border_grown(res, crop, m, box)


def _border_grown(res: np.ndarray, crop: np.ndarray, m: np.ndarray, box: tuple
                  ) -> np.ndarray:
    """The regions of ``res`` grown past the silhouette ``crop`` (both in the crop
    ``box`` of the view) that reach an image side the view's silhouette ``m`` does not."""
    grown = res & ~crop
    if not grown.any():
        return np.zeros_like(res)
    H, W = m.shape
    edge = np.zeros_like(res)
    if box[0] == 0 and not m[0].any():
        edge[0] = True
    if box[1] == H and not m[H - 1].any():
        edge[-1] = True
    if box[2] == 0 and not m[:, 0].any():
        edge[:, 0] = True
    if box[3] == W and not m[:, W - 1].any():
        edge[:, -1] = True
    if not (edge & grown).any():
        return np.zeros_like(res)
    lab, _ = ndimage.label(grown, np.ones((3, 3), bool))
    hit = np.unique(lab[edge & grown])
    return np.isin(lab, hit[hit > 0])


def _drop_pixel_floor(res: np.ndarray, pixel: Optional[np.ndarray], ground: np.ndarray,
                      img: np.ndarray, seed: int, sure: np.ndarray,
                      min_region: int = 1, reach: int = 0, density: float = 0.0,
                      reach_ground: float = 0.5) -> np.ndarray:
    """``res`` without the pixels the per-pixel plane votes call floor (``pixel_votes``)
    whose chromaticity also votes ground: k-NN against the rest of ``res`` and the floor the
    plane check found outside it (the crop's background when that is under 50 px). The
    sure-object seeds (``sure``, where OOI points project) stay, and so do removals smaller
    than ``min_region`` px that do not touch the mask's outside: specks inside the object
    (on the real bonsai they fell on the pot, the stand and the crown, session 15).
    ``reach`` / ``density``: the pixels near the votes are tested too; such a pixel (one that
    did not vote itself) leaves only when more than ``reach_ground`` of its neighbours in
    chromaticity are ground pixels."""
    if pixel is None or not pixel.any():
        return res
    if pixel.shape != res.shape:
        import cv2
        pixel = cv2.resize(pixel.astype(np.uint8), (res.shape[1], res.shape[0]),
                           interpolation=cv2.INTER_NEAREST).astype(bool)
        sure = cv2.resize(sure.astype(np.uint8), (res.shape[1], res.shape[0]),
                          interpolation=cv2.INTER_NEAREST).astype(bool)
    near = pixel
    if reach > 0:
        near = ndimage.binary_dilation(pixel, np.ones((2 * reach + 1,) * 2, bool))
        if density > 0:  # only where the votes are dense (lawn), not lone specks
            side = 2 * (reach + 1) + 1
            dense = ndimage.uniform_filter(pixel.astype(np.float32), side, mode="constant")
            near = pixel | (near & (dense >= density))
    cand = near & res & ~sure
    if not cand.any():
        return res
    bg = (ground | pixel) & ~res
    out = res.copy()
    share = chroma_vote(img, res & ~cand, bg if bg.sum() >= 50 else ~res, cand, seed,
                        share=True)
    out[cand] = np.where(pixel[cand], share > 0.5, share >= 1.0 - reach_ground)
    gone = res & ~out
    if min_region > 1 and gone.any():
        lab, n = ndimage.label(gone, np.ones((3, 3), bool))
        size = np.bincount(lab.ravel(), minlength=n + 1)
        outside = ndimage.binary_dilation(~res, np.ones((3, 3), bool), border_value=1)
        touches = np.zeros(n + 1, bool)
        touches[np.unique(lab[gone & outside])] = True
        back = (size < min_region) & ~touches
        back[0] = False
        out |= back[lab]
    return out


def chroma_vote(img: np.ndarray, obj: np.ndarray, bg: np.ndarray, test: np.ndarray,
                seed: int, n: int = 3000, k: int = 7, share: bool = False) -> np.ndarray:
    """Bool [m] for the ``test`` pixels of ``img`` (row-major order): whether most of their
    ``k`` nearest neighbours in chromaticity ((r, g) / (r + g + b), blind to shading) among
    up to ``n`` sampled ``obj`` pixels and ``n`` sampled ``bg`` pixels are object pixels
    (a k-NN vote; the samples are drawn with ``seed``). All False when a side is empty.
    ``share``: float [m], the object share of the neighbours instead (0 when a side is empty)."""
    from scipy.spatial import cKDTree
    im = img.astype(np.float32)
    ch = im[..., :2] / np.maximum(im.sum(-1, keepdims=True), 1.0)
    rng = np.random.default_rng(seed)
    fo, fb = ch[obj], ch[bg]
    if len(fo) == 0 or len(fb) == 0:
        return np.zeros(int(test.sum()), float if share else bool)
    fo = fo[rng.choice(len(fo), min(n, len(fo)), replace=False)]
    fb = fb[rng.choice(len(fb), min(n, len(fb)), replace=False)]
    lab = np.r_[np.ones(len(fo)), np.zeros(len(fb))]
    _, idx = cKDTree(np.vstack([fo, fb])).query(ch[test], k=k)
    votes = lab[idx].mean(axis=1)
    return votes if share else votes > 0.5


def edge_matte(img: np.ndarray, mask: np.ndarray, window: int, alpha: float = 0.5
               ) -> np.ndarray:
    """``mask`` grown by the pixels of its 1-px outer ring that look more like the object.

    An image's outline pixels mix object and background colour (anti-aliasing, lens blur); a
    pixel at least half covered by the object is object (the usual truth convention). For a
    ring pixel, the colour it would have if it were object (background) is estimated as the
    mean of the mask's interior (the background beyond the ring) within ``window`` px; the
    pixel joins the mask when its colour is nearer the object's mean -- the coverage > 0.5 test
    of a two-colour mix (``alpha``: the coverage threshold; with the pixel's colour c and the
    means F and B, coverage = (c - B).(F - B) / |F - B|^2). Only growth: GrabCut's result (a
    graph cut on reduced crops, then an opening) lies inside the true outline more often than
    outside it (measured).
    """
    if window <= 1 or not mask.any():
        return mask
    import cv2

    def box_mean(x: np.ndarray) -> np.ndarray:  # ndimage.uniform_filter(x, window,
        # mode="constant") within float32 rounding, several times faster
        return cv2.boxFilter(x, -1, (window, window), borderType=cv2.BORDER_CONSTANT)

    st = np.ones((3, 3), bool)
    inner = ndimage.binary_erosion(mask, st, border_value=1)
    grown = ndimage.binary_dilation(mask, st)
    ring = grown & ~mask
    outer = ~grown
    im = img.astype(np.float32)
    fi, fo = inner.astype(np.float32), outer.astype(np.float32)
    nf = box_mean(fi)
    nb = box_mean(fo)
    ok = ring & (nf > 1e-6) & (nb > 1e-6)
    if not ok.any():
        return mask
    dF = np.zeros(mask.shape, np.float32)
    dG = np.zeros(mask.shape, np.float32)
    dFG = np.zeros(mask.shape, np.float32)
    for c in range(im.shape[2]):
        F = box_mean(im[..., c] * fi)
        F /= np.maximum(nf, 1e-6)
        G = box_mean(im[..., c] * fo)
        G /= np.maximum(nb, 1e-6)
        dF += (im[..., c] - F) ** 2
        dG += (im[..., c] - G) ** 2
        dFG += (F - G) ** 2
    # coverage >= alpha  <=>  |c-F|^2 - |c-B|^2 <= (1 - 2 alpha) |F-B|^2 (0.5: nearer F)
    return mask | (ok & (dF - dG <= (1.0 - 2.0 * float(alpha)) * dFG))


def gmm_log_likelihood(model: np.ndarray, x: np.ndarray) -> np.ndarray:
    """log p(x) [N] of colours ``x`` [N, 3] under one of GrabCut's colour models.

    ``model`` is OpenCV's [1, 13 K] array (K = 5): the K weights, the K means [K, 3], the K
    covariances [K, 3, 3], in the colour order GrabCut was given (BGR here). Components of
    zero weight are skipped; a singular covariance gets the small diagonal OpenCV itself adds.
    """
    a = np.asarray(model, float).ravel()
    k = len(a) // 13
    w, mu, cov = a[:k], a[k:4 * k].reshape(k, 3), a[4 * k:13 * k].reshape(k, 3, 3)
    x = np.asarray(x, float).reshape(-1, 3)
    out = np.full(len(x), -np.inf)
    for i in range(k):
        if w[i] <= 0:
            continue
        c = cov[i]
        sign, logdet = np.linalg.slogdet(c)
        if sign <= 0 or not np.isfinite(logdet):
            c = c + 0.01 * np.eye(3)
            sign, logdet = np.linalg.slogdet(c)
        d = x - mu[i]
        maha = np.einsum("ni,ij,nj->n", d, np.linalg.inv(c), d)
        out = np.logaddexp(out, np.log(w[i]) - 0.5 * (logdet + maha + 3 * np.log(2 * np.pi)))
    return out


def _hull_interval(photo: PlaneConsistency, i: int, hull_xyz, vs: float,
                   ys: np.ndarray, xs: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(zmin, zmax, good) [k]: the depths along the rays of pixels (ys, xs) of view ``i``
    between which they cross the hull (voxel centres ``hull_xyz`` [N, 3] or a ``PointSet``
    of them, edge ``vs``); ``good`` where a ray meets it."""
    v = photo.views[i]
    c = v.camera
    cells = hull_xyz if isinstance(hull_xyz, PointSet) else PointSet(
        hull_xyz, np.ones(len(hull_xyz), bool))
    u, w, z = cells.project(c, v.pose)
    with np.errstate(invalid="ignore"):
        ok = (z > 1e-9) & (u > -0.5) & (u < c.width - 0.5) & (w > -0.5) & (w < c.height - 0.5)
    zo = z[ok].astype(float)
    r = int(np.ceil(0.5 * vs * c.fx / max(float(np.median(zo)) if len(zo) else 1.0, 1e-9)))
    half = max(r, 1)  # voxel centres leave gaps of up to a voxel's footprint
    # the interval is needed at (ys, xs) only: a box round them that holds their windows
    y0, y1 = max(int(ys.min()) - half, 0), min(int(ys.max()) + half + 1, c.height)
    x0, x1 = max(int(xs.min()) - half, 0), min(int(xs.max()) + half + 1, c.width)
    ui = np.rint(u[ok]).astype(np.int64) - x0
    vi = np.rint(w[ok]).astype(np.int64) - y0
    inb = (ui >= 0) & (ui < x1 - x0) & (vi >= 0) & (vi < y1 - y0)
    bw = x1 - x0
    zmin = np.full((y1 - y0) * bw, np.inf)
    zmax = np.full((y1 - y0) * bw, -np.inf)
    idx = vi[inb] * bw + ui[inb]
    np.minimum.at(zmin, idx, zo[inb])
    np.maximum.at(zmax, idx, zo[inb])
    size = 2 * half + 1
    zmin = ndimage.grey_erosion(zmin.reshape(y1 - y0, bw), size=size)[ys - y0, xs - x0]
    zmax = ndimage.grey_dilation(zmax.reshape(y1 - y0, bw), size=size)[ys - y0, xs - x0]
    return zmin, zmax, np.isfinite(zmin) & np.isfinite(zmax)


def _neighbour_agreement(photo: PlaneConsistency, i: int, ys: np.ndarray, xs: np.ndarray,
                         zk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(agree, seen) [k]: how many of view ``i``'s plane-check neighbours see the point at
    depth ``zk`` along the ray of pixel (ys, xs), and how many of those repeat its colour
    (mean absolute difference under ``max_diff``)."""
    v = photo.views[i]
    d = photo._rays(i)[ys, xs]  # camera-frame rays, z = 1
    own = photo._image(i)[ys, xs]
    tol = float(photo.cfg.max_diff)
    X = v.pose.t + (d * zk[:, None]) @ v.pose.R.T
    agree = np.zeros(len(ys), np.int32)
    seen = np.zeros(len(ys), np.int32)
    hit = np.ones(len(ys), bool)
    for j in photo.nbrs[i]:
        col, valid = photo.sample(int(j), X, hit, (len(ys), 1))
        diff = np.abs(col.reshape(-1, 3) - own).mean(1)
        agree += valid.ravel() & (diff < tol)
        seen += valid.ravel()
    return agree, seen


def _photo_consistent(photo: PlaneConsistency, i: int, hull_xyz, vs: float,
                      ys: np.ndarray, xs: np.ndarray, n_depths: int,
                      min_nbrs: int = 1, distinct: int = 0) -> np.ndarray:
    """Bool [k]: pixels (ys, xs) of view ``i`` whose colour ``min_nbrs`` neighbour views
    repeat at a depth inside the hull's interval along their ray (``hull_photo``); with
    ``distinct`` > 0 also refuted (fewer than ``min_nbrs`` of at least ``min_nbrs`` neighbours
    seeing the point repeat the colour) at ``distinct`` of the depths ``OFF_HULL`` off that
    interval (a pixel consistent all along its ray is textureless background, not evidence).
    ``hull_xyz``: the hull's voxel centres [N, 3], or a ``PointSet`` of them (built once when
    many views are tested)."""
    out = np.zeros(len(ys), bool)
    if not len(ys):
        return out
    zmin, zmax, good = _hull_interval(photo, i, hull_xyz, vs, ys, xs)
    if not good.any() or len(photo.nbrs[i]) == 0:
        return ~good | out  # no interval / no neighbour: no evidence against the pixel

    def consistent(sub: np.ndarray, zk: np.ndarray, refuted: bool = False) -> np.ndarray:
        """The test at depths ``zk`` of the pixels ``sub`` (indices into ys, xs)."""
        agree, seen = _neighbour_agreement(photo, i, ys[sub], xs[sub], zk)
        if refuted:  # too few neighbours see the point to refute it: not refuted
            return (agree < int(min_nbrs)) & (seen >= int(min_nbrs))
        return agree >= int(min_nbrs)

    for k in range(n_depths):  # a pixel found consistent is not tested again
        sub = np.flatnonzero(good & ~out)
        if not len(sub):
            break
        out[sub] = consistent(sub, zmin[sub] + (k + 0.5) / n_depths * (zmax[sub] - zmin[sub]))
    if distinct and out.any():
        sub = np.flatnonzero(out)  # depths off the interval the neighbours refute
        refuted = np.zeros(len(sub), np.int32)
        for near, f in OFF_HULL:
            refuted += consistent(sub, (zmin[sub] if near else zmax[sub]) * f, True)
        out[sub] = refuted >= int(distinct)
    return out | ~good


def _photo_behind(photo: PlaneConsistency, i: int, hull_xyz, vs: float, ys: np.ndarray,
                  xs: np.ndarray, margin: int, max_in: int, step_px: float = 4.0
                  ) -> np.ndarray:
    """Bool [k]: pixels (ys, xs) of view ``i`` that the neighbours place past the object.

    Per pixel, the most neighbours that repeat its colour at one depth inside the hull's
    interval along its ray, and at one depth beyond it (``BEHIND_RANGE`` x the interval's far
    end): a pixel is past the object where the best depth beyond beats the best inside by at
    least ``margin`` neighbours and at most ``max_in`` agree inside -- a winner-take-all depth
    vote between "on the object" and "behind it". Depths are even steps of inverse depth, as
    many as make the point move by at most ``step_px`` pixels per step in the farthest
    neighbour (the colours are compared pixel by pixel: a much coarser sweep steps over the
    object's own surface -- a fixed 8 depths lost the aircraft recall; nearer neighbours move
    less per step), at least 4 and at most ``BEHIND_MAX_DEPTHS`` per sweep. A uniform surface
    repeats its colour at every depth (no margin: no verdict); a ray that misses the hull, or a
    view without neighbours, gives no verdict (False)."""
    out = np.zeros(len(ys), bool)
    if not len(ys) or len(photo.nbrs[i]) == 0:
        return out
    zmin, zmax, good = _hull_interval(photo, i, hull_xyz, vs, ys, xs)
    sub = np.flatnonzero(good & (zmin > 0))
    if not len(sub):
        return out
    v = photo.views[i]
    # the parallax (px) between inverse depths w1, w2 in a neighbour at baseline b is about
    # f * b * |w1 - w2|
    px = float(max(v.camera.fx, v.camera.fy)) * max(
        float(np.linalg.norm(photo.views[int(j)].pose.t - v.pose.t)) for j in photo.nbrs[i])

    def sweep(live: np.ndarray, w0: np.ndarray, w1: np.ndarray, best: np.ndarray,
              cap: np.ndarray) -> np.ndarray:
        """Raise ``best[live]`` to the most agreeing neighbours at inverse depths from ``w0``
        to ``w1``; a pixel leaves the sweep once ``best`` passes its ``cap`` (its verdict can
        no longer change). The pixels left."""
        n = int(np.clip(np.ceil(px * float(np.abs(w0[live] - w1[live]).max()) / step_px),
                        4, BEHIND_MAX_DEPTHS))
        for k in _coarse_to_fine(n):  # a pixel finds its depth early and leaves the sweep
            if not len(live):
                break
            t = (k + 0.5) / n
            zk = 1.0 / ((1.0 - t) * w0[live] + t * w1[live])
            best[live] = np.maximum(best[live], _neighbour_agreement(
                photo, i, y[live], x[live], zk)[0])
            live = live[best[live] <= cap[live]]
        return live

    y, x = ys[sub], xs[sub]
    wlo, whi = 1.0 / zmin[sub], 1.0 / zmax[sub]
    best_in = np.zeros(len(sub), np.int32)
    live = sweep(np.arange(len(sub)), wlo, whi, best_in, np.full(len(sub), int(max_in)))
    if not len(live):
        return out
    best_off = np.zeros(len(sub), np.int32)  # done once it wins by the margin
    sweep(live, whi / BEHIND_RANGE[0], whi / BEHIND_RANGE[1], best_off,
          best_in + int(margin) - 1)
    out[sub] = (best_in <= int(max_in)) & (best_off - best_in >= int(margin))
    return out


# hull_thin_distinct: the depths off the hull's interval along a ray that it tests, as
# (from the interval's near end, else its far end; factor). Parallax to the neighbours grows
# with 1/z, so ratios of depth move a point by a similar number of pixels at any scene scale
OFF_HULL = ((True, 0.8), (False, 1.25), (False, 1.6), (False, 2.0))


def _coarse_to_fine(n: int) -> np.ndarray:
    """0..n-1 in van der Corput order (0, n/2, n/4, 3n/4, ...): every prefix of it spreads
    over the whole range."""
    bits = max(int(np.ceil(np.log2(max(n, 1)))), 1)
    r = np.array([int(format(k, f"0{bits}b")[::-1], 2) for k in range(1 << bits)])
    return r[r < n]


# behind_cut: where background past the object is looked for, as factors of the hull's far
# end along the ray (ratios, as OFF_HULL), and the most depths one sweep tests
BEHIND_RANGE = (1.1, 8.0)
BEHIND_MAX_DEPTHS = 128


def _loose_hull(masks: dict, views: list[View], models: dict, silhouettes: dict, hull: dict,
                grid: np.ndarray, extra: np.ndarray, radius: float, params: dict) -> dict:
    """{key: re-projection of the looser hull (``hull`` plus the voxels ``extra``)} for the
    views where a pixel lies outside both the silhouette and ``hull`` (the only pixels
    ``hull_cut_grown`` can cut), exact on those pixels: each view splats only the extra
    voxels whose disc can reach one of them (the others cannot change the cut)."""
    cfg = MaskConfig(closing_kernel=1)
    cells = PointSet(grid[extra], np.ones(int(extra.sum()), bool)) if extra.any() else None
    out, n_views, n_vox = {}, 0, 0
    for v in views:
        k = v.key
        if k not in models or k not in masks or k not in silhouettes:
            continue
        cand = masks[k] & ~hull[k] & ~silhouettes[k]
        if not cand.any():
            continue
        n_views += 1
        out[k] = hull[k]
        if cells is None:
            continue
        c = v.camera
        u, w, z = cells.project(c, v.pose)
        ok = (z > 1e-9) & np.isfinite(u) & np.isfinite(w)
        if not ok.any():
            continue
        rpx = np.clip(radius * float(c.fx) / z[ok], 0.5, cfg.max_splat_px)
        reach = int(np.ceil(float(rpx.max()))) + 1
        near = ndimage.binary_dilation(np.pad(cand, reach),
                                       np.ones((2 * reach + 1, 2 * reach + 1), bool))
        # clipped first: a voxel just in front of the camera projects to a huge coordinate,
        # whose int cast is undefined (numpy warned 'invalid value encountered in cast')
        ui = np.rint(np.clip(u[ok], -reach - 1, near.shape[1])).astype(np.int64) + reach
        vi = np.rint(np.clip(w[ok], -reach - 1, near.shape[0])).astype(np.int64) + reach
        inb = (ui >= 0) & (ui < near.shape[1]) & (vi >= 0) & (vi < near.shape[0])
        idx = np.nonzero(ok)[0][inb]
        idx = idx[near[vi[inb], ui[inb]]]
        if len(idx):
            n_vox += len(idx)
            sel = np.nonzero(extra)[0][idx]
            out[k] = hull[k] | point_masks(grid[sel], np.full(len(sel), radius), [v], cfg)[k]
    params.update({"cut_views": n_views, "cut_extra_voxels": int(extra.sum()),
                   "cut_splatted_voxels": n_vox})
    return out


def hull_additions(masks: dict[str, np.ndarray], views: list[View], xyz: np.ndarray,
                   models: dict, cfg: RefineConfig, photo: Optional[PlaneConsistency] = None,
                   silhouettes: Optional[dict] = None,
                   free_obs: Optional[list] = None) -> tuple[dict, dict]:
    """Masks grown by the pixels the other views' masks and this view's colours agree on.

    A voxel grid covers the OOI points' box (padded by 15% of its longest side, as the hull
    options in ``masks``); its voxel edge is ``hull_voxel_px`` pixels' footprint at the OOI
    points' median depth (median over the views), coarsened to at most ``hull_max_voxels``.
    A voxel is in the hull when more than ``hull_agree`` of the views that frame it hold it
    in their mask. Each view's new pixels are those the hull's re-projection covers, outside
    the mask, not called background by the plane check, whose colour GrabCut's object model
    of that view explains better than its background model. Pixels are only added: a part
    one view missed (no SfM point, GrabCut's smoothness cut it off) is brought back from the
    views that found it; the hull alone is fat around thin parts (the colour test decides).
    With ``hull_connected`` only the added pixels connected to the mask through other added
    pixels stay (single specks of an object-like colour in the floor's texture do not).
    Views without colour models (GrabCut not run) are left as they are. ``hull_cut`` also
    removes from those views' masks the pixels whose rays miss the hull; ``hull_cut_grown``
    (with the splatted ``silhouettes``) only those outside the silhouette whose rays miss
    the hull of ``hull_cut_agree`` (a looser hull: what few views hold). With ``hull_free``
    and ``free_obs`` (``_obs_depths`` of ``views``), the voxels that at least ``hull_free``
    views saw past (an observed feature more than ``hull_free_margin`` voxels beyond) leave
    every hull.
    """
    import cv2  # noqa: F401 -- the refinement's dependency; models come from cv2.grabCut
    keys = [v.key for v in views if v.key in masks]
    params: dict = {"voxels": 0, "added_px": 0}
    if len(xyz) < 4 or not keys:
        return masks, params
    depth_px = []
    for v in views:
        if v.key not in masks:
            continue
        _, z = project_distorted(xyz, v.camera, v.pose)
        z = z[z > 1e-9]
        if len(z):
            depth_px.append(float(np.median(z)) / float(v.camera.fx))
    if not depth_px:
        return masks, params
    lo, hi = xyz.min(0), xyz.max(0)
    pad = 0.15 * float((hi - lo).max())
    lo, hi = lo - pad, hi + pad
    vs = max(float(cfg.hull_voxel_px) * float(np.median(depth_px)), 1e-12)
    n_vox = np.prod(np.ceil((hi - lo) / vs))
    if n_vox > cfg.hull_max_voxels:
        vs *= float((n_vox / cfg.hull_max_voxels) ** (1.0 / 3.0))
    axes = [np.arange(lo[i] + vs / 2, hi[i], vs) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    seen = np.zeros(len(grid), np.int32)
    inside = np.zeros(len(grid), np.int32)
    # the grid (up to hull_max_voxels centres) is projected into every view: in float32
    # offsets from its centre, ~2-3x faster than float64 and the same pixel but where a
    # centre falls within ~1e-4 px of a pixel border
    cells = PointSet(grid, np.ones(len(grid), bool))
    carve = int(cfg.hull_free) > 0 and free_obs is not None
    free = np.zeros(len(grid), np.int32) if carve else None
    for j, v in enumerate(views):
        if v.key not in masks:
            continue
        c = v.camera
        u, w, z = cells.project(c, v.pose)
        ui, vi = np.rint(u), np.rint(w)
        ok = (z > 1e-9) & (ui >= 0) & (ui < c.width) & (vi >= 0) & (vi < c.height)
        seen += ok
        iu, iv = ui[ok].astype(int), vi[ok].astype(int)
        inside[ok] += masks[v.key][iv, iu]
        if carve:
            d = _seen_depth(free_obs[j], c.height, c.width, int(cfg.hull_free_dilate))
            free[ok] += d[iv, iu] > z[ok] + float(cfg.hull_free_margin) * vs
    solid = free < int(cfg.hull_free) if carve else np.ones(len(grid), bool)
    if carve:
        params["free_voxels"] = int(((seen > 0) & (inside > float(cfg.hull_cut_agree) * seen)
                                     & ~solid).sum())
    seen = np.where(solid, seen, 0)  # carved voxels are in no hull below
    keep = (seen > 0) & (inside > float(cfg.hull_agree) * seen)
    params.update({"voxel_size": vs, "voxels": int(keep.sum()), "grid": int(len(grid))})
    if not keep.any():
        return masks, params
    hull = point_masks(grid[keep], np.full(int(keep.sum()), 0.5 * vs),
                       [v for v in views if v.key in models], MaskConfig(closing_kernel=1))
    thin = {}  # hull_thin_agree: {key: re-projection of the voxels only the looser hull holds}
    if 0.0 < float(cfg.hull_thin_agree) < float(cfg.hull_agree):
        extra = (seen > 0) & (inside > float(cfg.hull_thin_agree) * seen) & ~keep
        params["thin_voxels"] = int(extra.sum())
        thin_xyz = PointSet(grid[keep | extra], np.ones(int((keep | extra).sum()), bool))
        if extra.any():
            thin = point_masks(grid[extra], np.full(int(extra.sum()), 0.5 * vs),
                               [v for v in views if v.key in models],
                               MaskConfig(closing_kernel=1))
    loose = {}  # hull_cut_grown: {key: the looser hull's re-projection} where it is needed
    if cfg.hull_cut_grown and silhouettes is not None:
        loose = _loose_hull(masks, views, models, silhouettes, hull, grid,
                            (seen > 0) & (inside > float(cfg.hull_cut_agree) * seen) & ~keep,
                            0.5 * vs, params)
    out = dict(masks)
    added = 0
    cut = 0
    border_cut = 0
    thin_added = 0
    graph_views = 0
    blended = False
    if (cfg.hull_graph == "compressed" and cfg.blend_detect
            and not all(v.compressed for v in views if v.key in models)):
        sharp = capture_chroma_sharpness([v for v in views if v.key in models])
        blended = sharp is not None and sharp < float(cfg.blend_max)
        params["chroma_sharpness"] = sharp
    params["blended"] = blended
    hull_xyz = grid[keep]
    index = {v.key: i for i, v in enumerate(views)}
    behind_xyz = thin_xyz if thin else PointSet(hull_xyz, np.ones(len(hull_xyz), bool))
    for v in views:
        if v.key not in models or v.key not in masks:
            continue
        bgd, fgd, sure_bg = models[v.key]
        m = masks[v.key]
        if cfg.hull_cut:
            m = m & hull[v.key]
            out[v.key] = m
        elif v.key in loose:
            drop = m & ~loose[v.key] & ~silhouettes[v.key]
            if drop.any():
                m = m & ~drop
                out[v.key] = m
                cut += int(drop.sum())
        if cfg.border_leak_hull and silhouettes is not None and v.key in silhouettes:
            s = silhouettes[v.key]
            drop = _border_grown(m, s, s, (0, m.shape[0], 0, m.shape[1])) & ~hull[v.key]
            if drop.any():
                m = m & ~drop
                out[v.key] = m
                border_cut += int(drop.sum())
        reach = hull[v.key] | thin[v.key] if v.key in thin else hull[v.key]
        cand = reach & ~m & ~sure_bg
        if not cand.any():
            continue
        col = v.get_image()[cand][:, ::-1].astype(float)  # BGR, as GrabCut saw it
        obj = gmm_log_likelihood(fgd, col) > gmm_log_likelihood(bgd, col)
        if obj.any() and (cfg.hull_graph == "on"
                          or (cfg.hull_graph == "compressed" and (v.compressed or blended))):
            obj &= _graph_verdict(v.get_image(), m, cand, bgd, fgd,
                                  float(cfg.hull_graph_thin_px))
            graph_views += 1
        if cfg.hull_photo and photo is not None and obj.any():
            ys, xs = np.nonzero(cand)
            sel = np.nonzero(obj)[0]
            obj[sel] = _photo_consistent(photo, index[v.key], hull_xyz, vs, ys[sel], xs[sel],
                                         max(1, int(cfg.hull_photo_depths)))
        if v.key in thin and photo is not None and obj.any():
            # from the looser hull only what two neighbour views repeat at one depth
            ys, xs = np.nonzero(cand)
            sel = np.nonzero(obj & ~hull[v.key][cand])[0]
            if len(sel):
                obj[sel] = _photo_consistent(photo, index[v.key], thin_xyz, vs, ys[sel],
                                             xs[sel], max(1, int(cfg.hull_photo_depths)), 2,
                                             int(cfg.hull_thin_distinct))
        if obj.any():
            grown = m.copy()
            grown[cand] = obj
            if cfg.hull_connected:
                lab, n = ndimage.label(grown, np.ones((3, 3), bool))
                hit = np.zeros(n + 1, bool)
                hit[np.unique(lab[m])] = True
                hit[0] = False
                grown = hit[lab]
                obj = grown[cand]
            if v.key in thin:
                thin_added += int((grown & ~m & ~hull[v.key]).sum())
            out[v.key] = grown
            added += int(obj.sum())
    behind_cut = 0
    for v in views if cfg.behind_cut != "off" and photo is not None else []:
        # behind_cut, on the grown masks (an addition placed behind the object goes too)
        if v.key not in models or v.key not in out:
            continue
        m = out[v.key]
        if cfg.behind_cut == "mask":
            test = m
        elif silhouettes is not None and v.key in silhouettes:  # "grown"
            test = m & ~silhouettes[v.key]
        else:
            continue
        ys, xs = np.nonzero(test)
        if not len(ys):
            continue
        far = _photo_behind(photo, index[v.key], behind_xyz, vs, ys, xs,
                            int(cfg.behind_margin), int(cfg.behind_max_in),
                            float(cfg.behind_step_px))
        if not far.any():
            continue
        refuted = np.zeros_like(m)
        refuted[ys[far], xs[far]] = True
        if cfg.behind_open:  # no lone pixels or 1-px lines (a striped surface's aliases)
            refuted = ndimage.binary_opening(refuted, np.ones((2, 2), bool))
        out[v.key] = m & ~refuted
        behind_cut += int(refuted.sum())
    params["added_px"] = added
    params["cut_px"] = cut
    params["border_cut_px"] = border_cut
    params["behind_cut_px"] = behind_cut
    if thin:
        params["thin_added_px"] = thin_added
    params["graph_views"] = graph_views
    return out, params


def chroma_sharpness(rgb: np.ndarray) -> Optional[float]:
    """How sharp an image's colour is next to its brightness: the ratio of high- to
    low-frequency gradient energy (mean |2nd difference| / mean |1st difference|, both axes)
    of the chroma channels (Cb, Cr; averaged) over the same ratio of the luma channel.

    Full-resolution colour changes where brightness changes and measures ~1 (the simulator's
    renders >= 1.04 on all 3,000 lossless views); colour stored at half resolution (JPEG's and
    video's 4:2:0 chroma, upsampled on decoding) is smoother than the luma: 0.6-0.8 on the
    same renders through JPEG. It measures colour blurred wider than brightness whatever the
    cause: the bonsai's JPEG photos give a median of 0.95 at 800x533 (made by downsizing
    larger photos) and 0.71 resized to half. None when the image is too small or has (almost)
    no colour gradients to measure (a grey image).
    """
    if rgb is None or rgb.ndim != 3 or rgb.shape[2] < 3 or min(rgb.shape[:2]) < 16:
        return None
    x = rgb[..., :3].astype(np.float32)
    y = x @ np.array([0.299, 0.587, 0.114], np.float32)
    cb = x @ np.array([-0.168736, -0.331264, 0.5], np.float32)
    cr = x @ np.array([0.5, -0.418688, -0.081312], np.float32)

    def ratio(c: np.ndarray) -> Optional[float]:
        d1 = np.abs(np.diff(c, axis=0)).mean() + np.abs(np.diff(c, axis=1)).mean()
        d2 = np.abs(np.diff(c, 2, axis=0)).mean() + np.abs(np.diff(c, 2, axis=1)).mean()
        return float(d2 / d1) if d1 > 0.05 else None  # under 1/20 grey level per pixel: flat

    ry = ratio(y)
    rc = [r for r in (ratio(cb), ratio(cr)) if r is not None]
    if ry is None or not rc:
        return None
    return float(np.mean(rc) / ry)


def capture_chroma_sharpness(views: list[View], max_views: int = 15) -> Optional[float]:
    """Median ``chroma_sharpness`` over up to ``max_views`` views spread over ``views`` (one
    capture comes through one camera and one codec; a single view can mislead: 19 of 2,640
    JPEG q90 simulator views measure >= 0.9, while per capture the medians are 0.69-0.81 on
    JPEG and 1.10-1.20 lossless). None when no view measures."""
    if not views:
        return None
    idx = np.unique(np.linspace(0, len(views) - 1, min(len(views), max_views)).astype(int))
    vals = [chroma_sharpness(views[i].get_image()) for i in idx]
    vals = [x for x in vals if x is not None]
    return float(np.median(vals)) if vals else None


def _graph_verdict(rgb: np.ndarray, mask: np.ndarray, cand: np.ndarray, bgd: np.ndarray,
                   fgd: np.ndarray, thin_px: float) -> np.ndarray:
    """[cand.sum()] bool: the candidate pixels a graph cut keeps, or that lie at thin parts.

    One GrabCut iteration with the view's colour models frozen on the crop around mask and
    candidates: mask pixels fixed object, candidates probably-object, the rest fixed
    background. A candidate whose neighbourhood (``thin_px`` px) holds no mask pixel at least
    ``thin_px`` px deep inside the mask is kept whatever the cut says (thin or missed parts).
    """
    import cv2
    ys, xs = np.nonzero(mask | cand)
    h, w = mask.shape
    y0, y1 = max(0, int(ys.min()) - 3), min(h, int(ys.max()) + 4)
    x0, x1 = max(0, int(xs.min()) - 3), min(w, int(xs.max()) + 4)
    lab = np.full((y1 - y0, x1 - x0), cv2.GC_BGD, np.uint8)
    lab[mask[y0:y1, x0:x1]] = cv2.GC_FGD
    lab[cand[y0:y1, x0:x1]] = cv2.GC_PR_FGD
    crop = np.ascontiguousarray(rgb[y0:y1, x0:x1, ::-1])  # BGR, as the models were fitted
    cv2.grabCut(crop, lab, None, bgd.copy(), fgd.copy(), 1, cv2.GC_EVAL_FREEZE_MODEL)
    keep = np.zeros_like(mask)
    keep[y0:y1, x0:x1] = (lab == cv2.GC_FGD) | (lab == cv2.GC_PR_FGD)
    r = max(int(np.ceil(thin_px)), 0)
    depth = ndimage.distance_transform_edt(mask)
    near = ndimage.grey_dilation(depth, footprint=np.ones((2 * r + 1, 2 * r + 1), bool))
    return (keep | (near < thin_px))[cand]


def point_support(xyz: np.ndarray, masks: dict[str, np.ndarray], views: list[View]
                  ) -> np.ndarray:
    """Share [N] of the views that frame each point whose mask contains its projection."""
    inside = np.zeros(len(xyz))
    seen = np.zeros(len(xyz))
    for v in views:
        if v.key not in masks:
            continue
        uv, z = project_distorted(xyz, v.camera, v.pose)
        c = v.camera
        ui, vi = np.rint(uv[:, 0]), np.rint(uv[:, 1])
        ok = (z > 1e-9) & (ui >= 0) & (ui < c.width) & (vi >= 0) & (vi < c.height)
        seen += ok
        inside[ok] += masks[v.key][vi[ok].astype(int), ui[ok].astype(int)]
    return inside / np.maximum(seen, 1)


def refine_masks(masks: dict[str, np.ndarray], views: list[View], ooi: SfmCloud,
                 background: SfmCloud, cfg: RefineConfig, plane: Optional[np.ndarray] = None,
                 target: Optional[np.ndarray] = None, context_masks: Optional[dict] = None,
                 seed_points: Optional[np.ndarray] = None,
                 plane_band: Optional[float] = None) -> tuple[dict, dict]:
    """GrabCut-refined masks {key: bool [H,W]} and counts of refined/rejected views.

    ``seed_points`` (optional, bool [len(ooi)]): with ``fg_seeds="projections"``, only these
    OOI points' projections seed the object (``density.sparse_seeds`` false).

    Only the views with a key in ``masks`` are refined (the result holds just those); the
    other ``views`` are context (neighbours of the plane check). A view's result does not
    depend on which other views are refined.

    ``fg_seeds="consistent"`` runs two passes: the first seeded by the observations; every
    OOI point is then scored by the share of views whose first-pass mask holds its projection,
    and the second pass (from the same splatted silhouettes) is seeded by the projections of
    the points scoring at least ``consistency`` -- many more seeds per view than the few
    features matched there, minus the stray points the views disagree about.

    With ``cfg.plane_check.enabled`` and a support ``plane`` (n.x + d = 0; or [P, 4] planes,
    the support plane first), the pixels that show a plane (``photo.PlaneConsistency``;
    ``target`` = the cameras' convergence point) are sure background.

    ``context_masks`` ({key: mask} of views *not* refined here) join the refined masks in the
    visual hull of ``hull_add`` (masks made earlier stand in for refining those views again).
    """
    if not 0.0 <= float(cfg.edge_alpha) <= 1.0:
        raise ValueError(f"refine.edge_alpha={cfg.edge_alpha}; it is a coverage in [0, 1]")
    if cfg.bridges.enabled:
        check_config(cfg.bridges)
    if not (np.isfinite(float(cfg.band_gaps)) and float(cfg.band_gaps) >= 0.0):
        raise ValueError(f"refine.band_gaps={cfg.band_gaps}; 0 (off) or a number of gaps > 0")
    if not (np.isfinite(float(cfg.seed_colour)) and float(cfg.seed_colour) >= 0.0):
        raise ValueError(f"refine.seed_colour={cfg.seed_colour}; 0 (off) or a factor > 0 of "
                         f"the view's median seed colour distance")
    if not (np.isfinite(float(cfg.seed_cover)) and 0.0 <= float(cfg.seed_cover) <= 1.0):
        raise ValueError(f"refine.seed_cover={cfg.seed_cover}; 0 (off) or a share in (0, 1]")
    if cfg.hull_graph not in ("compressed", "on", "off"):
        raise ValueError(f"refine.hull_graph={cfg.hull_graph!r}; use compressed, on or off")
    if cfg.hull_add and not (0.0 <= float(cfg.hull_agree) < 1.0 and cfg.hull_voxel_px > 0):
        raise ValueError(f"refine.hull_agree={cfg.hull_agree} (a share in [0, 1)) and "
                         f"refine.hull_voxel_px={cfg.hull_voxel_px} (> 0) for hull_add")
    if cfg.hull_add and not 0.0 <= float(cfg.hull_thin_agree) < float(cfg.hull_agree):
        raise ValueError(f"refine.hull_thin_agree={cfg.hull_thin_agree}; 0 (off) or a share "
                         f"below refine.hull_agree={cfg.hull_agree}")
    if not 0 <= int(cfg.hull_thin_distinct) <= len(OFF_HULL):
        raise ValueError(f"refine.hull_thin_distinct={cfg.hull_thin_distinct}; 0 (off) to "
                         f"{len(OFF_HULL)} (the depths off the hull it tests)")
    if cfg.behind_cut not in ("off", "grown", "mask"):
        raise ValueError(f"refine.behind_cut={cfg.behind_cut!r}; use off, grown or mask")
    if cfg.behind_cut != "off" and not (int(cfg.behind_margin) >= 1
                                        and int(cfg.behind_max_in) >= 0
                                        and float(cfg.behind_step_px) > 0):
        raise ValueError(f"refine.behind_margin={cfg.behind_margin} (>= 1 neighbour), "
                         f"refine.behind_max_in={cfg.behind_max_in} (>= 0) and "
                         f"refine.behind_step_px={cfg.behind_step_px} (> 0) for behind_cut")
    if cfg.hull_cut_grown and not 0.0 <= float(cfg.hull_cut_agree) < 1.0:
        raise ValueError(f"refine.hull_cut_agree={cfg.hull_cut_agree}; a share in [0, 1)")
    if cfg.plane_check.behind_window < 0:
        raise ValueError(f"refine.plane_check.behind_window={cfg.plane_check.behind_window}; "
                         f"use a patch side in px (0 = plane_check.window)")
    if int(cfg.enlarged_iterations) < -1:
        raise ValueError(f"refine.enlarged_iterations={cfg.enlarged_iterations}; use -1 (all "
                         f"on the enlarged crop), 0 (one frozen cut) or a count")
    if int(cfg.upsample) < 1:
        raise ValueError(f"refine.upsample={cfg.upsample}; use 1 (GrabCut at the image's size) "
                         f"or more")
    fg_obs = _obs_by_view(ooi, views)
    bg_obs = _obs_by_view(background, views)
    params: dict = {"fg_seeds": cfg.fg_seeds, "upsample": int(cfg.upsample),
                    "enlarged_iterations": int(cfg.enlarged_iterations)}
    floor = None
    if cfg.plane_check.enabled and plane is not None and target is not None:
        pc_cfg = cfg.plane_check
        if pc_cfg.adapt_noise > 0:
            noise = capture_noise(views)
            adapt = noise > pc_cfg.adapt_noise
            params["image_noise"] = {"sigma": round(noise, 3), "adapted": bool(adapt)}
            if adapt:
                pc_cfg = dataclasses.replace(pc_cfg, noise_ncc=True, exposure=True)
        floor = PlaneConsistency(views, np.asarray(plane, float), np.asarray(target, float),
                                 pc_cfg)
        if pc_cfg.exposure_auto and not pc_cfg.exposure:
            # exposure is the view's: measured on every surface the SfM matched, not on the
            # floor patches alone (whose brightness may change with the viewing angle)
            floor.exposures = view_exposures(_obs_ids_by_view([ooi, background], views), views)
            params["exposure_spread"] = round(float(np.ptp(floor.exposures)), 4)
        if cfg.plane_check.behind:
            floor.behind_xyz = background.xyz
        if (cfg.plane_check.behind or cfg.plane_check.shifted or cfg.plane_check.object_keep
                or cfg.plane_check.object_guard):
            floor.ooi_xyz = ooi.xyz
        if cfg.plane_check.tune_support > 0 and plane_band is not None:
            params["tune_support"] = floor.tune_support(masks, float(plane_band))
    cache: dict = {}
    models: Optional[dict] = {} if cfg.hull_add else None
    if cfg.fg_seeds == "observations":
        out, refined, rejected = _grabcut_pass(masks, views, fg_obs, bg_obs, cfg, floor, cache,
                                               models, params)
    elif cfg.fg_seeds in ("projections", "consistent"):
        xyz = ooi.xyz if seed_points is None else ooi.xyz[np.asarray(seed_points, bool)]
        if cfg.fg_seeds == "consistent":
            first, _, _ = _grabcut_pass(masks, views, fg_obs, bg_obs, cfg, floor, cache)
            support = point_support(xyz, first, views)
            xyz = xyz[support >= cfg.consistency]
            params["consistent_points"] = int(len(xyz))
        fg = [_in_frame(project_distorted(xyz, v.camera, v.pose), v) if v.key in masks
              else np.zeros((0, 2), np.float32) for v in views]
        if cfg.seed_colour > 0 and cfg.fg_seeds == "projections":
            rgb = (ooi.rgb if seed_points is None
                   else ooi.rgb[np.asarray(seed_points, bool)]).astype(np.float32)
            fg, dropped = _colour_seeds(xyz, rgb, views, masks, cfg.seed_colour)
            params["seed_colour_dropped"] = dropped
        init = first if cfg.fg_seeds == "consistent" and cfg.second_init == "first" else masks
        out, refined, rejected = _grabcut_pass(init, views, fg, bg_obs, cfg, floor, cache,
                                               models, params)
    else:
        raise ValueError(f"refine.fg_seeds={cfg.fg_seeds!r}; use observations, projections "
                         f"or consistent")
    if cfg.hull_add:
        both = {**(context_masks or {}), **out}
        free_obs = (_obs_depths([ooi, background], views) if int(cfg.hull_free) > 0
                    else None)
        both, params["hull_add"] = hull_additions(both, views, ooi.xyz, models or {}, cfg,
                                                  floor, silhouettes=masks, free_obs=free_obs)
        out = {k: both[k] for k in out}
        params["hull_add"]["context_views"] = len(context_masks or {})
    if cfg.edge_window > 1:
        for v in views:
            if v.key in out:
                out[v.key] = edge_matte(v.get_image(), out[v.key], int(cfg.edge_window),
                                        cfg.edge_alpha)
    if cfg.outline_vote:
        for v in views:
            if v.key in out:
                out[v.key] = outline_vote(out[v.key], v.get_image())
    if cfg.bridges.enabled:
        tot = {"views": 0, "bridges": 0, "added_px": 0}
        for v in views:
            if v.key in out:
                add, st = thin_bridges(v.get_image(), out[v.key], cfg.bridges)
                out[v.key] = out[v.key] | add
                tot["views"] += int(st["bridges"] > 0)
                tot["bridges"] += st["bridges"]
                tot["added_px"] += st["added_px"]
        params["bridges"] = tot
    params.update({"refined": refined, "rejected": rejected})
    if floor is not None:
        params["plane_check_s"] = round(floor.seconds, 3)
        params["planes"] = int(len(floor.planes))
    return out, params
