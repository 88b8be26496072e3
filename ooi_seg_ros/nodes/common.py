"""Shared machinery of the ROS 2 nodes: parameters from config dataclasses, QoS, diagnostics,
throttled warnings and exception-safe callbacks.

Nodes stay thin: they convert messages (``ooi_seg_ros.msgconv``), call the ROS-free core and
convert back. Everything here is about being a well-behaved node next to a drone stack.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import threading
import time
import typing
from typing import Any, Callable, Optional

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)

from .. import msgconv
from ..core.types import CameraIntrinsics, InputError, View


def sensor_qos(depth: int = 5) -> QoSProfile:
    """Best-effort, volatile, shallow: camera streams (REP 2003 sensor data)."""
    q = QoSProfile(**{k: getattr(qos_profile_sensor_data, k)
                      for k in ("reliability", "durability", "history")}, depth=depth)
    return q


def latched_qos(depth: int = 1) -> QoSProfile:
    """Reliable + transient-local: results a late subscriber must still receive."""
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL,
                      history=HistoryPolicy.KEEP_LAST)


def reliable_qos(depth: int = 10) -> QoSProfile:
    """Reliable, volatile: per-keyframe results (keyframes, masks)."""
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)


# ``ooi/mask`` carries two kinds of mask under one topic: *final* masks (a full segmentation
# run's, refined) and *provisional* ones (the unrefined silhouette of the current OOI cloud,
# published at once for keyframes no full run has covered yet). The kind travels in the
# message itself, so that it cannot race the mask: a provisional mask's header.frame_id is
# its camera frame with this suffix ("camera_optical_provisional"); a final mask's is the
# plain camera frame. Consumers that train or evaluate on masks (training_node) keep final
# masks only.
MASK_FRAME = "camera_optical"
PROVISIONAL_SUFFIX = "_provisional"


def mask_frame_id(provisional: bool, frame: str = MASK_FRAME) -> str:
    """header.frame_id of an ``ooi/mask`` message of that kind."""
    return frame + PROVISIONAL_SUFFIX if provisional else frame


def mask_is_provisional(msg) -> bool:
    """Whether an ``ooi/mask`` message is a provisional mask (see ``PROVISIONAL_SUFFIX``)."""
    return msg.header.frame_id.endswith(PROVISIONAL_SUFFIX)


@dataclasses.dataclass
class ParamSpec:
    """Description and valid range of one ROS parameter."""

    description: str
    min: Optional[float] = None
    max: Optional[float] = None
    choices: Optional[tuple] = None
    read_only: bool = False


# the ROS parameters of a node that keeps keyframes in a ``KeyframeAssembler``
KEYFRAME_STORE_SPECS = {
    "image_budget_mb": ParamSpec("MiB of kept keyframe images (0 = auto)", 0.0, 1e6,
                                 read_only=True),
    "image_downscale": ParamSpec("integer downscale of kept images (0 = auto)", 0, 64,
                                 read_only=True),
    "image_max_pixels": ParamSpec("pixel count kept images are reduced to (auto)", 10_000,
                                  100_000_000, read_only=True),
    "evict_policy": ParamSpec("keyframe evicted over budget", choices=("redundant", "oldest"),
                              read_only=True),
    "qos_depth": ParamSpec("history depth of the keyframe subscriptions", 1, 1000,
                           read_only=True),
}


def _field_doc(cls: type) -> dict[str, str]:
    """Per-field documentation: the dataclass field's ``metadata['doc']`` if present."""
    return {f.name: f.metadata.get("doc", "") for f in dataclasses.fields(cls)}


