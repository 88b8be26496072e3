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
orbit frames its object, and a neighbour beside it pulls the box off centre. A candidate
that lies inside a larger one whose further points have the same colours (``alike_colour``)
is a fragment of that one's object, not a choice of its own: the centring cannot tell a part
of the object that happens to sit nearer the convergence point (tabletop seed 7 with
``epipolar_band_matching``) from the object without its neighbour, the colours can (same
object 0.8-1.2 times the object's own colour spacing, the toy car's clutter 3.9-28; session
15). Measured on 726 clouds (the 66 simulator SfM clouds and 10 copies of each with 10% of
the points left out; the flags fall on tabletop and toy car clouds and on one bicycle copy):
with 10 draws and the colour rule the tie-break changed 13, all from a wrong OOI cloud to a
right one, and made none wrong; wrong OOI clouds 8 -> 1 (default SfM) and 9 -> 3 (band SfM;
no re-run flags three copies of toy car 4). Session 14's 5 draws with the centring alone:
8 -> 3 and 9 -> 4; 10 draws with the centring alone broke one (a same-coloured fragment,
tabletop 1). Stable captures (no flip) are never touched.

The flipped copies' own choice is a candidate too (``copies``) when at least half of the
copies made it (grouped by Jaccard, ``copies_choice``): re-running the noise stage on the whole
cloud at a copy's eps scale is not the same as what the copy chose, because the points a copy
leaves out can be the ones that bridged the object to its neighbour. Toy car seed 1 on JPEG
images (session 20): 5-7 of 10 copies chose the car (~510 points), the whole cloud at their
scale gave 954 points (car + part of the clutter, whose further points looked like it), so
car + clutter (1,122 points, mask IoU 0.38) stayed; with the copies' set (568 points, best
centred) the IoU is 0.92. On the other 40 lossless and 17 JPEG simulator clouds the choice did
not change (``bench_seg_stability.py``, BENCHMARKS); a single flipped copy's set is not offered
(it had replaced the right tabletop seed 3 with object + neighbour).

