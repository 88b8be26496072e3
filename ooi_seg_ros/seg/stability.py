"""Check after the point stages: would a slightly different SfM cloud give the same object?

The noise stage decides where the object ends and a neighbour begins from thresholds on how
its DBSCAN ladder moves (``noise.settle_change``, ``noise.max_extent_growth``). A capture
whose ladder sits near one of them flips between "the object", "a fragment of it" and "the
object with the clutter beside it" on a few SfM points more or less: the simulator's toy car
of seed 4 went from 534 OOI points (mask IoU 0.96) to 904 (the clutter beside it, IoU 0.54)
on an SfM cloud with 1% more points (BENCHMARKS, session 13). Nothing in the OOI cloud itself
says so, so the user would be shown a wrong object as success.

This check re-runs the point stages (the same functions and options) on ``draws`` copies of
the cloud with ``drop`` of its points left out at random (seeded: the same input gives the
same answer), and compares each copy's OOI set with the whole cloud's by the Jaccard index
over the points both copies hold. A copy below ``min_jaccard`` is a *flip*; any flip becomes
a warning in the report, the CLI's output and the node's log, naming the share of flips and
the sizes of the sets the copies chose. A majority vote of the copies would be no answer
(session 13: it fixes as many captures as it breaks; on toy car 4 the coin falls either way).

With ``resolve`` (default) a flip also gets a tie-break: the noise stage's DBSCAN selection
runs on the whole cloud's noise input at the eps scale each flipped copy stopped at, and of
those sets and the original choice the one whose box is best centred on the cameras'
convergence point is kept -- the premise the ROI and the central cluster already use: the
orbit frames its object, and a neighbour beside it pulls the box off centre. Measured on 726
clouds (the 66 simulator SfM clouds and 10 copies of each with 10% of the points left out):
it changed 10, all from a wrong OOI cloud to a right one, and made none wrong. Where it cannot
help: a fragment of the object that lies nearer the convergence point than the whole object's
box centre (tabletop seed 7 with ``epipolar_band_matching``) is kept. Stable captures (no
flip) are never touched.

Cost: ``draws`` more runs of the point stages (0.23-0.42 s in all on the simulator's clouds;
8.6 s on the bonsai's 97k points, next to the 149 s of its masks). Clouds with
more than ``max_points`` points are checked on a random ``max_points`` of them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .density import spacing
from .noise import NoiseConfig, _dbscan_at, _off_centre


@dataclass
class StabilityConfig:
    """Options of the OOI-cloud stability check (a warning only; the cloud is not changed)."""

    draws: int = 5  # copies of the cloud to re-run the point stages on (0 = no check)
    drop: float = 0.1  # share of the points each copy leaves out at random
    min_jaccard: float = 0.8  # a copy whose OOI set has a lower Jaccard index with the
    # whole cloud's (over the points both hold) is a flip
    max_points: int = 200_000  # larger clouds: the copies are drawn from this many points
    resolve: bool = True  # after a flip, keep whichever of the whole cloud's choice and the
    # flipped copies' (the noise stage on the whole input at their eps scale) is best centred
    # on the cameras' convergence point (see centred_alternative; measured, BENCHMARKS)


def stability_check(n: int, chosen: np.ndarray,
                    run_stages: Callable[[np.ndarray], tuple[np.ndarray, dict]],
                    cfg: StabilityConfig, seed: int) -> dict:
    """Re-run the point stages on copies of a cloud of ``n`` points and compare.

    ``chosen``: indices (into the cloud) of the OOI set the whole cloud gave.
    ``run_stages(idx)``: (the OOI set, as indices into the cloud, that the point stages
    choose from the points ``idx``; the last stage's parameters). The set is empty when they
    find no object.
    Returns {"draws", "drop", "jaccard": [per copy], "sizes": [OOI points per copy],
    "flips", "min_jaccard", "flip_scales": [the noise stage's final eps scale of each
    flipped copy, when it reports one]}.
    """
    out: dict = {"draws": int(cfg.draws), "drop": float(cfg.drop),
                 "min_jaccard": float(cfg.min_jaccard), "jaccard": [], "sizes": [], "flips": 0,
                 "flip_scales": []}
    if cfg.draws <= 0 or n == 0:
        return out
    if not 0.0 < cfg.drop < 1.0:
        raise ValueError(f"stability.drop={cfg.drop}; use a share between 0 and 1")
    rng = np.random.default_rng([int(seed), 0x5AB1E])
    base = np.arange(n)
    if n > cfg.max_points:
        base = np.sort(rng.choice(n, cfg.max_points, replace=False))
    whole = np.zeros(n, bool)
    whole[np.asarray(chosen, np.int64)] = True
    for _ in range(cfg.draws):
        idx = base[rng.random(len(base)) >= cfg.drop]
        got, info = run_stages(idx)
        sel = np.zeros(n, bool)
        sel[np.asarray(got, np.int64)] = True
        a, b = whole[idx], sel[idx]
        union = int((a | b).sum())
        jac = float((a & b).sum() / union) if union else 1.0
        out["jaccard"].append(round(jac, 4))
        out["sizes"].append(int(sel.sum()))
        if jac < cfg.min_jaccard:
            out["flips"] += 1
            if (info or {}).get("eps_scale") is not None and len(got):
                out["flip_scales"].append(float(info["eps_scale"]))
    return out


def centred_alternative(xyz: np.ndarray, chosen: np.ndarray, scales: list,
                        noise_cfg: NoiseConfig, target: np.ndarray, radius: float
                        ) -> tuple[np.ndarray, dict]:
    """The tie-break ``resolve`` applies after flips: of the noise stage's choice
    ``chosen`` (indices into its input ``xyz``) and the sets its DBSCAN selection gives on
    the same input at the eps scales the flipped copies stopped at, the one whose box is best
    centred on the cameras' convergence point (``noise._off_centre``: the orbit frames its
    object). Returns (indices, {"candidates": [[scale or None, points, off-centre]],
    "chosen_scale"})."""
    sp = spacing(xyz, noise_cfg.min_samples)
    best = (np.asarray(chosen, np.int64), None, _off_centre(xyz[chosen], target))
    cands = [[None, int(len(chosen)), round(best[2], 4)]]
    for sc in sorted(set(scales)):
        k, _ = _dbscan_at(xyz, noise_cfg, target, radius, sc * sp, sp)
        if len(k) < 4:
            continue
        off = _off_centre(xyz[k], target)
        cands.append([sc, int(len(k)), round(off, 4)])
        if off < best[2]:
            best = (k, sc, off)
    return best[0], {"candidates": cands, "chosen_scale": best[1]}


def stability_warning(check: dict, n_chosen: int) -> str:
    """The report's warning for a check with flips ('' when there are none)."""
    if not check.get("flips"):
        return ""
    flipped = [s for s, j in zip(check["sizes"], check["jaccard"]) if j < check["min_jaccard"]]
    sizes = (f"{min(flipped)}" if min(flipped) == max(flipped)
             else f"{min(flipped)}-{max(flipped)}")
    return (f"the object/neighbour decision is close: with {check['drop']:.0%} of the SfM "
            f"points left out, {check['flips']} of {check['draws']} re-runs of the point "
            f"stages chose a different OOI cloud (Jaccard {min(check['jaccard']):.2f} with "
            f"this one; {sizes} points instead of {n_chosen}); a "
            f"neighbouring object may be included or a part of the object left out -- look "
            f"at the OOI cloud and the masks in report.html")
