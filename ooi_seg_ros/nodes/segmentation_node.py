"""``segmentation_node``: SfM cloud + keyframes in, OOI cloud, mesh and per-keyframe masks out.

Subscribes: ``sfm/points`` and ``sfm/observations`` (latched), ``keyframe/image``,
``keyframe/camera_info``, ``keyframe/pose`` (matched by exact stamp). Runs the segmentation
pipeline (the same core code as ``ooi-seg segment``) every ``every_n_keyframes`` new keyframes
and on the ``~/segment`` service (std_srvs/Trigger), in a worker thread. Publishes ``ooi/points``
(PointCloud2, latched), ``ooi/mesh`` (visualization_msgs/Marker TRIANGLE_LIST, latched) and
``ooi/mask`` (mono8, one per keyframe, stamp = the keyframe image's stamp; all keyframes are
re-published whenever the mesh changes), plus ``diagnostics``.

Memory is bounded in bytes: keyframe images are kept downscaled by an integer factor derived
from their size (``image_downscale``/``image_max_pixels``) within ``image_budget_mb``; beyond
it the most redundant keyframe (camera closest to another kept one) is evicted, counted and
logged. The segmentation runs on those copies; masks are published at each keyframe's own
size (nearest upsampling of the mask rendered at the working size).
"""

from __future__ import annotations

import dataclasses
import threading
import time
import traceback
from typing import Optional

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.duration import Duration
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker

from .. import msgconv
from ..core.types import Capture, View
from ..seg.pipeline import SegmentationConfig, make_config, segment
from .common import (ConfigParams, Diagnostics, KeyframeAssembler, ParamSpec, Throttle,
                     auto_image_budget_bytes, guarded, latched_qos, reliable_qos, run_node,
                     upscale_mask)


@dataclasses.dataclass
class SegNodeConfig:
    """Parameters of the segmentation node (see config/segmentation_node.yaml)."""

    frame_id: str = dataclasses.field(default="map", metadata={"doc": "world frame of outputs"})
    method: str = dataclasses.field(
        default="ours", metadata={"doc": "segmentation preset: ours (default) or paper; "
                                         "seg.* parameters override single options"})
    every_n_keyframes: int = dataclasses.field(
        default=10, metadata={"doc": "re-segment after this many new keyframes (0 = only on "
                                     "the ~/segment service)"})
    idle_run_s: float = dataclasses.field(
        default=2.0, metadata={"doc": "also re-segment when keyframes came since the last run "
                                      "and no keyframe or cloud arrived for this long (the "
                                      "last keyframes of a flight need not wait for N more; "
                                      "0 = off)"})
    min_keyframes: int = dataclasses.field(
        default=8, metadata={"doc": "keyframes needed before the first automatic run"})
    max_keyframes: int = dataclasses.field(
        default=2000, metadata={"doc": "keyframes kept in memory (evicted beyond)"})
    image_budget_mb: float = dataclasses.field(
        default=0.0, metadata={"doc": "MiB of kept keyframe images; beyond it keyframes are "
                                      "evicted (0 = 1/32 of the RAM within 128..512)"})
    image_downscale: int = dataclasses.field(
        default=0, metadata={"doc": "keep keyframe images downscaled by this integer factor "
                                    "(0 = the smallest that brings them to image_max_pixels)"})
    image_max_pixels: int = dataclasses.field(
        default=400_000, metadata={"doc": "with image_downscale 0: pixel count kept images "
                                          "are reduced to"})
    evict_policy: str = dataclasses.field(
        default="redundant", metadata={"doc": "which keyframe goes when over budget: redundant "
                                              "(camera nearest another kept one) or oldest"})
    qos_depth: int = dataclasses.field(
        default=10, metadata={"doc": "history depth of the keyframe subscriptions"})
    mask_qos_depth: int = dataclasses.field(
        default=20, metadata={"doc": "masks the middleware keeps; a burst of more waits for "
                                     "the subscribers' acknowledgements"})
    mask_stride: int = dataclasses.field(
        default=1, metadata={"doc": "publish masks for every k-th keyframe (1 = all)"})


SPECS = {
    "every_n_keyframes": ParamSpec("re-segment after N new keyframes (0 = service only)", 0,
                                   100000),
    "idle_run_s": ParamSpec("re-segment after this long without input (0 = off)", 0.0, 3600.0),
    "min_keyframes": ParamSpec("keyframes before the first run", 2, 100000),
    "max_keyframes": ParamSpec("keyframes kept in memory", 2, 1000000, read_only=True),
    "mask_stride": ParamSpec("publish masks for every k-th keyframe", 1, 1000),
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
    "mask_qos_depth": ParamSpec("history depth of the mask publisher", 1, 10000,
                                read_only=True),
    "frame_id": ParamSpec("world frame of outputs", read_only=True),
    "method": ParamSpec("segmentation preset", choices=("ours", "paper"), read_only=True),
}


