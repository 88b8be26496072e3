"""Improved-mode stage: thin straight parts that bridge a hole of the mask (spokes, struts).

A part about a pixel wide (a spoke, a cable, a strut) has no SfM point of its own and is cut
away by GrabCut's smoothness term, whatever the colour models say: its boundary costs more
than its area earns. Where such a part spans a *hole* of the mask -- background enclosed by
the object, a wheel between its rim and its hub -- it is a straight line in the image whose
two ends meet the object, and that is what this pass looks for:

1. **Line response.** For each of ``orientations`` directions, the mean colour along a
   segment ``length`` px long through the pixel is compared with the means along the two
   parallel segments ``offset`` px to either side. The response is the smaller of the two
   colour distances, and zero unless the pixel differs from both sides the same way (a ridge
   or a valley, not an edge between two regions). Per pixel, the best direction wins, and
   only pixels at least as strong as their two neighbours across that direction stay (a line
   one pixel wide, not the band the filter's width smears it into).
2. **Thresholds from the hole's own texture.** The background seen through a hole has
   texture of its own (grass blades, the weave of a cloth), and some of it is line-like in
   a preferred direction. Per hole and direction, a candidate needs a response above the
   ``q_high`` percentile of that direction's responses over the hole (and above
   ``contrast``), and a bridge's support counts samples above the ``q_low`` percentile (and
   above ``contrast`` x ``low_share``): thin parts are sparse within a hole, so those
   percentiles measure the texture, not the parts.
3. **Straight.** Candidates of one direction (+-1 bin) are joined 8-connected; a run is kept
   when at least ``min_inliers`` of its pixels lie within 1 px of its principal axis (fitted
   again on those), at an RMS distance of at most ``max_rms``, the axis agrees with the
   direction and the inliers span at least ``min_length`` px (default: ``length``).
4. **A bridge.** The run's axis is followed both ways through the hole; both ends must reach
   the mask (not the image's side). The chord between them is sampled every pixel: it is a
   bridge when at least ``support`` of its samples (the best of the pixel and its two
   neighbours across the chord) respond above the low threshold, and then those pixels of
   the chord join the mask -- the whole span, including the stretches the candidate
   threshold missed.

Only pixels inside holes are added; nothing is removed. A texture streak in a hole rarely
spans it from one side of the object to the other at a response above the hole's own 90th
percentile; a spoke does. What it cannot tell is a straight line *behind* the hole from a
part across it: a shelf's edge seen between two stems joins as a spoke would (the tabletop
at 640x360, 125 px in 6 of 30 views). Measured (BENCHMARKS, Segmentation > Session 66): the
bicycle at 640x360 0.900 / 0.947 -> 0.922 / 0.973 IoU / recall; the four solid scenes and
the real bonsai's masks change by under 0.0001 IoU.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy import ndimage


@dataclass
class BridgeConfig:
    """Options of the thin-bridge pass (``refine.bridges``)."""

    enabled: bool = False  # add thin straight parts that span a hole of the mask
    length: int = 9  # px: length of the line filter's segments
    offset: int = 2  # px: distance of the two side segments from the centre one
    orientations: int = 12  # directions of the line filter over 180 degrees
    contrast: float = 20.0  # a candidate's response at least this (colour distance, 0-255)
    low_share: float = 0.5  # a support sample at least contrast x this
    q_high: float = 97.0  # candidate: above this percentile of the hole's responses in its
    # direction
    q_low: float = 90.0  # support sample: above this percentile of them
    min_length: int = 0  # px: shortest candidate run (0 = ``length``)
    max_rms: float = 0.8  # px: RMS distance of a run's pixels (those within 1 px) from its axis
    min_inliers: float = 0.7  # share of a run's pixels that must lie within 1 px of its axis
    # (a run along a spoke often carries a speck or a crossing spoke's pixel: refitted without)
    support: float = 0.9  # share of a chord's samples that must respond (a texture streak
    # wanders off a straight chord; measured: 0.75 let 4x more pixels off the spokes join)
    min_hole: int = 0  # px: holes smaller than this are skipped (0 = ``length`` squared)


def check_config(cfg: BridgeConfig) -> None:
    """ValueError naming the first ``refine.bridges`` option out of its range."""
    bad = None
    if int(cfg.length) < 3:
        bad = f"length={cfg.length}; a segment of at least 3 px"
    elif int(cfg.offset) < 1:
        bad = f"offset={cfg.offset}; the side segments lie at least 1 px off"
    elif int(cfg.orientations) < 4:
        bad = f"orientations={cfg.orientations}; at least 4 directions over 180 degrees"
    elif not 0.0 <= float(cfg.q_low) <= float(cfg.q_high) <= 100.0:
        bad = f"q_low={cfg.q_low}, q_high={cfg.q_high}; percentiles with q_low <= q_high"
    elif not 0.0 < float(cfg.support) <= 1.0:
        bad = f"support={cfg.support}; a share of the chord in (0, 1]"
    elif not 0.0 <= float(cfg.min_inliers) <= 1.0:
        bad = f"min_inliers={cfg.min_inliers}; a share of the run in [0, 1]"
    elif not (float(cfg.contrast) >= 0.0 and float(cfg.max_rms) > 0.0):
        bad = f"contrast={cfg.contrast}, max_rms={cfg.max_rms}; contrast >= 0, max_rms > 0"
    if bad:
        raise ValueError(f"refine.bridges.{bad}")


def _kernels(length: int, offset: int, n: int, sub: int = 8) -> list[tuple]:
    """For each direction, three normalised kernels (centre, side -, side +) of segments
    ``length`` px long and one px wide, drawn anti-aliased (``sub`` x ``sub`` sub-pixels)."""
    half = length // 2 + offset + 2
    size = 2 * half + 1
    yy, xx = np.mgrid[0:size * sub, 0:size * sub]
    px = (xx + 0.5) / sub - size / 2.0
    py = (yy + 0.5) / sub - size / 2.0
    out = []
    for t in range(n):
        th = np.pi * t / n
        a = px * np.cos(th) + py * np.sin(th)  # along the segment
        b = -px * np.sin(th) + py * np.cos(th)  # across it
        ks = []
        for off in (0.0, -float(offset), float(offset)):
            k = ((np.abs(a) <= length / 2.0) & (np.abs(b - off) <= 0.5)).astype(np.float32)
            k = k.reshape(size, sub, size, sub).mean(axis=(1, 3))
            ks.append(k / k.sum())
        out.append(tuple(ks))
    return out


def line_response(img: np.ndarray, length: int = 9, offset: int = 2, orientations: int = 12
                  ) -> np.ndarray:
    """Ridge/valley response [orientations, H, W] (float32) of an RGB image (see module)."""
    import cv2
    im = np.asarray(img, np.float32)
    if im.ndim == 2:
        im = im[..., None]
    out = np.zeros((orientations,) + im.shape[:2], np.float32)

    def filt(k: np.ndarray) -> np.ndarray:
        # the kernel cut to the box of its non-zero weights and its centre (a thin segment:
        # OpenCV filters a small kernel directly, a 17x17 one by DFT), anchored at the centre
        centre = k.shape[0] // 2
        rows, cols = np.nonzero(k.any(1))[0], np.nonzero(k.any(0))[0]
        r0, c0 = min(int(rows[0]), centre), min(int(cols[0]), centre)
        r1, c1 = max(int(rows[-1]), centre), max(int(cols[-1]), centre)
        box = np.ascontiguousarray(k[r0:r1 + 1, c0:c1 + 1])
        return cv2.filter2D(im, -1, box, anchor=(centre - c0, centre - r0),
                            borderType=cv2.BORDER_REFLECT)

    for t, (kc, k1, k2) in enumerate(_kernels(int(length), int(offset), int(orientations))):
        c = filt(kc)
        a = c - filt(k1)
        b = c - filt(k2)
        if a.ndim == 2:
            a, b = a[..., None], b[..., None]
        same = (a * b).sum(-1) > 0
        r = np.minimum(np.sqrt((a * a).sum(-1)), np.sqrt((b * b).sum(-1)))
        out[t] = np.where(same, r, 0.0)
    return out


def _across(t: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit pixel steps (dy, dx) across direction bin(s) ``t``."""
    th = np.pi * np.asarray(t) / n
    return np.rint(np.cos(th)).astype(int), np.rint(-np.sin(th)).astype(int)