The centring is refused a candidate larger than the first choice that reaches more than
``noise.max_extent_growth`` x as far from the convergence point (``extent_guard``), unless the
first choice is a fragment of it by colour: clutter on several sides of an object can frame the
convergence point better together with the object than the object alone. Session 68 (CI on the
tabletop's bare photos: 203 -> 295 points, mask IoU 0.80); on the 16 tabletop and toy car
captures and 10 copies each (``bench_seg_tiebreak.py``) the guard turns the 4 tabletop 3 copies
the tie-break made wrong (purity 0.70, the plant with the things on the table) back into the
plant (0.90) and changes no other cloud.

Cost: ``draws`` more runs of the point stages (about 0.05-0.08 s each on the simulator's
clouds; 1.7 s each on the bonsai's 97k points, next to the 149 s of its masks). Clouds with
more than ``max_points`` points are checked on a random ``max_points`` of them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
from scipy.spatial import cKDTree

from .density import spacing
from .noise import NoiseConfig, _dbscan_at, _extent, _off_centre


@dataclass
class StabilityConfig:
    """Options of the OOI-cloud stability check (a warning only; the cloud is not changed)."""

    draws: int = 10  # copies of the cloud to re-run the point stages on (0 = no check)
    drop: float = 0.1  # share of the points each copy leaves out at random
    min_jaccard: float = 0.8  # a copy whose OOI set has a lower Jaccard index with the
    # whole cloud's (over the points both hold) is a flip
    max_points: int = 200_000  # larger clouds: the copies are drawn from this many points
    resolve: bool = True  # after a flip, keep whichever of the whole cloud's choice and the
    # flipped copies' (the noise stage on the whole input at their eps scale) is best centred
    # on the cameras' convergence point (see centred_alternative; measured, BENCHMARKS)
    alike_colour: float = 2.0  # in that tie-break, a candidate inside a larger one whose
    # further points' colours are this alike (colour_ratio below it; ~1 = the same colours,
    # 0 = off) is a fragment of the larger one's object and is not chosen over it
    extent_guard: bool = True  # in that tie-break, a set larger than the first choice whose
    # extent grew past noise.max_extent_growth x its extent is no candidate (the step the
    # noise stage itself refuses; see centred_alternative, session 68)
    copies: bool = True  # in that tie-break, a set that at least half of the copies chose
    # themselves (``copies_choice``) is a candidate too, not only the noise stage re-run on
    # the whole cloud at their eps scale (measured: BENCHMARKS, session 20)


def stability_check(n: int, chosen: np.ndarray,
                    run_stages: Callable[[np.ndarray], tuple[np.ndarray, dict]],
                    cfg: StabilityConfig, seed: int,
                    flipped: Optional[list] = None) -> dict:
    """Re-run the point stages on copies of a cloud of ``n`` points and compare.

    ``chosen``: indices (into the cloud) of the OOI set the whole cloud gave.
    ``run_stages(idx)``: (the OOI set, as indices into the cloud, that the point stages
    choose from the points ``idx``; the last stage's parameters). The set is empty when they
    find no object.
    Returns {"draws", "drop", "jaccard": [per copy], "sizes": [OOI points per copy],
    "flips", "min_jaccard", "flip_scales": [the noise stage's final eps scale of each
    flipped copy, when it reports one]}.
    ``flipped`` (optional) receives, per flipped copy, (the points it held, the OOI set it
    chose), both as indices into the cloud (for ``copies_choice``).
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
            if flipped is not None and len(got):
                flipped.append((idx, np.asarray(got, np.int64)))
    return out


def copies_choice(n: int, flipped: list, min_jaccard: float, min_copies: int = 1
                  ) -> list[np.ndarray]:
    """The sets the flipped copies chose, as sets of the whole cloud (indices into its ``n``
    points): the copies are grouped by what they chose (a copy joins the first group whose
    first copy's set it matches with a Jaccard index of at least ``min_jaccard`` over the
    points both held), and each group's set is the points a majority of the group's copies
    that held them chose. Only groups of at least ``min_copies`` copies give a set (the
    pipeline asks for half the draws: when 9 of 10 copies agree with the whole cloud's choice,
    the one that did not is the exception, not an alternative). A copy's choice is what the
    point stages really do on that cloud; re-running only the noise stage on the whole cloud
    at the copy's eps scale is not the same set (the dropped points had bridged the object to
    a neighbour: toy car seed 1 on JPEG images, session 20)."""
    groups: list[list[tuple[np.ndarray, np.ndarray]]] = []
    for held, got in flipped:
        for g in groups:
            h0, g0 = g[0]
            both = np.intersect1d(held, h0, assume_unique=True)
            a, b = np.isin(both, g0), np.isin(both, got)
            union = int((a | b).sum())
            if union and (a & b).sum() / union >= min_jaccard:
                g.append((held, got))
                break
        else:
            groups.append([(held, got)])
    out = []
    for g in groups:
        if len(g) < min_copies:
            continue
        votes = np.zeros(n, np.int32)
        seen = np.zeros(n, np.int32)
        for held, got in g:
            seen[held] += 1
            votes[got] += 1
        out.append(np.nonzero((seen > 0) & (2 * votes > seen))[0])
    return out


def colour_ratio(core: np.ndarray, extra: np.ndarray) -> float:
    """How unlike the colours ``extra`` [M,3] are to the colours ``core`` [N,3]: the median
    distance (RGB) from an extra point's colour to its nearest core colour, over the median
    distance from a core colour to its nearest other core colour. About 1 when the extra
    points look like a sample of the core's colours; inf without colour information (fewer
    than 2 core points, no extra points, or a core of one exact colour)."""
    core = np.asarray(core, float)
    extra = np.asarray(extra, float)
    if len(core) < 2 or len(extra) == 0:
        return float("inf")
    tree = cKDTree(core)
    own = float(np.median(tree.query(core, k=2)[0][:, 1]))
    if own <= 1e-9:
        return float("inf")
    return float(np.median(tree.query(extra, k=1)[0])) / own


def centred_alternative(xyz: np.ndarray, chosen: np.ndarray, scales: list,
                        noise_cfg: NoiseConfig, target: np.ndarray, radius: float,
                        rgb: Optional[np.ndarray] = None, alike: float = 0.0,
                        copies: Optional[list] = None, max_growth: float = 0.0,
                        up_plane: Optional[np.ndarray] = None) -> tuple[np.ndarray, dict]:
    """The tie-break ``resolve`` applies after flips: of the noise stage's choice
    ``chosen`` (indices into its input ``xyz``) and the sets its DBSCAN selection gives on
    the same input at the eps scales the flipped copies stopped at, the one whose box is best
    centred on the cameras' convergence point (``noise._off_centre``: the orbit frames its
    object).

    With point colours ``rgb`` and ``alike`` > 0, a candidate that is (95% or more) inside a
    larger candidate whose further points look like it (``colour_ratio`` < ``alike``) is a
    fragment of that one's object and not a choice: the larger one stands in for it. This
    stops the centring from trading the whole object for a part of it that happens to sit
    nearer the convergence point (BENCHMARKS, session 15); a neighbour whose colours differ
    from the object's is still left to the centring.

    ``copies`` (optional): the sets the flipped copies themselves chose (``copies_choice``,
    as indices into ``xyz``), candidates too, labelled "copies".

    ``max_growth`` > 0: a candidate larger than ``chosen`` whose 98% extent around the
    convergence point (``noise._extent``) is more than this x the extent of ``chosen`` is
    not a choice, unless ``chosen`` is a fragment of it by the colour rule above. The noise
    stage refuses such a step on its own ladder (``max_extent_growth``: a neighbour joining);
    the centring alone accepted it when clutter lies on several sides of the object, so the
    object and its neighbours together frame the convergence point better than the object
    (the tabletop's bare photos in CI, session 68: 203 -> 295 points, mask IoU 0.80; on a
    cloud of the same photos the whole-noise-input set is off-centre 0.025 against the
    plant's 0.072, with 2.4x its extent and purity 0.58).

    ``up_plane``: the support plane, for the noise stage's ``central_weight`` "standing".

    Returns (indices, {"candidates": [[label (the eps scale, "copies", or None for
    ``chosen``), points, off-centre, label of the candidate it is a fragment of, or "-"]],
    "chosen_scale": the chosen candidate's label})."""
    sp = spacing(xyz, noise_cfg.min_samples)
    sets: list = [(None, np.asarray(chosen, np.int64))]
    for sc in sorted(set(scales)):
        k, _ = _dbscan_at(xyz, noise_cfg, target, radius, sc * sp, sp, up_plane)
        if len(k) >= 4:
            sets.append((sc, np.asarray(k, np.int64)))
    for k in copies or []:
        if len(k) >= 4:
            sets.append(("copies", np.asarray(k, np.int64)))
    offs = [_off_centre(xyz[k], target) for _, k in sets]
    part_of: list = ["-"] * len(sets)
    parent = [-1] * len(sets)  # index of the candidate each one is a fragment of
    if rgb is not None and alike > 0 and len(rgb) == len(xyz):
        rgb = np.asarray(rgb, float)
        for i, (_, a) in enumerate(sets):
            for j, (scj, b) in enumerate(sets):
                if len(b) <= len(a):
                    continue
                inside = np.isin(a, b)
                if inside.mean() < 0.95:
                    continue
                extra = b[~np.isin(b, a)]
                if colour_ratio(rgb[a], rgb[extra]) < alike:
                    part_of[i], parent[i] = scj, j
                    break
    wide = [False] * len(sets)
    if max_growth > 0 and len(sets) > 1:
        e0 = _extent(xyz[sets[0][1]], target)
        for i in range(1, len(sets)):
            wide[i] = (len(sets[i][1]) > len(sets[0][1]) and parent[0] != i
                       and _extent(xyz[sets[i][1]], target) > max_growth * e0)
    best = 0
    for i in range(1, len(sets)):
        if not wide[i] and part_of[i] == "-" and (part_of[best] != "-" or offs[i] < offs[best]):
            best = i
    if part_of[best] != "-":  # every candidate a fragment of another: keep the largest
        best = int(np.argmax([0 if w else len(k) for (_, k), w in zip(sets, wide)]))
    cands = [[sc, int(len(k)), round(o, 4), p] for (sc, k), o, p in zip(sets, offs, part_of)]
    out = {"candidates": cands, "chosen_scale": sets[best][0]}
    if any(wide):
        out["too_wide"] = [sets[i][0] for i in range(len(sets)) if wide[i]]
    return sets[best][1], out


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
