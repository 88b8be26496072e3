"""Improved-mode signal: which pixels show the support plane (plane-induced photo-consistency).

A pixel that sees the floor (apron, lawn, table top) sees a point *on the support plane*: its
ray meets the plane at that point, and a neighbouring camera sees the same point at the
plane's projection there. Warping a neighbour's image into this view through the plane (the
plane-induced homography, with lens distortion) therefore reproduces the floor's texture
pixel for pixel, while anything *above* the plane (the object) lands displaced by parallax.
A pixel is called floor when, in at least ``rank`` of a few nearby views, the warped patch
around it matches its own patch: normalised cross-correlation above ``min_ncc`` (texture that
lines up; robust to exposure changes) and mean colour difference below ``max_diff``. Plain
patches (no texture to line up) are never called floor, so a grey fuselage whose warped
neighbour is more grey fuselage is not mistaken for a grey apron. Walls and clutter off the
plane are never called floor either: the test says "this is the support plane", nothing else.

``behind`` applies the same patch test to the background seen *beyond* the object (a chair
between a plant's leaves, bushes behind a bicycle), which no plane explains: each pixel takes
the depth of the nearest background SfM point that lies farther than the object in this view
(a piecewise-constant depth, trusted only within ``behind_reach`` of a point). An object
pixel tested at that depth is displaced by a large parallax in the neighbours and does not
match; on the sim tabletop at 256x192 it called 0.002% of object pixels and 11% of the
background just beyond the plant background (the rest: plain wall, or the hypothesis depth
off by more than the patch tolerates). Its depth is rarely what fails (session 6, sim
tabletop): of the background pixels left inside the masks, two thirds had a hypothesis depth
within 2% of the truth, and the true depth would have let the patch test call only 8% of
them; the gaps between leaves are narrower than the 5-px patch, so ``behind_window`` gives
the behind test smaller patches of its own.

``shifted`` reaches the floor right next to the object, where the patch centred on a floor
pixel straddles the outline and never matches: a pixel inside a matching patch shifted by
``shifted_reach`` px is floor when its own colour matches the warp within the view pair's
noise (measured at the matching patches' centres) and better than at the object's depth.
``object_guard`` keeps a patch that matches through the support plane from voting floor where
the object's own depth (the OOI discs covering the whole patch) explains it at least as well:
low on the object, next to the floor, the two warps differ by little parallax (a tyre on
the lawn). ``parallax_guard`` is the same caution where no OOI disc covers the object (a
sparsely seeded pot's smooth foot): a neighbour votes floor at a pixel only where a surface a
little above the plane (a share of the object's radius) would land at least ``parallax_px``
from the plane's warp in it, i.e. where its baseline can tell the two apart at all.
``object_keep`` is the converse, a map of silhouette pixels whose colour the
object's depth (the nearest OOI point's disc over them) explains in the neighbours and the
support plane does not; the refinement keeps them object whatever GrabCut's colour models
say.

Measured against exact masks (sim aircraft / plant, every 6th view, NCC > 0.8, two views):
0.3-0.5% of object pixels but 38-50% of the background within 15 px of the object are called
floor -- the apron between wing and fuselage, the table around a pot, the lawn in a wheel.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy import ndimage

from ..core.geometry import finite_rows
from ..core.types import View
from .masks import project_distorted, undistorted_dirs

# cv2.remap's maps must have fewer rows and columns than SHRT_MAX (32767); longer lists of
# points are sampled as rows of REMAP_ROW
REMAP_MAX = 32767
REMAP_ROW = 4096


@dataclass
class PlaneCheckConfig:
    """Options of the plane-consistency floor test (used by the GrabCut refinement)."""

    enabled: bool = False  # mark pixels consistent with the support plane as background
    neighbours: int = 4  # nearby views compared per view
    min_deg: float = 2.0  # neighbours see the object from at least this angle apart ...
    max_deg: float = 25.0  # ... and at most this (occlusion and lighting change grow with it)
    rank: int = 2  # a pixel is floor when its patch matches in at least this many neighbours
    window: int = 5  # side (px) of the compared patches
    min_ncc: float = 0.8  # patches match: normalised cross-correlation above this ...
    max_diff: float = 15.0  # ... and mean absolute colour difference (0-255) below this
    min_std: float = 2.0  # patches with less grey-level std than this (plain) never match
    min_region: int = 9  # floor regions smaller than this (px) are dropped
    extra_planes: int = 0  # also test up to this many large background planes (walls) that
    # lie clear of the object (sequential RANSAC on the points the stages removed)
    tune_support: int = 0  # shift the support plane along its normal to the nearest peak of
    # the background pixels near the object that match their neighbours: offsets each side,
    # spread over the plane's inlier band (0 = off). The points' least-squares plane can sit
    # a few mm off the surface, and on fine texture a 1-px parallax error fails every patch
    tune_views: int = 8  # tune_support: views it scores (spread over the masked views)
    parallax_guard: float = 0.0  # support plane: a neighbour's matching patch votes floor only
    # where a surface this far above the plane (a share of the OOI points' radius) would be
    # displaced by >= ``parallax_px`` from the plane's warp in it (0 = off). Smooth parts of
    # the object just above its support (a pot's foot) move by less than a pixel between
    # close neighbours and match the plane's warp as well as the floor does. Off: 0.06 lifts
    # the sparsest stool capture (+0.008) but costs the bicycle 0.008 (far lawn) and lets the
    # real bonsai's cloth join (a dense capture's close neighbours; BENCHMARKS, session 65)
    parallax_px: float = 1.0  # parallax_guard: the displacement (px of the compared crop)
    over_seeds: bool = False  # floor pixels override the projected object seeds (an OOI
    # point that projects onto the floor is a floor point the earlier stages kept)
    cache_views: int = 24  # images kept in memory as float
    behind: bool = False  # also test the background *behind* the object (a chair between a
    # plant's leaves, bushes behind a bicycle): each pixel takes the depth of the nearest
    # background SfM point that lies beyond the object in this view, and is background when
    # nearby views agree with it at that depth (the same patch test as the planes)
    behind_rank: int = 2  # behind: matching neighbours needed (an object pixel tested at a
    # depth well beyond the object is displaced by a large parallax, so 1 can be safe)
    behind_reach: float = 0.1  # behind: a pixel takes a background point's depth only within
    # this fraction of the crop's longer side of it
    shifted: bool = False  # support plane: a pixel is also floor when a patch that merely
    # *contains* it (not centred on it) matches and its own colour matches the warp: next to
    # the object's outline the centred patch straddles object and floor and never matches
    shifted_reach: int = 1  # shifted: how far (px) the matching patch's centre may lie from
    # the pixel (at most window // 2; 1 lost fewer object edges than 2)
    pixel_quantile: float = 0.75  # shifted / object_keep: a pixel's own colour "matches" a warp
    # within this quantile of the per-pixel differences at the centres of the matching patches
    # (the view pair's noise and interpolation error, measured, not a constant)
    object_keep: bool = False  # silhouette pixels that the object explains and the support
    # plane does not (in >= rank neighbours, the colour at the depth of the OOI points whose
    # discs cover the pixel matches, the plane's does not) stay object after GrabCut: an object
    # edge as dark as the shadow beside it, which the colour models give to the background
    keep_discs: bool = False  # object_keep: keep the object pixels over the whole of the discs
    # the test sampled (one 4-NN spacing + 1 px), not only those inside the splatted mask
    # (discs of ``masks.splat_scale`` spacings): an object edge just past the last SfM point
    # (a featureless belly) is kept on the same multi-view evidence when its chromaticity
    # also votes object (k-NN against the view's object and background pixels; blind to
    # shading) and it joins the mask (or is >= min_region px)
    pixel_votes: bool = False  # shifted: also count the per-pixel floor vote (own colour
    # matches the plane's warp within the pair's noise, and better than at the depth of the
    # OOI disc covering it) in textured pixels away from any matching patch: ground seen
    # between spokes sits in patches that also hold the object. Weaker evidence than a patch,
    # so such a pixel (``pixel_floor``) leaves the refined mask only when its chromaticity
    # also votes ground (k-NN against the rest of the mask and the floor found outside it).
    # On in ``ours`` since session 23 (with ``pixel_strict``): IoU up on every benchmark
    # capture; it had been off since session 11 because it took the aircraft's recall under
    # 0.97, which the object guard has since made up for (BENCHMARKS.md, session 23)
    pixel_reach: int = 0  # pixel_votes: the chromaticity vote also decides the mask pixels
    # within this many px of a floor-voting pixel (ground between spokes votes in specks).
    # ``ours`` since session 62: 1, with density 0.2 and ground 0.8 (every simulator scene's
    # IoU up, recall -0.001 at most; on the real bonsai mostly the crown's gaps and a cloth
    # patch leave: BENCHMARKS.md, session 62)
    pixel_reach_density: float = 0.0  # pixel_reach: only where at least this share of the
    # (2 * reach + 3)-px window around the pixel voted (dense specks: ground, not a lone vote)
    pixel_reach_ground: float = 0.5  # pixel_reach: a pixel that did not vote itself leaves
    # only when more than this share of its chromaticity neighbours are ground (a margin:
    # a pixel whose colour lies between the object's and the ground's stays)
    pixel_strict: bool = True  # pixel_votes: a pixel votes floor only where the object's
    # depth also fails to explain it (its colour there off by more than the pair's noise),
    # not merely explains it worse: on dark, plain parts of real photos (the bonsai's pot)
    # both hypotheses fit within the noise, and the looser vote made holes there
    object_guard: bool = False  # support plane: a matching patch does not vote floor where
    # the object's depth explains it at least as well: where OOI discs cover the whole patch,
    # the neighbour is also sampled at the discs' depth, and a patch whose NCC there is >= its
    # NCC through the plane stays undecided (low on the object, next to the floor, both warps
    # line up: a tyre on the lawn, a stool's legs). Not applied to walls or the behind test
    exposure: bool = False  # match each neighbour's exposure to this view's before the colour
    # tests (``max_diff``, the per-pixel votes): the gain is the median ratio of the patch
    # means over the patches whose NCC (blind to gain) already matches, one per view pair.
    # Cameras auto-expose; a 10% gain moves a white floor line by 20+ grey levels and fails
    # ``max_diff`` while the grey floor around it passes (demo bag view 32: the line's patches
    # matched in 6-13% of two neighbours, 43-66% with the gain, object pixels 0-1.4%)
    noise_ncc: bool = False  # patch tests that allow for the images' own noise: each crop's
    # and warp's grey-level noise is measured (``noise_sigma``); a patch is textured when its
    # variance less the noise's exceeds ``min_std``^2 and the noise's own; its NCC is divided
    # by the ceiling two noisy copies of one texture reach (sqrt((1 - s_a^2/v_a)(1 - s_b^2/v_b)),
    # the correction for attenuation) before ``min_ncc``; ``max_diff`` gets the mean absolute
    # difference the noise alone makes. Noise lowers a true match's NCC: in a dim capture
    # (sensor noise 6/255) the floor stops matching and GrabCut takes it
    adapt_noise: float = 0.0  # switch ``noise_ncc`` and ``exposure`` on for a capture whose
    # images' median noise (``noise_sigma``, grey levels, over up to 8 views spread through
    # it) exceeds this (0 = off). Both lift a dim capture's masks (sensor noise 6/255 and 10%
    # exposure swings: aircraft 0.81 -> 0.91) but cost a clean one's recall a little
    # (aircraft 0.974 -> 0.969): the simulator's clean captures read 1.0-1.5, the real
    # bonsai photos 0.1-0.4, the dim ones 3.7-4.5 (BENCHMARKS, session 73)
    exposure_auto: bool = False  # ``exposure`` for a view pair only where its gain moves the
    # matching patches' median grey level by more than ``exposure_gate`` x ``max_diff`` (a
    # 12%+ change on a mid-grey floor; the default capture's 3% swings stay uncorrected), the
    # gain being the two views' exposure ratio measured on every surface the SfM matched
    # (``view_exposures``, set by the refinement), not the pair's floor patches: on the real
    # bonsai those gave 1.15-2.0 (the knit cloth's brightness changes with the viewing angle)
    # where the SfM points give 0.94-1.07, and 7 of 289 masks got worse (session 73); measured
    # on every surface, 0 masks change by over 5% (session 74). 10% exposure swings, seed 0:
    # aircraft 0.873 -> 0.923, tabletop 0.925 -> 0.930, bicycle 0.822 -> 0.862
    exposure_gate: float = 1.0  # exposure_auto corrects a pair whose exposure ratio moves the
    # matching patches' median grey level by more than this share of ``max_diff``: at 1 only
    # a change the colour test cannot absorb alone. 0.5 (session 73) also corrected the
    # default capture's larger 3% swings and cost the demo bag's recall 0.975 -> 0.969 (more
    # floor matched pulls the shaded belly and a tail into GrabCut's background); 10% swings,
    # seed 0: aircraft 0.928 at 0.5, 0.923 at 1 (0.873 uncorrected; session 74)
    behind_window: int = 0  # behind: side (px) of its compared patches; 0 = ``window``
    # (background seen between leaves or spokes is often narrower than the planes' patch, and
    # a patch that straddles the object never matches)


def _grey(x: np.ndarray) -> np.ndarray:
    """Channel mean [h, w] of an [h, w, 3] float image (faster than ``mean(axis=2)``)."""
    return (x[..., 0] + x[..., 1] + x[..., 2]) * np.float32(1.0 / 3.0)


def noise_sigma(g: np.ndarray, ok: Optional[np.ndarray] = None) -> float:
    """Std of a grey image's pixel noise (0-255 units), from its least textured parts: the
    response r to the 3x3 kernel [[1, -2, 1], [-2, 4, -2], [1, -2, 1]] (it cancels constant
    and linear shading; on white noise of std s its variance is 36 s^2), the mean of r^2 over
    7x7 windows, and the 10% quantile of those means over 36 -- which on white noise reads
    0.588 s^2 (the quantile of a mean of 49 correlated squares; measured on 10^6 px of
    N(0, 1)), so it is divided by that. Texture adds to r^2, so the windows that show least
    of it (a wall, a smooth fuselage) measure the noise. ``ok``: pixels to use (windows
    wholly inside); 0 with fewer than 25 windows."""
    import cv2
    w = 7
    if g.shape[0] < w + 2 or g.shape[1] < w + 2:
        return 0.0
    k = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    r = cv2.filter2D(g.astype(np.float32), -1, k, borderType=cv2.BORDER_REPLICATE)
    m = cv2.boxFilter(r * r, -1, (w, w), borderType=cv2.BORDER_REPLICATE)
    sel = np.zeros(g.shape, bool)
    h = w // 2 + 1  # the windows' kernel responses lie wholly inside the image
    sel[h:-h, h:-h] = True
    if ok is not None:
        sel &= ndimage.binary_erosion(ok, np.ones((w + 2, w + 2), bool))
    if sel.sum() < 25:
        return 0.0
    return float(np.sqrt(max(float(np.quantile(m[sel], 0.1)), 0.0) / (36.0 * 0.588)))


def capture_noise(views: list[View], count: int = 8) -> float:
    """Median ``noise_sigma`` of the grey images of up to ``count`` views spread evenly
    through the capture (0 with no readable image)."""
    if not views:
        return 0.0
    pick = np.unique(np.linspace(0, len(views) - 1, max(1, count)).round().astype(int))
    out = []
    for i in pick:
        im = views[int(i)].get_image()
        if im is None:
            continue
        im = np.asarray(im, np.float32)
        out.append(noise_sigma(_grey(im) if im.ndim == 3 else im))
    return float(np.median(out)) if out else 0.0


def _group_median(group: np.ndarray, x: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Median of ``x`` per ``group`` id (0..n-1) and each group's count (median 0 if empty)."""
    order = np.lexsort((x, group))
    g, xs = group[order], x[order]
    cnt = np.bincount(g, minlength=n)
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    med = np.zeros(n)
    has = cnt > 0
    lo = start[has] + (cnt[has] - 1) // 2
    hi = start[has] + cnt[has] // 2
    med[has] = 0.5 * (xs[lo] + xs[hi])
    return med, cnt


