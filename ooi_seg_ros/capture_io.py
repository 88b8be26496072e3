"""Load any supported input into a ``Capture`` and write captures as bags or folders.

Inputs (``read_capture`` dispatches on what the path is):
- a capture bag (``.mcap`` file or rosbag2 folder): ``/camera/image_raw`` (Image) or
  ``/camera/image_raw/compressed``, ``/camera/camera_info``, ``/camera/pose`` (PoseStamped of the
  optical frame in ``map``) or an Odometry topic (+ ``mount``), ground truth on
  ``/ground_truth/mask`` (mono8, image stamps) and ``/ground_truth/ooi_points`` (PointCloud2).
  Poses are interpolated to image stamps; images without a usable pose are dropped and counted
  in ``capture.meta["dropped"]``. View key = image stamp in integer ns.
- a COLMAP dataset folder as Mip-NeRF 360 ships it (``images/``, ``images_N/``, ``sparse/0``).
- a nerfstudio ``transforms.json`` folder (OpenGL camera-to-world; cx/cy with COLMAP's +0.5
  pixel-centre convention, converted to ROS's integer centres here).
- a plain image folder (no poses; intrinsics from EXIF or a default focal, noted in meta).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from collections import Counter
from pathlib import Path
from typing import Optional, Union

import numpy as np

from .core.geometry import pose_from_gl_c2w, pose_to_gl_c2w
from .core.sync import PoseBuffer
from .core.types import CameraIntrinsics, Capture, InputError, Pose, SfmCloud, View

log = logging.getLogger(__name__)

IMAGE_TOPIC = "/camera/image_raw"
COMPRESSED_TOPIC = "/camera/image_raw/compressed"
INFO_TOPIC = "/camera/camera_info"
POSE_TOPIC = "/camera/pose"
GT_MASK_TOPIC = "/ground_truth/mask"
GT_POINTS_TOPIC = "/ground_truth/ooi_points"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
DEFAULT_FOCAL_FACTOR = 1.2  # focal = 1.2 * max(w, h) when nothing better is known (~45 deg)
META_RECORD = "ooi_seg_capture"

PathLike = Union[str, Path]


# ============================================================================ dispatch
def read_capture(path: PathLike, *, downscale: float = 1.0, image_topic: Optional[str] = None,
                 info_topic: Optional[str] = None, pose_topic: Optional[str] = None,
                 pose_tolerance_ns: Optional[int] = None, mount: Optional[Pose] = None,
                 lazy_images: bool = False) -> Capture:
    """A ``Capture`` of a bag, COLMAP dataset, nerfstudio folder or plain image folder."""
    cap, _ = read_capture_and_cloud(path, downscale=downscale, image_topic=image_topic,
                                    info_topic=info_topic, pose_topic=pose_topic,
                                    pose_tolerance_ns=pose_tolerance_ns, mount=mount,
                                    lazy_images=lazy_images)
    return cap


def input_kind(path: PathLike) -> str:
    """"bag", "colmap", "nerfstudio" or "images"; InputError when the path is none of them."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"input {p} does not exist; give a bag (.mcap or rosbag2 folder), a "
                         "COLMAP dataset, a nerfstudio transforms.json folder or an image folder")
    if p.is_file():
        if p.suffix == ".mcap":
            return "bag"
        if p.name == "transforms.json":
            return "nerfstudio"
        raise InputError(f"{p} is not an .mcap bag; give a bag, a dataset folder or an image "
                         "folder")
    if (p / "metadata.yaml").is_file() or any(p.glob("*.mcap")):
        return "bag"
    if (p / "transforms.json").is_file():
        return "nerfstudio"
    if _colmap_sparse_dir(p) is not None:
        return "colmap"
    if _image_files(p) or _image_files(p / "images"):
        return "images"
    raise InputError(f"{p} holds no bag, COLMAP model (sparse/0), transforms.json or images; "
                     "point at the capture itself")


