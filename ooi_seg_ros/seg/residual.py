"""Optional stage: points whose track fits its rays worse than the cloud's typical track.

A point seen by 3+ cameras has more measurements (2 per observation) than unknowns (3), so its
reprojection error says how well its rays agree. A track chained through one wrong match (a
feature of the background matched to one of the object, a repeated texture) fits its rays
worse than the surface's points and lies off the surface -- in front of the object in some
views, beside it in others, where each such point seeds a false blob of object in the masks.
On the simulator's captures (session 38) the 3-view points of the OOI cloud lying off the
surface had 3x the median error of those on it (aircraft, 120 views: 0.64 vs 0.21 px), and a
denser capture makes more of them: they grow faster than the surface's points.

The test is relative to the cloud itself, so it carries no pixel threshold: the error is
corrected for its degrees of freedom (2L measurements - 3 unknowns; a 3-view point fits its
rays more loosely than a 10-view one with the same image noise) and compared with the median
of the cloud's 3+-view points. 2-view points carry no such evidence (two rays always meet
after refinement up to the epipolar error) and are left alone, as are clouds without
observations or errors (a PLY). The median comes from the whole cloud; the points it rejects
leave the OOI cloud the point stages chose (its splatted masks and GrabCut's sure seeds) and
the background's seeds. It runs after the point stages, not before: removing 10-20% of the
cloud first moved their close decisions (the tabletop of seed 3 merged a neighbour at 60 views,
IoU 0.936 -> 0.858), and the OOI choice is not where these points do harm.

Not on in ``ours``: it recovers about half of what a denser capture (120 views) loses, but
the surface's own badly fitting points go with the stray ones, and on a sparse OOI cloud they
are the only points of a part (the stool of seed 1 at 60 views: 31 -> 20 OOI points, IoU
0.872 -> 0.712). Keeping the points no kept point lies near keeps the sparse parts and loses
the gain: the stray points are the isolated ones. ``colour_factor`` keeps the suspects whose
colour the views repeat (a stray point lands on background in many of the views framing it):
at 60 views within 0.005 of the default's means (stool seed 1 0.852), at 120 views two thirds
of the aircraft's gain (BENCHMARKS, Segmentation > Session 38).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..core.types import SfmCloud, View
from .masks import project_distorted


@dataclass
class ResidualConfig:
    """Options of the reprojection-error test of the multi-view points."""

    enabled: bool = False  # the paper has no such stage; an option in ``ours`` (module doc)
    factor: float = 2.0  # drop 3+-view points whose error per degree of freedom exceeds this x
    # the median 3+-view point's (2 and 3 measured: BENCHMARKS, Segmentation > Session 38)
    colour_factor: float = 0.0  # > 0: a suspect OOI point leaves only when the pixels it
    # projects to in the views framing it differ from its own colour (median over the views
    # of the largest channel difference) by more than this x the same median of the kept OOI
    # points: a stray point lands on background in many views, the only point of a thin part
    # lands on that part (0 = off)
    min_tracks: int = 10  # fewer 3+-view points than this: no reliable median, keep all
    ooi_colour_vote: float = 0.0  # > 0 (independent of ``enabled``): an OOI point leaves the
    # OOI cloud when in fewer than this share of the views framing it its pixel is nearer the
    # OOI points' colours than the rest of the cloud's (``colour_vote``): a floater beside a
    # thin object shows the lawn behind it (0 = off)
    ooi_colour_vote_sparse: bool = False  # ooi_colour_vote: flag such points as density's
    # sparse points (capped discs, no GrabCut object seeds) instead of taking them out
    ooi_colour_vote_mismatch: float = 0.0  # ooi_colour_vote: > 0, a low-vote point counts
    # only when its pixels also disagree with its own colour (``colour_mismatch``) by more
    # than this x the OOI points' median: a floater shows a different background in each
    # view, a point on a grey object over a grey floor shows its own grey (0 = off)


def dof_corrected_error(cloud: SfmCloud) -> np.ndarray:
    """Mean reprojection error [N] scaled to one degree of freedom (NaN for tracks under 3).

    The least-squares residual of a point seen L times has 2L - 3 degrees of freedom among
    2L measurements: its expected size shrinks by sqrt((2L - 3) / 2L) with the same noise.
    """
    L = cloud.track_lengths().astype(float)
    err = np.asarray(cloud.error, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = err / np.sqrt((2 * L - 3) / (2 * L))
    return np.where(L >= 3, out, np.nan)


def residual_filter(cloud: SfmCloud, cfg: ResidualConfig) -> tuple[np.ndarray, dict]:
    """Indices of the points to keep and the parameters used (median, counts)."""
    n = len(cloud)
    keep_all = np.arange(n)
    ce = dof_corrected_error(cloud)
    multi = np.isfinite(ce) & (ce > 0)
    params: dict = {"factor": float(cfg.factor), "multi_view_points": int(multi.sum())}
    if not cfg.enabled or cfg.factor <= 0:
        return keep_all, dict(params, skipped="disabled")
    if multi.sum() < max(int(cfg.min_tracks), 1):
        # no observations (a PLY), no errors, or too few long tracks to judge by
        return keep_all, dict(params, skipped="too few 3+-view points with an error")
    med = float(np.median(ce[multi]))
    bad = multi & (ce > cfg.factor * med)
    params.update({"median_error_dof": med, "threshold_error_dof": float(cfg.factor * med),
                   "dropped": int(bad.sum())})
    return np.nonzero(~bad)[0], params


def colour_mismatch(xyz: np.ndarray, rgb: np.ndarray, views: list[View]) -> np.ndarray:
    """Median [N] over the views framing each point of the largest channel difference between
    the pixel it projects to and its own colour (NaN where no view frames it)."""
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    col = np.asarray(rgb, float).reshape(-1, 3)
    diffs = np.full((len(views), len(xyz)), np.nan, np.float32)
    for i, v in enumerate(views):
        uv, z = project_distorted(xyz, v.camera, v.pose)
        ui, vi = np.rint(uv[:, 0]), np.rint(uv[:, 1])
        c = v.camera
        ok = (z > 1e-9) & (ui >= 0) & (ui < c.width) & (vi >= 0) & (vi < c.height)
        if not ok.any():
            continue
        img = v.get_image()
        px = img[vi[ok].astype(int), ui[ok].astype(int)].astype(float)
        if px.ndim == 1:  # a grey image
            px = px[:, None]
        diffs[i, ok] = np.abs(px - col[ok][:, :px.shape[1]]).max(axis=1)
    out = np.full(len(xyz), np.nan)
    seen = np.isfinite(diffs).any(axis=0)  # nanmedian warns on an all-NaN column
    if seen.any():
        out[seen] = np.nanmedian(diffs[:, seen], axis=0)
    return out


def colour_vote(xyz: np.ndarray, obj_rgb: np.ndarray, bg_rgb: np.ndarray, views: list[View],
                k: int = 5, max_ref: int = 20000, seed: int = 0) -> np.ndarray:
    """Share [N] of the views framing each point whose pixel there is nearer (mean distance
    to its ``k`` nearest) the object's point colours ``obj_rgb`` than the background's
    ``bg_rgb`` (NaN where no view frames it). A point on the object shows the object's
    colours in most views; a floater beside a thin object shows what lies behind it."""
    from scipy.spatial import cKDTree
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    rng = np.random.default_rng(seed)

    def tree(rgb: np.ndarray) -> Optional[cKDTree]:
        rgb = np.asarray(rgb, float).reshape(-1, 3)
        if len(rgb) > max_ref:
            rgb = rgb[rng.choice(len(rgb), max_ref, replace=False)]
        return cKDTree(rgb) if len(rgb) else None

    t_obj, t_bg = tree(obj_rgb), tree(bg_rgb)
    out = np.full(len(xyz), np.nan)
    if t_obj is None or t_bg is None or not len(xyz):
        return out
    votes = np.zeros(len(xyz))
    seen = np.zeros(len(xyz))
    for v in views:
        uv, z = project_distorted(xyz, v.camera, v.pose)
        ui, vi = np.rint(uv[:, 0]), np.rint(uv[:, 1])
        c = v.camera
        ok = (z > 1e-9) & (ui >= 0) & (ui < c.width) & (vi >= 0) & (vi < c.height)
        if not ok.any():
            continue
        px = v.get_image()[vi[ok].astype(int), ui[ok].astype(int)].astype(float)
        if px.ndim == 1:  # a grey image: grey reference colours
            px = np.repeat(px[:, None], 3, axis=1)
        kk_o, kk_b = min(k, t_obj.n), min(k, t_bg.n)
        d_o = np.asarray(t_obj.query(px[:, :3], k=kk_o)[0]).reshape(len(px), -1).mean(axis=1)
        d_b = np.asarray(t_bg.query(px[:, :3], k=kk_b)[0]).reshape(len(px), -1).mean(axis=1)
        votes[ok] += d_o < d_b
        seen[ok] += 1
    has = seen > 0
    out[has] = votes[has] / seen[has]
    return out
