"""Improved-mode stage: region of interest from the orbit's camera layout.

An orbit frames its object: the object lies near the point the optical axes converge on, it is
inside (almost) every image, and it fits in the frame. Points that fall outside the frame of a
large share of the views (walls, far background) or farther from the convergence point than
the frame's half-extent at the object's distance cannot be the object. Both limits come from
the cameras (intrinsics, distances), not from constants fitted to a scene.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.geometry import project
from ..core.types import View


@dataclass
class RoiConfig:
    """Options of the camera-framing region of interest."""

    enabled: bool = True  # False keeps every point
    min_in_frame: float = 0.25  # keep points inside the frame of at least this share of views
    radius_scale: float = 1.5  # keep points within this x the frame half-extent at the object
    max_views: int = 120  # views sampled for the in-frame test (evenly spaced)


def frame_radius(views: list[View], target: np.ndarray) -> float:
    """Median half-diagonal of the image at the target's distance, in world units."""
    r = []
    for v in views:
        c = v.camera
        d = float(np.linalg.norm(v.pose.t - target))
        r.append(d * float(np.hypot(c.width / (2 * c.fx), c.height / (2 * c.fy))))
    return float(np.median(r)) if r else 0.0


def in_frame_fraction(xyz: np.ndarray, views: list[View], max_views: int) -> np.ndarray:
    """Share of views [N] whose image contains each point's projection (in front, in frame)."""
    if not views:
        return np.ones(len(xyz))
    step = max(1, len(views) // max_views)
    sel = views[::step]
    cnt = np.zeros(len(xyz))
    for v in sel:
        uv, z = project(xyz, v.camera, v.pose)
        ok = (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] < v.camera.width - 0.5)
        ok &= (uv[:, 1] >= -0.5) & (uv[:, 1] < v.camera.height - 0.5)
        cnt += ok
    return cnt / len(sel)


def roi_filter(xyz: np.ndarray, views: list[View], target: np.ndarray, cfg: RoiConfig
               ) -> tuple[np.ndarray, dict]:
    """Indices of points inside the orbit's region of interest, and the parameters used."""
    if not cfg.enabled or len(xyz) == 0:
        return np.arange(len(xyz)), {"enabled": False}
    rad = cfg.radius_scale * frame_radius(views, target)
    frac = in_frame_fraction(xyz, views, cfg.max_views)
    keep = (frac >= cfg.min_in_frame) & (np.linalg.norm(xyz - target, axis=1) <= rad)
    return np.nonzero(keep)[0], {"radius": rad, "min_in_frame": cfg.min_in_frame}
