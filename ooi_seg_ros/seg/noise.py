"""Stage 4.3: noise removal -- keep one DBSCAN cluster (or statistical outlier removal).

``eps`` is derived from the cloud: ``eps_scale`` times the median distance to the
``min_samples``-th neighbour. ``select="largest"`` is the paper's rule; ``select="central"``
(improved) keeps the cluster with most points near the cameras' convergence point, i.e. the
cluster the orbit is looking at, and also merges clusters that lie (mostly) within that
cluster's own reach from the convergence point (parts of one object split by a sparse gap).
"Most points near" is a count within the frame radius; a far orbit or a wide lens frames
the object's neighbours too, and a larger neighbour then outnumbers it (the tabletop's
plant, 107 points at the convergence point, against a box of 215 half a frame radius off:
IoU 0.54-0.62 on the far rings and through a 90 deg lens at 320x240). ``central_weight``
"standing" (``ours``) weights each point by 1 - distance / radius instead where the two
rules disagree and the count's cluster stands beside the other on the support plane (its
foot less than ``part_above`` of the other's height above the other's foot): the object the
orbit centres on. Where the count's cluster floats over the nearer one -- a bonsai's crown
over its pot, both split by a sparse trunk -- the count stands ("linear", weighting
everywhere, took the pot alone on one 72-photo subset of the real bonsai: 2,394 -> 589
points). ``central_inner`` (``ours``) goes one step further where even the weights favour
the neighbour: a cluster whose points all lie nearer the convergence point than the main
cluster's nearest points, that stands beside it and holds at least ``part_min_points`` as
many points, is the main cluster (the tabletop's far seed 5: box 272 points from 0.42 frame
radius out, weight 112.5; plant 125 points within 0.09-0.3, weight 99.3; IoU 0.58 -> 0.93).
``iterations`` > 1 repeats the removal until fewer than ``stop_fraction`` of the points are
removed in a round.

``eps_max_scale`` > ``eps_scale`` (improved) widens eps in steps of ``eps_step`` spacings
while the selected set stays as compact as at the first eps (its 98% extent around the
convergence point grows by at most ``max_extent_growth``x) and DBSCAN still finds more than
one cluster. Why: the spacing is a median, and it halves when the images get larger (the
SfM finds twice the points on the textured parts) while the gaps between an object's parts
(a tail, an engine) stay as wide in the world; a fixed eps in spacings then cuts those parts
off (aircraft at 640x360: 14 clusters, 17% of its points lost). A wider eps that joins a
neighbouring object (the clutter beside the toy car) moves the set's extent far out (x2.5),
which stops the widening there.

``settle_change`` > 0 (improved default) chooses that reference extent by persistence, the
argument of HDBSCAN: the widening starts low (1 spacing, where a neighbour that lies a little
over a spacing away is still apart), accepts every step while the object is still gathering
its own parts (its extent may triple as a wing or a tail joins), and takes as the reference
the extent at the first step that changes the selected set by less than ``settle_change`` of
it -- the object is whole there. A later step that moves the extent past
``max_extent_growth`` x that is a neighbour joining. Why not one fixed start: at 1.5 spacings
the toy car of seed 1 is already chained to the clutter beside it (IoU 0.40), while starting
at 1 spacing with the first extent as the reference cuts the aircraft's wings off (seed 1:
its fuselage alone at 1 spacing; the wings join at 1.25).
When the main cluster changes after the set settled (the object was in fragments within a
neighbour's reach; a wider eps makes it one cluster that outweighs the neighbour), the step
leaves out much of the settled set, and ``rebase_on_switch`` (``ours``) takes the new set's
extent as the reference: the settled extent was the neighbour's, and against it the
neighbour chaining back to the object at a wider eps passed (the tabletop's far seed 1).
A sparse object can settle on the half of it nearest the convergence point (the bicycle of
seed 6 at 320x240: 61 of its ~130 points); the other half then joins with a jump in extent
like a neighbour's, but it moves the centre of the set's box towards the point the cameras
converge on (``_off_centre`` falls), so it is taken as a part and the reference extent
follows it. A neighbour beside a centred object moves that centre away -- in metres; but
the offset is relative to the box, which the neighbour grows, so it can fall all the same
(the toy car's far seed 3: clutter on two sides, 0.020 -> 0.034 m off, relative 0.132 ->
0.117; IoU 0.72). ``centre_absolute`` (``ours``) lets the centre drift in metres only by less
than its relative offset falls (the bicycle's other half: 0.193 -> 0.201 m, relative 0.352
-> 0.230, still a part). Because a part that
centres the set passes whatever the growth, the improved default asks the question earlier
(``max_extent_growth`` 1.25 instead of 1.5): the toy car's clutter that joins at 1.35x
(seeds 5 and 6) is refused. That value was read off the simulator's clouds (at 1.15 a
tabletop part is lost, seed 3; at 1.35 the clutter stays): a fitted constant.

A part can also join with a jump and pull the box off the convergence point: the real
bonsai's crown, which leans to one side of the pot the cameras aim at, is cut from the pot
by the sparse trunk when fewer photos are kept (58 of the 289: the pot and trunk settle
alone, the crown joins with 2.3x the extent and is refused). ``part_above`` (0.25 in
``ours``) tells such a part by where it stands: the groups a step adds (connected at that
eps) whose lowest points lie a quarter of the kept set's height or more above its foot over
the support plane are held up by the object -- a crown on a trunk, leaves over a pot -- and
when they hold half of the added points, and at least ``part_min_points`` (0.25) as many
points as the kept set, the step is a part joining. A neighbour stands on the support beside
the object: on the 66 simulator SfM clouds every refused neighbour, taken whole, starts at
-0.15 to +0.04 of the object's height above its foot, the held-up parts at 0.51 (tabletop,
band-matched cloud of seed 7) and 1.23 (the bonsai's crown). Judged per group because a few
low crumbs can join in the same step as a crown (the bonsai with 73 photos); the size floor
because a neighbour's top can join before its lower part (toy car 5: ~30 points against the
car's ~590, where the parts above hold 0.8-3.5x the kept set). A neighbour on a higher
support (a shelf behind the object) would pass this test; the extent and centring tests
still come first. ``lookahead`` (``ours``): a sparse crown can first join in crumbs (the
trunk's few points, and a crown fragment within the set's reach) that move the extent past
the limit but hold too few points to count as held up; the first refused step used to stop
the widening there (the real bonsai with 37 of its photos: the pot alone, 177 of 466
points, 7 of 10 stability copies elsewhere). The wider eps steps are then tried against the
same kept set, and the first whose additions are held up by it is taken (there: 2 spacings,
465 points). A step that centres the set is looked ahead for only with ``centre_absolute``
(the relative test alone passes any neighbour that grows the box around the target): a
sparse bicycle's other half can join in two steps, the first of which fails the drift test
(today's SfM cloud of bicycle 5 at 640x360: IoU 0.771 -> 0.923 with it).

What the widening cannot tell apart it reports (``warn_apart_share``): in a cloud too sparse
for the gap between the object and a neighbour (the depth-proxy cloud of ``sim:toycar:5`` at
the CLI's 30 views, or the toy car with 6-20 views), a neighbour 1.4-1.8 spacings away is
chained to the object at 1.25-1.5 spacings, before the set settles, so no later step is
refused; the clutter beyond it then lies within the main cluster's reach and is kept too
(IoU 0.38 with no warning before session 28). The signs, in the point stage's own terms:
the widening ran to ``eps_max_scale`` without refusing a step, and groups that even that eps
keeps apart from the main cluster hold at least ``warn_apart_share`` (5%) of the kept
points. Measured (session 28) on depth-proxy clouds of the five simulator scenes at 6-60
views and the 25 SfM clouds of the quality bench: every cloud that ran to the widest eps
without a refusal and with anything apart was an impure toy car (9.5-29% apart, purity
0.43-0.79); the real bonsai (289 views) keeps 2.7% apart (two small groups) and is not
flagged. 5% lies between the two, read off these clouds: a fitted constant. A neighbour
chained to the object with nothing beyond it inside the reach shows nothing here (toy car,
8 views, seed 6: purity 0.77, no warning): the warning is a sign, not a guarantee.

``retreat`` (on in ``ours``) acts on that sign when the ladder also shows where the chain
happened. A denser capture chains the same way: the toy car of seed 1 at 120 views is in 44
fragments at 1 spacing (its 98% extent 0.13, the set centred on the convergence point,
off-centre 0.03), and at 1.25 spacings the clutter beside it joins (extent x2.1, off-centre
0.26) before the set has settled, when every step is accepted (IoU 0.40, warned). A part
that joins before settling either centres the set (the aircraft's wings, the bicycle's
other half) or is held up by it (``part_above``); a neighbour standing beside the object
does neither. So the stage remembers the first step before settling that moved the extent
past ``max_extent_growth`` x the previous step's, moved the set's box off the convergence
point and held nothing up -- or, after settling, the first jump taken as a part only
because it centred the set a little (the sparse toy car of seed 3 at 8 and 12 views:
off-centre 0.129 -> 0.112 as the clutter joins at 3.25 spacings) -- and when the widening
then ends with the warning's signs, it keeps the set from before that step (the toy car of
seed 1 at 120 views: IoU 0.963, recall 0.978) and the warning says what it kept. The same
step with no warning's signs is taken as it was: the rule only turns a reported failure into
a correction, and adds no constant of its own. On the 200 depth-proxy clouds of
``bench_noise_warning.py`` it makes 11 of the 14 impure ones pure (87-100% of the object's
points kept) and changes no other cloud; toy cars 1 and 5 at 6 views (the neighbour chains
at the first eps or with less than ``max_extent_growth``) stay impure and warned.

``retreat_centring`` (off in ``ours``, session 72) decides whether the jump taken because it
centred the set is such a step. It was made for the sparse toy car of seed 3, whose clutter
centred the set "a little" -- the case ``centre_absolute`` now refuses at the step itself
(the depth-proxy toy car of seed 3 at 8 views: with ``centre_absolute`` off the retreat is
what keeps it pure; with it on the step is refused and the retreat has nothing to do). Left
on beside ``centre_absolute`` it undid the other half of a sparse bicycle when some of the
bicycle's own groups stayed apart at the widest eps (seed 6 at 640x360, SfM run of session
71: the look-ahead took the whole bicycle at 3 spacings, 17% of it ended apart, and the
retreat went back to the half, IoU 0.54). Off, that cloud keeps the whole bicycle (0.919,
warned for the groups apart) and none of the 200 depth-proxy clouds, the 101 other cached
SfM clouds or the 24 real-bonsai subsets changes.

``widen_unclustered`` (on in ``ours``) starts and continues the widening while DBSCAN finds
one cluster but leaves at least ``settle_change`` of the points in none. "More than one
cluster" alone missed a sparse cloud whose thin parts are all DBSCAN noise at one spacing:
the stool of seed 5 at 320x240 with ``density.relative_cut`` 0.1 (66 points after the
floor, one cluster, 20% in none) kept
53 points -- while a cloud four points smaller happened to split in two
and widened to 57. It uses the stage's own persistence share, so it adds no constant: a
sixth of the points outside every cluster means the set has not settled. With the default
density cut it changes no OOI set of the 25 simulator clouds, the demo or the bonsai.

``grow_scale`` (an option, off) adds, once, after this stage and the stability tie-break chose
the OOI set (``pipeline.py``), the points of this stage's input within ``grow_scale``
spacings of a kept point (``grow_selection``). Why: the noise stage leaves an object's lone
points past eps out -- an aircraft's landing-gear wheels, points at the edge of its T-tail's
stabiliser 1.4-3.4 spacings past the fin's top -- noise at every eps the widening tries.
Measured (session 53, BENCHMARKS): at 3 spacings the four aircraft captures under the recall
bar rise over it (the gear's points seed the dark belly beside it; the stabiliser's edge
points do not bring the plate back), and the stool gains; but on a thin or
sparse object the lone points are mostly floaters, and one that seeds GrabCut brings a whole
bush or patch of lawn into the bicycle's masks (IoU -0.04 to -0.12), while on the toy car
the hop reaches the edge of the clutter beside it (-0.08 to -0.16).
``grow_unclustered_only`` keeps the clutter's own clusters out (the toy car's added points
that were in another DBSCAN cluster were all off the object), and ``grow_sparse`` caps the
grown points' discs and keeps them out of GrabCut's object seeds as density's sparse points:
together they leave the toy car and the bicycle near the default but give the aircraft's
gain back too. Lone points alone do not tell a thin part from a floater.
``grow_local`` (an option, off) confines what the grown points may change in the masks to
their own neighbourhood: the masks are made a second time without them (exactly as with
``grow_scale`` off), and a pixel joins that result only where the masks with them hold it
within ``grow_local`` median mask-disc radii of a grown point's projection; nothing leaves.
Why: on the real bonsai three grown points moved 12k mask pixels (session 62), most of them
far from any grown point, through the hull steps and GrabCut's colour models. It costs a
second pass of the masks on captures where points grow.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from .density import spacing


@dataclass
class NoiseConfig:
    """Options of the noise-removal stage."""

    method: str = "dbscan"  # "dbscan" | "sor" (statistical outlier removal) | "none"
    eps_scale: float = 2.0  # DBSCAN eps in units of the median min_samples-NN distance
    min_samples: int = 8  # DBSCAN core-point neighbourhood size
    select: str = "largest"  # "largest" (paper) | "central" (nearest the convergence point)
    central_weight: str = "count"  # central: the main cluster holds the most points within
    # the frame radius of the convergence point ("count"), or the most such points weighted
    # by 1 - distance / radius ("linear": a neighbour at the frame's edge counts less than
    # the object the orbit centres on), or "standing": the linear choice where the count's
    # choice stands beside it on the support (its foot less than part_above of the linear
    # choice's height above that one's foot), the count's where it floats over it (a crown)
    sor_neighbours: int = 16  # SOR: neighbours per point
    sor_std_ratio: float = 2.0  # SOR: mean-distance threshold in standard deviations
    grow_scale: float = 0.0  # after this stage and the tie-break, add points of its input
    # within this x the median min_samples-NN distance of a kept point (one hop; 0 = off)
    grow_unclustered_only: bool = False  # grow_scale: only points DBSCAN left in no cluster
    grow_colour_vote: float = 0.0  # grow_scale: > 0, a point joins only when in at least
    # this share of the views framing it its pixel is nearer the OOI points' colours than the
    # rest of the cloud's (residual.colour_vote)
    grow_sparse: bool = False  # grow_scale: the grown points are flagged as density's sparse
    # points are (capped mask discs; no GrabCut object seeds unless density.sparse_seeds)
    grow_local: float = 0.0  # grow_scale: > 0, the grown points change the masks only within
    # this x the median mask disc radius of a grown point (a second pass of the masks without
    # them; elsewhere their hull steps and GrabCut seeds move pixels they never touch)
    merge_reach_quantile: float = 0.98  # central: the main cluster's reach = this quantile
    # of its points' distances to the convergence point; other clusters within it are merged
    # (0: within the frame radius instead)
    merge_reach_scale: float = 1.0  # central: clusters within this x the main cluster's reach
    # are merged (a leaf or a tail may stick out beyond the compact core the orbit centres on)
    eps_max_scale: float = 0.0  # widen eps up to this many spacings while the selected set
    # stays compact (see max_extent_growth); <= eps_scale: a single eps
    eps_step: float = 0.5  # step of the widening, in spacings
    max_extent_growth: float = 1.5  # a wider eps is accepted while the selected set's 98%
    # extent around the convergence point stays within this x its reference extent (the
    # extent at eps_scale, or at the settled eps, see settle_change)
    part_above: float = 0.0  # > 0 (with settle_change and a support plane): a group that
    # joins with a jump in extent is a part when its lowest points (2% quantile of height over
    # the support plane) lie at least this share of the selected set's own height (2-98%)
    # above that set's bottom -- held up by the object (a crown on a trunk), not standing
    # beside it on the support as a neighbour does. 0 = off (the paper)
    part_min_points: float = 0.25  # part_above: the held-up groups must also hold at least
    # this share of the selected set's points (a part, not a neighbour's top that joins first)
    settle_change: float = 0.0  # > 0: the reference extent is the one at the first eps whose
    # selected set differs from the previous eps's by less than this share of it (the object
    # is whole: HDBSCAN's persistence); until then every widening is accepted. 0 = the
    # reference is the extent at eps_scale
    grid_above_pairs: int = 20_000_000  # DBSCAN runs on a voxel grid (cells of eps x
    # grid_cell_scale, weighted by their point counts) when the cloud's estimated number of
    # eps-neighbour pairs exceeds this; below it the exact per-point DBSCAN runs
    grid_cell_scale: float = 0.125  # grid DBSCAN: cell side in units of eps
    warn_apart_share: float = 0.05  # a warning when the widening ran to eps_max_scale
    # without refusing a step and groups that even that eps keeps apart from the main
    # cluster (kept by merge_reach) hold at least this share of the kept points: a
    # neighbouring object may be in the OOI cloud (0 = no warning)
    retreat: bool = False  # with the warning above: when a step accepted before the set
    # settled moved its extent past max_extent_growth x the previous step's and moved the
    # set off the convergence point (and held nothing up), or a later jump was taken as a
    # part because it centred the set, keep the set from before the first such step (the
    # object before the neighbour chained to it); the warning says so
    retreat_centring: bool = True  # with retreat: a jump after settling taken as a part
    # because it centred the set is a step the retreat may go back before. False: only the
    # pre-settle off-centring step is (see module)
    widen_unclustered: bool = False  # with settle_change: the widening also goes on while
    # one cluster is left but at least settle_change of the points are in none (DBSCAN's
    # noise): a sparse cloud's parts (the stool's leaves) are not yet in the set, which has
    # not settled. False: only while DBSCAN finds more than one cluster
    central_inner: bool = False  # central (with part_above and a support plane): a cluster
    # whose points (98%) all lie nearer the convergence point than the main cluster's nearest
    # (2%), that stands beside it on the support and holds at least part_min_points of its
    # points, is the main cluster instead (the object at the centre of a far orbit's frames,
    # the main one a larger neighbour in the outer frame)
    centre_absolute: bool = False  # with settle_change: a jump counts as centring the set
    # only when its box centre's offset from the convergence point grows in metres by less
    # than it falls relative to the (grown) box's size, not merely falls relative to it
    lookahead: bool = False  # with settle_change and part_above: a step refused as a jump
    # is replaced by the first wider eps (up to eps_max_scale) whose additions, against the
    # same kept set, are held up by it (a crown after its trunk's crumbs) or, with
    # centre_absolute, centre it; the widening goes on from there. False: the first refused
    # step stops it
    rebase_on_switch: bool = False  # with settle_change: after the set settled, a step that
    # leaves out at least settle_change of its points (the main cluster changed) makes the
    # new set's extent the reference; False: the settled set's extent stays the reference
    iterations: int = 1  # repeat the removal (stops early, see stop_fraction)
    stop_fraction: float = 0.01  # stop iterating when a round removes fewer than this fraction


def _extent(xyz: np.ndarray, target: np.ndarray) -> float:
    """98% quantile of the distances of ``xyz`` to ``target`` (0 for no points)."""
    if len(xyz) == 0:
        return 0.0
    return float(np.quantile(np.linalg.norm(xyz - target, axis=1), 0.98))


def _box(xyz: np.ndarray) -> tuple[np.ndarray, float]:
    """(centre, half-diagonal) of the points' box: the 2-98% quantile range along the
    principal axes, so a sparse tail or the denser half of an object do not move it."""
    mu = xyz.mean(axis=0)
    _, _, vt = np.linalg.svd(xyz - mu, full_matrices=False)
    q = (xyz - mu) @ vt.T
    lo, hi = np.quantile(q, 0.02, axis=0), np.quantile(q, 0.98, axis=0)
    return mu + ((lo + hi) / 2) @ vt, float(np.linalg.norm((hi - lo) / 2))


def _off_centre(xyz: np.ndarray, target: np.ndarray) -> float:
    """How far ``target`` is from the centre of the points' box (``_box``), in units of the
    box's half-diagonal (0 = centred)."""
    if len(xyz) < 4:
        return float("inf")
    centre, half = _box(xyz)
    return float(np.linalg.norm(centre - target)) / max(half, 1e-12)


