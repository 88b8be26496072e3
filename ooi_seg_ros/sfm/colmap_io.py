"""Read a COLMAP sparse model (with pycolmap) into the package's ``Capture`` + ``SfmCloud``.

COLMAP stores world-to-camera poses; they are converted to camera-to-world here. Camera models
map onto ROS distortion models: SIMPLE_PINHOLE/PINHOLE -> none, SIMPLE_RADIAL/RADIAL/OPENCV ->
plumb_bob (k1, k2, p1, p2, k3), FULL_OPENCV -> rational_polynomial, OPENCV_FISHEYE -> equidistant.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ..core.types import CameraIntrinsics, Capture, InputError, Pose, SfmCloud, View


def camera_from_colmap(cam) -> CameraIntrinsics:
    """CameraIntrinsics of a pycolmap.Camera."""
    model = cam.model.name if hasattr(cam.model, "name") else str(cam.model)
    p = np.asarray(cam.params, dtype=float).copy()
    w, h = int(cam.width), int(cam.height)
    # COLMAP puts pixel centres at +0.5; ROS/OpenCV (this package) at integer coordinates.
    ci = 1 if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL") else 2
    p[ci:ci + 2] -= 0.5
    if model == "SIMPLE_PINHOLE":
        return CameraIntrinsics(w, h, p[0], p[0], p[1], p[2])
    if model == "PINHOLE":
        return CameraIntrinsics(w, h, p[0], p[1], p[2], p[3])
    if model == "SIMPLE_RADIAL":
        return CameraIntrinsics(w, h, p[0], p[0], p[1], p[2], "plumb_bob",
                                np.array([p[3], 0, 0, 0, 0]))
    if model == "RADIAL":
        return CameraIntrinsics(w, h, p[0], p[0], p[1], p[2], "plumb_bob",
                                np.array([p[3], p[4], 0, 0, 0]))
    if model == "OPENCV":
        return CameraIntrinsics(w, h, p[0], p[1], p[2], p[3], "plumb_bob",
                                np.array([p[4], p[5], p[6], p[7], 0]))
    if model == "FULL_OPENCV":  # k1 k2 p1 p2 k3 k4 k5 k6
        return CameraIntrinsics(w, h, p[0], p[1], p[2], p[3], "rational_polynomial",
                                np.array(p[4:12]))
    if model == "OPENCV_FISHEYE":
        return CameraIntrinsics(w, h, p[0], p[1], p[2], p[3], "equidistant", np.array(p[4:8]))
    raise InputError(f"COLMAP camera model {model} is not supported; re-run SfM with OPENCV")


def _pil_loader(path: Path, size: Optional[tuple[int, int]] = None):
    def load() -> np.ndarray:
        from PIL import Image, UnidentifiedImageError
        try:
            with Image.open(path) as im:
                im = im.convert("RGB")
                if size is not None and im.size != size:
                    im = im.resize(size, Image.Resampling.LANCZOS)
                return np.asarray(im)
        except FileNotFoundError:  # a traceback once; the model names a file not there
            raise InputError(f"the COLMAP model's image {path.name} is not in {path.parent}; "
                             "pass --images with the folder of the model's photos") from None
        except (OSError, UnidentifiedImageError) as exc:
            raise InputError(f"cannot read image {path} ({exc}); replace or remove it") from exc
    return load


def load_colmap_model(sparse_dir: str | Path, images_dir: str | Path | None = None,
                      downscale: float = 1.0) -> tuple[Capture, SfmCloud]:
    """Capture (views in file-name order, images loaded lazily) and cloud of a COLMAP model.

    ``downscale`` > 1 reads images from ``images_dir`` at 1/downscale resolution and scales the
    intrinsics and observation coordinates to match.
    """
    import pycolmap

    sparse_dir = Path(sparse_dir)
    if not sparse_dir.is_dir():
        raise InputError(f"{sparse_dir} is not a COLMAP sparse model folder")
    try:
        rec = pycolmap.Reconstruction(str(sparse_dir))
    except Exception as exc:  # pycolmap raises its own types
        raise InputError(f"cannot read COLMAP model {sparse_dir}: {exc}") from exc
    images = sorted(rec.images.values(), key=lambda im: im.name)
    views: list[View] = []
    index_of: dict[int, int] = {}
    for im in images:
        if not im.has_pose:
            continue
        cam = camera_from_colmap(im.camera)
        if downscale != 1.0:
            cam = cam.scaled(1.0 / downscale)
        cfw = im.cam_from_world()
        R_cw = np.asarray(cfw.rotation.matrix())
        t_cw = np.asarray(cfw.translation)
        pose = Pose(R_cw.T, -R_cw.T @ t_cw)
        src = Path(images_dir) / im.name if images_dir is not None else Path(im.name)
        index_of[im.image_id] = len(views)
        views.append(View(key=Path(im.name).stem, stamp_ns=len(views), camera=cam, pose=pose,
                          loader=_pil_loader(src, (cam.width, cam.height)), source=str(src),
                          compressed=src.suffix.lower() in (".jpg", ".jpeg")))
    if images_dir is not None:  # before any work: a missing photo once crashed the masks
        missing = [v.source for v in views if not Path(v.source).is_file()]
        if missing:
            raise InputError(f"{len(missing)} of the COLMAP model's {len(views)} images are "
                             f"missing from {images_dir} (e.g. {Path(missing[0]).name}); pass "
                             "--images with the folder of the model's photos")
    pids = sorted(rec.points3D.keys())
    n = len(pids)
    xyz = np.zeros((n, 3))
    rgb = np.zeros((n, 3), np.uint8)
    err = np.zeros(n)
    ptr = np.zeros(n + 1, np.int64)
    ov: list[int] = []
    oxy: list[tuple[float, float]] = []
    s = 1.0 / downscale
    for i, pid in enumerate(pids):
        p = rec.points3D[pid]
        xyz[i] = p.xyz
        rgb[i] = p.color
        err[i] = p.error
        for el in p.track.elements:
            vi = index_of.get(el.image_id)
            if vi is None:
                continue
            xy = rec.images[el.image_id].points2D[el.point2D_idx].xy
            ov.append(vi)
            oxy.append((xy[0] * s - 0.5, xy[1] * s - 0.5))  # COLMAP +0.5 centres -> ROS
        ptr[i + 1] = len(ov)
    cloud = SfmCloud(xyz, rgb, err, ptr, np.asarray(ov, np.int32),
                     np.asarray(oxy, np.float32).reshape(-1, 2), views)
    return Capture(views=views, source=str(sparse_dir)), cloud
