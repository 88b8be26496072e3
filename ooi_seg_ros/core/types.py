"""Typed data shared by every pipeline stage (ROS-free).

Conventions (REP 103/105 and the conversion layer in ``core.geometry``):
- World frame ``map``: right-handed, z up (ENU), metres.
- Camera optical frame: x right, y down, z forward (same as OpenCV / COLMAP).
- ``Pose`` is always camera-to-world (the pose of the optical frame in ``map``), i.e. the
  message ``geometry_msgs/PoseStamped`` of the optical frame. COLMAP's world-to-camera form is
  obtained with ``Pose.world_to_cam()``.
- Images are ``uint8`` RGB ``[H, W, 3]``; masks are ``bool`` ``[H, W]`` (True = object).
- A view's ``key`` names its outputs (``masks/<key>.png``): the image header stamp in integer
  nanoseconds for bag input, the image file stem for folder input.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

DISTORTION_MODELS = ("none", "plumb_bob", "rational_polynomial", "equidistant")


class OoiSegError(Exception):
    """Base class of the package's own errors; the message says what to do about it."""


class InputError(OoiSegError):
    """Input data that cannot be used (bad file, missing topic, malformed message)."""


@dataclass
class CameraIntrinsics:
    """Pinhole intrinsics plus an optional distortion model (ROS CameraInfo naming)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion_model: str = "none"  # one of DISTORTION_MODELS
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [k] float64, ROS order

    def K(self) -> np.ndarray:  # [3, 3] float64
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def validate(self) -> None:
        """Raise InputError when the intrinsics cannot describe a camera."""
        vals = np.array([self.fx, self.fy, self.cx, self.cy], dtype=float)
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"camera size {self.width}x{self.height} is not positive")
        if not np.all(np.isfinite(vals)) or self.fx <= 0 or self.fy <= 0:
            raise InputError(
                f"camera intrinsics fx={self.fx} fy={self.fy} cx={self.cx} cy={self.cy} are "
                "zero/NaN; publish a calibrated CameraInfo (K must not be all zeros)")
        if self.distortion_model not in DISTORTION_MODELS:
            raise InputError(f"distortion model {self.distortion_model!r} is not supported; "
                             f"use one of {DISTORTION_MODELS}")
        if np.any(~np.isfinite(np.asarray(self.dist, dtype=float))):
            raise InputError("distortion coefficients contain NaN/inf")

    @property
    def has_distortion(self) -> bool:
        return self.distortion_model != "none" and bool(np.any(np.asarray(self.dist) != 0))

    def scaled(self, factor: float) -> "CameraIntrinsics":
        """Intrinsics of the image resized by ``factor`` (e.g. 0.5 for images_2)."""
        w = int(round(self.width * factor))
        h = int(round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return CameraIntrinsics(w, h, self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5,
                                (self.cy + 0.5) * sy - 0.5, self.distortion_model,
                                np.array(self.dist, dtype=float))


@dataclass
class Pose:
    """Rigid transform camera-to-world: ``x_world = R @ x_cam + t``."""

    R: np.ndarray  # [3, 3] float64
    t: np.ndarray  # [3] float64

    @staticmethod
    def identity() -> "Pose":
        return Pose(np.eye(3), np.zeros(3))

    def matrix(self) -> np.ndarray:  # [4, 4]
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    @staticmethod
    def from_matrix(m: np.ndarray) -> "Pose":
        return Pose(np.array(m[:3, :3], dtype=float), np.array(m[:3, 3], dtype=float))

    def inverse(self) -> "Pose":
        return Pose(self.R.T, -self.R.T @ self.t)

    def world_to_cam(self) -> tuple[np.ndarray, np.ndarray]:
        """(R_cw [3,3], t_cw [3]) so that ``x_cam = R_cw @ x_world + t_cw`` (COLMAP form)."""
        return self.R.T, -self.R.T @ self.t

    @property
    def center(self) -> np.ndarray:  # [3]
        return self.t

    @property
    def forward(self) -> np.ndarray:  # [3] optical axis (+z of the camera) in the world
        return self.R[:, 2]


@dataclass
class View:
    """One camera image with its calibration, pose and (optional) ground-truth mask."""

    key: str
    stamp_ns: int
    camera: CameraIntrinsics
    pose: Optional[Pose]
    image: Optional[np.ndarray] = None  # [H, W, 3] uint8 RGB; None if loaded lazily
    gt_mask: Optional[np.ndarray] = None  # [H, W] bool
    loader: Optional[Callable[[], np.ndarray]] = field(default=None, repr=False)
    source: str = ""  # file path or topic the image came from
    compressed: bool = False  # the image went through lossy compression (JPEG) at this size

    def get_image(self) -> np.ndarray:
        """The RGB image, loading it on first use when the view was created lazily."""
        if self.image is None:
            if self.loader is None:
                raise InputError(f"view {self.key} has no image data")
            self.image = self.loader()
        return self.image


@dataclass
class Capture:
    """An ordered set of views (capture order) plus optional ground truth."""

    views: list[View]
    source: str = ""
    gt_ooi_points: Optional[np.ndarray] = None  # [M, 3] points on the true OOI surface
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.views)

    @property
    def has_poses(self) -> bool:
        return all(v.pose is not None for v in self.views)

    @property
    def has_gt_masks(self) -> bool:
        return len(self.views) > 0 and all(v.gt_mask is not None for v in self.views)


@dataclass
class SfmCloud:
    """An SfM point cloud with per-point colour, error and visibility.

    Observations are stored compressed (CSR): the observations of point ``i`` are
    ``obs_view[obs_ptr[i]:obs_ptr[i+1]]`` (index into ``views``) with pixel coordinates
    ``obs_xy[...]``. Later stages use visibility (which views saw a point, and where).
    """

    xyz: np.ndarray  # [N, 3] float64
    rgb: np.ndarray  # [N, 3] uint8
    error: np.ndarray  # [N] float64 mean reprojection error in pixels
    obs_ptr: np.ndarray  # [N + 1] int64
    obs_view: np.ndarray  # [M] int32
    obs_xy: np.ndarray  # [M, 2] float32
    views: list[View] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    @staticmethod
    def empty(views: Optional[list[View]] = None) -> "SfmCloud":
        return SfmCloud(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0),
                        np.zeros(1, np.int64), np.zeros(0, np.int32), np.zeros((0, 2), np.float32),
                        list(views or []))

    @staticmethod
    def from_points(xyz: np.ndarray, rgb: Optional[np.ndarray] = None,
                    views: Optional[list[View]] = None) -> "SfmCloud":
        """A cloud without observations (e.g. loaded from a PLY)."""
        xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
        n = xyz.shape[0]
        if rgb is None:
            rgb = np.full((n, 3), 128, np.uint8)
        return SfmCloud(xyz, np.asarray(rgb, np.uint8).reshape(-1, 3), np.zeros(n),
                        np.zeros(n + 1, np.int64), np.zeros(0, np.int32),
                        np.zeros((0, 2), np.float32), list(views or []))

    def track_lengths(self) -> np.ndarray:  # [N] int
        return np.diff(self.obs_ptr)

    def observations(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        s, e = self.obs_ptr[i], self.obs_ptr[i + 1]
        return self.obs_view[s:e], self.obs_xy[s:e]

    def subset(self, idx: np.ndarray) -> "SfmCloud":
        """The points ``idx`` (indices or a bool mask) with their observations."""
        idx = np.asarray(idx)
        if idx.dtype == bool:
            idx = np.nonzero(idx)[0]
        lens = self.track_lengths()[idx]
        ptr = np.zeros(len(idx) + 1, np.int64)
        np.cumsum(lens, out=ptr[1:])
        if len(idx) and ptr[-1]:
            starts = self.obs_ptr[idx]
            gather = np.repeat(starts - ptr[:-1], lens) + np.arange(ptr[-1])
            ov, oxy = self.obs_view[gather], self.obs_xy[gather]
        else:
            ov, oxy = np.zeros(0, np.int32), np.zeros((0, 2), np.float32)
        return SfmCloud(self.xyz[idx], self.rgb[idx], self.error[idx], ptr, ov, oxy, self.views)


@dataclass
class TriMesh:
    """A triangle mesh in the world frame."""

    vertices: np.ndarray  # [V, 3] float64
    triangles: np.ndarray  # [F, 3] int32

    @property
    def is_empty(self) -> bool:
        return self.vertices.shape[0] == 0 or self.triangles.shape[0] == 0