def _box_centre_offset(xyz: np.ndarray, target: np.ndarray) -> float:
    """How far ``target`` is from the centre of the points' box (``_box``), in metres."""
    if len(xyz) < 4:
        return float("inf")
    return float(np.linalg.norm(_box(xyz)[0] - target))


def _held_up(xyz: np.ndarray, keep: np.ndarray, grown: np.ndarray,
             up_plane: Optional[np.ndarray], share: float, eps: float,
             min_points: float = 0.0) -> bool:
    """Whether most of what ``grown`` adds to ``keep`` is held up by the object: the added
    points' groups (connected at ``eps``) whose lowest points (2% quantile of height over the
    support plane ``up_plane``, normal towards the cameras) lie at least ``share`` of the kept
    set's own height (2-98%) above its bottom hold half of the added points or more, and at
    least ``min_points`` x as many points as the kept set. A neighbour stands on the support
    beside the object (its bottom at the object's foot); a crown over a pot does not. Judged
    per group, so that a few low crumbs joining in the same step do not hide a part that
    floats; the size floor keeps out the top of a neighbour whose lower part is still apart
    (a few dozen points over the toy car's clutter)."""
    if up_plane is None or share <= 0 or len(keep) < 4:
        return False
    added = np.setdiff1d(grown, keep)
    if len(added) == 0:
        return False
    plane = np.asarray(up_plane, float)
    h_keep = xyz[keep] @ plane[:3] + plane[3]
    lo, hi = np.quantile(h_keep, [0.02, 0.98])
    if hi <= lo:
        return False
    h = xyz[added] @ plane[:3] + plane[3]
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    pairs = cKDTree(xyz[added]).query_pairs(eps, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                       shape=(len(added), len(added)))
    _, group = connected_components(graph, directed=False)
    held = 0
    for g in np.unique(group):
        hg = h[group == g]
        if np.quantile(hg, 0.02) - lo >= share * (hi - lo):
            held += len(hg)
    return bool(held >= 0.5 * len(added) and held >= min_points * len(keep))