class ConfigParams:
    """Declares one ROS parameter per scalar field of a config dataclass and validates updates.

    ``prefix`` namespaces the parameters (``seg.floor.ransac_iterations``). Nested dataclasses
    recurse. Values are validated on set (type, range, choices) and the on-set callback rejects
    bad ones with a reason, as REP 2004-style nodes should.
    """

    def __init__(self, node: Node, config: Any, prefix: str = "",
                 specs: Optional[dict[str, ParamSpec]] = None) -> None:
        self.node = node
        self.config = config
        self.specs = specs or {}
        self._names: dict[str, tuple[Any, str]] = {}  # param name -> (owner obj, field)
        self._declare(config, prefix)
        node.add_on_set_parameters_callback(self._on_set)

    def _declare(self, obj: Any, prefix: str) -> None:
        hints = typing.get_type_hints(type(obj))
        docs = _field_doc(type(obj))
        for f in dataclasses.fields(obj):
            name = f"{prefix}{f.name}"
            val = getattr(obj, f.name)
            if dataclasses.is_dataclass(val):
                self._declare(val, name + ".")
                continue
            if not isinstance(val, (bool, int, float, str)):
                continue  # lists/arrays are not exposed as parameters
            spec = self.specs.get(name)
            desc = ParameterDescriptor(description=(spec.description if spec else docs[f.name])
                                       or f"{type(obj).__name__}.{f.name}",
                                       read_only=bool(spec and spec.read_only))
            if spec and (spec.min is not None or spec.max is not None):
                lo = spec.min if spec.min is not None else -1e308
                hi = spec.max if spec.max is not None else 1e308
                if isinstance(val, bool):
                    pass
                elif isinstance(val, int) and hints.get(f.name) is int:
                    desc.integer_range = [IntegerRange(from_value=int(max(lo, -2**62)),
                                                       to_value=int(min(hi, 2**62)), step=0)]
                else:
                    desc.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                                    to_value=float(hi), step=0.0)]
            if spec and spec.choices:
                desc.additional_constraints = "one of: " + ", ".join(map(str, spec.choices))
            if hints.get(f.name) is float and isinstance(val, int):
                val = float(val)
            param = self.node.declare_parameter(name, val, desc)
            ok, reason = self._check(name, param.value, val)
            if not ok:
                raise ValueError(f"parameter {name}: {reason}")
            setattr(obj, f.name, param.value)
            self._names[name] = (obj, f.name)

    def _check(self, name: str, value: Any, current: Any) -> tuple[bool, str]:
        spec = self.specs.get(name)
        if isinstance(current, bool) != isinstance(value, bool):
            return False, f"expected a bool, got {value!r}"
        if isinstance(current, (int, float)) and not isinstance(current, bool):
            if not isinstance(value, (int, float)) or value != value:  # NaN check
                return False, f"expected a number, got {value!r}"
            if spec and spec.min is not None and value < spec.min:
                return False, f"{value} is below the minimum {spec.min}"
            if spec and spec.max is not None and value > spec.max:
                return False, f"{value} is above the maximum {spec.max}"
        if spec and spec.choices and value not in spec.choices:
            return False, f"{value!r} is not one of {list(spec.choices)}"
        return True, ""

    def _on_set(self, params: list) -> SetParametersResult:
        for p in params:
            if p.name not in self._names:
                continue
            obj, field = self._names[p.name]
            ok, reason = self._check(p.name, p.value, getattr(obj, field))
            if not ok:
                return SetParametersResult(successful=False, reason=f"{p.name}: {reason}")
        for p in params:
            if p.name in self._names:
                obj, field = self._names[p.name]
                setattr(obj, field, p.value)
        return SetParametersResult(successful=True)


class Diagnostics:
    """Counters, timings and a state line published as ``diagnostics`` (DiagnosticArray)."""

    def __init__(self, node: Node, period_s: float = 1.0) -> None:
        self.node = node
        self.state = "starting"
        self.level = DiagnosticStatus.OK
        self.counters: dict[str, int] = {}
        self.timings: dict[str, float] = {}
        self.values: dict[str, str] = {}
        self._lock = threading.Lock()
        self._pub = node.create_publisher(DiagnosticArray, "diagnostics", 10)
        self._timer = node.create_timer(period_s, self.publish)

    def count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self.counters[key] = self.counters.get(key, 0) + n

    def set_count(self, key: str, n: int) -> None:
        """Sets a counter kept elsewhere (e.g. the keyframe selector's drops) under the lock:
        a key added while ``publish`` iterates the counters would raise in the timer."""
        with self._lock:
            self.counters[key] = int(n)

    def timing(self, key: str, seconds: float) -> None:
        with self._lock:
            self.timings[key] = seconds

    def set(self, key: str, value: Any) -> None:
        with self._lock:
            self.values[key] = str(value)

    def set_state(self, state: str, level: int = DiagnosticStatus.OK) -> None:
        with self._lock:
            self.state, self.level = state, level

    def snapshot(self) -> dict:
        with self._lock:
            return {"state": self.state, "counters": dict(self.counters),
                    "timings": dict(self.timings), "values": dict(self.values)}

    def publish(self) -> None:
        with self._lock:
            kv = [KeyValue(key=k, value=str(v)) for k, v in sorted(self.counters.items())]
            kv += [KeyValue(key=f"time_{k}_s", value=f"{v:.3f}")
                   for k, v in sorted(self.timings.items())]
            kv += [KeyValue(key=k, value=v) for k, v in sorted(self.values.items())]
            level = self.level
            bad = any(k.startswith(("dropped", "error")) and v for k, v in self.counters.items())
            if level == DiagnosticStatus.OK and bad:
                level = DiagnosticStatus.WARN
            st = DiagnosticStatus(level=level, name=self.node.get_fully_qualified_name(),
                                  message=self.state, hardware_id="ooi_seg_ros", values=kv)
        msg = DiagnosticArray(status=[st])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self._pub.publish(msg)


