"""Stage 4.2: floor / support-plane removal.

``mode="paper"`` follows section 4.2: RANSAC plane fits at ``n_thresholds`` distance
thresholds; the inlier ratio as a function of the threshold is differentiated twice and the
threshold at the minimum of the second derivative is taken (the knee where the ratio stops
rising steeply). Orientation analysis: points are split by the plane's side; the inliers and
the side holding fewer points are removed. Thresholds are derived from the cloud's spacing
(median k-NN distance), never metres.

``mode="support"`` (the improved default) is stable against the threshold jumps FINDINGS.md
measured: several planes are extracted one after another at a fixed threshold of a few
spacings; the support plane is the one whose normal, oriented towards the cameras, agrees with
the cameras' mean "up" direction, that has the cameras' convergence point (the object) on the
cameras' side, and holds the most points (after a least-squares refit of its inliers). Its
inliers within a band derived from the inlier residuals, and everything on the far side, are
removed. The band is at least the floor's measured thickness: the ``band_mirror_quantile``
of the depths of points just *below* the plane, where only floor lies -- a lawn or a rough
floor scatters its SfM points upwards as far as downwards, and a band from the inliers'
residuals alone left a ring of lawn points around a bicycle (IoU 0.18).

Two options for a support that stands on a floor (a table, a cloth-covered stool):
``support_select="nearest"`` takes, of the planes that qualify, the nearest one below the
convergence point whose inliers surround the object's foot (at least ``surround_sectors`` of 8
sectors around it) and under whose interior the farther planes are hidden (``max_under``: an
opaque support hides the floor under its middle; a plane through the object's middle, e.g. a
toy car's surrounding clutter tops, does not) instead of the one with the most inliers (which
stays the fallback) -- the floor under a stool often holds more points than the stool's top
(simulator scene ``stool``: IoU 0.16 -> 0.8, the stool was taken for part of the object).
``max_under_density`` (0.1 in ``ours``) also lets a plane qualify whose farther planes'
points under its interior are at most that share of their density in the ring around it:
per inlier, a sparse support over a dense floor fails (through a 90 deg lens at 320x240 the
stool's 106-point top had 6 of 2,712 floor points under it, 0.057 per inlier, and the stool
was kept with the plant: IoU 0.118), while per area the floor there is 0.035 as dense as
around it. Planes through an object's middle read 0.34 and more (the object hides part of
the ground under them too), so the per-inlier rule stays first. ``band_interior`` measures
the skin only under the support's interior (points nearer the foot than the median inlier):
a table's apron or a cloth's sides hang below the support's edge, and read as skin they made
the band as tall as the object's pot. ``band_tail`` (off) instead ends the skin where the
depth histogram below the plane stops decaying. ``band_gap`` (session 72): where the depths
under the interior are fewer than 1 / (1 - ``band_mirror_quantile``) (100 for the 99%
quantile), that quantile is the deepest point or two, and one SfM stray under an opaque top
sets the band -- the stool through a 90 deg lens at 544x408, seed 2: 61 depths, two strays at
0.14 and 0.22 m under a 1.6 cm skin, band 0.169 m, the whole pot removed (IoU 0.66). There
the depths end at the first gap between consecutive depths wider than the fit threshold.

``band_local`` (4 in ``ours``) measures the skin again, the same way, beyond the interior: in
that many rings of equal inlier counts from the median inlier radius outwards, each ring's
band is the larger of the interior's and the quantile of the depths below the plane in that
ring. The floor far from the object is seen from farther off and at a shallower angle, so its
skin of SfM points is thicker there than under the object: through a 90 deg lens at 320x240
the bicycle scene's lawn left points above the interior's band (2.3 cm; the four rings beyond
measure 3.3, 2.3, 3.6 and 8.9 cm): 100 of the 122 OOI points were lawn and the masks covered
the lawn and the trees (IoU 0.200; ring by ring, 50 points and IoU 0.738). The interior,
where the object stands, keeps the interior's band, so the object's foot is cut no deeper
than before; a table's apron hangs under its outer rings and lifts their
band, which only removes more of what stands near the table's edge, not the object the
cameras converge on.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from .density import spacing


@dataclass
class FloorConfig:
    """Options of the floor/support-plane stage."""

    mode: str = "paper"  # "paper" (threshold sweep) | "support" (camera-aware) | "none"
    n_thresholds: int = 50  # thresholds swept by the paper rule
    threshold_min: float = 0.25  # smallest swept threshold, in cloud spacings
    threshold_max: float = 25.0  # largest swept threshold, in cloud spacings
    sweep_sample: int = 30000  # points used for the threshold sweep (full cloud for the cut)
    ransac_iterations: int = 1000  # RANSAC iterations per fit
    support_threshold: float = 2.0  # support mode: inlier threshold in nearest-neighbour spacings
    support_k: int = 1  # support mode: neighbour rank of the spacing used for the threshold
    support_max_planes: int = 6  # support mode: planes extracted one after another
    support_min_inliers: float = 0.1  # support mode: smallest plane, fraction of the cloud
    support_min_of: str = "cloud"  # support mode: support_min_inliers is a share of the
    # whole cloud ("cloud"), or of the points the planes extracted before left ("remaining":
    # the share of background a wide lens or a far orbit lets in does not hide a small support)
    support_min_up: float = 0.7  # support mode: min cos(normal, mean camera up)
    band_sigmas: float = 2.5  # support mode: removal band >= this x inlier residual std
    band_mirror_quantile: float = 0.99  # support mode: band >= this quantile of the depths of
    # the points just below the plane (only floor lies below it, so its underside measures how
    # thick the floor's skin of SfM points is; 0 disables)
    layer_attach: float = 0.0  # support mode: keep points between the inliers' band and the
    # floor's thickness under the interior (the layer a pot's or a tyre's foot stands in) that
    # lie within this x threshold of a point above the band (0 = off)
    band_mirror_window: float = 10.0  # support mode: "just below" = within this x threshold
    support_select: str = "most"  # support mode, of the planes that qualify: "most" inliers,
    # or the "nearest" below the convergence point among those whose inliers surround its foot
    # (a stool's top under the object, not the floor the stool stands on)
    surround_sectors: int = 6  # "nearest": of 8 sectors around the foot, this many must each
    # hold >= 2% of the plane's inliers
    max_under: float = 0.05  # "nearest": at most this many inliers of the farther qualifying
    # planes per inlier lie under the plane's interior (an opaque support hides the floor under
    # its middle; a plane through the object's middle does not hide the ground below it)
    max_under_density: float = 0.0  # "nearest", > 0: a plane that fails max_under still
    # qualifies when the farther planes' points under its interior are at most this share of
    # their density in the ring around it (out to twice the interior's radius; at least
    # ``under_ring_min`` points there). Per area, not per inlier: a wide frame's floor
    # outnumbers a small support's top, and its few points seen under a stool's edge then
    # exceed a per-inlier bound while the floor there is still mostly hidden
    under_ring_min: int = 20  # max_under_density: fewest ring points the ratio is read from
    band_interior: bool = False  # support mode: measure the skin only under the support's
    # interior (closer to the object's foot than the median inlier), away from its edges
    band_local: int = 0  # support mode, > 0: outside the support's interior the band is also
    # measured locally, in this many rings of equal inlier counts around the object's foot
    # (the skin of a far floor seen at a shallow angle is thicker than under the object)
    band_gap: bool = False  # support mode: where the depths below the plane are too few for
    # band_mirror_quantile to rest on more than the deepest one (under 1 / (1 - quantile)),
    # they end at the first gap wider than the fit threshold between consecutive depths;
    # deeper points under an opaque support's interior are SfM strays (the stool through a
    # 90 deg lens at 544x408, seed 2: 2 of 61 depths at 0.14-0.22 m set the 99% quantile to
    # 0.169 m, 10x the skin, and the band took the whole pot)
    band_tail: bool = False  # support mode: the skin ends where the depths below the plane
    # fall to the level of their outer half (a table's or cloth's sides hanging below the
    # support, which the quantile alone reads as skin up to the window's edge)
    seed: int = 0  # RANSAC seed


def _fit_plane(xyz: np.ndarray, thr: float, iters: int, seed: int, score_sample: int = 20000
               ) -> tuple[np.ndarray, np.ndarray]:
    """Plane (a,b,c,d) with unit normal and its inlier indices, by a seeded RANSAC.

    ``iters`` planes through random point triples are scored by their inliers (distance <
    ``thr``) among at most ``score_sample`` points of the cloud; the best is refined by least
    squares through its inliers, whose indices over the whole cloud are returned. Written
    here rather than open3d's ``segment_plane`` because that one is not reproducible: with
    the same seed and one thread it returned different planes from call to call (40 calls on
    a test scene: six different results, three of which cut the object away).
    """
    n = len(xyz)
    rng = np.random.default_rng(seed)
    if n < 3:
        return np.array([0.0, 0.0, 1.0, 0.0]), np.zeros(0, np.int64)
    tri = rng.integers(0, n, (max(1, int(iters)), 3))
    p0 = xyz[tri[:, 0]]
    nrm = np.cross(xyz[tri[:, 1]] - p0, xyz[tri[:, 2]] - p0)
    length = np.linalg.norm(nrm, axis=1)
    valid = length > 1e-12 * max(float(np.ptp(xyz, axis=0).max()), 1e-12) ** 2
    nrm = nrm / np.where(valid, length, 1.0)[:, None]
    off = -(nrm * p0).sum(axis=1)
    pts = xyz if n <= score_sample else xyz[rng.choice(n, score_sample, replace=False)]
    count = np.zeros(len(tri), np.int64)
    for s in range(0, len(pts), 4096):
        count += (np.abs(pts[s:s + 4096] @ nrm.T + off) < thr).sum(axis=0)
    count[~valid] = -1
    best = int(np.argmax(count))
    plane = np.append(nrm[best], off[best]) if valid[best] else np.array([0.0, 0.0, 1.0, 0.0])
    inl = np.nonzero(np.abs(xyz @ plane[:3] + plane[3]) < thr)[0]
    if len(inl) >= 3:
        plane = _refit(xyz[inl], plane)
        inl = np.nonzero(np.abs(xyz @ plane[:3] + plane[3]) < thr)[0]
    return plane, inl.astype(np.int64)


def _refit(pts: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """Least-squares plane through ``pts`` (normal sign kept as in ``plane``)."""
    c = pts.mean(axis=0)
    n = np.linalg.svd(pts - c, full_matrices=False)[2][-1]
    n = n if n @ plane[:3] >= 0 else -n
    return np.append(n, -n @ c)


def paper_floor(xyz: np.ndarray, cfg: FloorConfig) -> tuple[np.ndarray, dict]:
    """Indices kept by the paper's rule and the parameters used."""
    n = len(xyz)
    s = spacing(xyz, seed=cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    sample = xyz if n <= cfg.sweep_sample else xyz[rng.choice(n, cfg.sweep_sample, False)]
    thrs = s * np.geomspace(cfg.threshold_min, cfg.threshold_max, cfg.n_thresholds)
    ratio = np.array([len(_fit_plane(sample, t, cfg.ransac_iterations, cfg.seed)[1]) / len(sample)
                      for t in thrs])
    d2 = np.gradient(np.gradient(ratio, thrs), thrs)
    k = int(np.argmin(d2[1:-1]) + 1) if len(d2) > 2 else 0
    thr = float(thrs[k])
    plane, inl = _fit_plane(xyz, thr, cfg.ransac_iterations, cfg.seed)
    sd = xyz @ plane[:3] + plane[3]
    out = np.zeros(n, bool)
    out[inl] = True
    rest = ~out
    pos, neg = int((sd[rest] > 0).sum()), int((sd[rest] < 0).sum())
    out |= (sd < 0) if pos >= neg else (sd > 0)
    return np.nonzero(~out)[0], {"threshold": thr, "threshold_spacings": thr / s,
                                 "plane": plane.tolist(), "inlier_ratio_curve":
                                 [float(r) for r in ratio]}


def skin_end(depths: np.ndarray, window: float, bin_width: float) -> float:
    """Depth at which the histogram of ``depths`` (in [0, window)) first falls to the level
    of its outer half, the tail that does not decay.

    Below a support plane lie the floor's skin of SfM points, whose count decays with depth,
    and whatever hangs under the support (a table's apron, a cloth's sides), which spreads
    evenly over depth. The tail's level is the mean count per bin over the window's outer
    half; the skin ends at the first bin not above that level by two Poisson standard
    deviations. With no tail (a lawn, a floor: under one point per bin) this returns
    ``window``, so the caller's quantile decides.
    """
    n_bins = max(2, int(round(window / max(bin_width, 1e-12))))
    hist, edges = np.histogram(depths, bins=n_bins, range=(0.0, window))
    level = float(np.mean(hist[n_bins // 2:]))
    if level < 1.0:
        return float(window)
    ends = np.nonzero(hist <= level + 2.0 * np.sqrt(level))[0]
    return float(edges[ends[0]]) if len(ends) else float(window)


def surround(points: np.ndarray, plane: np.ndarray, target: np.ndarray) -> int:
    """How many of 8 equal sectors around the foot of ``target`` on ``plane`` hold at least
    2% of ``points`` (the plane's inliers): 8 for a floor or table top that the object stands
    on, fewer for a plane beside it or for the object's own flat parts (a wing)."""
    n = plane[:3]
    foot = target - (target @ n + plane[3]) * n
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    q = points - foot
    sec = np.floor((np.arctan2(q @ b, q @ a) + np.pi) / (np.pi / 4)).astype(int) % 8
    cnt = np.bincount(sec, minlength=8)
    return int(np.sum(cnt >= 0.02 * max(len(points), 1)))


def foot_radius(xyz: np.ndarray, plane: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Horizontal distance of every point of ``xyz`` from the foot of ``target`` on
    ``plane`` (measured along the plane)."""
    n = plane[:3]
    q = xyz - (target - (target @ n + plane[3]) * n)
    return np.linalg.norm(q - np.outer(q @ n, n), axis=1)


def _interior(xyz: np.ndarray, plane: np.ndarray, target: np.ndarray, sd: np.ndarray,
              thr: float) -> np.ndarray:
    """Points nearer the foot of ``target`` on ``plane`` (horizontally) than the median of
    the plane's inliers (``|sd| < thr``): under the support's interior, away from its edges."""
    r = foot_radius(xyz, plane, target)
    return r < np.median(r[np.abs(sd) < thr])


def under_interior(plane: np.ndarray, inliers: np.ndarray, target: np.ndarray,
                   lower: np.ndarray) -> float:
    """Points of ``lower`` (the inliers of the planes farther below) that lie under the
    interior of ``plane`` (nearer the foot than the median of its ``inliers``), per inlier."""
    if len(lower) == 0:
        return 0.0
    r_in = float(np.median(foot_radius(inliers, plane, target)))
    return float(np.sum(foot_radius(lower, plane, target) < r_in)) / max(len(inliers), 1)


def under_density(plane: np.ndarray, inliers: np.ndarray, target: np.ndarray,
                  lower: np.ndarray, ring_min: int = 20) -> Optional[float]:
    """Density (per area along ``plane``) of the points of ``lower`` under the interior of
    ``plane`` (nearer the foot than the median of its ``inliers``, radius r) against their
    density in the ring from r to 2r around it; None when the ring holds fewer than
    ``ring_min`` of them (too few to read a ratio from). About 1 under a plane that hides
    nothing (the ground seen below a plane through an object's middle), near 0 under an
    opaque support."""
    if len(lower) == 0:
        return None
    r_in = float(np.median(foot_radius(inliers, plane, target)))
    r = foot_radius(lower, plane, target)
    ring = int(np.sum((r >= r_in) & (r < 2 * r_in)))
    if ring < max(ring_min, 1):
        return None
    return float(3.0 * np.sum(r < r_in) / ring)  # ring area = 3x the interior's


def support_floor(xyz: np.ndarray, cfg: FloorConfig, cam_centers: np.ndarray,
                  cam_up: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, dict]:
    """Indices kept after removing the camera-aware support plane (see module doc)."""
    n = len(xyz)
    s = spacing(xyz, cfg.support_k, seed=cfg.seed)
    thr = cfg.support_threshold * s
    up = cam_up / max(np.linalg.norm(cam_up), 1e-12)
    remaining = np.arange(n)
    best: Optional[tuple[float, np.ndarray, float]] = None  # the most inliers
    nearest: Optional[tuple[float, np.ndarray, float]] = None  # nearest below, surrounding
    qualified: list = []  # "nearest": (height of the target, plane, res std, inliers, k)
    tried = []
    if cfg.support_min_of not in ("cloud", "remaining"):
        raise ValueError(f"floor.support_min_of={cfg.support_min_of!r}; use cloud or "
                         "remaining")
    for j in range(cfg.support_max_planes):
        # the smallest plane worth a look: a share of the whole cloud, or of what the planes
        # before it left (a stool's top once the floor around it is gone)
        basis = n if cfg.support_min_of == "cloud" else len(remaining)
        if len(remaining) < max(10, cfg.support_min_inliers * basis):
            break
        plane, inl = _fit_plane(xyz[remaining], thr, cfg.ransac_iterations, cfg.seed + j)
        if len(inl) < cfg.support_min_inliers * basis:
            break
        plane = _refit(xyz[remaining[inl]], plane)
        inl = np.nonzero(np.abs(xyz[remaining] @ plane[:3] + plane[3]) < thr)[0]
        side = np.sign(np.median(cam_centers @ plane[:3] + plane[3]))
        plane = plane * (side if side != 0 else 1.0)  # normal points to the cameras
        h_target = float(target @ plane[:3] + plane[3])
        cam_frac = float(np.mean(cam_centers @ plane[:3] + plane[3] > 0))
        cos_up = float(plane[:3] @ up)
        tried.append({"plane": plane.tolist(), "inliers": int(len(inl)), "cos_up": cos_up,
                      "target_height": h_target, "cameras_above": cam_frac})
        if cos_up >= cfg.support_min_up and h_target > 0 and cam_frac >= 0.9:
            res = xyz[remaining[inl]] @ plane[:3] + plane[3]
            if cfg.support_select not in ("most", "nearest"):
                raise ValueError(f"floor.support_select={cfg.support_select!r}; use most or "
                                 "nearest")
            cand = (float(len(inl)), plane, float(np.std(res)))
            if best is None or cand[0] > best[0]:
                best = cand
            if cfg.support_select == "nearest":
                qualified.append((h_target, plane, cand[2], remaining[inl], len(tried) - 1))
        remaining = np.delete(remaining, inl)
    qualified.sort(key=lambda q: q[0])
    for k, (h_target, plane, res_std, inl_idx, t) in enumerate(qualified):
        sectors = surround(xyz[inl_idx], plane, target)
        lower = np.concatenate([q[3] for q in qualified[k + 1:]] or [np.zeros(0, np.int64)])
        hidden = under_interior(plane, xyz[inl_idx], target, xyz[lower])
        tried[t].update(surround_sectors=sectors, under_interior=hidden)
        hides = hidden <= cfg.max_under
        if not hides and cfg.max_under_density > 0:
            ratio = under_density(plane, xyz[inl_idx], target, xyz[lower], cfg.under_ring_min)
            tried[t]["under_density"] = ratio
            hides = ratio is not None and ratio <= cfg.max_under_density
        if sectors >= cfg.surround_sectors and hides:
            nearest = (h_target, plane, res_std)
            break
    if best is None:
        return np.arange(n), {"support_plane": None, "planes_tried": tried,
                              "warning": "no support plane below the object with the cameras "
                                         "above it; floor stage kept every point"}
    _, plane, res_std = nearest if nearest is not None else best
    band = band_inliers = max(cfg.band_sigmas * res_std, 0.5 * thr)
    sd = xyz @ plane[:3] + plane[3]
    mirror = 0.0
    if cfg.band_mirror_quantile > 0:
        near = (sd < 0) & (sd > -cfg.band_mirror_window * thr)
        if cfg.band_interior:
            # under the support's interior only: a table's apron or a cloth's sides hang at
            # its edge, and an opaque support hides everything under its middle but its skin
            near &= _interior(xyz, plane, target, sd, thr)
        below = -sd[near]
        few = 1.0 / max(1.0 - cfg.band_mirror_quantile, 1e-9)
        if cfg.band_gap and 20 <= len(below) < few:
            # too few depths for the quantile to rest on more than the deepest one or two
            below = np.sort(below)
            gaps = np.nonzero(np.diff(below) > thr)[0]
            if len(gaps):
                below = below[:gaps[0] + 1]
        if len(below) >= 20:
            mirror = float(np.quantile(below, cfg.band_mirror_quantile))
            if cfg.band_tail:
                mirror = min(mirror, skin_end(below, cfg.band_mirror_window * thr, thr / 2))
            band = max(band, mirror)
    local = np.full(n, band)
    ring_bands: list = []
    if cfg.band_local > 0 and cfg.band_mirror_quantile > 0:
        rad = foot_radius(xyz, plane, target)
        r_in = rad[np.abs(sd) < thr]
        edges = np.quantile(r_in, np.linspace(0.5, 1.0, cfg.band_local + 1))
        edges[-1] = np.inf
        for a, b in zip(edges[:-1], edges[1:]):
            ring = (rad >= a) & (rad < b)
            below = -sd[ring & (sd < 0) & (sd > -cfg.band_mirror_window * thr)]
            rb = float(np.quantile(below, cfg.band_mirror_quantile)) if len(below) >= 20 else band
            rb = max(rb, band)
            local[ring] = rb
            ring_bands.append(round(rb, 6))
    keep = sd > local
    # the layer is the interior's skin only: beyond the interior the rings' thicker bands
    # reach far background (crates, a wall's foot) that would attach to background above them
    layer = (sd > band_inliers) & (sd <= band) & ~keep
    if cfg.layer_attach > 0 and layer.any() and keep.any():
        # the object's foot (a pot's base, a tyre) lies in the layer between the inliers' band
        # and the floor's thickness: layer points touching a point above the band stay
        from scipy.spatial import cKDTree
        d, _ = cKDTree(xyz[keep]).query(xyz[layer], k=1,
                                        distance_upper_bound=cfg.layer_attach * thr)
        keep[np.nonzero(layer)[0][np.isfinite(d)]] = True
    return np.nonzero(keep)[0], {"support_plane": plane.tolist(), "band": band,
                                 "band_inliers": band_inliers, "band_mirror": mirror,
                                 **({"band_rings": ring_bands} if cfg.band_local > 0 else {}),
                                 "threshold": thr,
                                 "planes_tried": tried}


def floor_filter(xyz: np.ndarray, cfg: FloorConfig, cam_centers: np.ndarray,
                 cam_up: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, dict]:
    """Dispatch on ``cfg.mode``; returns kept indices and parameters used."""
    if cfg.mode == "none" or len(xyz) < 10:
        return np.arange(len(xyz)), {"mode": "none"}
    if cfg.mode == "paper":
        keep, p = paper_floor(xyz, cfg)
    elif cfg.mode == "support":
        keep, p = support_floor(xyz, cfg, cam_centers, cam_up, target)
    else:
        raise ValueError(f"floor.mode={cfg.mode!r}; use paper, support or none")
    p["mode"] = cfg.mode
    return keep, p