def _judge_jump(xyz: np.ndarray, keep: np.ndarray, k2: np.ndarray, target: np.ndarray,
                up_plane: Optional[np.ndarray], cfg: NoiseConfig, settle: bool, eps: float
                ) -> tuple[bool, bool]:
    """(centres, held): whether the step from ``keep`` to ``k2`` brings the set's centre
    nearer the convergence point, or what it adds is held up by the set (see module)."""
    r0, r1 = _off_centre(xyz[keep], target), _off_centre(xyz[k2], target)
    centres = settle and r1 < r0
    if centres and cfg.centre_absolute:
        # a grown box lowers the relative offset by its size alone: a neighbour beside a
        # centred object moves the centre away in metres yet passed (the toy car's far seed
        # 3: 0.020 -> 0.034 m, x1.74, while relative 0.132 -> 0.117, x0.89). The centre may
        # drift in metres only by less than the relative offset falls (the bicycle's other
        # half, seed 6: 0.193 -> 0.201 m, x1.04, relative 0.352 -> 0.230, x0.65)
        a0, a1 = _box_centre_offset(xyz[keep], target), _box_centre_offset(xyz[k2], target)
        centres = a1 * r1 < a0 * r0
    held = (not centres and settle
            and _held_up(xyz, keep, k2, up_plane, cfg.part_above, eps, cfg.part_min_points))
    return bool(centres), bool(held)