class Throttle:
    """Logs a warning per key at most once per ``period_s`` (with the count it stood for)."""

    def __init__(self, node: Node, period_s: float = 5.0) -> None:
        self.node = node
        self.period_s = period_s
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warn(self, key: str, message: str) -> None:
        now = time.monotonic()
        if now - self._last.get(key, -1e9) >= self.period_s:
            n = self._suppressed.pop(key, 0)
            extra = f" ({n} more like this suppressed)" if n else ""
            self.node.get_logger().warning(message + extra)
            self._last[key] = now
        else:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1


def guarded(counter: str) -> Callable:
    """Decorator for node callbacks: an exception is logged (throttled), counted, swallowed.

    The node must have ``self.diag`` (Diagnostics) and ``self.throttle`` (Throttle).
    """

    def deco(fn: Callable) -> Callable:
        @functools.wraps(fn)
        def wrapper(self, *args, **kwargs):
            try:
                return fn(self, *args, **kwargs)
            except Exception as exc:  # noqa: BLE001 — callback boundary: never kill the node
                self.diag.count(counter)
                self.throttle.warn(counter, f"{fn.__name__}: dropped ({type(exc).__name__}: "
                                            f"{exc})")
                return None
        return wrapper
    return deco


def limit_heap_growth(mmap_threshold: int = 2 ** 20, arenas: int = 2) -> bool:
    """Makes glibc return freed image-sized buffers to the OS (no-op elsewhere).

    A node handles many short-lived multi-megabyte arrays (decoded frames, masks) in several
    threads. glibc's default raises its mmap threshold after the first such buffer is freed,
    after which they come from per-thread heaps that fragment and rarely shrink: resident
    memory then keeps the high-water mark of every thread. A fixed threshold (and few arenas)
    keeps big buffers in mmap, released on free. Returns True when applied.
    """
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        m_mmap_threshold, m_arena_max = -3, -8  # <malloc.h>
        return bool(libc.mallopt(m_mmap_threshold, int(mmap_threshold))
                    and libc.mallopt(m_arena_max, int(arenas)))
    except (OSError, AttributeError):
        return False


def run_node(node_factory: Callable[[], Node], args: Optional[list[str]] = None,
             multithreaded: bool = True) -> None:
    """Jazzy-style main(): init, spin, clean shutdown on Ctrl-C or external shutdown."""
    limit_heap_growth()
    rclpy.init(args=args)
    node = None
    try:
        node = node_factory()
        if multithreaded:
            from rclpy.executors import MultiThreadedExecutor
            ex = MultiThreadedExecutor(num_threads=2)
            ex.add_node(node)
            ex.spin()
        else:
            rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            close = getattr(node, "close", None)
            if close is not None:
                close()
            node.destroy_node()
        rclpy.try_shutdown()


