"""Stage 4.3: noise removal -- keep one DBSCAN cluster (or statistical outlier removal).

``eps`` is derived from the cloud: ``eps_scale`` times the median distance to the
``min_samples``-th neighbour. ``select="largest"`` is the paper's rule; ``select="central"``
(improved) keeps the cluster with most points near the cameras' convergence point, i.e. the
cluster the orbit is looking at, and also merges clusters that lie (mostly) within that
cluster's own reach from the convergence point (parts of one object split by a sparse gap).
``iterations`` > 1 repeats the removal until fewer than ``stop_fraction`` of the points are
removed in a round.
"""

from __future__ import annotations

from dataclasses import dataclass

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
    sor_neighbours: int = 16  # SOR: neighbours per point
    sor_std_ratio: float = 2.0  # SOR: mean-distance threshold in standard deviations
    grow_scale: float = 0.0  # after selection, add points within this x the median
    # min_samples-NN distance of a kept point (one hop; 0 = off)
    merge_reach_quantile: float = 0.98  # central: the main cluster's reach = this quantile
    # of its points' distances to the convergence point; other clusters within it are merged
    # (0: within the frame radius instead)
    iterations: int = 1  # repeat the removal (stops early, see stop_fraction)
    stop_fraction: float = 0.01  # stop iterating when a round removes fewer than this fraction


def _dbscan(xyz: np.ndarray, cfg: NoiseConfig, target: np.ndarray, radius: float
            ) -> tuple[np.ndarray, dict]:
    import open3d as o3d
    eps = cfg.eps_scale * spacing(xyz, cfg.min_samples)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    labels = np.asarray(pc.cluster_dbscan(eps=float(eps), min_points=int(cfg.min_samples)))
    ids, counts = np.unique(labels[labels >= 0], return_counts=True)
    if len(ids) == 0:
        return np.zeros(0, np.int64), {"eps": eps, "clusters": 0}
    if cfg.select == "central":
        d = np.linalg.norm(xyz - target, axis=1)
        near = np.array([(d[labels == i] < radius).sum() for i in ids])
        if near.max() == 0:
            chosen = [ids[np.argmin([d[labels == i].min() for i in ids])]]
        else:
            # the cluster the orbit looks at, plus clusters lying within its own reach of the
            # convergence point (a part split off by a sparse gap; not the neighbour on the
            # table, which lies farther out than the object itself reaches)
            main = ids[np.argmax(near)]
            reach = (float(np.quantile(d[labels == main], cfg.merge_reach_quantile))
                     if cfg.merge_reach_quantile > 0 else radius)
            within = np.array([(d[labels == i] <= reach).mean() for i in ids])
            chosen = list(ids[(within >= 0.5) | (ids == main)])
        keep = np.isin(labels, chosen)
    else:
        keep = labels == ids[np.argmax(counts)]
    if cfg.grow_scale > 0 and keep.any() and not keep.all():
        # one hop of a wider radius: points a gap too wide for eps from the kept cluster (a
        # leaf tip, a strut) come back, a whole neighbouring object does not
        tree = cKDTree(xyz[keep])
        reach = cfg.grow_scale * eps / cfg.eps_scale
        d_keep, _ = tree.query(xyz[~keep], k=1, distance_upper_bound=reach)
        out = np.nonzero(~keep)[0]
        keep[out[np.isfinite(d_keep)]] = True
    return np.nonzero(keep)[0], {"eps": float(eps), "clusters": int(len(ids)),
                                 "chosen_clusters": int(len(np.unique(labels[keep])))}


def _sor(xyz: np.ndarray, cfg: NoiseConfig) -> tuple[np.ndarray, dict]:
    k = int(min(cfg.sor_neighbours, len(xyz) - 1))
    d, _ = cKDTree(xyz).query(xyz, k=k + 1)
    m = d[:, 1:].mean(axis=1)
    thr = m.mean() + cfg.sor_std_ratio * m.std()
    return np.nonzero(m <= thr)[0], {"sor_threshold": float(thr)}


def noise_filter(xyz: np.ndarray, cfg: NoiseConfig, target: np.ndarray, radius: float
                 ) -> tuple[np.ndarray, dict]:
    """Indices kept by the noise stage and the parameters used (last round)."""
    idx = np.arange(len(xyz))
    params: dict = {"method": cfg.method, "rounds": 0}
    if cfg.method == "none":
        return idx, params
    for _ in range(max(1, cfg.iterations)):
        if len(idx) < max(cfg.min_samples, 4):
            break
        sub = xyz[idx]
        if cfg.method == "dbscan":
            k, p = _dbscan(sub, cfg, target, radius)
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
