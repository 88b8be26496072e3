"""The one module that converts ROS 2 messages to and from numpy / the package's core types.

Images become ``uint8`` RGB ``[H, W, 3]``; masks ``bool [H, W]`` (mono8, nonzero = object);
``CameraInfo`` <-> ``CameraIntrinsics``; poses are camera-to-world of the optical frame;
``PointCloud2`` carries ``x y z`` float32 (+ ``rgb`` packed into a float32 as RViz expects) and any
extra float32 fields by name. Malformed messages raise ``InputError`` naming the fix.
"""

from __future__ import annotations

import io
from typing import Optional, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point
from geometry_msgs.msg import Pose as PoseMsg
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2, PointField
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker

from .core.geometry import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from .core.types import CameraIntrinsics, InputError, Pose, SfmCloud, TriMesh, View

# encoding -> (channels, dtype, channel order to RGB or None for mono)
IMAGE_ENCODINGS = {
    "rgb8": (3, np.uint8, [0, 1, 2]),
    "bgr8": (3, np.uint8, [2, 1, 0]),
    "rgba8": (4, np.uint8, [0, 1, 2]),
    "bgra8": (4, np.uint8, [2, 1, 0]),
    "mono8": (1, np.uint8, None),
    "8UC1": (1, np.uint8, None),
    "mono16": (1, np.uint16, None),
    "16UC1": (1, np.uint16, None),
}


# ----------------------------------------------------------------------------- stamps
def stamp_to_ns(stamp: Time) -> int:
    """Integer nanoseconds of a builtin_interfaces/Time."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    """builtin_interfaces/Time of integer nanoseconds (sec may be negative, nanosec in range)."""
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return Time(sec=int(sec), nanosec=int(nsec))


def make_header(stamp, frame_id: str) -> Header:
    """A Header from a Time or integer nanoseconds."""
    if not isinstance(stamp, Time):
        stamp = ns_to_stamp(int(stamp))
    return Header(stamp=stamp, frame_id=frame_id)


# ----------------------------------------------------------------------------- images
def _image_array(msg: Image) -> tuple[np.ndarray, str]:
    """The message pixels as [H, W, C] array of the encoding's dtype (validated)."""
    enc = msg.encoding
    if enc not in IMAGE_ENCODINGS:
        raise InputError(f"image encoding {enc!r} is not supported; publish one of "
                         f"{sorted(IMAGE_ENCODINGS)} (e.g. debayer with image_proc first)")
    ch, dtype, _ = IMAGE_ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    isz = np.dtype(dtype).itemsize
    if h <= 0 or w <= 0:
        raise InputError(f"image is {w}x{h}; a camera image must have positive size")
    if step < w * ch * isz:
        raise InputError(f"image step {step} < width {w} x {ch * isz} bytes/pixel for {enc}; "
                         "the publisher sets step wrongly (step = width * bytes per pixel)")
    data = msg.data
    buf = data.tobytes() if hasattr(data, "tobytes") else bytes(data)
    if len(buf) != h * step:
        raise InputError(f"image data has {len(buf)} bytes but height {h} x step {step} = "
                         f"{h * step}; the message is truncated or its size fields are wrong")
    rows = np.frombuffer(buf, np.uint8).reshape(h, step)[:, :w * ch * isz]
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    arr = np.ascontiguousarray(rows).view(dt).reshape(h, w, ch)
    return arr.astype(dtype, copy=False), enc


def image_to_rgb(msg: Image) -> np.ndarray:
    """uint8 RGB [H, W, 3] of a sensor_msgs/Image (mono is replicated, mono16 scaled >> 8)."""
    arr, enc = _image_array(msg)
    order = IMAGE_ENCODINGS[enc][2]
    if order is None:
        g = arr[..., 0]
        if g.dtype == np.uint16:
            g = (g >> 8).astype(np.uint8)
        return np.repeat(g[..., None], 3, axis=2)
    return np.ascontiguousarray(arr[..., order])


def image_to_mask(msg: Image) -> np.ndarray:
    """bool [H, W] of a mono8/mono16 mask image (nonzero = object)."""
    arr, enc = _image_array(msg)
    if IMAGE_ENCODINGS[enc][2] is not None:
        raise InputError(f"mask image has encoding {enc}; publish masks as mono8 (0/255)")
    return arr[..., 0] != 0