def physical_memory_bytes() -> int:
    """Total physical memory of this machine (0 when the OS does not say)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 0


def auto_image_budget_bytes() -> int:
    """Default byte budget for kept keyframe images: 1/32 of the RAM, within 128..512 MiB.

    A drone's companion computer (8-16 GB) gets 256-512 MiB; the nodes' other state (clouds,
    features, DDS buffers) and the segmentation/training runs need the rest.
    """
    mib = 2 ** 20
    ram = physical_memory_bytes()
    return int(min(max(ram // 32, 128 * mib), 512 * mib)) if ram else 256 * mib


def downscale_factor(width: int, height: int, max_pixels: int) -> int:
    """Smallest integer factor f with (width // f) * (height // f) <= max_pixels (>= 1).

    ``max_pixels <= 0`` means "keep full resolution" (1).
    """
    if max_pixels <= 0:
        return 1
    f = 1
    while (width // f) * (height // f) > max_pixels and min(width, height) // (f + 1) >= 8:
        f += 1
    return f


def downscale_rgb(rgb: np.ndarray, factor: int) -> np.ndarray:
    """Box-filtered [H//f, W//f, C] uint8 copy (the right/bottom remainder is cropped)."""
    if factor <= 1:
        return rgb
    h, w = rgb.shape[0] // factor, rgb.shape[1] // factor
    blocks = rgb[:h * factor, :w * factor].reshape(h, factor, w, factor, -1)
    out = blocks.sum(axis=(1, 3), dtype=np.uint32)
    out += (factor * factor) // 2  # round to nearest
    out //= factor * factor
    return out.astype(np.uint8).reshape(h, w, *rgb.shape[2:])


def downscale_camera(cam: CameraIntrinsics, factor: int) -> CameraIntrinsics:
    """Intrinsics of ``downscale_rgb(image, factor)`` (ROS pixel centres at integers).

    Block ``i`` averages source pixels ``f*i .. f*i+f-1``, so its centre is at ``f*i + (f-1)/2``
    in the source: ``c' = (c + 0.5) / f - 0.5``; the cropped remainder does not move it.
    """
    if factor <= 1:
        return cam
    f = float(factor)
    return CameraIntrinsics(cam.width // factor, cam.height // factor, cam.fx / f, cam.fy / f,
                            (cam.cx + 0.5) / f - 0.5, (cam.cy + 0.5) / f - 0.5,
                            cam.distortion_model, np.array(cam.dist, dtype=float))


def encode_guide(rgb: np.ndarray, quality: int) -> Optional[bytes]:
    """JPEG bytes of an RGB image at ``quality`` (1-100; 0 or less: None)."""
    if quality <= 0:
        return None
    import cv2
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]),
                           [cv2.IMWRITE_JPEG_QUALITY, int(min(quality, 100))])
    return buf.tobytes() if ok else None


def decode_guide(data: bytes) -> Optional[np.ndarray]:
    """The RGB image of ``encode_guide``'s bytes (None if they do not decode)."""
    import cv2
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    return None if bgr is None else np.ascontiguousarray(bgr[..., ::-1])


def upscale_mask(mask: np.ndarray, factor: int, width: int, height: int,
                 guide: Optional[np.ndarray] = None) -> np.ndarray:
    """bool [height, width] of a mask rendered at 1/factor (``downscale_rgb``'s blocks):
    enlarged bilinearly and kept >= 0.5 (a smooth outline, not factor-sized steps;
    ``seg.masks.mask_at_size``), the cropped remainder replicated from the edge. ``guide``:
    the image at [height, width]; the outline is then placed by its pixels (joint bilateral
    upsampling, ``seg.masks.guided_enlarge``)."""
    if factor <= 1 and mask.shape == (height, width):
        return mask
    from ..seg.masks import mask_at_size
    h, w = mask.shape
    if guide is not None and guide.shape[:2] == (height, width):
        guide = guide[:h * factor, :w * factor]
    else:
        guide = None
    up = mask_at_size(mask, (w * factor, h * factor), guide=guide)[:height, :width]
    if up.shape != (height, width):
        up = np.pad(up, ((0, height - up.shape[0]), (0, width - up.shape[1])), mode="edge")
    return up


def scale_pixels(xy: np.ndarray, factor: float) -> np.ndarray:
    """Pixel coordinates [N, 2] in an image ``factor`` times larger (ROS pixel centres)."""
    return ((np.asarray(xy, np.float64) + 0.5) * factor - 0.5).astype(np.float32)