def _dbscan(xyz: np.ndarray, cfg: NoiseConfig, target: np.ndarray, radius: float,
            up_plane: Optional[np.ndarray] = None) -> tuple[np.ndarray, dict]:
    """DBSCAN selection, with eps widened while the selection stays compact (see module)."""
    sp = spacing(xyz, cfg.min_samples)
    return _dbscan_widened(xyz, cfg, target, radius, up_plane, sp)


def _dbscan_widened(xyz: np.ndarray, cfg: NoiseConfig, target: np.ndarray, radius: float,
                    up_plane: Optional[np.ndarray], sp: float) -> tuple[np.ndarray, dict]:
    keep, p = _dbscan_at(xyz, cfg, target, radius, cfg.eps_scale * sp, sp, up_plane)
    p["eps_scale"] = round(cfg.eps_scale, 3)
    settle = cfg.settle_change > 0

    def unsettled(q: dict) -> bool:  # DBSCAN still leaves parts out at this eps
        return q["clusters"] > 1 or bool(
            settle and cfg.widen_unclustered and q.get("unclustered", 0) >= cfg.settle_change)

    if cfg.eps_max_scale <= cfg.eps_scale or len(keep) == 0 or not unsettled(p):
        return keep, p
    e0 = None if settle else _extent(xyz[keep], target)
    tried = [round(cfg.eps_scale, 3)]
    scale = cfg.eps_scale
    suspect = None  # (scale, set, params before it) of the first off-centring jump pre-settle
    while scale + cfg.eps_step <= cfg.eps_max_scale + 1e-9 and unsettled(p):
        scale += max(cfg.eps_step, 1e-3)
        tried.append(round(scale, 3))
        k2, p2 = _dbscan_at(xyz, cfg, target, radius, scale * sp, sp, up_plane)
        p2["eps_scale"] = round(scale, 3)
        if len(k2) == 0:
            p["stopped_at_scale"] = round(scale, 3)
            break
        e2 = _extent(xyz[k2], target)
        if e0 is not None and e2 > cfg.max_extent_growth * e0:
            centres, held = _judge_jump(xyz, keep, k2, target, up_plane, cfg, settle, scale * sp)
            ahead = scale
            while (not (centres or held) and cfg.lookahead and settle
                   and up_plane is not None and cfg.part_above > 0
                   and ahead + cfg.eps_step <= cfg.eps_max_scale + 1e-9):
                # a part of a sparse object can join in crumbs too few to count as held up
                # (a trunk's points before the crown's); a wider eps may bring the rest: take
                # that step if what it adds is held up by the set, else stop here as before
                # (a step that only centres the set is not looked ahead for)
                ahead += max(cfg.eps_step, 1e-3)
                k3, p3 = _dbscan_at(xyz, cfg, target, radius, ahead * sp, sp, up_plane)
                if len(k3) == 0:
                    break
                if cfg.centre_absolute:  # centring asked in metres too: safe to look for
                    c3, h3 = _judge_jump(xyz, keep, k3, target, up_plane, cfg, settle,
                                         ahead * sp)
                else:  # held up only (a grown box alone passes the relative centring)
                    c3, h3 = False, _held_up(xyz, keep, k3, up_plane, cfg.part_above,
                                             ahead * sp, cfg.part_min_points)
                if c3 or h3:
                    tried.append(round(ahead, 3))
                    p3["eps_scale"] = round(ahead, 3)
                    p3["looked_ahead_from"] = p.get("looked_ahead_from", []) + [round(scale, 3)]
                    scale, k2, p2, centres, held = ahead, k3, p3, c3, h3
                    e2 = _extent(xyz[k2], target)
            if not (centres or held):
                p["stopped_at_scale"] = round(scale, 3)
                break
            # what joined brings the set's centre nearer the point the cameras converge on
            # (the other half of the object the orbit frames, not a neighbour beside it), or
            # it floats above the set's foot (held up by the object; a neighbour stands on
            # the support)
            if centres and suspect is None and cfg.retreat and cfg.retreat_centring:
                # taken as a part because it centres the set; if the widening ends with the
                # warning's signs, this jump is where a neighbour may have joined
                suspect = (round(scale, 3), keep, dict(p), e2 / max(e0, 1e-12))
            e0 = e2
            p2["parts_joined_at"] = p.get("parts_joined_at", []) + [round(scale, 3)]
            if held:
                p2["parts_held_up_at"] = p.get("parts_held_up_at", []) + [round(scale, 3)]
        if (e0 is None and suspect is None and cfg.retreat
                and e2 > cfg.max_extent_growth * _extent(xyz[keep], target)
                and _off_centre(xyz[k2], target) > _off_centre(xyz[keep], target)
                and not _held_up(xyz, keep, k2, up_plane, cfg.part_above, scale * sp,
                                 cfg.part_min_points)):
            # accepted (the set has not settled: the object may still be gathering its
            # parts), but remembered: a part that centres the set or is held up by it passes,
            # a neighbour beside the object moves the set's box away from the convergence point
            grow = e2 / max(_extent(xyz[keep], target), 1e-12)
            suspect = (round(scale, 3), keep, dict(p), grow)
        if e0 is None and len(np.setxor1d(keep, k2)) < cfg.settle_change * len(keep):
            # the set barely changed over this step: the object is whole from here on, and
            # a later step that moves its extent far out joins a neighbour, not a part
            e0 = e2
            p2["settled_at_scale"] = round(scale, 3)
        elif e0 is not None:
            if (cfg.rebase_on_switch
                    and len(np.setdiff1d(keep, k2)) >= cfg.settle_change * len(keep)):
                # the step left out much of the settled set: the main cluster changed (a
                # nearer cluster now outweighs a neighbour that outnumbered it); the extent
                # the set settled at was the neighbour's, so the new set's is the reference
                e0 = e2
                p2["rebased_at"] = p.get("rebased_at", []) + [round(scale, 3)]
            for key in ("settled_at_scale", "parts_joined_at", "parts_held_up_at",
                        "rebased_at", "looked_ahead_from"):
                if key in p and key not in p2:
                    p2[key] = p[key]
        keep, p = k2, p2
    p["eps_scales_tried"] = tried
    apart = 1.0 - p.get("main_share", 1.0)
    if ("stopped_at_scale" not in p and scale + cfg.eps_step > cfg.eps_max_scale + 1e-9
            and cfg.warn_apart_share > 0 and apart >= cfg.warn_apart_share
            and suspect is not None):
        at, keep, p0, grow = suspect
        p = dict(p0, eps_scales_tried=tried, retreated_from_scale=at,
                 retreat_apart_share=round(apart, 4))
        p["warning"] = (
            f"the DBSCAN widening ran to its widest eps ({scale:g} spacings) without refusing "
            f"a step and kept {apart:.0%} of the points in groups apart from the main one: "
            f"a neighbouring object was likely chained to the OOI -- kept instead the "
            f"{len(keep)} points chosen before the step at {at:g} spacings, which moved the "
            f"set's extent out {grow:.1f}x and off the cameras' convergence point; look at "
            f"the OOI cloud and the masks in report.html")
    elif ("stopped_at_scale" not in p and scale + cfg.eps_step > cfg.eps_max_scale + 1e-9
            and cfg.warn_apart_share > 0 and apart >= cfg.warn_apart_share):
        p["warning"] = (
            f"{apart:.0%} of the OOI points lie in {p['chosen_clusters'] - 1} group(s) apart "
            f"from the main one even at the widest DBSCAN eps ({scale:g} spacings), kept "
            f"because they lie within its reach of the cameras' convergence point, and no "
            f"widening step was refused: a neighbouring object may be in the OOI cloud (a "
            f"sparse cloud does not show the gap between them) -- look at the OOI cloud and "
            f"the masks in report.html; more views or larger images give a denser cloud")
    return keep, p