def _thin_max(r: np.ndarray, arg: np.ndarray, n: int) -> np.ndarray:
    """Pixels at least as strong as both neighbours across their best direction."""
    h, w = r.shape
    dy, dx = _across(arg, n)
    yy, xx = np.mgrid[0:h, 0:w]
    keep = np.ones((h, w), bool)
    for s in (1, -1):
        keep &= r >= r[np.clip(yy + s * dy, 0, h - 1), np.clip(xx + s * dx, 0, w - 1)]
    return keep


def _chord_end(c0: np.ndarray, ax: np.ndarray, start: float, sign: int, mask: np.ndarray,
               holes: np.ndarray) -> Optional[float]:
    """Axis coordinate where the ray from ``start`` meets the mask; None when it leaves the
    hole any other way (the image's side)."""
    h, w = mask.shape
    s = start + sign * np.arange(1, h + w + 2)
    x = np.rint(c0[0] + s * ax[0]).astype(int)
    y = np.rint(c0[1] + s * ax[1]).astype(int)
    inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    stop = np.nonzero(~inside)[0]
    n = stop[0] if len(stop) else len(s)
    x, y = x[:n], y[:n]
    off = np.nonzero(~holes[y, x])[0]
    if not len(off):
        return None
    i = off[0]
    return float(s[i]) if mask[y[i], x[i]] else None