def read_capture_and_cloud(path: PathLike, *, downscale: float = 1.0,
                           image_topic: Optional[str] = None, info_topic: Optional[str] = None,
                           pose_topic: Optional[str] = None,
                           pose_tolerance_ns: Optional[int] = None, mount: Optional[Pose] = None,
                           lazy_images: bool = False) -> tuple[Capture, Optional[SfmCloud]]:
    """(Capture, SfmCloud or None): the cloud comes with COLMAP datasets only.

    Folder inputs always load images lazily; bags only with ``lazy_images``.
    """
    if not (downscale >= 1.0 and np.isfinite(downscale)):
        raise InputError(f"downscale {downscale} must be >= 1 (2 = half resolution)")
    p = Path(path)
    kind = input_kind(p)
    if p.is_file() and kind == "nerfstudio":
        p = p.parent
    if kind == "bag":
        return read_bag_capture(p, downscale=downscale, image_topic=image_topic,
                                info_topic=info_topic, pose_topic=pose_topic,
                                pose_tolerance_ns=pose_tolerance_ns, mount=mount,
                                lazy_images=lazy_images), None
    if kind == "colmap":
        return read_colmap_dataset(p, downscale=downscale)
    if kind == "nerfstudio":
        return read_nerfstudio(p, downscale=downscale), None
    return read_image_folder(p, downscale=downscale), None


def write_capture(capture: Capture, out: PathLike, compressed: bool = False,
                  jpeg_quality: int = 0) -> Path:
    """Writes a bag when ``out`` ends in ``.mcap``, else a nerfstudio-style folder.

    ``jpeg_quality`` 1-100: the images as JPEG at that quality (a bag's as CompressedImage,
    as a camera's ``image/compressed`` topic delivers them; a folder's as ``.jpg`` files);
    0: lossless (``compressed``: a bag's images as PNG CompressedImage)."""
    out = Path(out)
    q = int(jpeg_quality)
    if not 0 <= q <= 100:
        raise InputError(f"JPEG quality {jpeg_quality}: use 1-100 (0 = lossless images)")
    if out.suffix == ".mcap":
        write_capture_bag(capture, out, compressed=compressed or q > 0,
                          image_format="jpeg" if q else "png", quality=q or 95)
    else:
        write_capture_folder(capture, out, jpeg_quality=q)
    return out