def grow_selection(xyz: np.ndarray, keep: np.ndarray, cfg: NoiseConfig, sp: float,
                   eps: Optional[float] = None) -> np.ndarray:
    """``keep`` (indices into ``xyz``) plus the points within ``grow_scale`` spacings of a
    kept point: one hop. The pipeline applies it once, to the OOI set the noise stage and
    the stability tie-break chose (not to the widening's trial sets, whose extents decide
    what joins, nor to the tie-break's candidates). With ``eps`` (the selection's DBSCAN eps) only
    the points DBSCAN left in no cluster at that eps: a neighbouring object's cluster stays
    out however near its edge comes."""
    keep = np.asarray(keep, np.int64)
    if cfg.grow_scale <= 0 or len(keep) == 0 or len(keep) == len(xyz) or sp <= 0:
        return keep
    inside = np.zeros(len(xyz), bool)
    inside[keep] = True
    if eps is not None:
        labels, _ = dbscan_labels(xyz, eps, cfg.min_samples, cfg.grid_above_pairs,
                                  cfg.grid_cell_scale)
        inside |= labels >= 0
    out = np.nonzero(~inside)[0]
    d, _ = cKDTree(xyz[keep]).query(xyz[out], k=1,
                                    distance_upper_bound=cfg.grow_scale * sp)
    return np.sort(np.concatenate([keep, out[np.isfinite(d)]]))