def _straight(p: np.ndarray, max_rms: float, min_inliers: float
              ) -> Optional[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Principal axis of the points ``p`` [N, 2] (x, y) refitted on the points within 1 px
    of the first fit -- a texture speck or a crossing line touching a run does not bend it
    -- when at least ``min_inliers`` of them lie there at an RMS distance of at most
    ``max_rms``: (centre, unit axis, the inliers' coordinates along it); else None."""
    sel = np.ones(len(p), bool)
    for _ in range(2):
        c0 = p[sel].mean(0)
        q = p[sel] - c0
        _, vec = np.linalg.eigh(q.T @ q / len(q))
        perp = (p - c0) @ vec[:, 0]
        sel = np.abs(perp) <= 1.0
        if sel.sum() < 2:
            return None
    if sel.mean() < min_inliers or np.sqrt((perp[sel] ** 2).mean()) > max_rms:
        return None
    return c0, vec[:, 1], (p[sel] - c0) @ vec[:, 1]


def thin_bridges(img: np.ndarray, mask: np.ndarray, cfg: BridgeConfig
                 ) -> tuple[np.ndarray, dict]:
    """Pixels (bool [H, W]) of thin straight parts bridging holes of ``mask``, and counts."""
    mask = np.asarray(mask, bool)
    stats = {"holes": 0, "candidates": 0, "bridges": 0, "added_px": 0}
    added = np.zeros_like(mask)
    holes = ndimage.binary_fill_holes(mask) & ~mask
    n_dir = int(cfg.orientations)
    length = int(cfg.length)
    min_len = float(cfg.min_length or length)
    min_hole = int(cfg.min_hole or length * length)
    lab, nh = ndimage.label(holes)
    if nh == 0:
        return added, stats
    area = np.bincount(lab.ravel(), minlength=nh + 1)
    big = area >= min_hole
    big[0] = False
    holes = big[lab]
    if not holes.any():
        return added, stats
    # work on the holes' box, padded by the filter's reach
    pad = length // 2 + int(cfg.offset) + 3
    ys, xs = np.nonzero(holes)
    y0, y1 = max(int(ys.min()) - pad, 0), min(int(ys.max()) + pad + 1, mask.shape[0])
    x0, x1 = max(int(xs.min()) - pad, 0), min(int(xs.max()) + pad + 1, mask.shape[1])
    m = mask[y0:y1, x0:x1]
    ho = holes[y0:y1, x0:x1]
    hl = lab[y0:y1, x0:x1] * ho
    ids = np.unique(hl[ho])
    stats["holes"] = int(len(ids))
    rs = line_response(img[y0:y1, x0:x1], length, int(cfg.offset), n_dir)
    best = rs.max(0)
    arg = rs.argmax(0)
    lo_floor = float(cfg.contrast) * float(cfg.low_share)
    t_hi = np.full((int(lab.max()) + 1, n_dir), np.inf, np.float32)
    t_lo = np.full((int(lab.max()) + 1, n_dir), np.inf, np.float32)
    hv = hl[ho]
    for t in range(n_dir):
        v = rs[t][ho]
        for h in ids:
            vv = v[hv == h]
            t_hi[h, t] = max(float(cfg.contrast), float(np.percentile(vv, cfg.q_high)))
            t_lo[h, t] = max(lo_floor, float(np.percentile(vv, cfg.q_low)))
    cand = ho & _thin_max(best, arg, n_dir) & (best > t_hi[hl, arg])
    stats["candidates"] = int(cand.sum())
    hh, ww = m.shape
    out = np.zeros_like(m)
    eight = np.ones((3, 3), bool)
    cos_tol = np.cos(np.deg2rad(180.0 / n_dir + 5.0))
    for t in range(n_dir):
        near = np.abs((arg - t + n_dir // 2) % n_dir - n_dir // 2) <= 1
        runs, n_runs = ndimage.label(cand & near, eight)
        if n_runs == 0:
            continue
        th = np.pi * t / n_dir
        u = np.array([np.cos(th), np.sin(th)])
        rr = np.maximum.reduce([rs[(t + d) % n_dir] for d in (-1, 0, 1)])
        dy, dx = _across(t, n_dir)
        for i, sl in enumerate(ndimage.find_objects(runs)):
            ry, rx = np.nonzero(runs[sl] == i + 1)
            if len(ry) < 0.7 * min_len:
                continue
            p = np.stack([rx + sl[1].start, ry + sl[0].start], 1).astype(float)
            fit = _straight(p, cfg.max_rms, cfg.min_inliers)
            if fit is None:
                continue
            c0, ax, along = fit
            if along.max() - along.min() < min_len:
                continue
            if abs(float(ax @ u)) < cos_tol:
                continue
            e_hi = _chord_end(c0, ax, float(along.max()), 1, m, ho)
            e_lo = _chord_end(c0, ax, float(along.min()), -1, m, ho)
            if e_hi is None or e_lo is None:
                continue
            s = np.arange(np.ceil(e_lo), np.floor(e_hi) + 1)
            cx = np.rint(c0[0] + s * ax[0]).astype(int)
            cy = np.rint(c0[1] + s * ax[1]).astype(int)
            ok = (cx >= 0) & (cx < ww) & (cy >= 0) & (cy < hh)
            cx, cy = cx[ok], cy[ok]
            inner = ho[cy, cx]
            if not inner.any():
                continue
            cx, cy = cx[inner], cy[inner]
            hole = int(np.bincount(hl[cy, cx]).argmax())
            lo = t_lo[hole, t]
            ny = np.stack([np.clip(cy + k * dy, 0, hh - 1) for k in (-1, 0, 1)])
            nx = np.stack([np.clip(cx + k * dx, 0, ww - 1) for k in (-1, 0, 1)])
            val = rr[ny, nx]  # [3, samples]
            k = val.argmax(0)
            top = val[k, np.arange(len(k))]
            if (top > lo).mean() < cfg.support:
                continue
            sel = top > lo
            j = np.arange(len(k))[sel]
            out[ny[k[sel], j], nx[k[sel], j]] = True
            stats["bridges"] += 1
    out &= ho
    added[y0:y1, x0:x1] = out
    stats["added_px"] = int(out.sum())
    return added, stats
