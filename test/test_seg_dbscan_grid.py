"""DBSCAN's grid path (large, dense clouds) against the exact path, and the path choice."""

from __future__ import annotations

import numpy as np

from ooi_seg_ros.seg.noise import NoiseConfig, dbscan_labels, noise_filter


def _blobs(seed: int = 0) -> np.ndarray:
    """Two dense spherical shells 3 units apart, a sparse bridge-free gap, scattered noise."""
    rng = np.random.default_rng(seed)
    s = rng.normal(size=(6000, 3))
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    a = s[:3000] + [0, 0, 0]
    b = 0.6 * s[3000:] + [3.0, 0, 0]
    noise = rng.uniform(-4, 7, (200, 3))
    return np.vstack([a, b, noise])


def test_grid_labels_match_exact_clusters():
    x = _blobs()
    eps = 0.15
    exact, p1 = dbscan_labels(x, eps, 8, grid_above_pairs=10**12)
    grid, p2 = dbscan_labels(x, eps, 8, grid_above_pairs=0)
    assert (p1, p2) == ("exact", "grid")
    # the two shells are found as two clusters by both paths, with the same members
    for lab in (exact, grid):
        assert len(np.unique(lab[:3000])) == 1 and lab[0] >= 0
        assert len(np.unique(lab[3000:6000])) == 1 and lab[3000] >= 0
        assert lab[0] != lab[3000]
    # the scattered points are noise for both (a cell holds too few of them to be core)
    assert (exact[6000:] == -1).mean() > 0.95 and (grid[6000:] == -1).mean() > 0.95


def test_noise_filter_reports_the_path_and_keeps_the_same_points():
    x = _blobs()
    target = np.zeros(3)
    k_exact, p_exact = noise_filter(x, NoiseConfig(select="central"), target, 1.5)
    k_grid, p_grid = noise_filter(x, NoiseConfig(select="central", grid_above_pairs=0), target,
                                  1.5)
    assert p_exact["dbscan"] == "exact" and p_grid["dbscan"] == "grid"
    assert set(range(3000)) <= set(k_exact.tolist())
    a, b = set(k_exact.tolist()), set(k_grid.tolist())
    assert len(a & b) / len(a | b) > 0.99