def _pair_estimate(xyz: np.ndarray, eps: float, sample: int = 2000, seed: int = 0) -> float:
    """Estimated number of (ordered) point pairs closer than ``eps`` (DBSCAN's work)."""
    n = len(xyz)
    rng = np.random.default_rng(seed)
    q = xyz if n <= sample else xyz[rng.choice(n, sample, replace=False)]
    counts = cKDTree(xyz).query_ball_point(q, eps, return_length=True)
    return float(np.mean(counts)) * n


def dbscan_labels(xyz: np.ndarray, eps: float, min_points: int,
                  grid_above_pairs: int = 20_000_000, grid_cell_scale: float = 0.125
                  ) -> tuple[np.ndarray, str]:
    """DBSCAN labels (-1 = noise) and which path computed them ("exact" or "grid").

    Exact DBSCAN lists every point's eps-neighbours, so its time and memory grow with the
    number of neighbour pairs, not only with N: on a cloud whose eps (a median spacing) is wide
    for its densest part, the pairs grow faster than N (a 1M-point synthetic cloud: 400M pairs,
    26x the 100k time). Above ``grid_above_pairs`` estimated pairs the points are binned into
    cells of ``grid_cell_scale`` x eps, and DBSCAN runs on the cell centroids weighted by their
    point counts (a cell is core when the points within eps of it number min_points); every
    point takes its cell's label. Distances are then off by at most the cell diagonal (22% of
    eps at the default), and the cost is bounded by the occupied cells.
    """
    if len(xyz) == 0:
        return np.zeros(0, np.int64), "exact"
    if _pair_estimate(xyz, eps) <= grid_above_pairs:
        import open3d as o3d
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
        return np.asarray(pc.cluster_dbscan(eps=float(eps), min_points=int(min_points))), "exact"
    from sklearn.cluster import DBSCAN
    cell = grid_cell_scale * eps
    keys = np.floor((xyz - xyz.min(axis=0)) / cell).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    cent = np.stack([np.bincount(inv, weights=xyz[:, j]) for j in range(3)], axis=1)
    cent /= counts[:, None]
    lab = DBSCAN(eps=float(eps), min_samples=int(min_points), algorithm="kd_tree").fit(
        cent, sample_weight=counts).labels_
    return lab[inv].astype(np.int64), "grid"


