"""Improved-mode stage: region of interest from the orbit's camera layout.

An orbit frames its object: the object lies near the point the optical axes converge on, it is
inside (almost) every image, and it fits in the frame. Points that fall outside the frame of a
large share of the views (walls, far background) or farther from the convergence point than
the frame's half-extent at the object's distance cannot be the object. Both limits come from
the cameras (intrinsics, distances), not from constants fitted to a scene.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

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
    framed_views: float = 0.5  # the OOI check: a point is framed when it lies inside the
    # frame of at least this share of the views (the drone keeps its object in frame)
    warn_unframed_share: float = 0.02  # a warning when more than this share of the final OOI
    # points is not framed: something around the object is in the OOI (0 = no warning)


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


def framing_warning(xyz: np.ndarray, views: list[View], cfg: RoiConfig) -> Optional[str]:
    """A warning when the final OOI cloud holds points the cameras do not keep in frame.

    The drone frames the object it orbits. On the simulator's SfM clouds (every scene, camera
    layout and image size cached by the benches: 131 clouds with the OOI the default keeps),
    the 200 depth-proxy clouds of ``bench_noise_warning.py`` (6-30 views) and the 24 real
    bonsai subsets, no OOI point lies inside the frame of fewer than half the views; the
    closest to the edge are the aircraft's wing tips and the bicycle's wheels (out of frame
    in up to a quarter of the views: 4.5% of the aircraft's points with 6 views, 2.0% of the
    bicycle's at 640x360). A neighbour chained to the object lies farther out: the toy car of
    seed 1 on one ring (clutter touching the car at the first DBSCAN eps, the rest within the
    chained set's reach; IoU 0.45, no warning before) has 5.9% of its OOI points in the frame
    of fewer than half the views (11.8% out of more than a quarter). The 2% share lies between
    0 and that: read off these clouds, a fitted constant. It only reports: which points are
    the neighbour is not known here."""
    if cfg.warn_unframed_share <= 0 or len(xyz) == 0 or not views:
        return None
    frac = in_frame_fraction(xyz, views, cfg.max_views)
    share = float(np.mean(frac < cfg.framed_views))
    if share <= cfg.warn_unframed_share:
        return None
    return (f"{share:.1%} of the OOI points lie inside the frame of fewer than "
            f"{cfg.framed_views:.0%} of the views: the cameras frame the object they orbit, "
            f"so the OOI cloud likely holds something around it (a neighbour chained to it) "
            f"-- look at the OOI cloud and the masks in report.html")