# ============================================================================ helpers
def _resize_rgb(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    from PIL import Image
    if (img.shape[1], img.shape[0]) == size:
        return img
    return np.asarray(Image.fromarray(img).resize(size, Image.Resampling.BOX))


def _resize_mask(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    from PIL import Image
    if (mask.shape[1], mask.shape[0]) == size:
        return mask
    im = Image.fromarray(mask.astype(np.uint8) * 255).resize(size, Image.Resampling.BOX)
    return np.asarray(im) >= 128


def exif_orientation(im) -> int:
    """The EXIF Orientation tag (1-8) of an open PIL image; 1 (upright) when absent or bad."""
    try:
        o = int(im.getexif().get(0x0112, 1) or 1)
    except (AttributeError, TypeError, ValueError, OSError, SyntaxError):
        return 1
    return o if 1 <= o <= 8 else 1


def _upright(im):
    """``im`` turned as its EXIF Orientation says (what photo viewers show), else itself."""
    if exif_orientation(im) == 1:
        return im
    from PIL import ImageOps
    try:
        return ImageOps.exif_transpose(im)
    except (OSError, ValueError, SyntaxError):
        return im


def _load_rgb(path: Path, size: Optional[tuple[int, int]] = None,
              upright: bool = False) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError
    try:
        with Image.open(path) as im:
            arr = np.asarray((_upright(im) if upright else im).convert("RGB"))
    except (OSError, UnidentifiedImageError, SyntaxError) as exc:
        raise InputError(f"cannot read image {path} ({exc}); replace or remove it") from exc
    return _resize_rgb(arr, size) if size is not None else arr


def _load_mask(path: Path, size: Optional[tuple[int, int]] = None) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError
    try:
        with Image.open(path) as im:
            arr = np.asarray(im.convert("L")) >= 128
    except (OSError, UnidentifiedImageError) as exc:
        raise InputError(f"cannot read mask {path} ({exc}); replace or remove it") from exc
    return _resize_mask(arr, size) if size is not None else arr


def _image_files(d: Path) -> list[Path]:
    """The photos of folder ``d``, by name: image suffixes in any case; hidden files are not
    photos (macOS writes "._NAME.JPG" metadata beside every photo copied to an SD card)."""
    if not d.is_dir():
        return []
    return sorted(p for p in d.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
                  and not p.name.startswith("."))


def _rgb_loader(path: Path, size: Optional[tuple[int, int]], upright: bool = False):
    return lambda: _load_rgb(path, size, upright)


def read_ply_points(path: PathLike) -> np.ndarray:
    """[N, 3] float64 vertex positions of a PLY point cloud.

    The layout ``write_ply_points`` makes is parsed directly; any other PLY goes through open3d
    (whose import costs about a second).
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"point file {p} does not exist")
    raw = p.read_bytes()
    end = raw.find(b"end_header\n")
    if end > 0:
        head = raw[:end].decode("ascii", "replace").splitlines()
        props = [ln.split()[-1] for ln in head if ln.startswith("property")]
        verts = [ln for ln in head if ln.startswith("element vertex")]
        if ("format binary_little_endian 1.0" in head and props == ["x", "y", "z"]
                and all(ln.split()[1] == "float" for ln in head if ln.startswith("property"))
                and len(verts) == 1 and len([ln for ln in head if ln.startswith("element")]) == 1):
            n = int(verts[0].split()[-1])
            body = raw[end + len("end_header\n"):]
            if len(body) >= n * 12 and n > 0:
                return np.frombuffer(body, "<f4", count=n * 3).reshape(n, 3).astype(float)
    import open3d as o3d
    pc = o3d.io.read_point_cloud(str(p))
    pts = np.asarray(pc.points, dtype=float)
    if len(pts) == 0:
        raise InputError(f"{p} holds no points (or is not a PLY point cloud)")
    return pts


def write_ply_points(path: PathLike, xyz: np.ndarray) -> None:
    """A binary little-endian PLY of float32 x y z (deterministic bytes)."""
    xyz = np.asarray(xyz, np.float32).reshape(-1, 3)
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\n"
            "property float x\nproperty float y\nproperty float z\nend_header\n")
    with open(path, "wb") as f:
        f.write(head.encode("ascii"))
        f.write(xyz.astype("<f4").tobytes())


def _json_safe(obj):
    """meta dicts may carry numpy values; JSON needs plain types."""
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (str, int, float, bool)) or obj is None:
        return obj
    return str(obj)


# ============================================================================ bags
def read_bag_capture(path: PathLike, *, downscale: float = 1.0,
                     image_topic: Optional[str] = None, info_topic: Optional[str] = None,
                     pose_topic: Optional[str] = None, pose_tolerance_ns: Optional[int] = None,
                     mount: Optional[Pose] = None, lazy_images: bool = False) -> Capture:
    """A Capture from a capture bag (see the module doc for topics).

    ``lazy_images`` keeps only image stamps and sizes in memory (every image is still decoded
    and validated once here); ``View.get_image()`` then reads its message from the bag again.
    Ignored for a damaged bag, which can only be read front to back.
    """
    from . import msgconv
    from .bag import BagReader

    reader = BagReader(path)
    topics = reader.topics()
    if image_topic is None:
        image_topic = next((t for t in (IMAGE_TOPIC, COMPRESSED_TOPIC)
                            if t in topics and topics[t].count > 0), None)
        if image_topic is None:
            imgs = [t for t, i in topics.items()
                    if i.type in ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")]
            raise InputError(f"bag {path} has no {IMAGE_TOPIC} or {COMPRESSED_TOPIC} messages; "
                             f"pass image_topic (image topics in the bag: {imgs or 'none'})")
    info_topic = info_topic or INFO_TOPIC
    if pose_topic is None:
        pose_topic = POSE_TOPIC if POSE_TOPIC in topics else next(
            (t for t, i in sorted(topics.items()) if i.type == "nav_msgs/msg/Odometry"), None)
    reader.require_topics([image_topic, info_topic] + ([pose_topic] if pose_topic else []))
    img_type = topics[image_topic].type
    if img_type not in ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"):
        raise InputError(f"{image_topic} carries {img_type}, not sensor_msgs Image or "
                         "CompressedImage; pass the right image_topic")
    pose_type = topics[pose_topic].type if pose_topic else None
    if pose_type not in (None, "geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry"):
        raise InputError(f"{pose_topic} carries {pose_type}; poses must be PoseStamped or "
                         "Odometry")
    want = [image_topic, info_topic] + [t for t in (pose_topic, GT_MASK_TOPIC, GT_POINTS_TOPIC)
                                        if t and t in topics]
    images: list[tuple[int, Optional[np.ndarray], tuple[int, int], int]] = []
    poses: list[tuple[int, Pose]] = []
    infos: list[tuple[int, CameraIntrinsics]] = []
    masks: dict[int, np.ndarray] = {}
    gt_points = None
    info_error = ""
    dropped: Counter = Counter()
    lossy: set[int] = set()  # stamps of JPEG CompressedImage messages
    lazy = lazy_images and not reader.truncated
    for topic, ty, log_t, data in reader.messages(topics=want):
        msg = reader.decode(ty, data, topic)
        if topic == image_topic:
            stamp = msgconv.stamp_to_ns(msg.header.stamp)
            rgb = _bag_image_rgb(msg, ty)
            images.append((stamp, None if lazy else rgb, rgb.shape[:2], log_t))
            if not ty.endswith("/Image") and msgconv.is_lossy(msg):
                lossy.add(stamp)
        elif topic == info_topic:
            try:
                infos.append((msgconv.stamp_to_ns(msg.header.stamp),
                              msgconv.camera_info_to_intrinsics(msg)))
            except InputError as exc:
                dropped["invalid_camera_info"] += 1
                info_error = str(exc)
        elif topic == pose_topic:
            try:
                if pose_type == "nav_msgs/msg/Odometry":
                    stamp, pose = msgconv.odometry_to_pose(msg)
                else:
                    stamp, pose = msgconv.pose_stamped_to_pose(msg)
            except InputError:
                dropped["invalid_pose_message"] += 1
                continue
            poses.append((stamp, pose))
        elif topic == GT_MASK_TOPIC:
            masks[msgconv.stamp_to_ns(msg.header.stamp)] = msgconv.image_to_mask(msg)
        elif topic == GT_POINTS_TOPIC:
            gt_points, _ = msgconv.pointcloud2_to_xyzrgb(msg)
    if not images:
        raise InputError(f"bag {path} has no messages on {image_topic}")
    if not infos:
        if info_error:
            raise InputError(f"bag {path}: no usable camera_info on {info_topic}: {info_error}")
        raise InputError(f"bag {path} has no messages on {info_topic}; record the camera_info "
                         "topic with the images")
    images.sort(key=lambda x: x[0])
    info_stamps = np.array([s for s, _ in infos], np.int64)
    # tolerance: default 1.5 pose periods (derived from the pose stream), at least 1 ms
    poses.sort(key=lambda x: x[0])
    if pose_tolerance_ns is None:
        if len(poses) >= 2:
            gaps = np.diff([s for s, _ in poses])
            gaps = gaps[gaps > 0]
            pose_tolerance_ns = int(max(1.5 * np.median(gaps), 1e6)) if len(gaps) else 10**6
        else:
            pose_tolerance_ns = 10**6
    buf = PoseBuffer(max_age_ns=2**62, tolerance_ns=pose_tolerance_ns, mount=mount,
                     max_len=len(poses) + 1)
    for s, p in poses:
        buf.add(s, p)
    for reason, n in buf.rejected.items():
        dropped[f"pose_{reason}"] += n
    views: list[View] = []
    seen: set[int] = set()
    for stamp, rgb, (h, w), log_t in images:
        if stamp in seen:
            dropped["duplicate_image_stamp"] += 1
            continue
        seen.add(stamp)
        pose = buf.lookup(stamp) if pose_topic else None
        if pose_topic and pose is None:
            dropped["no_pose_within_tolerance"] += 1
            continue
        cam = infos[int(np.argmin(np.abs(info_stamps - stamp)))][1]
        if (w, h) != (cam.width, cam.height):
            dropped["size_differs_from_camera_info"] += 1
            continue
        mask = masks.get(stamp)
        if mask is not None and mask.shape != (h, w):
            raise InputError(f"ground-truth mask at {stamp} is {mask.shape[1]}x{mask.shape[0]}, "
                             f"its image {w}x{h}; re-export the masks")
        if downscale != 1.0:
            cam = cam.scaled(1.0 / downscale)
            size = (cam.width, cam.height)
            rgb = _resize_rgb(rgb, size) if rgb is not None else None
            mask = _resize_mask(mask, size) if mask is not None else None
        loader = (_bag_image_loader(reader, image_topic, stamp, log_t, (cam.width, cam.height))
                  if rgb is None else None)
        views.append(View(key=str(stamp), stamp_ns=stamp, camera=cam, pose=pose, image=rgb,
                          gt_mask=mask, loader=loader, source=f"{path}:{image_topic}",
                          compressed=stamp in lossy))
    if dropped:
        log.warning("read_capture %s: dropped %s", path, dict(dropped))
    if not views:
        raise InputError(f"bag {path}: none of {len(images)} images is usable ({dict(dropped)}); "
                         "check that poses cover the image stamps (or raise pose_tolerance_ns)")
    meta: dict = {}
    rec = reader.metadata(META_RECORD)
    if rec and "meta_json" in rec:
        try:
            meta.update(json.loads(rec["meta_json"]))
        except ValueError:
            pass
    meta.update({"input": "bag", "image_topic": image_topic, "pose_topic": pose_topic,
                 "pose_tolerance_ns": pose_tolerance_ns, "dropped": dict(dropped),
                 "bag_warnings": list(reader.warnings)})
    if not pose_topic:
        meta["note"] = "the bag has no pose topic: views have no poses (SfM must estimate them)"
    return Capture(views=views, source=str(path), gt_ooi_points=gt_points, meta=meta)


def is_lossy_file(path: PathLike) -> bool:
    """True for a JPEG image file (by its name: .jpg / .jpeg, any case)."""
    return Path(path).suffix.lower() in (".jpg", ".jpeg")


def _bag_image_rgb(msg, type_name: str) -> np.ndarray:
    from . import msgconv
    return (msgconv.image_to_rgb(msg) if type_name.endswith("/Image")
            else msgconv.compressed_to_rgb(msg))


def _bag_image_loader(reader, topic: str, stamp: int, log_t: int, size: tuple[int, int]):
    """Loader that reads the image with header stamp ``stamp`` logged at ``log_t`` again."""
    from . import msgconv

    def load() -> np.ndarray:
        for _t, ty, _lt, data in reader.messages(topics=[topic], start_ns=log_t,
                                                 end_ns=log_t + 1):
            msg = reader.decode(ty, data, topic)
            if msgconv.stamp_to_ns(msg.header.stamp) == stamp:
                return _resize_rgb(_bag_image_rgb(msg, ty), size)
        raise InputError(f"image {stamp} is no longer in {reader.path}; was the bag changed?")
    return load


def write_capture_bag(capture: Capture, path: PathLike, compressed: bool = False,
                      image_format: str = "png", quality: int = 95) -> Path:
    """A capture bag (images, camera_info, poses, ground truth); same capture -> same bytes.

    Messages are logged at their view stamps. Written atomically (``<path>.part`` renamed).
    ``compressed``: images as sensor_msgs/CompressedImage in ``image_format`` (png, lossless;
    or jpeg at ``quality``, 95 by default, as many drone cameras deliver them).
    """
    from . import msgconv
    from .bag import BagWriter

    path = Path(path)
    if not capture.views:
        raise InputError("the capture has no views to write")
    img_topic = COMPRESSED_TOPIC if compressed else IMAGE_TOPIC
    with BagWriter(path, atomic=True) as w:
        w.add_topic(img_topic, "sensor_msgs/msg/CompressedImage" if compressed
                    else "sensor_msgs/msg/Image", "reliable")
        w.add_topic(INFO_TOPIC, "sensor_msgs/msg/CameraInfo", "reliable")
        if any(v.pose is not None for v in capture.views):
            w.add_topic(POSE_TOPIC, "geometry_msgs/msg/PoseStamped", "reliable")
        if any(v.gt_mask is not None for v in capture.views):
            w.add_topic(GT_MASK_TOPIC, "sensor_msgs/msg/Image", "reliable")
        if capture.gt_ooi_points is not None:
            w.add_topic(GT_POINTS_TOPIC, "sensor_msgs/msg/PointCloud2", "transient_local")
        w.add_metadata(META_RECORD, {"meta_json": json.dumps(_json_safe(capture.meta),
                                                             sort_keys=True),
                                     "source": capture.source})
        last = None
        for v in sorted(capture.views, key=lambda v: v.stamp_ns):
            if last is not None and v.stamp_ns == last:
                raise InputError(f"two views share stamp {v.stamp_ns}; bag views need distinct "
                                 "stamps")
            last = v.stamp_ns
            t = int(v.stamp_ns)
            stamp = msgconv.ns_to_stamp(t)
            if v.pose is not None:
                w.write(POSE_TOPIC, msgconv.pose_to_pose_stamped(v.pose, stamp, "map"), t)
            w.write(INFO_TOPIC, msgconv.intrinsics_to_camera_info(v.camera, stamp), t)
            img = v.get_image()
            w.write(img_topic, msgconv.rgb_to_compressed(img, stamp, fmt=image_format,
                                                         quality=quality)
                    if compressed
                    else msgconv.rgb_to_image(img, stamp), t)
            if v.gt_mask is not None:
                w.write(GT_MASK_TOPIC, msgconv.mask_to_image(v.gt_mask, stamp), t)
        if capture.gt_ooi_points is not None:
            t0 = int(min(v.stamp_ns for v in capture.views))
            w.write(GT_POINTS_TOPIC, msgconv.xyzrgb_to_pointcloud2(
                capture.gt_ooi_points, None, msgconv.ns_to_stamp(t0), "map"), t0)
    return path


# ============================================================================ COLMAP
def _colmap_sparse_dir(p: Path) -> Optional[Path]:
    for cand in (p / "sparse" / "0", p / "sparse", p):
        if any((cand / f"cameras{ext}").is_file() for ext in (".bin", ".txt")):
            return cand
    return None


def read_colmap_dataset(path: PathLike, downscale: float = 1.0
                        ) -> tuple[Capture, SfmCloud]:
    """Capture + cloud of a Mip-NeRF-360-style COLMAP folder (``images_N`` used if present)."""
    from .sfm.colmap_io import load_colmap_model

    p = Path(path)
    sparse = _colmap_sparse_dir(p)
    if sparse is None:
        raise InputError(f"{p} has no COLMAP model (sparse/0/cameras.bin or .txt)")
    images_dir = p / "images"
    n = int(round(downscale))
    if downscale != 1.0 and abs(downscale - n) < 1e-9 and (p / f"images_{n}").is_dir():
        images_dir = p / f"images_{n}"
    if not images_dir.is_dir():
        raise InputError(f"{p} has a COLMAP model but no images/ folder next to it")
    capture, cloud = load_colmap_model(sparse, images_dir, downscale)
    missing = [v.source for v in capture.views if not Path(v.source).is_file()]
    if missing:
        raise InputError(f"{len(missing)} images of the COLMAP model are missing from "
                         f"{images_dir} (e.g. {missing[0]}); copy them or use the right folder")
    capture.meta.update({"input": "colmap", "images_dir": str(images_dir),
                         "sparse_dir": str(sparse)})
    return capture, cloud


# ============================================================================ nerfstudio
def _ns_camera(d: dict, base: Optional[dict] = None) -> CameraIntrinsics:
    """CameraIntrinsics of nerfstudio keys (per-frame keys override the global ones)."""
    g = dict(base or {})
    g.update({k: v for k, v in d.items() if k not in ("frames",)})
    try:
        w, h = int(g["w"]), int(g["h"])
        fx = float(g["fl_x"])
        fy = float(g.get("fl_y", fx))
        cx = float(g.get("cx", w / 2.0)) - 0.5  # nerfstudio/COLMAP centres -> ROS
        cy = float(g.get("cy", h / 2.0)) - 0.5
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"transforms.json lacks camera key {exc} (need w, h, fl_x "
                         "globally or per frame)") from exc
    if "ooi_seg_distortion_model" in g:
        model = g["ooi_seg_distortion_model"]
        dist = np.asarray(g.get("ooi_seg_dist", []), float)
    else:
        cm = g.get("camera_model", "OPENCV")
        if cm == "OPENCV_FISHEYE":
            model = "equidistant"
            dist = np.array([g.get(k, 0.0) for k in ("k1", "k2", "k3", "k4")], float)
        else:
            model = "plumb_bob"
            dist = np.array([g.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")], float)
        if not np.any(dist):
            model, dist = "none", np.zeros(0)
    cam = CameraIntrinsics(w, h, fx, fy, cx, cy, model, dist)
    cam.validate()
    return cam


def read_nerfstudio(path: PathLike, downscale: float = 1.0) -> Capture:
    """Capture of a nerfstudio folder (``transforms.json``); images are loaded lazily."""
    p = Path(path)
    tf = p / "transforms.json"
    try:
        data = json.loads(tf.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read {tf} ({exc}); it must be nerfstudio JSON") from exc
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise InputError(f"{tf} has no frames")
    views: list[View] = []
    for i, fr in enumerate(frames):
        fp = fr.get("file_path")
        if not fp:
            raise InputError(f"{tf}: frame {i} has no file_path")
        img_path = p / fp
        if not img_path.is_file():
            raise InputError(f"{tf}: frame {i} image {img_path} does not exist")
        cam = _ns_camera(fr, data)
        if downscale != 1.0:
            cam = cam.scaled(1.0 / downscale)
        size = (cam.width, cam.height)
        pose = None
        if "transform_matrix" in fr:
            m = np.asarray(fr["transform_matrix"], float)
            if m.shape not in ((4, 4), (3, 4)) or not np.all(np.isfinite(m)):
                raise InputError(f"{tf}: frame {i} transform_matrix is not a finite 4x4 matrix")
            pose = pose_from_gl_c2w(m if m.shape == (4, 4) else np.vstack([m, [0, 0, 0, 1]]))
        mask = None
        if fr.get("gt_mask_path"):
            mask = _load_mask(p / fr["gt_mask_path"], size)
        views.append(View(key=Path(fp).stem, stamp_ns=int(fr.get("stamp_ns", i)), camera=cam,
                          pose=pose, gt_mask=mask, loader=_rgb_loader(img_path, size),
                          source=str(img_path), compressed=is_lossy_file(img_path)))
    gt = None
    for cand in (data.get("ooi_points_path"), "ooi_points.ply", data.get("ply_file_path")):
        if cand and (p / cand).is_file():
            gt = read_ply_points(p / cand)
            break
    meta = dict(data.get("ooi_seg_meta", {}))
    meta.update({"input": "nerfstudio"})
    return Capture(views=views, source=str(p), gt_ooi_points=gt, meta=meta)


def _ns_camera_dict(cam: CameraIntrinsics) -> dict:
    d = {"w": cam.width, "h": cam.height, "fl_x": cam.fx, "fl_y": cam.fy,
         "cx": cam.cx + 0.5, "cy": cam.cy + 0.5}
    dist = np.asarray(cam.dist, float)
    if cam.distortion_model == "plumb_bob":
        d["camera_model"] = "OPENCV"
        for k, v in zip(("k1", "k2", "p1", "p2", "k3"), dist):
            d[k] = float(v)
    elif cam.distortion_model == "equidistant":
        d["camera_model"] = "OPENCV_FISHEYE"
        for k, v in zip(("k1", "k2", "k3", "k4"), dist):
            d[k] = float(v)
    else:
        d["camera_model"] = "OPENCV"
    d["ooi_seg_distortion_model"] = cam.distortion_model
    d["ooi_seg_dist"] = [float(v) for v in dist]
    return d


def write_capture_folder(capture: Capture, out: PathLike, jpeg_quality: int = 0) -> Path:
    """nerfstudio-style folder: transforms.json, images/*.png, masks/*.png, ooi_points.ply.

    Written into ``<out>.part`` and renamed when complete; an existing ``out`` is replaced only
    if it is a capture folder (has transforms.json). ``jpeg_quality`` 1-100: images/*.jpg at
    that quality instead of PNG.
    """
    out = Path(out)
    if not capture.views:
        raise InputError("the capture has no views to write")
    if out.exists() and not (out / "transforms.json").is_file():
        raise InputError(f"{out} exists and is not a capture folder; choose a new path")
    keys = [v.key for v in capture.views]
    if len(set(keys)) != len(keys):
        raise InputError("view keys are not unique; they name the image files")
    bad = [k for k in keys if not k or "/" in k or "\\" in k or k in (".", "..")]
    if bad:
        raise InputError(f"view key {bad[0]!r} cannot be a file name; rename the views")
    tmp = out.with_name(out.name + ".part")
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        _write_folder_contents(capture, tmp, int(jpeg_quality))
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if out.exists():
        shutil.rmtree(out)
    os.replace(tmp, out)
    return out


def _write_folder_contents(capture: Capture, tmp: Path, jpeg_quality: int = 0) -> None:
    """Everything ``write_capture_folder`` writes, into ``tmp``."""
    from PIL import Image

    (tmp / "images").mkdir(parents=True)
    cams = [_ns_camera_dict(v.camera) for v in capture.views]
    shared = all(c == cams[0] for c in cams)
    data: dict = dict(cams[0]) if shared else {}
    frames = []
    has_masks = any(v.gt_mask is not None for v in capture.views)
    if has_masks:
        (tmp / "masks").mkdir()
    for v, c in zip(capture.views, cams):
        ext = "jpg" if jpeg_quality else "png"
        fr: dict = {"file_path": f"images/{v.key}.{ext}", "stamp_ns": int(v.stamp_ns)}
        img = v.get_image()
        if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
            raise InputError(f"view {v.key}: image is {img.dtype} {img.shape}, expected uint8 "
                             "[H, W, 3] RGB")
        if jpeg_quality:
            Image.fromarray(img).save(tmp / fr["file_path"], quality=int(jpeg_quality))
        else:
            Image.fromarray(img).save(tmp / fr["file_path"], compress_level=6)
        if v.pose is not None:
            fr["transform_matrix"] = pose_to_gl_c2w(v.pose).tolist()
        if v.gt_mask is not None:
            fr["gt_mask_path"] = f"masks/{v.key}.png"
            Image.fromarray(v.gt_mask.astype(np.uint8) * 255).save(tmp / fr["gt_mask_path"])
        if not shared:
            fr.update(c)
        frames.append(fr)
    data["frames"] = frames
    if capture.gt_ooi_points is not None:
        write_ply_points(tmp / "ooi_points.ply", capture.gt_ooi_points)
        data["ooi_points_path"] = "ooi_points.ply"
    data["ooi_seg_meta"] = _json_safe(capture.meta)
    (tmp / "transforms.json").write_text(json.dumps(data, indent=2, sort_keys=False))


# ============================================================================ images
def _exif_focal_px(path: Path, w: int, h: int) -> Optional[float]:
    """Focal length in pixels from EXIF FocalLengthIn35mmFilm, or None."""
    from PIL import Image
    try:
        with Image.open(path) as im:
            exif = im.getexif()
            sub = exif.get_ifd(0x8769) if exif else {}
    except OSError:
        return None
    f35 = sub.get(0xA405) if sub else None
    if not f35:
        return None
    return float(f35) / 36.0 * max(w, h)


def read_image_folder(path: PathLike, downscale: float = 1.0) -> Capture:
    """Views without poses; focal from EXIF (35 mm equivalent) or 1.2 * max(w, h).

    Photos are used upright, as viewers show them: a photo whose EXIF Orientation says it
    is turned (a phone held in portrait) is turned back on load, so its view, its mask and
    the SfM camera all live in the upright frame. Files that cannot be opened as images are
    dropped, counted in ``meta["dropped"]`` and named in ``meta["unreadable"]`` (one bad
    file in a few hundred photos should not stop a run); none readable is an error."""
    from PIL import Image, UnidentifiedImageError

    p = Path(path)
    files = _image_files(p) or _image_files(p / "images")
    if not files:
        raise InputError(f"{p} holds no images ({', '.join(IMAGE_SUFFIXES)})")
    views: list[View] = []
    focal_src: Counter = Counter()
    unreadable: list[str] = []
    errors: list[str] = []
    turned = 0
    for i, f in enumerate(files):
        try:
            with Image.open(f) as im:
                w, h = im.size
                orient = exif_orientation(im)
        except (OSError, UnidentifiedImageError, SyntaxError) as exc:
            unreadable.append(f.name)
            errors.append(f"{f.name}: {exc}")
            continue
        if orient in (5, 6, 7, 8):  # turned by a quarter: upright width is the height
            w, h = h, w
        turned += orient != 1
        fpx = _exif_focal_px(f, w, h)
        focal_src["exif" if fpx else "default"] += 1
        if fpx is None:
            fpx = DEFAULT_FOCAL_FACTOR * max(w, h)
        cam = CameraIntrinsics(w, h, fpx, fpx, (w - 1) / 2.0, (h - 1) / 2.0)
        if downscale != 1.0:
            cam = cam.scaled(1.0 / downscale)
        views.append(View(key=f.stem, stamp_ns=i, camera=cam, pose=None,
                          loader=_rgb_loader(f, (cam.width, cam.height), orient != 1),
                          source=str(f), compressed=is_lossy_file(f)))
    if not views:
        raise InputError(f"{p}: none of its {len(files)} image files can be read "
                         f"({'; '.join(errors[:3])})")
    meta = {"input": "images", "focal_source": dict(focal_src),
            "note": "no poses; intrinsics are a guess (EXIF or focal = "
                    f"{DEFAULT_FOCAL_FACTOR} * max(w, h)) for SfM to refine"}
    if turned:
        meta["exif_turned"] = turned
    if unreadable:
        meta["dropped"] = {"unreadable_image": len(unreadable)}
        meta["unreadable"] = unreadable
        log.warning("read_image_folder %s: dropped %d unreadable file(s): %s", p,
                    len(unreadable), "; ".join(errors[:5]))
    return Capture(views=views, source=str(p), meta=meta)