def _beside(xyz: np.ndarray, other: np.ndarray, central: np.ndarray,
            up_plane: Optional[np.ndarray], share: float) -> bool:
    """Whether the points ``other`` stand beside the points ``central`` on the support plane
    ``up_plane`` rather than float over them: ``other``'s foot (2% quantile of height) lies
    less than ``share`` of ``central``'s own height (2-98%) above ``central``'s foot."""
    if up_plane is None or share <= 0:
        return False
    plane = np.asarray(up_plane, float)
    hc = xyz[central] @ plane[:3] + plane[3]
    lo, hi = np.quantile(hc, [0.02, 0.98])
    ho = float(np.quantile(xyz[other] @ plane[:3] + plane[3], 0.02))
    return bool(hi > lo and ho - lo < share * (hi - lo))


def _dbscan_at(xyz: np.ndarray, cfg: NoiseConfig, target: np.ndarray, radius: float,
               eps: float, sp: float, up_plane: Optional[np.ndarray] = None
               ) -> tuple[np.ndarray, dict]:
    """Indices of the cluster(s) DBSCAN at ``eps`` selects (``sp`` = the cloud's spacing),
    and its parameters."""
    labels, path = dbscan_labels(xyz, eps, cfg.min_samples, cfg.grid_above_pairs,
                                 cfg.grid_cell_scale)
    ids, counts = np.unique(labels[labels >= 0], return_counts=True)
    if len(ids) == 0:
        return np.zeros(0, np.int64), {"eps": eps, "clusters": 0, "dbscan": path}
    if cfg.select == "central":
        d = np.linalg.norm(xyz - target, axis=1)
        lab = labels[labels >= 0]  # cluster ids are 0..C-1 (per-cluster sums by bincount)
        dl = d[labels >= 0]
        if cfg.central_weight not in ("count", "linear", "standing"):
            raise ValueError(f"noise.central_weight={cfg.central_weight!r}; use count, "
                             "linear or standing")
        near = np.bincount(lab, weights=dl < radius, minlength=len(ids))[ids]
        if cfg.central_weight != "count":
            lin = np.bincount(lab, weights=np.clip(1.0 - dl / max(radius, 1e-12), 0.0, None),
                              minlength=len(ids))[ids]
            a, b = int(np.argmax(near)), int(np.argmax(lin))
            if a != b and near.max() > 0 and (cfg.central_weight == "linear" or _beside(
                    xyz, labels == ids[a], labels == ids[b], up_plane, cfg.part_above)):
                near = lin
        if cfg.central_inner and near.max() > 0:
            # a cluster wholly nearer the convergence point than the main one comes, standing
            # beside it on the support, is the object the orbit centres on (the main one a
            # neighbour in the outer frame that outnumbers it even by nearness)
            a = int(np.argmax(near))
            lo_a = float(np.quantile(dl[lab == ids[a]], 0.02))
            inner = [j for j in range(len(ids)) if j != a
                     and counts[j] >= cfg.part_min_points * counts[a]
                     and float(np.quantile(dl[lab == ids[j]], 0.98)) < lo_a]
            if inner:
                b = max(inner, key=lambda j: near[j])
                if _beside(xyz, labels == ids[a], labels == ids[b], up_plane, cfg.part_above):
                    near = np.where(np.arange(len(ids)) == b, near.max() + 1.0, near)
        if near.max() == 0:
            dmin = np.full(len(ids), np.inf)
            np.minimum.at(dmin, np.searchsorted(ids, lab), dl)
            chosen = [ids[np.argmin(dmin)]]
        else:
            # the cluster the orbit looks at, plus clusters lying within its own reach of the
            # convergence point (a part split off by a sparse gap; not the neighbour on the
            # table, which lies farther out than the object itself reaches)
            main = ids[np.argmax(near)]
            reach = (cfg.merge_reach_scale
                     * float(np.quantile(d[labels == main], cfg.merge_reach_quantile))
                     if cfg.merge_reach_quantile > 0 else radius)
            within = (np.bincount(lab, weights=dl <= reach, minlength=len(ids))[ids]
                      / counts)
            chosen = list(ids[(within >= 0.5) | (ids == main)])
        keep = np.isin(labels, chosen)
        main_n = int((labels == main).sum()) if near.max() > 0 else int(keep.sum())
    else:
        keep = labels == ids[np.argmax(counts)]
        main_n = int(keep.sum())
    main_share = main_n / max(int(keep.sum()), 1)
    return np.nonzero(keep)[0], {"eps": float(eps), "clusters": int(len(ids)),
                                 "unclustered": round(float((labels < 0).mean()), 4),
                                 "chosen_clusters": int(len(np.unique(labels[keep]))),
                                 "main_share": round(main_share, 4),
                                 "dbscan": path}


