"""Pose look-up at image stamps (ROS-free): a bounded, time-ordered buffer of stamped poses.

Images and poses arrive on separate topics with different rates; an image's pose is the
interpolation (linear position, slerp rotation) between the two poses bracketing its stamp,
accepted only when both are within ``tolerance_ns`` of it. A pose stream may come from the
vehicle (Odometry of the body); ``mount`` then turns it into the camera optical frame pose:
``T_map_cam = T_map_body * T_body_cam``.
"""

from __future__ import annotations

import bisect
from collections import Counter
from typing import Optional

import numpy as np

from .geometry import interpolate_pose
from .types import Pose


def apply_mount(body: Pose, mount: Optional[Pose]) -> Pose:
    """Camera pose of a body pose and the static body->camera-optical transform (or body)."""
    if mount is None:
        return body
    return Pose(body.R @ mount.R, body.R @ mount.t + body.t)


def pose_is_valid(pose: Pose, tol: float = 1e-3) -> bool:
    """Finite translation and a proper rotation matrix (orthonormal, det +1)."""
    R, t = np.asarray(pose.R, float), np.asarray(pose.t, float)
    if R.shape != (3, 3) or t.shape != (3,):
        return False
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return False
    return bool(np.abs(R.T @ R - np.eye(3)).max() < tol and abs(np.linalg.det(R) - 1.0) < tol)


class PoseBuffer:
    """Stamped poses in increasing stamp order, bounded in age and count.

    ``add`` rejects (and counts in ``rejected``) NaN/invalid poses and stamps that do not
    increase. ``lookup`` interpolates between the bracketing poses when both are within
    ``tolerance_ns`` of the stamp; an exact stamp match needs no neighbour.
    """

    def __init__(self, max_age_ns: int = 10_000_000_000, tolerance_ns: int = 100_000_000,
                 mount: Optional[Pose] = None, max_len: int = 100_000) -> None:
        self.max_age_ns = int(max_age_ns)
        self.tolerance_ns = int(tolerance_ns)
        self.mount = mount
        self.max_len = int(max_len)
        self._stamps: list[int] = []
        self._poses: list[Pose] = []
        self.rejected: Counter = Counter()

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def latest_ns(self) -> Optional[int]:
        return self._stamps[-1] if self._stamps else None

    def add(self, stamp_ns: int, pose: Pose) -> bool:
        """Stores a pose (after the mount transform); False (and counted) when rejected."""
        if not pose_is_valid(pose):
            self.rejected["invalid_pose"] += 1
            return False
        stamp_ns = int(stamp_ns)
        if self._stamps and stamp_ns <= self._stamps[-1]:
            self.rejected["stamp_not_increasing"] += 1
            return False
        self._stamps.append(stamp_ns)
        self._poses.append(apply_mount(pose, self.mount))
        self._trim()
        return True

    def _trim(self) -> None:
        newest = self._stamps[-1]
        cut = bisect.bisect_left(self._stamps, newest - self.max_age_ns)
        cut = max(cut, len(self._stamps) - self.max_len)
        if cut > 0:
            del self._stamps[:cut]
            del self._poses[:cut]

    def lookup(self, stamp_ns: int) -> Optional[Pose]:
        """Interpolated pose at ``stamp_ns``, or None without bracketing poses in tolerance."""
        s = self._stamps
        i = bisect.bisect_left(s, int(stamp_ns))
        if i < len(s) and s[i] == stamp_ns:
            return self._poses[i]
        if i == 0 or i == len(s):
            return None
        t0, t1 = s[i - 1], s[i]
        if stamp_ns - t0 > self.tolerance_ns or t1 - stamp_ns > self.tolerance_ns:
            return None
        return interpolate_pose(t0, self._poses[i - 1], t1, self._poses[i], int(stamp_ns))

    def is_too_old(self, stamp_ns: int) -> bool:
        """True when no later pose can make ``lookup(stamp_ns)`` succeed any more."""
        s = self._stamps
        if not s:
            return False
        if stamp_ns < s[0]:
            return True  # older than what the buffer keeps
        # a pose after the stamp already exists: the bracket is final
        return s[-1] > stamp_ns and self.lookup(stamp_ns) is None