def check_image_msg(msg) -> None:
    """The checks of ``msgconv.image_to_rgb`` that need no copy of the pixels.

    An image callback at 30 Hz validates every frame with this and decodes only the frames
    that may become keyframes. Raises InputError naming the fix.
    """
    enc = msg.encoding
    if enc not in msgconv.IMAGE_ENCODINGS:
        raise InputError(f"image encoding {enc!r} is not supported; publish one of "
                         f"{sorted(msgconv.IMAGE_ENCODINGS)}")
    ch, dtype, _ = msgconv.IMAGE_ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise InputError(f"image is {w}x{h}; a camera image must have positive size")
    if step < w * ch * np.dtype(dtype).itemsize:
        raise InputError(f"image step {step} is smaller than width {w} x bytes per pixel of "
                         f"{enc}; the publisher sets step wrongly")
    if len(msg.data) != h * step:
        raise InputError(f"image data has {len(msg.data)} bytes, height {h} x step {step} = "
                         f"{h * step}; the message is truncated or its size fields are wrong")


class KeyframeAssembler:
    """Pairs ``keyframe/image``, ``keyframe/camera_info`` and ``keyframe/pose`` by exact stamp.

    ``keyframes`` is an ordered {stamp_ns: View} whose images are kept at 1/``factor`` of the
    source resolution (``downscale``: a fixed factor, or 0 to derive it from the image size and
    ``max_pixels``) with the matching scaled camera; ``full_cameras`` keeps the source
    intrinsics so that outputs (masks) can be published at the keyframe's own size.

    Memory is bounded in bytes: when the kept images exceed ``max_bytes`` (or their count
    exceeds ``max_keyframes``) keyframes are evicted, each counted in ``diag``
    (``dropped_keyframe_budget`` / ``dropped_old_keyframes``), logged through ``warn`` and
    reported to ``on_evict``. ``evict_policy`` "redundant" evicts the older of the two kept
    keyframes whose cameras are closest (the least new view of the object); "oldest" evicts
    in arrival order. The newest keyframe is never evicted. At most ``max_pending``
    incomplete stamps wait for their missing parts. Thread-safe.
    """

    PARTS = ("image", "info", "pose")

    @classmethod
    def from_config(cls, diag: Diagnostics, cfg, warn: Optional[Callable[[str, str], None]],
                    on_evict: Optional[Callable[[int], None]] = None) -> "KeyframeAssembler":
        """The store a node's config asks for (``max_keyframes`` and ``KEYFRAME_STORE_SPECS``'
        fields; ``image_budget_mb`` 0 = ``auto_image_budget_bytes``), the budget used recorded
        in ``diag``."""
        budget = (int(cfg.image_budget_mb * 2 ** 20) if cfg.image_budget_mb > 0
                  else auto_image_budget_bytes())
        out = cls(diag, cfg.max_keyframes, max_bytes=budget, downscale=cfg.image_downscale,
                  max_pixels=cfg.image_max_pixels, evict_policy=cfg.evict_policy, warn=warn,
                  on_evict=on_evict, guide_quality=int(getattr(cfg, "mask_guide_quality", 0)))
        diag.set("image_budget_mb", f"{budget / 2 ** 20:.0f}")
        return out

    def __init__(self, diag: Diagnostics, max_keyframes: int, max_pending: int = 100,
                 on_evict: Optional[Callable[[int], None]] = None, max_bytes: int = 0,
                 downscale: int = 1, max_pixels: int = 0, evict_policy: str = "redundant",
                 warn: Optional[Callable[[str, str], None]] = None,
                 guide_quality: int = 0) -> None:
        import collections

        self.diag = diag
        self.max_keyframes = max_keyframes
        self.max_pending = max_pending
        self.on_evict = on_evict
        self.max_bytes = int(max_bytes)
        self.downscale = int(downscale)
        self.max_pixels = int(max_pixels)
        self.evict_policy = evict_policy
        self.warn = warn
        self.keyframes: "collections.OrderedDict[int, Any]" = collections.OrderedDict()
        self.full_cameras: dict[int, CameraIntrinsics] = {}
        self.factors: dict[int, int] = {}
        self.guide_quality = int(guide_quality)
        self.guides: dict[int, bytes] = {}  # JPEG of the received image (kept smaller only)
        self.nbytes = 0
        self._parts: dict[int, dict] = {}
        self.lock = threading.Lock()

    def factor_for(self, cam: CameraIntrinsics) -> int:
        """The downscale factor applied to a keyframe of camera ``cam``."""
        if self.downscale > 0:
            return self.downscale
        return downscale_factor(cam.width, cam.height, self.max_pixels)

    def add(self, stamp_ns: int, part: str, value: Any) -> bool:
        """Stores one part; True when it completed a keyframe."""
        with self.lock:
            parts = self._parts.setdefault(stamp_ns, {})
            parts[part] = value
            complete = len(parts) == len(self.PARTS)
            if complete:
                del self._parts[stamp_ns]
            while len(self._parts) > self.max_pending:  # parts whose siblings never came
                self._parts.pop(next(iter(self._parts)))
                self.diag.count("dropped_incomplete_keyframe")
        if not complete:
            return False
        cam, rgb = parts["info"], parts["image"]
        if rgb.shape[0] != cam.height or rgb.shape[1] != cam.width:
            self.diag.count("dropped_keyframe_size_mismatch")
            if self.warn:
                self.warn("kfsize", f"keyframe {stamp_ns} dropped: image {rgb.shape[1]}x"
                                    f"{rgb.shape[0]} does not match its camera_info "
                                    f"{cam.width}x{cam.height}")
            return False
        f = self.factor_for(cam)
        small = np.ascontiguousarray(downscale_rgb(rgb, f))  # outside the lock: ~10 ms
        view = View(key=str(stamp_ns), stamp_ns=stamp_ns, camera=downscale_camera(cam, f),
                    pose=parts["pose"], image=small)
        guide = encode_guide(rgb, self.guide_quality) if f > 1 else None
        evicted = []
        with self.lock:
            if stamp_ns in self.keyframes:  # a repeated keyframe replaces the old one
                self.nbytes -= self.keyframes.pop(stamp_ns).image.nbytes
                self.nbytes -= len(self.guides.pop(stamp_ns, b""))
            self.keyframes[stamp_ns] = view
            self.full_cameras[stamp_ns] = cam
            self.factors[stamp_ns] = f
            self.nbytes += small.nbytes
            if guide is not None:
                self.guides[stamp_ns] = guide
                self.nbytes += len(guide)
            while len(self.keyframes) > 1 and (
                    len(self.keyframes) > self.max_keyframes
                    or (self.max_bytes > 0 and self.nbytes > self.max_bytes)):
                over_count = len(self.keyframes) > self.max_keyframes
                old = self._victim()
                gone = self.keyframes.pop(old)
                self.full_cameras.pop(old, None)
                self.factors.pop(old, None)
                self.nbytes -= gone.image.nbytes + len(self.guides.pop(old, b""))
                self.diag.count("dropped_old_keyframes" if over_count
                                else "dropped_keyframe_budget")
                evicted.append(old)
            n, nbytes = len(self.keyframes), self.nbytes
        for old in evicted:
            if self.warn:
                self.warn("kfevict", f"keyframe {old} evicted: kept keyframe images would "
                                     f"exceed {self.max_bytes / 2 ** 20:.0f} MiB or "
                                     f"{self.max_keyframes} keyframes (raise image_budget_mb "
                                     "or image_max_pixels lower)")
            if self.on_evict:
                self.on_evict(old)
        self.diag.set("keyframes", n)
        self.diag.set("keyframe_image_mb", f"{nbytes / 2 ** 20:.1f}")
        return True

    def guide(self, stamp_ns: int) -> Optional[np.ndarray]:
        """The received (full-size) image of a keyframe kept smaller, decoded from its JPEG;
        None when none is kept (kept at full size, evicted, or ``guide_quality`` 0)."""
        with self.lock:
            data = self.guides.get(stamp_ns)
        return decode_guide(data) if data is not None else None

    def _victim(self) -> int:
        """Stamp of the keyframe to evict (caller holds the lock; >= 2 keyframes kept)."""
        stamps = list(self.keyframes)
        if self.evict_policy == "oldest" or len(stamps) < 3:
            return stamps[0]
        c = np.stack([self.keyframes[s].pose.t for s in stamps])  # [N, 3]
        d = np.linalg.norm(c[:, None, :] - c[None, :, :], axis=2)
        d[np.arange(len(c)), np.arange(len(c))] = np.inf
        d[-1, :] = np.inf  # the newest keyframe is never the victim
        nn = d.min(axis=1)
        return stamps[int(np.argmin(nn))]  # argmin takes the oldest among ties

    def views(self) -> list:
        with self.lock:
            return list(self.keyframes.values())

    def __len__(self) -> int:
        return len(self.keyframes)
