"""A stand-in SfM cloud for simulated captures, for tests and benchmarks only.

Real SfM (the ``ooi_seg_ros.sfm`` module) is the production path. Until it runs in the tests,
this makes an SfM-like cloud from a simulator's exact depth maps: in every view, pixels with
image texture (gradient above the view's median, as feature detectors favour) are sampled,
lifted to 3D with the rendered depth plus relative depth noise, and each point gets an
observation in every view where it is in frame and not occluded (depth test). Like SfM, the
textured floor dominates the cloud and thin parts get few points.
"""

from __future__ import annotations

import numpy as np

from ..core.types import SfmCloud
from .masks import project_distorted, undistorted_dirs


def depth_proxy_cloud(sim, points_per_view: int = 300, depth_noise: float = 0.003,
                      seed: int = 0) -> SfmCloud:
    """SfM-like cloud of a ``SimCapture`` (see module doc); ``depth_noise`` is relative."""
    rng = np.random.default_rng(seed)
    views = sim.capture.views
    pts, cols = [], []
    for v, depth in zip(views, sim.depths):
        img = v.get_image().astype(float).mean(axis=2)
        gy, gx = np.gradient(img)
        g = np.hypot(gx, gy).ravel()
        ok = np.isfinite(depth.ravel()) & (g > np.median(g))
        cand = np.nonzero(ok)[0]
        if len(cand) == 0:
            continue
        pick = rng.choice(cand, min(points_per_view, len(cand)), replace=False)
        z = depth.ravel()[pick] * (1 + depth_noise * rng.standard_normal(len(pick)))
        d = undistorted_dirs(v.camera)[pick] * z[:, None]
        pts.append(d @ v.pose.R.T + v.pose.t)
        cols.append(v.get_image().reshape(-1, 3)[pick])
    xyz = np.concatenate(pts) if pts else np.zeros((0, 3))
    rgb = np.concatenate(cols) if cols else np.zeros((0, 3), np.uint8)
    obs = [[] for _ in range(len(xyz))]
    for j, (v, depth) in enumerate(zip(views, sim.depths)):
        uv, z = project_distorted(xyz, v.camera, v.pose)
        ui, vi = np.rint(uv[:, 0]), np.rint(uv[:, 1])
        c = v.camera
        ok = (z > 0) & (ui >= 0) & (ui < c.width) & (vi >= 0) & (vi < c.height)
        idx = np.nonzero(ok)[0]
        dz = depth[vi[idx].astype(int), ui[idx].astype(int)]
        vis = idx[np.abs(dz - z[idx]) < 0.02 * z[idx]]
        for i in vis:
            obs[i].append((j, uv[i, 0], uv[i, 1]))
    keep = np.array([len(o) >= 2 for o in obs], bool) if len(obs) else np.zeros(0, bool)
    xyz, rgb = xyz[keep], rgb[keep]
    obs = [o for o, k in zip(obs, keep) if k]
    lens = np.array([len(o) for o in obs], np.int64)
    ptr = np.zeros(len(obs) + 1, np.int64)
    np.cumsum(lens, out=ptr[1:])
    flat = [t for o in obs for t in o]
    ov = np.array([t[0] for t in flat], np.int32)
    oxy = np.array([[t[1], t[2]] for t in flat], np.float32).reshape(-1, 2)
    return SfmCloud(xyz, rgb, np.full(len(xyz), 0.5), ptr, ov, oxy, list(views))