def _sor(xyz: np.ndarray, cfg: NoiseConfig) -> tuple[np.ndarray, dict]:
    k = int(min(cfg.sor_neighbours, len(xyz) - 1))
    d, _ = cKDTree(xyz).query(xyz, k=k + 1)
    m = d[:, 1:].mean(axis=1)
    thr = m.mean() + cfg.sor_std_ratio * m.std()
    return np.nonzero(m <= thr)[0], {"sor_threshold": float(thr)}


def noise_filter(xyz: np.ndarray, cfg: NoiseConfig, target: np.ndarray, radius: float,
                 up_plane: Optional[np.ndarray] = None) -> tuple[np.ndarray, dict]:
    """Indices kept by the noise stage and the parameters used (last round). ``up_plane``:
    the support plane (a, b, c, d; normal towards the cameras) for ``part_above``."""
    idx = np.arange(len(xyz))
    params: dict = {"method": cfg.method, "rounds": 0}
    if cfg.method == "none":
        return idx, params
    for _ in range(max(1, cfg.iterations)):
        if len(idx) < max(cfg.min_samples, 4):
            break
        sub = xyz[idx]
        if cfg.method == "dbscan":
            k, p = _dbscan(sub, cfg, target, radius, up_plane)
        elif cfg.method == "sor":
            k, p = _sor(sub, cfg)
        else:
            raise ValueError(f"noise.method={cfg.method!r}; use dbscan, sor or none")
        params.update(p)
        params["rounds"] += 1
        removed = len(idx) - len(k)
        idx = idx[k]
        if removed < cfg.stop_fraction * (len(idx) + removed):
            break
    return idx, params
