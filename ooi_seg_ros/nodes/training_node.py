"""``training_node``: keyframes + OOI masks + OOI cloud in, object-only Gaussian splats out.

Subscribes: ``keyframe/image``, ``keyframe/camera_info``, ``keyframe/pose`` (matched by stamp),
``ooi/mask`` (mono8, stamp = keyframe stamp) and ``ooi/points`` (latched). Training starts on
the ``~/train`` service (std_srvs/Trigger), or by itself once the OOI is stable
(``auto_start``: the OOI cloud's size changed by less than ``stable_change`` over
``stable_updates`` updates and every kept keyframe has a final mask). Training runs in a worker
thread with the same core code as ``ooi-seg train``.

Final masks only. ``ooi/mask`` carries the segmentation node's *provisional* masks (unrefined
silhouettes of the current OOI cloud, header.frame_id ending in ``_provisional``, see
``common.PROVISIONAL_SUFFIX``) as well as its *final* ones (a full run's). Provisional masks
are recorded but never trained on: auto-start waits until every kept keyframe has a final
mask, and ``~/train`` trains on the keyframes that have one, saying in its response how many
keyframes were left out because their mask is still provisional or missing (diagnostics:
``masks_final``, ``masks_provisional``). A provisional mask never replaces a final one.

Publishes ``splats`` (PointCloud2 whose fields carry the Gaussians under the 3DGS PLY names:
x y z f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3, latched), ``splat/render`` previews and
``diagnostics``. Everything it receives and publishes is recorded into an MCAP bag
(``record_path``) for offline review; the bag is finished on shutdown (SIGINT/SIGTERM) and,
being written in flushed chunks, stays readable up to its last chunk even after a SIGKILL.

Memory is bounded in bytes: keyframe images are kept at full resolution by default (the
photometric loss wants every pixel; ``image_downscale`` trades that for memory) within
``image_budget_mb``, beyond which the most redundant keyframe is evicted (counted, logged);
masks are kept bit-packed (1/8 of a byte per pixel) and only for kept keyframes.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import time
import traceback
from typing import Optional

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Float32MultiArray
from std_srvs.srv import Trigger

from .. import msgconv
from ..bag import BagWriter
from ..core.types import Capture
from ..train.gaussians import PLY_FIELDS, to_ply_array
from ..train.trainer import TrainConfig, train
from .common import (KEYFRAME_STORE_SPECS, ConfigParams, Diagnostics, KeyframeAssembler,
                     ParamSpec, Throttle, guarded, latched_qos, mask_is_provisional,
                     reliable_qos, run_node)

SPLAT_SKIP_FIELDS = ("nx", "ny", "nz")  # the PLY's unused normals are not published


@dataclasses.dataclass
class TrainNodeConfig:
    """Parameters of the training node (see config/training_node.yaml)."""

    frame_id: str = dataclasses.field(default="map", metadata={"doc": "world frame of outputs"})
    auto_start: bool = dataclasses.field(
        default=False, metadata={"doc": "start by itself once the OOI is stable"})
    stable_updates: int = dataclasses.field(
        default=2, metadata={"doc": "OOI updates with little change before auto start"})
    stable_change: float = dataclasses.field(
        default=0.05, metadata={"doc": "relative OOI size change counted as 'little'"})
    min_keyframes: int = dataclasses.field(
        default=8, metadata={"doc": "keyframes with masks needed to start"})
    record_path: str = dataclasses.field(
        default="", metadata={"doc": "MCAP bag recording inputs and outputs ('' = "
                                     "ooi_training_<time>.mcap in the working directory, "
                                     "'none' = no recording)"})
    max_keyframes: int = dataclasses.field(
        default=2000, metadata={"doc": "keyframes kept in memory (evicted beyond)"})
    image_budget_mb: float = dataclasses.field(
        default=0.0, metadata={"doc": "MiB of kept keyframe images; beyond it keyframes are "
                                      "evicted (0 = 1/32 of the RAM within 128..512)"})
    image_downscale: int = dataclasses.field(
        default=1, metadata={"doc": "keep (and train on) keyframe images downscaled by this "
                                    "integer factor (1 = full resolution, 0 = the smallest "
                                    "factor that brings them to image_max_pixels)"})
    image_max_pixels: int = dataclasses.field(
        default=1_000_000, metadata={"doc": "with image_downscale 0: pixel count kept images "
                                            "are reduced to"})
    evict_policy: str = dataclasses.field(
        default="redundant", metadata={"doc": "which keyframe goes when over budget: redundant "
                                              "(camera nearest another kept one) or oldest"})
    qos_depth: int = dataclasses.field(
        default=10, metadata={"doc": "history depth of the keyframe subscriptions"})


SPECS = {
    "stable_updates": ParamSpec("OOI updates with little change before auto start", 1, 1000),
    "stable_change": ParamSpec("relative OOI size change counted as little", 0.0, 1.0),
    "min_keyframes": ParamSpec("keyframes with masks needed to start", 2, 100000),
    "record_path": ParamSpec("MCAP bag recording inputs and outputs", read_only=True),
    "max_keyframes": ParamSpec("keyframes kept in memory", 2, 1000000, read_only=True),
    **KEYFRAME_STORE_SPECS,
    "frame_id": ParamSpec("world frame of outputs", read_only=True),
}


def splats_to_pointcloud2(model, stamp, frame_id: str) -> PointCloud2:
    """PointCloud2 with one float32 field per 3DGS PLY property (normals left out)."""
    arr = to_ply_array(model)  # [N, len(PLY_FIELDS)] float32
    fields = {n: np.ascontiguousarray(arr[:, i]) for i, n in enumerate(PLY_FIELDS)
              if n not in SPLAT_SKIP_FIELDS}
    return msgconv.fields_to_pointcloud2(fields, stamp, frame_id)


def _mask_at(bits: np.ndarray, shape: tuple, factor: int) -> np.ndarray:
    """bool mask [H//f, W//f] of a packed full-size mask (a block is in when half of it is)."""
    mask = np.unpackbits(bits, count=shape[0] * shape[1]).reshape(shape).astype(bool)
    if factor <= 1:
        return mask
    h, w = shape[0] // factor, shape[1] // factor
    blocks = mask[:h * factor, :w * factor].reshape(h, factor, w, factor)
    return blocks.mean(axis=(1, 3)) >= 0.5


class TrainingNode(Node):
    """Collects keyframes, masks and the OOI cloud; trains splats on request or when stable."""

    def __init__(self, **kwargs) -> None:
        super().__init__("training_node", **kwargs)
        self.cfg = TrainNodeConfig()
        self.train_cfg = TrainConfig()
        ConfigParams(self, self.cfg, specs=SPECS)
        ConfigParams(self, self.train_cfg, prefix="train.")
        self.diag = Diagnostics(self)
        self.throttle = Throttle(self)
        self._lock = threading.Lock()
        self.masks: dict[int, tuple] = {}  # stamp -> (packed bits, (H, W)) of a final mask
        self.provisional: set[int] = set()  # stamps whose latest mask is provisional (no bits)
        self.assembler = KeyframeAssembler.from_config(self.diag, self.cfg, self.throttle.warn,
                                                       self._on_evict)
        self.keyframes = self.assembler.keyframes  # {stamp_ns: View}, capture order
        # (xyz, rgb) of the latest OOI cloud, swapped as one: the training thread reads the
        # pair while the executor may store the next cloud
        self._ooi: Optional[tuple[np.ndarray, Optional[np.ndarray]]] = None
        self._ooi_sizes: list[int] = []
        self._busy = threading.Lock()
        self.result = None
        self.runs = 0

        self.recorder: Optional[BagWriter] = None
        path = self.cfg.record_path
        if path.lower() != "none":
            if not path:
                path = os.path.abspath(time.strftime("ooi_training_%Y%m%d_%H%M%S.mcap"))
            self.recorder = BagWriter(path, atomic=False)
            self.record_path = path
            for topic, type_name, qos in (
                    ("keyframe/image", "sensor_msgs/msg/Image", "reliable"),
                    ("keyframe/camera_info", "sensor_msgs/msg/CameraInfo", "reliable"),
                    ("keyframe/pose", "geometry_msgs/msg/PoseStamped", "reliable"),
                    ("ooi/mask", "sensor_msgs/msg/Image", "reliable"),
                    ("ooi/points", "sensor_msgs/msg/PointCloud2", "transient_local"),
                    ("splats", "sensor_msgs/msg/PointCloud2", "transient_local"),
                    ("splat/render", "sensor_msgs/msg/Image", "reliable"),
                    ("splat/loss", "std_msgs/msg/Float32MultiArray", "reliable")):
                self.recorder.add_topic(self._abs(topic), type_name, qos)
            self.diag.set("record_path", path)

        rq = reliable_qos(depth=self.cfg.qos_depth)
        self.create_subscription(Image, "keyframe/image", self.on_kf_image, rq)
        self.create_subscription(CameraInfo, "keyframe/camera_info", self.on_kf_info, rq)
        self.create_subscription(PoseStamped, "keyframe/pose", self.on_kf_pose, rq)
        self.create_subscription(Image, "ooi/mask", self.on_mask, reliable_qos(depth=100))
        self.create_subscription(PointCloud2, "ooi/points", self.on_ooi_points, latched_qos())
        self.pub_splats = self.create_publisher(PointCloud2, "splats", latched_qos())
        self.pub_render = self.create_publisher(Image, "splat/render", reliable_qos(depth=10))
        self.pub_loss = self.create_publisher(Float32MultiArray, "splat/loss", reliable_qos())
        self.create_service(Trigger, "~/train", self.on_train_srv)
        self.diag.set_state("waiting for keyframes, masks and the OOI cloud")

    def _on_evict(self, stamp_ns: int) -> None:
        with self._lock:
            self.masks.pop(stamp_ns, None)
            self.provisional.discard(stamp_ns)

    def _abs(self, topic: str) -> str:
        return self.resolve_topic_name(topic)

    def _record(self, topic: str, msg, stamp_ns: Optional[int] = None) -> None:
        if self.recorder is None:
            return
        with self._lock:
            if self.recorder is not None:
                self.recorder.write(self._abs(topic), serialize_message(msg),
                                    stamp_ns or self.get_clock().now().nanoseconds)

    # ---- inputs -------------------------------------------------------------------------
    def _part(self, msg, stamp_ns: int, key: str, value, topic: str) -> None:
        self._record(topic, msg, stamp_ns)
        self.assembler.add(stamp_ns, key, value)

    @guarded("dropped_keyframe_image")
    def on_kf_image(self, msg: Image) -> None:
        self._part(msg, msgconv.stamp_to_ns(msg.header.stamp), "image",
                   msgconv.image_to_rgb(msg), "keyframe/image")

    @guarded("dropped_keyframe_info")
    def on_kf_info(self, msg: CameraInfo) -> None:
        self._part(msg, msgconv.stamp_to_ns(msg.header.stamp), "info",
                   msgconv.camera_info_to_intrinsics(msg), "keyframe/camera_info")

    @guarded("dropped_keyframe_pose")
    def on_kf_pose(self, msg: PoseStamped) -> None:
        self._part(msg, msgconv.stamp_to_ns(msg.header.stamp), "pose",
                   msgconv.pose_from_msg(msg.pose), "keyframe/pose")

    @guarded("dropped_mask")
    def on_mask(self, msg: Image) -> None:
        stamp_ns = msgconv.stamp_to_ns(msg.header.stamp)
        self._record("ooi/mask", msg, stamp_ns)
        mask = msgconv.image_to_mask(msg)  # validates provisional masks too
        if mask_is_provisional(msg):
            with self.assembler.lock, self._lock:
                if stamp_ns in self.masks:  # never replaces a final mask
                    self.diag.count("masks_provisional_ignored")
                else:
                    self.provisional.add(stamp_ns)
                self._bound_masks()
            self._report_masks()
            return
        packed = (np.packbits(mask, axis=None), mask.shape)
        with self.assembler.lock, self._lock:
            self.masks[stamp_ns] = packed
            self.provisional.discard(stamp_ns)
            self._bound_masks()
        self._report_masks()
        self._maybe_auto_start()

    def _bound_masks(self) -> None:
        """Masks wait for their keyframe, but masks of evicted/unknown stamps do not pile up
        (caller holds ``self.assembler.lock`` and ``self._lock``)."""
        kept = self.assembler.keyframes
        for store in (self.masks, self.provisional):
            extra = len(store) - len(kept) - self.assembler.max_pending
            if extra > 0:
                for k in [k for k in store if k not in kept][:extra]:
                    if isinstance(store, dict):
                        del store[k]
                    else:
                        store.discard(k)
                    self.diag.count("dropped_mask_without_keyframe")

    def mask_counts(self) -> tuple[int, int, int]:
        """(final, provisional, missing): kept keyframes by the kind of their latest mask."""
        with self.assembler.lock, self._lock:
            kept = list(self.keyframes)
            final = sum(1 for k in kept if k in self.masks)
            prov = sum(1 for k in kept if k not in self.masks and k in self.provisional)
        return final, prov, len(kept) - final - prov

    def _report_masks(self) -> None:
        final, prov, missing = self.mask_counts()
        self.diag.set("masks", final)
        self.diag.set("masks_final", final)
        self.diag.set("masks_provisional", prov)
        self.diag.set("masks_missing", missing)

    @guarded("dropped_ooi_points")
    def on_ooi_points(self, msg: PointCloud2) -> None:
        self._record("ooi/points", msg, msgconv.stamp_to_ns(msg.header.stamp))
        xyz, rgb = msgconv.pointcloud2_to_xyzrgb(msg)
        self._ooi = (xyz, rgb)
        self._ooi_sizes.append(len(xyz))
        self.diag.set("ooi_points", len(xyz))
        self._maybe_auto_start()

    @property
    def ooi_xyz(self) -> Optional[np.ndarray]:
        """The latest OOI cloud's points (None before the first)."""
        ooi = self._ooi
        return None if ooi is None else ooi[0]

    @property
    def ooi_rgb(self) -> Optional[np.ndarray]:
        ooi = self._ooi
        return None if ooi is None else ooi[1]

    # ---- training ---------------------------------------------------------------------------
    def ooi_is_stable(self) -> bool:
        s = self._ooi_sizes[-(self.cfg.stable_updates + 1):]
        if len(s) < self.cfg.stable_updates + 1 or s[-1] == 0:
            return False
        return max(s) - min(s) <= self.cfg.stable_change * max(s)

    def ready(self) -> tuple[bool, str]:
        """Whether training can start, and why (counts of final / provisional / no masks)."""
        n, prov, missing = self.mask_counts()
        why = f"{n} keyframes with final masks"
        if prov or missing:
            why += (f"; left out: {prov} with a provisional mask only, {missing} without a "
                    f"mask")
        if self.ooi_xyz is None:
            return False, "no OOI cloud received yet"
        if n < self.cfg.min_keyframes:
            return False, f"{why}; need {self.cfg.min_keyframes} with final masks"
        return True, why

    def _maybe_auto_start(self) -> None:
        """Starts training once the OOI is stable and every kept keyframe has a final mask."""
        if self.cfg.auto_start and self.runs == 0 and self.ooi_is_stable() and self.ready()[0]:
            _n, prov, missing = self.mask_counts()
            if prov == 0 and missing == 0:
                self.start()

    def start(self) -> bool:
        if not self._busy.acquire(blocking=False):
            return False
        threading.Thread(target=self._train, daemon=True).start()
        return True

    def _progress(self, it: int, loss: float, psnr: float, n: int) -> None:
        msg = Float32MultiArray(data=[float(it), float(loss), float(psnr), float(n)])
        self.pub_loss.publish(msg)
        self._record("splat/loss", msg)
        self.diag.set_state(f"training: it {it}, loss {loss:.4f}, PSNR {psnr:.2f}, {n} "
                            "Gaussians")

    def _train(self) -> None:
        try:
            t0 = time.monotonic()
            with self.assembler.lock, self._lock:
                views = [v for k, v in self.keyframes.items() if k in self.masks]
                packed = {k: (self.masks[k], self.assembler.factors[k]) for k in self.keyframes
                          if k in self.masks}
            masks = {str(k): _mask_at(bits, shape, f) for k, ((bits, shape), f) in packed.items()}
            capture = Capture(views=views, source="ros")
            ooi_xyz, ooi_rgb = self._ooi
            result = train(capture, masks, ooi_xyz, self.train_cfg,
                           init_colors=ooi_rgb, progress=self._progress)
            self.result = result
            self.runs += 1
            stamp = msgconv.ns_to_stamp(views[-1].stamp_ns)
            for it, model in result.snapshots:
                snap = splats_to_pointcloud2(model, stamp, self.cfg.frame_id)
                self._record("splats", snap)
            final = splats_to_pointcloud2(result.model, stamp, self.cfg.frame_id)
            self.pub_splats.publish(final)
            self._record("splats", final)
            for _it, key, rgb in result.previews:
                ns = int(key) if str(key).isdigit() else views[-1].stamp_ns
                img = msgconv.rgb_to_image(rgb, msgconv.ns_to_stamp(ns), "camera_optical")
                self.pub_render.publish(img)
                self._record("splat/render", img)
            self.diag.timing("train", time.monotonic() - t0)
            m = result.metrics()
            self.diag.set("heldout_psnr", m.get("heldout_psnr"))
            self.diag.set("heldout_spill", m.get("heldout_spill"))  # opacity past the masks
            self.diag.set_state(f"trained {len(result.model)} Gaussians in "
                                f"{time.monotonic() - t0:.0f} s, held-out PSNR "
                                f"{m.get('heldout_psnr')}")
        except Exception as exc:  # noqa: BLE001 — the node keeps running
            self.diag.count("error_training")
            self.throttle.warn("trainfail", f"training failed: {type(exc).__name__}: {exc}")
            self.last_error = traceback.format_exc()
        finally:
            self._busy.release()

    def on_train_srv(self, request, response):
        ok, why = self.ready()
        if not ok:
            response.success, response.message = False, f"not ready: {why}"
            return response
        started = self.start()
        response.success = started
        response.message = f"training started ({why})" if started else "already training"
        return response

    def wait_idle(self, timeout_s: float) -> bool:
        """Blocks until no training runs (tests and shutdown)."""
        if self._busy.acquire(timeout=timeout_s):
            self._busy.release()
            return True
        return False

    def close(self) -> None:
        """Finishes the recording bag (called on shutdown)."""
        with self._lock:
            if self.recorder is not None:
                self.recorder.close()
                self.recorder = None


def main(args=None) -> None:
    run_node(TrainingNode, args)


if __name__ == "__main__":
    main()