def view_exposures(obs: list[tuple[np.ndarray, np.ndarray]], views: list[View],
                   min_points: int = 20, iterations: int = 10,
                   max_obs: int = 250_000) -> np.ndarray:
    """Each view's log exposure [V] (median 0 over the views it is known for; 0 where unknown)
    from the SfM observations: ``obs`` = per view (point ids, pixel xy) of the features it saw.

    A surface point's grey level in view i is its brightness times view i's exposure, so with
    x = log(5x5 mean grey level at the observation), x = s_point + e_view; solved by
    alternating medians (robust to the few points whose brightness changes with the viewing
    angle: sheen, specular highlights, a mismatched feature). Levels outside 10..245 (noise
    floor, clipping) are not used; a view with fewer than ``min_points`` usable observations
    of points seen in another view stays at 0. Every surface the SfM matched counts -- walls,
    object, floor alike -- so a brightness change of one surface seen from another angle (a
    knit cloth's sheen) is not taken for an exposure change. Over ``max_obs`` observations, a
    seeded random share of the points is used (each view keeps its share of them; the medians
    need hundreds per view, not thousands)."""
    vid, pid, val = [], [], []
    d = np.arange(-2, 3)
    total = sum(len(o[0]) for o in obs)
    keep_share = min(1.0, max_obs / total) if total else 1.0
    for i, (ids, xy) in enumerate(obs):
        if keep_share < 1.0 and len(ids):
            # the same points in every view: a hash of the id, not a per-view draw
            pick = (np.asarray(ids, np.uint64) * np.uint64(2654435761) % np.uint64(1 << 32)) \
                < np.uint64(keep_share * (1 << 32))
            ids, xy = np.asarray(ids)[pick], np.asarray(xy)[pick]
        if len(ids) == 0:
            continue
        im = np.asarray(views[i].get_image())
        h, w = im.shape[:2]
        # the 5x5 mean grey level around each observation, read at the observations only
        # (a full-frame filter would cost as much per view as the whole solve on large photos)
        x = np.clip(np.round(xy[:, 0]).astype(np.int64)[:, None] + d[None], 0, w - 1)
        y = np.clip(np.round(xy[:, 1]).astype(np.int64)[:, None] + d[None], 0, h - 1)
        win = im[y[:, :, None], x[:, None, :]].astype(np.float32)  # [n, 5, 5(, 3)]
        v = win.reshape(len(x), -1).mean(1)
        if im.dtype != np.uint8 and float(im.max()) <= 1.0:
            v = v * 255.0
        ok = (v > 10.0) & (v < 245.0)
        vid.append(np.full(int(ok.sum()), i, np.int64))
        pid.append(np.asarray(ids, np.int64)[ok])
        val.append(np.log(v[ok].astype(np.float64)))
    e = np.zeros(len(views))
    if not vid:
        return e
    vid, pid, val = np.concatenate(vid), np.concatenate(pid), np.concatenate(val)
    _, pid = np.unique(pid, return_inverse=True)
    seen = np.bincount(pid)
    keep = seen[pid] >= 2  # points seen in at least two views tie the views together
    vid, pid, val = vid[keep], pid[keep], val[keep]
    if not len(val):
        return e
    npts = int(pid.max()) + 1
    known = np.bincount(vid, minlength=len(views)) >= min_points
    for _ in range(int(iterations)):
        s, _ = _group_median(pid, val - e[vid], npts)
        e, _ = _group_median(vid, val - s[pid], len(views))
        e[~known] = 0.0
        if known.any():
            e[known] -= np.median(e[known])
    return e


