"""Keyframe selection for a posed image stream (a drone's 30 Hz camera).

A frame becomes a keyframe when the camera moved far enough since the last keyframe
(translation as a fraction of the scene scale, or rotation in degrees) and it is not blurry.
The scene scale comes from the data: the distance of the cameras to the point their optical axes
converge on (an orbit's centre); until enough poses have been seen to estimate it, the distance
travelled over the first poses stands in. Blur is the variance of the Laplacian of a small
grey thumbnail, compared with the running median of the frames seen so far (relative, so a
dim or low-texture scene is not rejected wholesale).
"""

from __future__ import annotations

import logging
from collections import Counter, deque
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..core.geometry import cameras_convergence_point
from ..core.types import InputError, Pose, View

LOG = logging.getLogger(__name__)


@dataclass
class KeyframeConfig:
    """When a frame of the stream becomes a keyframe."""

    translation_frac: float = 0.08  # accept after moving this fraction of the scene scale
    rotation_deg: float = 10.0  # ... or after rotating this many degrees
    blur_frac: float = 0.35  # reject when Laplacian variance < this x running median
    blur_window: int = 30  # frames in the running median of the sharpness
    blur_min_history: int = 5  # frames needed before the blur test applies
    thumb_size: int = 160  # long side of the grey thumbnail the blur test runs on
    scale_min_poses: int = 8  # poses needed before the convergence point sets the scale
    max_keyframes: int = 0  # stop accepting after this many (0 = no limit)


def laplacian_variance(image: np.ndarray, thumb_size: int = 160) -> float:
    """Variance of the 4-neighbour Laplacian of a green-channel thumbnail (sharpness).

    Only frames that pass the motion test get here, so a 30 Hz stream pays it at keyframe rate.
    """
    img = np.asarray(image)
    g = img[..., 1] if img.ndim == 3 else img  # green: most of the luminance, 1/3 the cost
    step = max(1, int(np.ceil(max(g.shape) / max(thumb_size, 8))))
    if step > 1:
        h, w = (g.shape[0] // step) * step, (g.shape[1] // step) * step
        blocks = g[:h, :w].reshape(h // step, step, w // step, step)
        g = blocks.sum(axis=(1, 3), dtype=np.float32)
        g /= step * step
    else:
        g = g.astype(np.float32)
    lap = (g[1:-1, :-2] + g[1:-1, 2:] + g[:-2, 1:-1] + g[2:, 1:-1] - 4 * g[1:-1, 1:-1])
    return float(lap.var()) if lap.size else 0.0


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle of the relative rotation between two rotation matrices, in degrees."""
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


class KeyframeSelector:
    """Streams views through ``offer(view)``; True means "use it as a keyframe"."""

    def __init__(self, config: Optional[KeyframeConfig] = None):
        self.config = config or KeyframeConfig()
        self.dropped: Counter = Counter()
        self.accepted = 0
        self.seen = 0
        self._last: Optional[Pose] = None
        self._last_stamp: Optional[int] = None
        self._sharp: deque = deque(maxlen=max(self.config.blur_window, 1))
        self._poses: list[Pose] = []
        self._scale: Optional[float] = None

    @property
    def scene_scale(self) -> Optional[float]:
        """Median camera-to-convergence-point distance (None until estimated)."""
        return self._scale

    def set_scene_scale(self, scale: float) -> None:
        """Use a known scene scale (e.g. from the whole capture when offline)."""
        if not np.isfinite(scale) or scale <= 0:
            raise InputError(f"scene scale {scale} must be positive and finite")
        self._scale = float(scale)

    def _update_scale(self, pose: Pose) -> None:
        if self._scale is not None and len(self._poses) >= self.config.scale_min_poses:
            return
        if not self._poses or np.linalg.norm(pose.t - self._poses[-1].t) > 0 or \
                rotation_angle_deg(pose.R, self._poses[-1].R) > 1.0:
            self._poses.append(pose)
        if len(self._poses) >= self.config.scale_min_poses:
            c = cameras_convergence_point(self._poses)
            d = np.linalg.norm(np.stack([p.t for p in self._poses]) - c, axis=1)
            if np.all(np.isfinite(d)) and np.median(d) > 0:
                self._scale = float(np.median(d))

    def _drop(self, reason: str) -> bool:
        self.dropped[reason] += 1
        LOG.debug("frame dropped: %s", reason)
        return False

    def offer(self, view: View) -> bool:
        """Decide whether ``view`` becomes a keyframe (drops are counted by reason)."""
        cfg = self.config
        self.seen += 1
        pose = view.pose
        if pose is None:
            return self._drop("no_pose")
        if not (np.all(np.isfinite(pose.R)) and np.all(np.isfinite(pose.t))):
            return self._drop("nan_pose")
        if self._last_stamp is not None and view.stamp_ns < self._last_stamp:
            return self._drop("stamp_backwards")
        if cfg.max_keyframes and self.accepted >= cfg.max_keyframes:
            return self._drop("max_keyframes")
        self._update_scale(pose)
        if self._last is not None:
            moved = float(np.linalg.norm(pose.t - self._last.t))
            turned = rotation_angle_deg(self._last.R, pose.R)
            scale = self._scale
            if scale is None:  # early in the stream: judge by rotation only, plus a floor
                far = False
            else:
                far = moved > cfg.translation_frac * scale
            if not far and turned < cfg.rotation_deg:
                return self._drop("too_close")
        sharp = laplacian_variance(view.get_image(), cfg.thumb_size)
        history = list(self._sharp)
        self._sharp.append(sharp)
        if len(history) >= cfg.blur_min_history and sharp < cfg.blur_frac * np.median(history):
            return self._drop("blurry")
        self._last = pose
        self._last_stamp = view.stamp_ns
        self.accepted += 1
        return True

    def report(self) -> dict:
        return {"frames_seen": self.seen, "keyframes": self.accepted,
                "dropped": dict(self.dropped), "scene_scale": self._scale}
