"""Export an ``SfmCloud`` as a COLMAP binary sparse model and as a PLY.

The COLMAP model is written in the documented binary layout (cameras.bin, images.bin,
points3D.bin) so that it carries our fixed poses and observations exactly; pycolmap then reads
it back (``pycolmap.Reconstruction(dir)``) for checks, bundle adjustment or the batch route.
COLMAP puts pixel centres at +0.5, this package at integer coordinates: +0.5 on the way out.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.geometry import matrix_to_quat_xyzw
from ..core.types import CameraIntrinsics, InputError, SfmCloud, View

# COLMAP camera model ids
_PINHOLE, _OPENCV, _OPENCV_FISHEYE, _FULL_OPENCV = 1, 4, 5, 6


def camera_to_colmap(cam: CameraIntrinsics) -> tuple[int, list[float]]:
    """(COLMAP model id, params) of an intrinsics object (pixel centres shifted by +0.5)."""
    f = [cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5]
    d = np.zeros(8)
    dist = np.asarray(cam.dist, float)
    d[:min(8, dist.size)] = dist[:8]
    if not cam.has_distortion:
        return _PINHOLE, f
    if cam.distortion_model == "equidistant":
        return _OPENCV_FISHEYE, f + list(d[:4])
    if cam.distortion_model == "plumb_bob" and d[4] == 0:
        return _OPENCV, f + list(d[:4])
    return _FULL_OPENCV, f + list(d[:8])


def _camera_ids(views: list[View]) -> tuple[list[int], dict[int, CameraIntrinsics]]:
    ids, cams, seen = [], {}, {}
    for v in views:
        c = v.camera
        key = (c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.distortion_model,
               tuple(np.asarray(c.dist, float).ravel()))
        if key not in seen:
            seen[key] = len(seen) + 1
            cams[seen[key]] = c
        ids.append(seen[key])
    return ids, cams


def image_name(view: View) -> str:
    """File name a view gets in the COLMAP model (its source file name when it has one)."""
    from ..capture_io import IMAGE_SUFFIXES  # any photo the readers take (.tif and .bmp too)
    src = Path(view.source) if view.source else None
    if src is not None and src.suffix.lower() in IMAGE_SUFFIXES:
        return src.name
    return f"{view.key}.png"


def write_colmap_model(cloud: SfmCloud, out_dir: str | Path,
                       views: Optional[list[View]] = None,
                       image_ids: Optional[list[int]] = None,
                       names: Optional[list[str]] = None) -> Path:
    """Write ``cloud`` (poses of ``cloud.views``) as a COLMAP binary model in ``out_dir``.

    ``image_ids``/``names`` override the default ids (1..n) and file names, e.g. to match the
    images of a COLMAP database.
    """
    views = list(views if views is not None else cloud.views)
    image_ids = list(image_ids) if image_ids is not None else list(range(1, len(views) + 1))
    names = list(names) if names is not None else [image_name(v) for v in views]
    if any(v.pose is None for v in views):
        raise InputError("cannot export a COLMAP model: some views have no pose")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cam_ids, cams = _camera_ids(views)
    with open(out / "cameras.bin", "wb") as fh:
        fh.write(struct.pack("<Q", len(cams)))
        for cid, c in cams.items():
            model, params = camera_to_colmap(c)
            fh.write(struct.pack("<iiQQ", cid, model, c.width, c.height))
            fh.write(struct.pack(f"<{len(params)}d", *params))
    # per image: list of (x, y, point3D_id); per point: list of (image_id, point2D_idx)
    n = len(cloud)
    per_image: list[list[tuple[float, float, int]]] = [[] for _ in views]
    tracks: list[list[tuple[int, int]]] = [[] for _ in range(n)]
    for i in range(n):
        s, e = int(cloud.obs_ptr[i]), int(cloud.obs_ptr[i + 1])
        for vi, (x, y) in zip(cloud.obs_view[s:e], cloud.obs_xy[s:e]):
            lst = per_image[int(vi)]
            tracks[i].append((image_ids[int(vi)], len(lst)))
            lst.append((float(x) + 0.5, float(y) + 0.5, i + 1))
    with open(out / "images.bin", "wb") as fh:
        fh.write(struct.pack("<Q", len(views)))
        for k, v in enumerate(views):
            R_cw, t_cw = v.pose.world_to_cam()
            q = matrix_to_quat_xyzw(R_cw)
            fh.write(struct.pack("<i4d3di", image_ids[k], q[3], q[0], q[1], q[2], *t_cw,
                                 cam_ids[k]))
            fh.write(names[k].encode() + b"\0")
            fh.write(struct.pack("<Q", len(per_image[k])))
            for x, y, pid in per_image[k]:
                fh.write(struct.pack("<ddq", x, y, pid))
    with open(out / "points3D.bin", "wb") as fh:
        fh.write(struct.pack("<Q", n))
        for i in range(n):
            fh.write(struct.pack("<Q3d3Bd", i + 1, *cloud.xyz[i], *cloud.rgb[i],
                                 float(cloud.error[i])))
            fh.write(struct.pack("<Q", len(tracks[i])))
            for img_id, idx in tracks[i]:
                fh.write(struct.pack("<ii", img_id, idx))
    return out


def write_ply(xyz: np.ndarray, rgb: np.ndarray, path: str | Path) -> Path:
    """Binary little-endian PLY with float xyz and uchar rgb."""
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    rgb = np.asarray(rgb, np.uint8).reshape(-1, 3)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rec = np.zeros(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                    ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    rec["x"], rec["y"], rec["z"] = xyz.T
    rec["red"], rec["green"], rec["blue"] = rgb.T
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(xyz)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    with open(path, "wb") as fh:
        fh.write(header.encode())
        fh.write(rec.tobytes())
    return path