def _warp_ncc(ga: np.ndarray, ma: np.ndarray, va: np.ndarray, b: np.ndarray, ok: np.ndarray,
              box_mean, noise_a: Optional[float] = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Patch NCC of grey crop ``ga`` (patch means ``ma``, variances ``va``) against a
    neighbour's warp ``b`` [h, w, 3] (valid where ``ok``), where the whole patch lies inside
    the neighbour's frame, the warp's patch means, and the warp's noise std (0 unless
    ``noise_a``, the crop's noise std, is given: then the NCC is corrected for both noises,
    ``PlaneCheckConfig.noise_ncc``)."""
    gb = _grey(b)
    mb = box_mean(gb)
    vb = np.maximum(box_mean(gb * gb) - mb * mb, 0.0)
    ncc = (box_mean(ga * gb) - ma * mb) / np.sqrt(np.maximum(va * vb, 1e-6))
    whole = box_mean(ok.astype(np.float32)) > 0.999
    nb = 0.0
    if noise_a is not None:
        nb = noise_sigma(gb, ok)
        ceil = np.sqrt(np.clip(1.0 - noise_a ** 2 / np.maximum(va, 1e-6), 1e-3, 1.0)
                       * np.clip(1.0 - nb ** 2 / np.maximum(vb, 1e-6), 1e-3, 1.0))
        ncc = ncc / ceil
    return ncc, whole, mb, nb


def _pair_gain(ma: np.ndarray, mb: np.ndarray, sel: np.ndarray, lo: float = 0.5,
               hi: float = 2.0) -> float:
    """The exposure gain that brings a neighbour's warp (patch means ``mb``) to this view's
    (``ma``): the median ratio over the patches ``sel`` (those that line up); 1 with fewer
    than 50 such patches. Clipped to [lo, hi]: a larger ratio is no exposure change."""
    if int(sel.sum()) < 50:
        return 1.0
    r = ma[sel] / np.maximum(mb[sel], 1e-3)
    return float(np.clip(np.median(r), lo, hi))


def disc_zbuffer(u: np.ndarray, v: np.ndarray, r: np.ndarray, z: np.ndarray,
                 shape: tuple[int, int]) -> np.ndarray:
    """Least ``z`` [h, w] over discs of centre (``u``, ``v``) px and radius ``r`` px (a pixel
    (x, y) is covered when (x - u)^2 + (y - v)^2 <= r^2); inf where no disc covers it.

    Vectorised by radius: the discs whose bounding square has the same half side ``R`` are
    tested against one offset grid together (one pass per distinct R, not per disc), so the
    cost is numpy's, not the interpreter's (a per-disc loop held the GIL for most of a
    segmentation run inside the node's process)."""
    h, w = shape
    zmin = np.full(h * w, np.inf)
    if len(u) == 0:
        return zmin.reshape(h, w)
    R = np.ceil(r).astype(np.int64) + 1  # covers every pixel within r of (u, v)
    fu, fv = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    r2 = r * r
    for rr in np.unique(R):
        sel = np.nonzero(R == rr)[0]
        d = np.arange(-rr, rr + 1)
        step = max(1, 2_000_000 // len(d) ** 2)  # bounded temporaries for big discs
        for s0 in range(0, len(sel), step):
            q = sel[s0:s0 + step]
            xx = fu[q, None, None] + d[None, None, :]  # [n, 1, k]
            yy = fv[q, None, None] + d[None, :, None]  # [n, k, 1]
            inside = ((xx - u[q, None, None]) ** 2 + (yy - v[q, None, None]) ** 2
                      <= r2[q, None, None])
            inside &= (xx >= 0) & (xx < w) & (yy >= 0) & (yy < h)
            n_i, y_i, x_i = np.nonzero(inside)
            if len(n_i) == 0:
                continue
            pix = (fv[q][n_i] + d[y_i]) * w + fu[q][n_i] + d[x_i]
            np.minimum.at(zmin, pix, z[q][n_i])
    return zmin.reshape(h, w)


class PointSet:
    """3D points [N] prepared for projecting into many views (``PlaneConsistency.sample``):
    float32 offsets [3, N] from a float64 ``origin`` near them, and which of them exist (``hit``).

    The plane check projects every crop pixel's 3D point into each of its neighbours; in float32
    these projections cost about a third of the float64 ones. Taken from a nearby origin the
    offsets lose < 1e-7 of the object's extent, a few 1e-5 px after projection."""

    def __init__(self, X: np.ndarray, hit: np.ndarray) -> None:
        X = np.asarray(X, float).reshape(-1, 3)
        self.hit = np.asarray(hit, bool).reshape(-1)
        # any finite points of the set make an origin (a sample: the mean of all costs more)
        idx = np.flatnonzero(self.hit[::97]) * 97
        idx = idx[np.isfinite(X[idx]).all(1)]
        if not len(idx):
            idx = np.flatnonzero(self.hit & np.isfinite(X).all(1))
        self.origin = X[idx].mean(0) if len(idx) else np.zeros(3)
        self.rel = np.empty((3, len(X)), np.float32)
        miss = ~self.hit
        with np.errstate(invalid="ignore", over="ignore"):
            for k in range(3):
                np.subtract(X[:, k], self.origin[k], out=self.rel[k], casting="unsafe")
                np.copyto(self.rel[k], 0.0, where=miss)  # unhit rows may hold inf or nan

    def __len__(self) -> int:
        return len(self.hit)

    def project(self, cam, pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u, v, z) float32 [N] in ``cam`` at ``pose`` (plumb_bob distortion as
        ``masks.project_distorted``); u, v are not finite where z <= 0."""
        R_cw, t_cw = pose.world_to_cam()
        t = (R_cw @ self.origin + t_cw).astype(np.float32)
        R = R_cw.astype(np.float32)
        x, y, z = self.rel
        cam_xyz = []
        for k in range(3):
            c = R[k, 0] * x
            c += R[k, 1] * y
            c += R[k, 2] * z
            c += t[k]
            cam_xyz.append(c)
        xc, yc, zc = cam_xyz
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.float32(1.0) / zc
            xc *= inv
            yc *= inv
        if cam.has_distortion:
            d = np.zeros(5, np.float32)
            d[:min(5, len(cam.dist))] = np.asarray(cam.dist, np.float32)[:5]
            k1, k2, p1, p2, k3 = d
            with np.errstate(invalid="ignore", over="ignore"):
                r2 = xc * xc + yc * yc
                rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
                xy = xc * yc
                xd = xc * rad + 2 * p1 * xy + p2 * (r2 + 2 * xc * xc)
                yd = yc * rad + p1 * (r2 + 2 * yc * yc) + 2 * p2 * xy
            xc, yc = xd, yd
        xc *= np.float32(cam.fx)
        xc += np.float32(cam.cx)
        yc *= np.float32(cam.fy)
        yc += np.float32(cam.cy)
        return xc, yc, zc


class PlaneConsistency:
    """Floor maps of crops of ``views`` by plane-induced warping of nearby views.

    ``planes`` = [P, 4] (or one [4]) planes (a, b, c, d) with unit normals, n.x + d = 0; a
    pixel is background when it is consistent with any of them. ``target`` is the point the
    cameras converge on (neighbours are the views nearest in angle seen from it, within
    ``min_deg``..``max_deg``).
    """

    def __init__(self, views: list[View], planes: np.ndarray, target: np.ndarray,
                 cfg: PlaneCheckConfig) -> None:
        self.views = views
        self.planes = np.atleast_2d(np.asarray(planes, float))
        self.cfg = cfg
        c = np.array([v.pose.t for v in views], float) - target
        c /= np.maximum(np.linalg.norm(c, axis=1, keepdims=True), 1e-12)
        ang = np.degrees(np.arccos(np.clip(c @ c.T, -1.0, 1.0)))  # [V, V]
        self.nbrs = []
        for i in range(len(views)):
            ok = np.nonzero((ang[i] >= cfg.min_deg) & (ang[i] <= cfg.max_deg))[0]
            self.nbrs.append(ok[np.argsort(ang[i, ok], kind="stable")][:cfg.neighbours])
        self._dirs: dict = {}
        self.behind_xyz: Optional[np.ndarray] = None  # background points for ``cfg.behind``
        self.ooi_xyz: Optional[np.ndarray] = None  # the object's points (its depth per view)
        self._radii: Optional[np.ndarray] = None  # their 4-NN spacing (``radii``)
        self._img: OrderedDict = OrderedDict()
        self.seconds = 0.0  # time spent in floor_map (reported by the refinement)
        self.pixel_floor: dict = {}  # (view, box) -> ``pixel_votes`` floor not in the floor
        self.exposures: Optional[np.ndarray] = None  # per-view log exposure (``view_exposures``;
        # exposure_auto's gains when set, else each pair's gain over the matching patches)

    def _image(self, j: int) -> np.ndarray:
        if j in self._img:
            self._img.move_to_end(j)
            return self._img[j]
        im = self.views[j].get_image().astype(np.float32)
        self._img[j] = im
        while len(self._img) > max(2, self.cfg.cache_views):
            self._img.popitem(last=False)
        return im

    def _rays(self, i: int) -> np.ndarray:
        c = self.views[i].camera
        key = (c.width, c.height, c.fx, c.fy, c.cx, c.cy, tuple(np.asarray(c.dist).tolist()))
        if key not in self._dirs:
            self._dirs[key] = undistorted_dirs(c).reshape(c.height, c.width, 3)
        return self._dirs[key]

    def _crop_dirs(self, i: int, box: tuple[int, int, int, int],
                   shape: Optional[tuple[int, int]] = None) -> np.ndarray:
        """Camera-frame ray directions [h*w, 3] of crop ``box`` of view ``i``, sampled on a
        ``shape`` grid over the crop (pixel centres of the resized crop; default: every
        pixel)."""
        y0, y1, x0, x1 = box
        rays = self._rays(i)
        if shape is None or tuple(shape) == (y1 - y0, x1 - x0):
            return rays[y0:y1, x0:x1].reshape(-1, 3)
        import cv2
        h, w = shape
        cols = (x0 + (np.arange(w) + 0.5) * (x1 - x0) / w - 0.5).astype(np.float32)
        rows = (y0 + (np.arange(h) + 0.5) * (y1 - y0) / h - 0.5).astype(np.float32)
        mx, my = np.meshgrid(cols, rows)
        d = cv2.remap(rays.astype(np.float32), mx, my, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REPLICATE)
        return d.reshape(-1, 3).astype(float)

    def plane_points(self, i: int, box: tuple[int, int, int, int], k: int = 0,
                     shape: Optional[tuple[int, int]] = None
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Where the rays of crop ``box`` of view ``i`` (on a ``shape`` grid, see
        ``_crop_dirs``) meet plane ``k``: ([h*w, 3], hit)."""
        v = self.views[i]
        n, d0 = self.planes[k, :3], self.planes[k, 3]
        d = self._crop_dirs(i, box, shape) @ v.pose.R.T  # world ray directions
        den = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -(v.pose.t @ n + d0) / den
        hit = np.isfinite(t) & (t > 0)
        return v.pose.t + np.where(hit, t, 0.0)[:, None] * d, hit

    def tune_support(self, masks: dict, span: float) -> dict:
        """Shift the support plane (``planes[0]``) along its normal by the offset in
        [-``span``, ``span``] (``cfg.tune_support`` steps each side) at the peak of the count
        of textured background pixels near the object that match the warp into >= ``rank``
        neighbours nearest the fitted plane (a hill climb from offset 0). Scored on up to
        ``cfg.tune_views`` views, in the box around each mask (enlarged by half its size)
        outside the mask dilated by a patch: the object never votes. Keeps the plane where
        no offset matches more pixels than the plane as fitted.
        """
        import cv2
        t0 = time.perf_counter()
        cfg = self.cfg
        steps = int(cfg.tune_support)
        out: dict = {"offset": 0.0, "span": float(span)}
        if steps <= 0 or not np.isfinite(span) or span <= 0:
            return out
        idx = [i for i, v in enumerate(self.views) if v.key in masks and masks[v.key].any()]
        if not idx:
            return out
        spread = np.linspace(0, len(idx) - 1, max(1, int(cfg.tune_views)))
        pick = [idx[int(k)] for k in np.unique(spread.round().astype(int))]
        offsets = np.linspace(-span, span, 2 * steps + 1)
        counts = np.zeros(len(offsets), np.int64)
        win = max(1, int(cfg.window))
        n0, d0 = self.planes[0, :3], float(self.planes[0, 3])

        def box_mean(x: np.ndarray) -> np.ndarray:
            return cv2.boxFilter(x, -1, (win, win), borderType=cv2.BORDER_REPLICATE)

        for i in pick:
            v = self.views[i]
            m = masks[v.key]
            ys, xs = np.nonzero(m)
            ph = max(win, int(0.5 * (ys.max() - ys.min() + 1)))
            pw = max(win, int(0.5 * (xs.max() - xs.min() + 1)))
            box = (max(0, ys.min() - ph), min(m.shape[0], ys.max() + ph + 1),
                   max(0, xs.min() - pw), min(m.shape[1], xs.max() + pw + 1))
            y0, y1, x0, x1 = box
            test = ~ndimage.binary_dilation(m, iterations=win)[y0:y1, x0:x1]
            ga = _grey(self._image(i)[y0:y1, x0:x1])
            ma = box_mean(ga)
            va = np.maximum(box_mean(ga * ga) - ma * ma, 0.0)
            test &= va > cfg.min_std ** 2
            if not test.any():
                continue
            d = self._crop_dirs(i, box) @ v.pose.R.T
            den = d @ n0
            for o, off in enumerate(offsets):
                with np.errstate(divide="ignore", invalid="ignore"):
                    t = -(v.pose.t @ n0 + d0 - off) / den
                hit = np.isfinite(t) & (t > 0)
                pts = PointSet(v.pose.t + np.where(hit, t, 0.0)[:, None] * d, hit)
                votes = np.zeros(ga.shape, np.int32)
                for j in self.nbrs[i]:
                    b, ok = self.sample(j, pts, None, ga.shape)
                    if not ok.any():
                        continue
                    ncc, whole, mb, _ = _warp_ncc(ga, ma, va, b, ok, box_mean)
                    diff = box_mean(_grey(np.abs(self._image(i)[y0:y1, x0:x1] - b)))
                    votes += whole & (ncc > cfg.min_ncc) & (diff < cfg.max_diff)
                counts[o] += int(((votes >= max(1, cfg.rank)) & test).sum())
        # climb from the fitted plane to the nearest peak of the count, not the highest one:
        # a periodic texture (a knit, tiles) matches again at an offset whose parallax is one
        # period, and the fitted plane is off by its noise, not by a period
        best = steps
        while True:
            up = [k for k in (best - 1, best + 1) if 0 <= k < len(counts)
                  and counts[k] > counts[best]]
            if not up:
                break
            best = max(up, key=lambda k: counts[k])
        if counts[best] > counts[steps]:
            self.planes[0, 3] = d0 - offsets[best]
            out["offset"] = float(offsets[best])
        out["matched"] = counts.tolist()
        out["views"] = len(pick)
        out["seconds"] = round(time.perf_counter() - t0, 3)
        self.seconds += time.perf_counter() - t0
        return out

    def sample(self, j: int, X, hit: Optional[np.ndarray], shape: tuple[int, int]
               ) -> tuple[np.ndarray, np.ndarray]:
        """View ``j``'s image at the projections of ``X`` (bilinear): ([*shape, 3], valid).

        ``X``: [N, 3] points with ``hit`` [N], or a ``PointSet`` (``hit`` None) when the same
        points are sampled in several views."""
        import cv2
        P = X if isinstance(X, PointSet) else PointSet(X, hit)
        cj = self.views[j].camera
        u, v, z = P.project(cj, self.views[j].pose)
        with np.errstate(invalid="ignore"):
            # comparisons are False on nan: a pixel projecting to nan is never valid
            ok = P.hit & (z > 0) & (u >= 0) & (u <= cj.width - 1)
            ok &= (v >= 0) & (v <= cj.height - 1)
        u[~ok] = -1.0
        v[~ok] = -1.0
        h, w = shape
        if max(h, w) < REMAP_MAX:
            col = cv2.remap(self._image(j), u.reshape(shape), v.reshape(shape),
                            cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            return col, ok.reshape(shape)
        # cv2.remap takes maps of fewer than 32767 rows and columns: a long list of points
        # (every mask pixel of a large image, as one column) is sampled in rows of REMAP_ROW
        n = len(u)
        rows = -(-n // REMAP_ROW)
        pad = rows * REMAP_ROW - n
        um = np.concatenate([u, np.full(pad, -1.0, u.dtype)]).reshape(rows, REMAP_ROW)
        vm = np.concatenate([v, np.full(pad, -1.0, v.dtype)]).reshape(rows, REMAP_ROW)
        col = cv2.remap(self._image(j), um, vm, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        rest = col.shape[2:]
        col = col.reshape(rows * REMAP_ROW, *rest)[:n]
        return col.reshape(*shape, *rest), ok.reshape(shape)

    def behind_points(self, i: int, box: tuple[int, int, int, int], shape: tuple[int, int]
                      ) -> tuple[np.ndarray, np.ndarray]:
        """3D points [h*w, 3] of crop ``box`` of view ``i`` (on a ``shape`` grid) at the depth
        of the nearest background point that lies beyond the object in this view, and the
        pixels that have one within ``behind_reach`` of the crop's longer side."""
        v = self.views[i]
        y0, y1, x0, x1 = box
        h, w = shape
        n = h * w
        zo = project_distorted(self.ooi_xyz, v.camera, v.pose)[1]
        zo = zo[zo > 1e-9]
        if len(zo) == 0 or len(self.behind_xyz) == 0:
            return np.zeros((n, 3)), np.zeros(n, bool)
        uv, z = project_distorted(self.behind_xyz, v.camera, v.pose)
        far = (z > np.quantile(zo, 0.98)) & finite_rows(uv)
        gx = np.rint((uv[far, 0] - x0 + 0.5) * w / (x1 - x0) - 0.5).astype(int)
        gy = np.rint((uv[far, 1] - y0 + 0.5) * h / (y1 - y0) - 0.5).astype(int)
        zf = z[far]
        ok = (gx >= 0) & (gx < w) & (gy >= 0) & (gy < h)
        if not ok.any():
            return np.zeros((n, 3)), np.zeros(n, bool)
        dep = np.full((h, w), np.inf)
        np.minimum.at(dep, (gy[ok], gx[ok]), zf[ok])  # the nearest surface beyond the object
        has = np.isfinite(dep)
        dist, (iy, ix) = ndimage.distance_transform_edt(~has, return_indices=True)
        d = dep[iy, ix].reshape(-1)
        hit = (dist <= self.cfg.behind_reach * max(h, w)).reshape(-1)
        dirs = self._crop_dirs(i, box, shape)  # camera frame, z = 1: depth scales them
        X = v.pose.t + (dirs * np.where(hit, d, 0.0)[:, None]) @ v.pose.R.T
        return X, hit

    def warp(self, i: int, box: tuple[int, int, int, int], j: int, k: int = 0
             ) -> tuple[np.ndarray, np.ndarray]:
        """View ``j``'s image warped through plane ``k`` onto crop ``box`` of view ``i``:
        (colours [h, w, 3] float32, valid [h, w] bool)."""
        X, hit = self.plane_points(i, box, k)
        return self.sample(j, X, hit, (box[1] - box[0], box[3] - box[2]))

    def _pixel_tol(self, match: np.ndarray, pix: np.ndarray) -> Optional[float]:
        """Per-pixel colour tolerance of one view pair: the ``pixel_quantile`` of the per-pixel
        differences ``pix`` at the centres of the matching (textured) patches ``match``; None
        when fewer than 4 patches match (no measure of the pair's noise)."""
        if match.sum() < 4:
            return None
        return float(np.quantile(pix[match], self.cfg.pixel_quantile))

    def radii(self) -> np.ndarray:
        """4-NN spacing [N] of the OOI points (capped at 3x the median; cached)."""
        if self._radii is None or len(self._radii) != len(self.ooi_xyz):
            from .masks import point_radii
            self._radii = point_radii(self.ooi_xyz, 4, 1.0)
        return self._radii

    def disc_depth(self, i: int, box: tuple[int, int, int, int], shape: tuple[int, int]
                   ) -> np.ndarray:
        """Per pixel [h, w] of the crop (on a ``shape`` grid): the least depth of the OOI
        points whose disc of one 4-NN spacing (+1 px) covers it; inf where none does."""
        v = self.views[i]
        c = v.camera
        y0, y1, x0, x1 = box
        h, w = shape
        sx, sy = w / (x1 - x0), h / (y1 - y0)
        uv, z = project_distorted(self.ooi_xyz, c, v.pose)
        r = self.radii()
        ok = (z > 1e-9) & finite_rows(uv)
        gu = (uv[ok, 0] - x0 + 0.5) * sx - 0.5
        gv = (uv[ok, 1] - y0 + 0.5) * sy - 0.5
        rpx = r[ok] * c.fx / z[ok] * sx + 1.0  # the splat's closing reaches ~1 px further
        inside = (gu > -rpx) & (gu < w - 1 + rpx) & (gv > -rpx) & (gv < h - 1 + rpx)
        return disc_zbuffer(gu[inside], gv[inside], rpx[inside], z[ok][inside], (h, w))

    def ooi_radius(self) -> float:
        """The OOI points' radius: the 90th percentile of their distance from their median
        (0 without points)."""
        if self.ooi_xyz is None or not len(self.ooi_xyz):
            return 0.0
        X = np.asarray(self.ooi_xyz, float)
        return float(np.quantile(np.linalg.norm(X - np.median(X, 0), axis=1), 0.9))

    def _raised_points(self, i: int, box: tuple[int, int, int, int],
                       shape: Optional[tuple[int, int]]) -> Optional[PointSet]:
        """Where the rays of the crop (as ``plane_points``) meet the support plane raised by
        ``parallax_guard`` x ``ooi_radius`` towards the object (towards the camera without OOI
        points); None when the height is 0."""
        h = self.cfg.parallax_guard * self.ooi_radius()
        if h <= 0:
            return None
        v = self.views[i]
        n, d0 = self.planes[0, :3], float(self.planes[0, 3])
        ref = (np.median(self.ooi_xyz @ n) if self.ooi_xyz is not None and len(self.ooi_xyz)
               else v.pose.t @ n)
        side = 1.0 if ref + d0 >= 0 else -1.0
        d = self._crop_dirs(i, box, shape) @ v.pose.R.T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (side * h - d0 - v.pose.t @ n) / (d @ n)
        hit = np.isfinite(t) & (t > 0)
        return PointSet(v.pose.t + np.where(hit, t, 0.0)[:, None] * d, hit)

    def _parallax(self, j: int, pts: PointSet, raised: PointSet,
                  box: tuple[int, int, int, int], shape: tuple[int, int]) -> np.ndarray:
        """Per pixel [h, w] of the crop: how far (px of the ``shape`` grid) the raised
        plane's point lies from the plane's in view ``j``; inf where either does not project
        (no surface at that height is seen there to confuse)."""
        cj, pj = self.views[j].camera, self.views[j].pose
        u0, v0, z0 = pts.project(cj, pj)
        u1, v1, z1 = raised.project(cj, pj)
        y0, y1, x0, x1 = box
        sx, sy = shape[1] / (x1 - x0), shape[0] / (y1 - y0)
        with np.errstate(invalid="ignore", over="ignore"):
            par = np.hypot((u1 - u0) * sx, (v1 - v0) * sy)
            par[~(pts.hit & raised.hit & (z0 > 0) & (z1 > 0))] = np.inf
        return par.reshape(shape)

    def floor_map(self, i: int, box: tuple[int, int, int, int],
                  shape: Optional[tuple[int, int]] = None) -> np.ndarray:
        """Bool [h, w] of the crop ``box`` (y0, y1, x0, x1) of view ``i``: pixels on the floor.

        ``shape`` (h, w) computes it on the crop resized to that size (what GrabCut works on;
        the cost then does not grow with the image resolution); default: the crop's own size.
        """
        return self.floor_maps(i, box, shape)[0]

    def floor_maps(self, i: int, box: tuple[int, int, int, int],
                   shape: Optional[tuple[int, int]] = None) -> tuple[np.ndarray, np.ndarray]:
        """(floor, object) bool [h, w] maps of the crop, as ``floor_map``: ``floor`` = the
        floor map; ``object`` = with ``object_keep``, the pixels whose colour the object's
        depth explains and the support plane does not (else empty; never overlapping floor).

        ``shifted``: next to the object's outline the patch centred on a floor pixel straddles
        the object and never matches, but a patch shifted by up to ``shifted_reach`` px away
        from the object does. Such a pixel is floor when its own colour matches the warp
        within the pair's noise and better than the warp at the object's depth (where an OOI
        disc covers it): an object edge warped through the plane is displaced by parallax.
        """
        import cv2
        t0 = time.perf_counter()
        y0, y1, x0, x1 = box
        cfg = self.cfg
        a = self._image(i)[y0:y1, x0:x1]
        if shape is not None and tuple(shape) != a.shape[:2]:
            a = cv2.resize(a, (int(shape[1]), int(shape[0])), interpolation=cv2.INTER_AREA)
        else:
            shape = None
        ga = _grey(a)

        obj = None  # the rays at the depth of the OOI discs covering them
        if (cfg.shifted or cfg.object_keep or cfg.object_guard) and self.ooi_xyz is not None:
            zo = self.disc_depth(i, box, ga.shape).reshape(-1)
            has = np.isfinite(zo)
            dirs = self._crop_dirs(i, box, None if shape is None else ga.shape)
            v = self.views[i]
            obj = PointSet(v.pose.t + (dirs * np.where(has, zo, 0.0)[:, None]) @ v.pose.R.T,
                           has)
        keep = np.zeros(ga.shape, np.int32)
        pixel = np.zeros(ga.shape, np.int32)  # pixel_votes: per-pixel floor votes
        raised = None  # parallax_guard: the rays' points a height above the support plane
        if cfg.parallax_guard > 0:
            raised = self._raised_points(i, box, None if shape is None else ga.shape)

        def consistent(X: np.ndarray, hit: np.ndarray, rank: int, win: int,
                       support: bool = False, guard: bool = False) -> np.ndarray:
            """Textured pixels whose ``win``-px patch matches in >= ``rank`` neighbours when
            warped through the 3D points ``X`` (``support``: also the shifted-patch floor and
            the object-keep votes of the support plane)."""
            win = max(1, int(win))

            def box_mean(x: np.ndarray) -> np.ndarray:
                # ndimage.uniform_filter(x, win, mode="nearest") within float32 rounding,
                # 4x faster (the plane check's NCC takes ~10 of these per neighbour)
                return cv2.boxFilter(x, -1, (win, win), borderType=cv2.BORDER_REPLICATE)

            ma = box_mean(ga)
            va = np.maximum(box_mean(ga * ga) - ma * ma, 0.0)
            na = noise_sigma(ga) if cfg.noise_ncc else None
            if na is None:
                textured = va > cfg.min_std ** 2
            else:  # texture, not noise: its variance less the noise's over both floors
                textured = va - na ** 2 > max(cfg.min_std ** 2, na ** 2)
            votes = np.zeros(ga.shape, np.int32)
            votes_s = np.zeros(ga.shape, np.int32)
            pts = PointSet(X, hit)  # sampled in every neighbour
            for j in self.nbrs[i]:
                b, ok = self.sample(j, pts, None, ga.shape)
                if not ok.any():
                    continue
                ncc, whole, mb, nb = _warp_ncc(ga, ma, va, b, ok, box_mean, na)
                max_diff = cfg.max_diff
                if na is not None:  # the mean |a - b| two noises alone make
                    max_diff += float(np.sqrt(2.0 / np.pi) * np.hypot(na, nb))
                gain = 1.0
                if cfg.exposure or cfg.exposure_auto:
                    sel = whole & textured & (ncc > cfg.min_ncc)
                    if cfg.exposure or self.exposures is None:
                        gain = _pair_gain(ma, mb, sel)
                    elif int(sel.sum()) >= 50:  # exposure_auto: the views' own exposures
                        gain = float(np.exp(self.exposures[i] - self.exposures[j]))
                    if (not cfg.exposure and gain != 1.0
                            and abs(gain - 1.0) * float(np.median(mb[sel]))
                            <= cfg.exposure_gate * max_diff):
                        gain = 1.0  # exposure_auto: the change is within the colour test's play
                    if gain != 1.0:
                        b = b * gain
                pix = _grey(np.abs(a - b))  # per-pixel colour difference to the warp
                diff = box_mean(pix)
                match = whole & (ncc > cfg.min_ncc) & (diff < max_diff)
                if support and raised is not None:
                    match &= self._parallax(j, pts, raised, box, ga.shape) >= cfg.parallax_px
                bo = oko = None  # the neighbour at the object's depth (sampled once)
                if guard and obj is not None:
                    bo, oko = self.sample(j, obj, None, ga.shape)
                    bo = bo * gain if gain != 1.0 else bo
                    go = _grey(bo)
                    mo = box_mean(go)
                    vo = np.maximum(box_mean(go * go) - mo * mo, 0.0)
                    ncc_o = (box_mean(ga * go) - ma * mo) / np.sqrt(np.maximum(va * vo, 1e-6))
                    whole_o = box_mean(oko.astype(np.float32)) > 0.999
                    match &= ~(whole_o & (ncc_o >= ncc))
                votes += match
                if not support or obj is None:
                    continue
                tol = self._pixel_tol(match & textured, pix)
                if tol is None:
                    continue
                if bo is None:
                    bo, oko = self.sample(j, obj, None, ga.shape)
                    bo = bo * gain if gain != 1.0 else bo
                pix_o = _grey(np.abs(a - bo))  # the same at the object's depth
                if cfg.shifted:
                    reach = int(min(max(0, cfg.shifted_reach), win // 2))
                    near = ndimage.maximum_filter(match & textured, size=2 * reach + 1,
                                                  mode="constant")
                    # no disc covers the pixel: the object hypothesis does not apply there
                    votes_s += near & ok & (pix <= tol) & (~oko | (pix < pix_o))
                    if cfg.pixel_votes:  # both hypotheses tested (a disc covers the pixel)
                        vote = textured & ok & oko & (pix <= tol) & (pix < pix_o)
                        if cfg.pixel_strict:
                            vote &= pix_o > tol
                        np.add(pixel, vote, out=pixel)
                if cfg.object_keep:
                    np.add(keep, oko & ok & (pix_o <= tol) & (pix > tol), out=keep)
            fl = (votes >= max(1, rank)) & textured
            if support and cfg.shifted:
                fl |= votes_s >= max(1, rank)
            return fl

        fl = np.zeros(ga.shape, bool)
        for k in range(len(self.planes)):
            X, hit = self.plane_points(i, box, k, shape)
            # the object guard on the support plane only: a wall lies clear of the object by
            # its radius (``background_planes``), so no part of the object is near it
            fl |= consistent(X, hit, cfg.rank, cfg.window, support=(k == 0),
                             guard=cfg.object_guard and k == 0)
        if cfg.behind and self.behind_xyz is not None and self.ooi_xyz is not None:
            X, hit = self.behind_points(i, box, ga.shape)
            if hit.any():
                fl |= consistent(X, hit, cfg.behind_rank, cfg.behind_window or cfg.window)
        if cfg.min_region > 1 and fl.any():
            lab, n = ndimage.label(fl)
            sizes = np.bincount(lab.ravel(), minlength=n + 1)
            big = sizes >= cfg.min_region
            big[0] = False
            fl = big[lab]
        if cfg.pixel_votes:
            self.pixel_floor[(i, tuple(box))] = (pixel >= max(1, cfg.rank)) & ~fl
        self.seconds += time.perf_counter() - t0
        return fl, (keep >= max(1, cfg.rank)) & ~fl


def background_planes(bg_xyz: np.ndarray, ooi_xyz: np.ndarray, cam_centers: np.ndarray,
                      threshold: float, max_planes: int, seed: int = 0) -> np.ndarray:
    """Up to ``max_planes`` large planes [P, 4] of the background points (walls, a table
    behind), each with the cameras on one side and every OOI point on the cameras' side and
    clear of it (farther than the object's own radius), so no plane can explain the object.

    Planes come from sequential RANSAC at ``threshold`` (the floor stage's inlier threshold;
    its seeded ``_fit_plane``, so the same input gives the same planes);
    a plane needs >= 5% of the background points (and >= 50); a plane parallel to one already
    kept and within the object's radius of it is the same surface again and is skipped.
    """
    from .floor import _fit_plane
    out: list[np.ndarray] = []
    if max_planes <= 0 or len(bg_xyz) < 50 or len(ooi_xyz) == 0:
        return np.zeros((0, 4))
    c = ooi_xyz.mean(axis=0)
    r_obj = float(np.quantile(np.linalg.norm(ooi_xyz - c, axis=1), 0.95))
    rest = bg_xyz
    min_in = max(50, int(0.05 * len(bg_xyz)))
    for k in range(3 * max_planes):
        if len(out) >= max_planes or len(rest) < min_in:
            break
        # the floor stage's seeded RANSAC: open3d's segment_plane, used here until session
        # 28, returns different planes from call to call whatever its seed (its iterations
        # run in parallel), which moved ~1% of a capture's mask pixels from run to run
        model, inl = _fit_plane(rest, float(threshold), 1000, int(seed) + 7919 * (k + 1))
        if len(inl) < min_in:
            break
        m = np.asarray(model, float)
        m /= np.linalg.norm(m[:3])
        side = np.sign(np.median(cam_centers @ m[:3] + m[3]))
        m = m * (side if side != 0 else 1.0)  # normal towards the cameras
        cams_ok = np.mean(cam_centers @ m[:3] + m[3] > 0) >= 0.9
        h = ooi_xyz @ m[:3] + m[3]
        # the same surface found again (a thick floor's second layer) is not a new plane
        dup = any(abs(float(m[:3] @ q[:3])) > 0.98 and abs(float(m[3] - q[3])) < r_obj
                  for q in out)
        if cams_ok and not dup and np.quantile(h, 0.02) > max(r_obj, 3 * threshold):
            out.append(m)
        rest = np.delete(rest, np.asarray(inl, np.int64), axis=0)
    return np.array(out).reshape(-1, 4)