def rgb_to_image(rgb: np.ndarray, stamp, frame_id: str = "camera_optical") -> Image:
    """sensor_msgs/Image (rgb8) of a uint8 RGB array."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise InputError(f"expected a uint8 [H, W, 3] RGB image, got {rgb.dtype} {rgb.shape}")
    h, w = rgb.shape[:2]
    return Image(header=make_header(stamp, frame_id), height=h, width=w, encoding="rgb8",
                 is_bigendian=0, step=w * 3, data=np.ascontiguousarray(rgb).tobytes())


def mask_to_image(mask: np.ndarray, stamp, frame_id: str = "camera_optical") -> Image:
    """mono8 sensor_msgs/Image (0 / 255) of a bool mask."""
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise InputError(f"expected a [H, W] mask, got shape {mask.shape}")
    h, w = mask.shape
    data = np.where(mask.astype(bool), 255, 0).astype(np.uint8)
    return Image(header=make_header(stamp, frame_id), height=h, width=w, encoding="mono8",
                 is_bigendian=0, step=w, data=data.tobytes())


def compressed_to_rgb(msg: CompressedImage) -> np.ndarray:
    """uint8 RGB [H, W, 3] of a jpeg/png sensor_msgs/CompressedImage."""
    from PIL import Image as PILImage, UnidentifiedImageError

    data = msg.data
    buf = data.tobytes() if hasattr(data, "tobytes") else bytes(data)
    try:
        with PILImage.open(io.BytesIO(buf)) as im:
            return np.asarray(im.convert("RGB"))
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise InputError(f"compressed image (format {msg.format!r}) cannot be decoded ({exc}); "
                         "publish jpeg or png") from exc


def is_lossy(msg: CompressedImage) -> bool:
    """True when a sensor_msgs/CompressedImage is JPEG (its ``format``, e.g. "jpeg" or
    "rgb8; jpeg compressed bgr8", names it); png is lossless."""
    fmt = str(msg.format).lower()
    return "jpeg" in fmt or "jpg" in fmt


def rgb_to_compressed(rgb: np.ndarray, stamp, frame_id: str = "camera_optical",
                      fmt: str = "png", quality: int = 95) -> CompressedImage:
    """sensor_msgs/CompressedImage (png lossless by default, or jpeg) of a uint8 RGB array."""
    from PIL import Image as PILImage

    fmt = fmt.lower()
    if fmt not in ("png", "jpeg", "jpg"):
        raise InputError(f"compressed format {fmt!r} is not png or jpeg")
    bio = io.BytesIO()
    im = PILImage.fromarray(np.asarray(rgb, np.uint8), "RGB")
    if fmt == "png":
        im.save(bio, format="PNG", optimize=False, compress_level=6)
    else:
        im.save(bio, format="JPEG", quality=int(quality))
    return CompressedImage(header=make_header(stamp, frame_id),
                           format="png" if fmt == "png" else "jpeg", data=bio.getvalue())


# ----------------------------------------------------------------------------- camera
def camera_info_to_intrinsics(msg: CameraInfo) -> CameraIntrinsics:
    """CameraIntrinsics of a CameraInfo (K, D, distortion_model); InputError when unusable."""
    k = np.asarray(msg.k, dtype=float).reshape(3, 3)
    if not np.any(k):
        raise InputError("camera_info K is all zeros (uncalibrated camera); calibrate it "
                         "(camera_calibration) and publish the result")
    model = (msg.distortion_model or "").strip()
    d = np.asarray(msg.d, dtype=float)
    if not np.any(d) and model in ("", "none", "plumb_bob", "rational_polynomial"):
        model = "none"  # all-zero coefficients: a pinhole camera whatever the name
    if model == "none" and np.any(d):
        model = "plumb_bob"
    cam = CameraIntrinsics(int(msg.width), int(msg.height), k[0, 0], k[1, 1], k[0, 2], k[1, 2],
                           model, d if model != "none" else np.zeros(0))
    cam.validate()
    return cam


def intrinsics_to_camera_info(cam: CameraIntrinsics, stamp,
                              frame_id: str = "camera_optical") -> CameraInfo:
    """CameraInfo (K, P, R = I, D) of CameraIntrinsics."""
    k = cam.K()
    p = np.zeros((3, 4))
    p[:, :3] = k
    model = cam.distortion_model if cam.distortion_model != "none" else "plumb_bob"
    d = np.asarray(cam.dist, dtype=float)
    if cam.distortion_model == "none":
        d = np.zeros(5)
    return CameraInfo(header=make_header(stamp, frame_id), height=int(cam.height),
                      width=int(cam.width), distortion_model=model, d=d.tolist(),
                      k=k.ravel().tolist(), r=np.eye(3).ravel().tolist(), p=p.ravel().tolist())


# ----------------------------------------------------------------------------- poses
def pose_from_msg(msg: PoseMsg) -> Pose:
    """Pose of a geometry_msgs/Pose; InputError for NaN or a zero/non-unit quaternion."""
    q = np.array([msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w])
    t = np.array([msg.position.x, msg.position.y, msg.position.z])
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))):
        raise InputError("pose contains NaN/inf; fix the pose source")
    try:
        R = quat_xyzw_to_matrix(q)
    except (ValueError, InputError) as exc:
        raise InputError(f"pose quaternion {q.tolist()} is not a unit quaternion ({exc})") \
            from exc
    return Pose(R, t)


def pose_to_msg(pose: Pose) -> PoseMsg:
    """geometry_msgs/Pose of a Pose."""
    q = matrix_to_quat_xyzw(pose.R)
    m = PoseMsg()
    m.position.x, m.position.y, m.position.z = (float(v) for v in pose.t)
    m.orientation.x, m.orientation.y, m.orientation.z, m.orientation.w = (float(v) for v in q)
    return m


def pose_to_pose_stamped(pose: Pose, stamp, frame_id: str = "map") -> PoseStamped:
    """PoseStamped (optical frame in ``frame_id``) of a Pose."""
    return PoseStamped(header=make_header(stamp, frame_id), pose=pose_to_msg(pose))


def pose_stamped_to_pose(msg: PoseStamped) -> tuple[int, Pose]:
    """(stamp ns, Pose) of a PoseStamped."""
    return stamp_to_ns(msg.header.stamp), pose_from_msg(msg.pose)


def odometry_to_pose(msg) -> tuple[int, Pose]:
    """(stamp ns, body Pose in the odometry frame) of a nav_msgs/Odometry."""
    return stamp_to_ns(msg.header.stamp), pose_from_msg(msg.pose.pose)


# ----------------------------------------------------------------------------- point clouds
_PF_DTYPES = {PointField.INT8: "i1", PointField.UINT8: "u1", PointField.INT16: "i2",
              PointField.UINT16: "u2", PointField.INT32: "i4", PointField.UINT32: "u4",
              PointField.FLOAT32: "f4", PointField.FLOAT64: "f8"}


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """[N] float32 whose bits are 0x00RRGGBB (PCL/RViz ``rgb`` field)."""
    rgb = np.asarray(rgb, np.uint8).reshape(-1, 3).astype(np.uint32)
    packed = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
    return packed.astype(np.uint32).view(np.float32)


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    """[N, 3] uint8 of a packed ``rgb`` float32 field."""
    u = np.asarray(packed, np.float32).view(np.uint32)
    return np.stack([(u >> 16) & 255, (u >> 8) & 255, u & 255], axis=1).astype(np.uint8)


def fields_to_pointcloud2(fields: dict[str, np.ndarray], stamp, frame_id: str = "map",
                          dtypes: Optional[dict[str, str]] = None) -> PointCloud2:
    """An unorganised PointCloud2 of named 1-D columns (float32 unless ``dtypes`` says else).

    Field order follows the dict order, as the training node's Gaussians (x y z f_dc_0..2
    f_rest_* opacity scale_0..2 rot_0..3) need.
    """
    names = list(fields)
    if not names:
        raise InputError("a point cloud needs at least one field")
    n = len(np.asarray(fields[names[0]]).reshape(-1))
    dt_map = {v: k for k, v in _PF_DTYPES.items()}
    descr = []
    for name in names:
        col = np.asarray(fields[name]).reshape(-1)
        if len(col) != n:
            raise InputError(f"point field {name} has {len(col)} values, not {n}")
        code = np.dtype((dtypes or {}).get(name, "f4")).str.lstrip("<>|=")
        if code not in dt_map:
            raise InputError(f"point field {name}: dtype {code} cannot go into a PointCloud2")
        descr.append((name, "<" + code))
    rec = np.zeros(n, dtype=np.dtype(descr))
    offsets = []
    for name, code in descr:
        rec[name] = np.asarray(fields[name]).reshape(-1)
        offsets.append(rec.dtype.fields[name][1])
    pfs = [PointField(name=name, offset=int(off), datatype=dt_map[code[1:]], count=1)
           for (name, code), off in zip(descr, offsets)]
    return PointCloud2(header=make_header(stamp, frame_id), height=1, width=n, fields=pfs,
                       is_bigendian=False, point_step=rec.dtype.itemsize,
                       row_step=rec.dtype.itemsize * n, data=rec.tobytes(), is_dense=True)


def pointcloud2_to_fields(msg: PointCloud2,
                          names: Optional[Sequence[str]] = None) -> dict[str, np.ndarray]:
    """{field name: [N] array} of a PointCloud2 (count == 1 fields; ``names`` to pick)."""
    n = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    data = msg.data
    buf = data.tobytes() if hasattr(data, "tobytes") else bytes(data)
    row = int(msg.width) * step
    if n and (int(msg.row_step) < row or len(buf) < int(msg.row_step) * int(msg.height)):
        raise InputError(f"point cloud data has {len(buf)} bytes for {msg.height} rows of "
                         f"row_step {msg.row_step} ({msg.width} x {step} bytes); the message is "
                         "truncated or its size fields are wrong")
    if n and int(msg.row_step) != row:  # organised cloud with row padding
        rows = np.frombuffer(buf, np.uint8, count=int(msg.row_step) * int(msg.height))
        buf = rows.reshape(int(msg.height), int(msg.row_step))[:, :row].tobytes()
    endian = ">" if msg.is_bigendian else "<"
    out: dict[str, np.ndarray] = {}
    have = {f.name: f for f in msg.fields}
    for name in (names if names is not None else list(have)):
        f = have.get(name)
        if f is None:
            raise InputError(f"point cloud has no field {name!r}; it has {sorted(have)}")
        code = _PF_DTYPES.get(f.datatype)
        if code is None:
            raise InputError(f"point field {name} has unknown datatype {f.datatype}")
        dt = np.dtype(endian + code)
        if n == 0:
            out[name] = np.zeros(0, dt.newbyteorder("="))
            continue
        rows = np.frombuffer(buf, np.uint8, count=n * step).reshape(n, step)
        col = rows[:, f.offset:f.offset + dt.itemsize].copy().view(dt).reshape(n)
        out[name] = col.astype(dt.newbyteorder("="))
    return out


def xyzrgb_to_pointcloud2(xyz: np.ndarray, rgb: Optional[np.ndarray], stamp,
                          frame_id: str = "map",
                          extra: Optional[dict[str, np.ndarray]] = None) -> PointCloud2:
    """PointCloud2 with x y z (float32), packed rgb (if given) and extra float32 fields."""
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    fields: dict[str, np.ndarray] = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    if rgb is not None:
        fields["rgb"] = pack_rgb(rgb)
    for k, v in (extra or {}).items():
        fields[k] = np.asarray(v, np.float32)
    return fields_to_pointcloud2(fields, stamp, frame_id)


def pointcloud2_to_xyzrgb(msg: PointCloud2) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """([N, 3] float64 xyz, [N, 3] uint8 rgb or None) of a PointCloud2."""
    names = {f.name for f in msg.fields}
    f = pointcloud2_to_fields(msg, ["x", "y", "z"])
    xyz = np.stack([f["x"], f["y"], f["z"]], axis=1).astype(float)
    rgb = None
    if "rgb" in names or "rgba" in names:
        key = "rgb" if "rgb" in names else "rgba"
        col = pointcloud2_to_fields(msg, [key])[key]
        rgb = unpack_rgb(col.view(np.float32) if col.dtype.itemsize == 4 else col)
    return xyz, rgb


def _split_ns(ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ns = np.asarray(ns, np.int64)
    return (ns // 1_000_000_000).astype(np.uint32), (ns % 1_000_000_000).astype(np.uint32)


def observations_to_pointcloud2(cloud: SfmCloud, stamp, frame_id: str = "map") -> PointCloud2:
    """The cloud's observations, one PointCloud2 point per (point, view) observation.

    Fields: ``point`` (uint32 point index), ``stamp_sec``/``stamp_nsec`` (uint32, the observing
    view's stamp, so receivers match views by stamp), ``u`` ``v`` (float32 pixel, ROS
    convention) and the per-point ``error`` is sent with the points, not here.
    """
    lens = cloud.track_lengths()
    point = np.repeat(np.arange(len(cloud), dtype=np.uint32), lens)
    stamps = np.array([v.stamp_ns for v in cloud.views], np.int64)
    vs = stamps[cloud.obs_view] if len(cloud.obs_view) else np.zeros(0, np.int64)
    sec, nsec = _split_ns(vs)
    return fields_to_pointcloud2(
        {"point": point, "stamp_sec": sec, "stamp_nsec": nsec,
         "u": cloud.obs_xy[:, 0], "v": cloud.obs_xy[:, 1]}, stamp, frame_id,
        dtypes={"point": "u4", "stamp_sec": "u4", "stamp_nsec": "u4"})


def sfm_cloud_to_pointcloud2(cloud: SfmCloud, stamp, frame_id: str = "map") -> PointCloud2:
    """Points of an SfmCloud: x y z rgb + ``error`` (mean reprojection error, px)."""
    return xyzrgb_to_pointcloud2(cloud.xyz, cloud.rgb, stamp, frame_id,
                                 extra={"error": cloud.error})


def pointcloud2_to_sfm_cloud(points_msg: PointCloud2, obs_msg: Optional[PointCloud2],
                             views: list[View]) -> SfmCloud:
    """SfmCloud from the points message and the observations message (may be None).

    Observations are matched to ``views`` by stamp; those of views not in ``views`` are
    dropped (a receiver may know only a subset of keyframes).
    """
    xyz, rgb = pointcloud2_to_xyzrgb(points_msg)
    n = len(xyz)
    if rgb is None:
        rgb = np.full((n, 3), 128, np.uint8)
    names = {f.name for f in points_msg.fields}
    err = (pointcloud2_to_fields(points_msg, ["error"])["error"].astype(float)
           if "error" in names else np.zeros(n))
    if obs_msg is None:
        cloud = SfmCloud.from_points(xyz, rgb, views)
        cloud.error = err
        return cloud
    f = pointcloud2_to_fields(obs_msg, ["point", "stamp_sec", "stamp_nsec", "u", "v"])
    stamp = f["stamp_sec"].astype(np.int64) * 1_000_000_000 + f["stamp_nsec"].astype(np.int64)
    index = {int(v.stamp_ns): i for i, v in enumerate(views)}
    vi = np.array([index.get(int(s), -1) for s in stamp], np.int64)
    pt = f["point"].astype(np.int64)
    ok = (vi >= 0) & (pt < n)
    pt, vi = pt[ok], vi[ok]
    uv = np.stack([f["u"], f["v"]], axis=1).astype(np.float32)[ok]
    order = np.argsort(pt, kind="stable")
    pt, vi, uv = pt[order], vi[order], uv[order]
    ptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(pt, minlength=n), out=ptr[1:])
    return SfmCloud(xyz, rgb, err, ptr, vi.astype(np.int32), uv, views)


# ----------------------------------------------------------------------------- meshes
def mesh_to_marker(mesh: TriMesh, stamp, frame_id: str = "map", ns: str = "ooi",
                   marker_id: int = 0,
                   color: tuple[float, float, float, float] = (0.9, 0.6, 0.1, 0.8)) -> Marker:
    """visualization_msgs/Marker TRIANGLE_LIST of a mesh (3 points per triangle)."""
    v = np.asarray(mesh.vertices, float)
    tri = np.asarray(mesh.triangles, np.int64).reshape(-1, 3)
    m = Marker(header=make_header(stamp, frame_id), ns=ns, id=int(marker_id),
               type=Marker.TRIANGLE_LIST, action=Marker.ADD)
    m.pose.orientation.w = 1.0
    m.scale.x = m.scale.y = m.scale.z = 1.0
    m.color = ColorRGBA(r=float(color[0]), g=float(color[1]), b=float(color[2]),
                        a=float(color[3]))
    pts = v[tri.reshape(-1)] if len(tri) else np.zeros((0, 3))
    m.points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in pts]
    return m


def marker_to_mesh(msg: Marker) -> TriMesh:
    """TriMesh of a TRIANGLE_LIST marker (vertices not merged)."""
    if msg.type != Marker.TRIANGLE_LIST:
        raise InputError(f"marker type {msg.type} is not TRIANGLE_LIST ({Marker.TRIANGLE_LIST})")
    pts = np.array([[p.x, p.y, p.z] for p in msg.points], float).reshape(-1, 3)
    if len(pts) % 3:
        raise InputError(f"TRIANGLE_LIST marker has {len(pts)} points, not a multiple of 3")
    return TriMesh(pts, np.arange(len(pts), dtype=np.int32).reshape(-1, 3))