class SegmentationNode(Node):
    """Keeps the keyframes and the latest cloud, segments on demand or every N keyframes."""

    def __init__(self, **kwargs) -> None:
        super().__init__("segmentation_node", **kwargs)
        self.cfg = SegNodeConfig()
        ConfigParams(self, self.cfg, specs=SPECS)
        self.seg_cfg: SegmentationConfig = make_config(self.cfg.method)
        ConfigParams(self, self.seg_cfg, prefix="seg.")
        self.diag = Diagnostics(self)
        self.throttle = Throttle(self)
        self._lock = threading.Lock()
        budget = (int(self.cfg.image_budget_mb * 2 ** 20) if self.cfg.image_budget_mb > 0
                  else auto_image_budget_bytes())
        self.assembler = KeyframeAssembler(
            self.diag, self.cfg.max_keyframes, max_bytes=budget,
            downscale=self.cfg.image_downscale, max_pixels=self.cfg.image_max_pixels,
            evict_policy=self.cfg.evict_policy, warn=self.throttle.warn)
        self.diag.set("image_budget_mb", f"{budget / 2 ** 20:.0f}")
        self.keyframes = self.assembler.keyframes  # {stamp_ns: View}, capture order
        self._points_msg: Optional[PointCloud2] = None
        self._obs_msg: Optional[PointCloud2] = None
        self._new_since_run = 0
        self._busy = threading.Lock()
        self.runs = 0
        self.last_result = None
        self.last_error: Optional[str] = None

        rq = reliable_qos(depth=self.cfg.qos_depth)
        self.create_subscription(Image, "keyframe/image", self.on_kf_image, rq)
        self.create_subscription(CameraInfo, "keyframe/camera_info", self.on_kf_info, rq)
        self.create_subscription(PoseStamped, "keyframe/pose", self.on_kf_pose, rq)
        self.create_subscription(PointCloud2, "sfm/points", self.on_points, latched_qos())
        self.create_subscription(PointCloud2, "sfm/observations", self.on_obs, latched_qos())
        self.pub_points = self.create_publisher(PointCloud2, "ooi/points", latched_qos())
        self.pub_mesh = self.create_publisher(Marker, "ooi/mesh", latched_qos())
        self.pub_mask = self.create_publisher(Image, "ooi/mask",
                                              reliable_qos(depth=self.cfg.mask_qos_depth))
        self.create_service(Trigger, "~/segment", self.on_segment_srv)
        self._last_input = time.monotonic()
        self.last_run_newest_ns: Optional[int] = None  # newest keyframe of the last run
        self.create_timer(0.5, self._on_idle_timer)
        self.diag.set_state("waiting for keyframes and the SfM cloud")

    # ---- inputs -------------------------------------------------------------------------
    def _part(self, stamp_ns: int, key: str, value) -> None:
        if self.assembler.add(stamp_ns, key, value):
            self._new_since_run += 1
            self._last_input = time.monotonic()
        self._maybe_run()

    @guarded("dropped_keyframe_image")
    def on_kf_image(self, msg: Image) -> None:
        self._part(msgconv.stamp_to_ns(msg.header.stamp), "image", msgconv.image_to_rgb(msg))

    @guarded("dropped_keyframe_info")
    def on_kf_info(self, msg: CameraInfo) -> None:
        self._part(msgconv.stamp_to_ns(msg.header.stamp), "info",
                   msgconv.camera_info_to_intrinsics(msg))

    @guarded("dropped_keyframe_pose")
    def on_kf_pose(self, msg: PoseStamped) -> None:
        self._part(msgconv.stamp_to_ns(msg.header.stamp), "pose",
                   msgconv.pose_from_msg(msg.pose))

    @guarded("dropped_cloud")
    def on_points(self, msg: PointCloud2) -> None:
        self._points_msg = msg
        self._last_input = time.monotonic()
        self._maybe_run()

    @guarded("dropped_cloud")
    def on_obs(self, msg: PointCloud2) -> None:
        self._obs_msg = msg

    # ---- running the pipeline -------------------------------------------------------------
    def _maybe_run(self) -> None:
        n = self.cfg.every_n_keyframes
        if n <= 0 or self._points_msg is None or len(self.keyframes) < self.cfg.min_keyframes:
            return
        if self._new_since_run >= n or self.runs == 0:
            self.trigger()

    def _on_idle_timer(self) -> None:
        idle = self.cfg.idle_run_s
        if (idle > 0 and self.cfg.every_n_keyframes > 0 and self._new_since_run > 0
                and self._points_msg is not None
                and len(self.keyframes) >= self.cfg.min_keyframes
                and time.monotonic() - self._last_input >= idle):
            self.trigger()

    def trigger(self) -> bool:
        """Starts a segmentation run in the background unless one is running."""
        if not self._busy.acquire(blocking=False):
            return False
        self._new_since_run = 0
        threading.Thread(target=self._run, daemon=True).start()
        return True

    def _run(self) -> None:
        try:
            t0 = time.monotonic()
            with self.assembler.lock:
                views = list(self.assembler.keyframes.values())
                full = {v.stamp_ns: (self.assembler.full_cameras[v.stamp_ns],
                                     self.assembler.factors[v.stamp_ns]) for v in views}
            if self._points_msg is None or len(views) < 2:
                self.throttle.warn("segnodata", "segment: need the SfM cloud and >= 2 keyframes")
                return
            cloud = msgconv.pointcloud2_to_sfm_cloud(self._points_msg, self._obs_msg, views)
            if len(cloud.obs_xy) and any(f > 1 for _c, f in full.values()):
                # observations come in source pixels; the kept views are downscaled
                f = np.array([full[v.stamp_ns][1] for v in views], np.float64)
                cloud.obs_xy = ((cloud.obs_xy + 0.5) / f[cloud.obs_view, None]
                                - 0.5).astype(np.float32)
                cloud.error = np.asarray(cloud.error) / float(np.median(f))
            capture = Capture(views=views, source="ros")
            self.diag.set_state(f"segmenting {len(cloud)} points over {len(views)} keyframes")
            result = segment(capture, cloud, self.seg_cfg)
            self.last_result = result
            self.runs += 1
            self.last_run_newest_ns = max(v.stamp_ns for v in views)
            self.diag.timing("segment", time.monotonic() - t0)
            self._publish(result, views, full)
            for w in getattr(result, "warnings", []) or []:
                self.throttle.warn("segwarn:" + w[:40], f"segmentation: {w}")
            self.diag.set_state(f"run {self.runs}: {len(result.ooi_cloud)} OOI points, "
                                f"{len(result.masks)} masks")
        except Exception as exc:  # noqa: BLE001 — the node keeps running
            self.diag.count("error_segmentation")
            self.last_error = traceback.format_exc()
            self.throttle.warn("segfail", f"segmentation failed: {type(exc).__name__}: {exc}")
        finally:
            self._busy.release()

    def _publish(self, result, views: list[View], full: dict) -> None:
        stamp = msgconv.ns_to_stamp(views[-1].stamp_ns)
        oc = result.ooi_cloud
        self.pub_points.publish(msgconv.xyzrgb_to_pointcloud2(oc.xyz, oc.rgb, stamp,
                                                              self.cfg.frame_id))
        if result.mesh is not None and not result.mesh.is_empty:
            self.pub_mesh.publish(msgconv.mesh_to_marker(result.mesh, stamp, self.cfg.frame_id))
        batch = 0
        for i, v in enumerate(views):
            if i % self.cfg.mask_stride:
                continue
            mask = result.masks.get(v.key)
            if mask is None:
                self.diag.count("masks_missing")
                continue
            if batch == self.cfg.mask_qos_depth:
                # the middleware keeps only mask_qos_depth masks: let the subscribers catch up
                # rather than overwrite masks they have not acknowledged yet
                if not self.pub_mask.wait_for_all_acked(Duration(seconds=10.0)):
                    self.diag.count("mask_ack_timeouts")
                    self.throttle.warn("maskack", "a mask subscriber did not acknowledge "
                                                  "within 10 s; it may miss masks")
                batch = 0
            cam, f = full[v.stamp_ns]
            mask = upscale_mask(np.asarray(mask, bool), f, cam.width, cam.height)
            self.pub_mask.publish(msgconv.mask_to_image(mask, msgconv.ns_to_stamp(v.stamp_ns),
                                                        "camera_optical"))
            batch += 1
            self.diag.count("masks_published")

    def on_segment_srv(self, request, response):
        if self._points_msg is None or len(self.keyframes) < 2:
            response.success = False
            response.message = (f"not ready: cloud={'yes' if self._points_msg else 'no'}, "
                                f"keyframes={len(self.keyframes)} (need the SfM cloud and >= 2)")
            return response
        started = self.trigger()
        response.success = started
        response.message = "segmentation started" if started else "a run is already in progress"
        return response


def main(args=None) -> None:
    run_node(SegmentationNode, args)


if __name__ == "__main__":
    main()
