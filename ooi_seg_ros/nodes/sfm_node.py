"""``sfm_node``: images + camera_info + poses in, keyframes and a growing SfM cloud out.

Subscribes (sensor-data QoS, remappable): ``image`` (sensor_msgs/Image), ``image/compressed``
(CompressedImage), ``camera_info``, ``pose`` (PoseStamped of the camera optical frame, or with
``pose_type: odometry`` nav_msgs/Odometry of the vehicle and the static ``mount_*`` transform).
Publishes: ``keyframe/image``, ``keyframe/camera_info``, ``keyframe/pose`` (stamp = the source
image's stamp; a keyframe that came as a JPEG CompressedImage also goes out unchanged on
``keyframe/image/compressed`` -- how the segmentation knows its pixels are JPEG's),
``sfm/points`` (PointCloud2 xyz+rgb in ``frame_id``, latched) and
``sfm/observations`` (PointCloud2 rows point_index, stamp_sec, stamp_nanosec, u, v: which
keyframe saw which point where — the segmentation uses visibility), and ``diagnostics``.

Keeping up with a 30 Hz camera: the image callback only checks the message's header and size
fields (no copy of the pixels) and queues the message; a frame is decoded only when its pose
(interpolated between pose samples, across lost pose messages up to a tolerance derived from
the pose rate) passes the keyframe selector's motion test, and only such candidates pay the
blur test. Keyframes are republished as received. SfM runs on a copy downscaled by an integer
factor derived from the image size (``sfm_downscale``/``sfm_max_pixels``), in a worker thread
behind a bounded queue: when the drone produces keyframes faster than SfM takes them, the
oldest waiting keyframe is dropped and counted, never queued forever. Where a second core is
free, the SIFT of the next keyframes runs in a feature-extraction process while the current one
is matched and triangulated (``feature_workers``; ``sfm.prefetch.PipelinedSfM``: the same cloud
as the serial path, at up to ``features_ahead`` keyframes in flight). The worker keeps no
images once a keyframe's features are extracted. Observations are published in the source
image's pixel coordinates.
"""

from __future__ import annotations

import collections
import dataclasses
import queue
import threading
import time
from typing import Optional

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2
from std_srvs.srv import Trigger

from .. import msgconv
from ..core.geometry import quat_xyzw_to_matrix
from ..core.sync import PoseBuffer
from ..core.types import CameraIntrinsics, InputError, Pose, View
from ..sfm.incremental import IncrementalConfig, IncrementalSfM
from ..sfm.prefetch import PipelinedSfM
from ..sfm.keyframes import KeyframeConfig, KeyframeSelector, rotation_angle_deg
from .common import (ConfigParams, Diagnostics, ParamSpec, Throttle, check_image_msg,
                     downscale_camera, downscale_factor, downscale_rgb, guarded, latched_qos,
                     physical_memory_bytes, reliable_qos, run_node, scale_pixels, sensor_qos)
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node


@dataclasses.dataclass
class SfmNodeConfig:
    """Parameters of the SfM node (see config/sfm_node.yaml)."""

    frame_id: str = dataclasses.field(default="map", metadata={"doc": "world frame of outputs"})
    pose_type: str = dataclasses.field(
        default="pose_stamped", metadata={"doc": "pose_stamped (optical frame) or odometry"})
    pose_tolerance_s: float = dataclasses.field(
        default=0.0, metadata={"doc": "max time from an image stamp to each of the two pose "
                                      "samples it is interpolated between (0 = derived from "
                                      "the pose rate: (pose_max_lost + 1) pose periods)"})
    pose_max_lost: int = dataclasses.field(
        default=4, metadata={"doc": "with pose_tolerance_s 0: consecutive lost pose messages "
                                    "that interpolation may still bridge"})
    pose_buffer_s: float = dataclasses.field(
        default=10.0, metadata={"doc": "seconds of pose history kept"})
    mount_xyz: str = dataclasses.field(
        default="0 0 0", metadata={"doc": "camera optical frame in the vehicle frame: x y z (m)"})
    mount_quat_xyzw: str = dataclasses.field(
        default="0 0 0 1", metadata={"doc": "camera optical frame in the vehicle frame: quat"})
    queue_size: int = dataclasses.field(
        default=4, metadata={"doc": "keyframes waiting for SfM before the oldest is dropped"})
    pending_images: int = dataclasses.field(
        default=30, metadata={"doc": "images kept while waiting for a pose newer than them"})
    publish_every: int = dataclasses.field(
        default=1, metadata={"doc": "publish the cloud every N processed keyframes"})
    sfm_downscale: int = dataclasses.field(
        default=0, metadata={"doc": "SfM runs on images downscaled by this integer factor (0 = "
                                    "the smallest factor that brings them to sfm_max_pixels)"})
    sfm_max_pixels: int = dataclasses.field(
        default=400_000, metadata={"doc": "with sfm_downscale 0: pixel count SfM images are "
                                          "reduced to (feature extraction cost grows with it)"})
    image_qos_depth: int = dataclasses.field(
        default=5, metadata={"doc": "depth of the image subscriptions (sensor-data QoS; "
                                    "frames beyond it are the transport's drops)"})
    pose_qos_depth: int = dataclasses.field(
        default=30, metadata={"doc": "depth of the pose subscription: rides out a busy moment "
                                     "without letting poses lag the images by more than "
                                     "pending_images can wait"})
    sfm_budget_mb: float = dataclasses.field(
        default=0.0, metadata={"doc": "MiB the SfM map (features, tracks) may grow to; beyond "
                                      "it no further keyframes are taken, counted and logged "
                                      "(0 = 1/16 of the RAM within 256..1024)"})
    keyframe_qos_depth: int = dataclasses.field(
        default=10, metadata={"doc": "history depth of the keyframe publishers (full-size "
                                     "images held by the middleware)"})
    feature_workers: int = dataclasses.field(
        default=-1, metadata={"doc": "processes extracting SIFT of the next keyframes while "
                                     "the current one is matched (-1 = one where 2+ cores are "
                                     "usable, 0 = extract in the SfM thread)"})
    features_ahead: int = dataclasses.field(
        default=2, metadata={"doc": "keyframes in flight in the feature worker (each holds "
                                    "one SfM-size image and its features)"})


SPECS = {
    "pose_type": ParamSpec("pose_stamped (optical frame) or odometry (vehicle + mount)",
                           choices=("pose_stamped", "odometry"), read_only=True),
    "pose_tolerance_s": ParamSpec("max gap to a pose sample for interpolation (s, 0 = from "
                                  "the pose rate)", 0.0, 10.0),
    "pose_max_lost": ParamSpec("lost pose messages interpolation may bridge", 0, 1000),
    "sfm_downscale": ParamSpec("integer downscale of SfM images (0 = auto)", 0, 64,
                               read_only=True),
    "sfm_max_pixels": ParamSpec("pixel count SfM images are reduced to (auto)", 10_000,
                                100_000_000, read_only=True),
    "image_qos_depth": ParamSpec("depth of the image subscriptions", 1, 1000, read_only=True),
    "pose_qos_depth": ParamSpec("depth of the pose subscription", 1, 100000,
                                read_only=True),
    "sfm_budget_mb": ParamSpec("MiB the SfM map may grow to (0 = auto)", 0.0, 1e6,
                               read_only=True),
    "keyframe_qos_depth": ParamSpec("history depth of the keyframe publishers", 1, 1000,
                                    read_only=True),
    "pose_buffer_s": ParamSpec("seconds of pose history kept", 0.1, 600.0),
    "queue_size": ParamSpec("keyframes waiting for SfM before dropping", 1, 1000),
    "pending_images": ParamSpec("images waiting for a pose", 1, 1000),
    "publish_every": ParamSpec("publish the cloud every N keyframes", 1, 1000),
    "frame_id": ParamSpec("world frame of outputs", read_only=True),
    "feature_workers": ParamSpec("SIFT worker processes (-1 = auto, 0 = none)", -1, 1,
                                 read_only=True),
    "features_ahead": ParamSpec("keyframes in flight in the feature worker", 1, 16,
                                read_only=True),
}


def _floats(text: str, n: int, name: str) -> np.ndarray:
    try:
        vals = np.array([float(x) for x in str(text).replace(",", " ").split()])
    except ValueError:
        raise InputError(f"parameter {name} must be {n} numbers, got {text!r}") from None
    if vals.shape != (n,) or not np.all(np.isfinite(vals)):
        raise InputError(f"parameter {name} must be {n} finite numbers, got {text!r}")
    return vals


class SfmNode(Node):
    """Keyframe selection + incremental known-pose SfM on live topics."""

    def __init__(self, **kwargs) -> None:
        super().__init__("sfm_node", **kwargs)
        self.cfg = SfmNodeConfig()
        self.kf_cfg = KeyframeConfig()
        self.sfm_cfg = IncrementalConfig()
        self.params = ConfigParams(self, self.cfg, specs=SPECS)
        ConfigParams(self, self.kf_cfg, prefix="keyframes.")
        ConfigParams(self, self.sfm_cfg, prefix="sfm.")
        mount = Pose(quat_xyzw_to_matrix(_floats(self.cfg.mount_quat_xyzw, 4, "mount_quat_xyzw")),
                     _floats(self.cfg.mount_xyz, 3, "mount_xyz"))
        self.mount = None if self.cfg.pose_type == "pose_stamped" else mount
        self.diag = Diagnostics(self)
        self.throttle = Throttle(self)
        self.poses = PoseBuffer(max_age_ns=int(self.cfg.pose_buffer_s * 1e9),
                                tolerance_ns=int(self.cfg.pose_tolerance_s * 1e9))
        self._pose_dts: collections.deque = collections.deque(maxlen=64)  # recent periods, ns
        self._last_pose: Optional[Pose] = None
        self._prev_pose: Optional[tuple[int, Pose]] = None  # the pose before the last one
        self._jumps: collections.deque = collections.deque(maxlen=64)  # (t0, t1) ns
        self.selector = KeyframeSelector(self.kf_cfg)
        self.sfm = IncrementalSfM(self.sfm_cfg)
        self.pipe = PipelinedSfM(self.sfm, ahead=self.cfg.features_ahead,
                                 workers=None if self.cfg.feature_workers < 0
                                 else self.cfg.feature_workers, keep_images=False)
        self._submitted: dict = {}  # key -> monotonic time the keyframe entered SfM
        self.camera: Optional[CameraIntrinsics] = None
        self._camera_key: Optional[tuple] = None
        self.pending: collections.deque = collections.deque(maxlen=self.cfg.pending_images)
        self.work: queue.Queue = queue.Queue(maxsize=self.cfg.queue_size)
        self._lock = threading.Lock()
        self._select_lock = threading.Lock()  # keyframe selection is stateful: one at a time
        self._publish_lock = threading.Lock()  # points + observations go out as one pair
        self._last_image_ns = -1
        self.keyframes_processed = 0
        mib = 2 ** 20
        ram = physical_memory_bytes()
        self.map_budget = (int(self.cfg.sfm_budget_mb * mib) if self.cfg.sfm_budget_mb > 0
                           else int(min(max(ram // 16, 256 * mib), 1024 * mib)) if ram
                           else 512 * mib)
        self.map_bytes = 0
        self.map_full = False
        self.keyframe_times: collections.deque = collections.deque(maxlen=200)  # s per kf
        self.sfm_factor: Optional[int] = None  # downscale of SfM's images (first keyframe)

        # images, poses and camera_info in separate callback groups: a multi-threaded
        # executor then never holds a pose back behind another callback (a late pose makes
        # images wait, a lost one costs them)
        images, poses = MutuallyExclusiveCallbackGroup(), MutuallyExclusiveCallbackGroup()
        sq = sensor_qos(self.cfg.image_qos_depth)
        pq = sensor_qos(self.cfg.pose_qos_depth)
        self.create_subscription(Image, "image", self.on_image, sq, callback_group=images)
        self.create_subscription(CompressedImage, "image/compressed", self.on_compressed, sq,
                                 callback_group=images)
        self.create_subscription(CameraInfo, "camera_info", self.on_camera_info,
                                 sensor_qos(5), callback_group=MutuallyExclusiveCallbackGroup())
        if self.cfg.pose_type == "odometry":
            self.create_subscription(Odometry, "pose", self.on_odometry, pq,
                                     callback_group=poses)
        else:
            self.create_subscription(PoseStamped, "pose", self.on_pose, pq,
                                     callback_group=poses)
        rq = reliable_qos(depth=self.cfg.keyframe_qos_depth)
        self.pub_kf_image = self.create_publisher(Image, "keyframe/image", rq)
        self.pub_kf_lossy = self.create_publisher(CompressedImage, "keyframe/image/compressed",
                                                  rq)
        self.pub_kf_info = self.create_publisher(CameraInfo, "keyframe/camera_info", rq)
        self.pub_kf_pose = self.create_publisher(PoseStamped, "keyframe/pose", rq)
        self.pub_points = self.create_publisher(PointCloud2, "sfm/points", latched_qos())
        self.pub_obs = self.create_publisher(PointCloud2, "sfm/observations", latched_qos())
        self.create_service(Trigger, "~/publish_cloud", self.on_publish_cloud)
        self._stop = threading.Event()
        self._worker = threading.Thread(target=self._work_loop, daemon=True)
        self._worker.start()
        self.diag.set_state("waiting for camera_info, poses and images")

    # ---- inputs -------------------------------------------------------------------------
    @guarded("dropped_camera_info")
    def on_camera_info(self, msg: CameraInfo) -> None:
        key = (msg.width, msg.height, msg.distortion_model, tuple(msg.k), tuple(msg.d))
        if self.camera is not None and key == self._camera_key:
            return  # the same calibration at 30 Hz: nothing to convert
        cam = msgconv.camera_info_to_intrinsics(msg)  # raises InputError on K all zeros etc.
        self.camera, self._camera_key = cam, key

    @guarded("dropped_pose")
    def on_pose(self, msg: PoseStamped) -> None:
        self._add_pose(msgconv.stamp_to_ns(msg.header.stamp), msgconv.pose_from_msg(msg.pose))

    @guarded("dropped_pose")
    def on_odometry(self, msg: Odometry) -> None:
        body = msgconv.pose_from_msg(msg.pose.pose)
        cam = Pose(body.R @ self.mount.R, body.R @ self.mount.t + body.t)
        self._add_pose(msgconv.stamp_to_ns(msg.header.stamp), cam)

    def _add_pose(self, stamp_ns: int, pose: Pose) -> None:
        with self._lock:  # lookups run in the image callback's thread
            last = self.poses.latest_ns
            last_pose = self._last_pose
            added = self.poses.add(stamp_ns, pose)
        if not added:
            self.diag.count("dropped_pose")
            self.throttle.warn("pose", f"pose at {stamp_ns} ns rejected (stamps going "
                                       "backwards or invalid); check the pose source")
            return
        if last is not None:
            self._pose_dts.append(stamp_ns - last)
        self.poses.tolerance_ns = self.pose_tolerance_ns()
        if last is not None and stamp_ns - last > self.poses.tolerance_ns:
            self.diag.count("pose_gaps")  # images inside this gap get no pose
            self.diag.set("pose_gap_last_s", f"{(stamp_ns - last) / 1e9:.3f}")
        elif last is not None and self._pose_dts and \
                stamp_ns - last > 1.5 * float(np.median(self._pose_dts)):
            with self._lock:  # poses were lost: interpolate across only if motion was smooth
                self._check_gap(last, last_pose, stamp_ns, pose)
        if last is not None:
            self._prev_pose = (last, last_pose)
        self._last_pose = pose
        self._drain_pending()

    def pose_tolerance_ns(self) -> int:
        """Tolerance of the pose interpolation: the parameter, or derived from the pose rate.

        Derived: ``(pose_max_lost + 1)`` times the median of the recent pose periods (gaps of
        lost messages included, so the median stays the nominal period while fewer than half
        are lost); 0.1 s until two poses have arrived.
        """
        if self.cfg.pose_tolerance_s > 0:
            return int(self.cfg.pose_tolerance_s * 1e9)
        if not self._pose_dts:
            return 100_000_000
        period = float(np.median(np.asarray(self._pose_dts, np.float64)))
        return int((self.cfg.pose_max_lost + 1) * period)

    def _check_gap(self, t0: int, p0: Pose, t1: int, p1: Pose) -> None:
        """Marks the pose gap (t0, t1) as a jump when the camera moved across it much more than
        its speed just before predicts (a teleport, a reset of the pose source): images in it
        get no interpolated pose. Smooth motion, however fast, interpolates."""
        prev = self._prev_pose
        if prev is None:
            return
        tp, pp = prev
        dt_prev, dt_gap = max(t0 - tp, 1), t1 - t0
        rate_r = rotation_angle_deg(pp.R, p0.R) / dt_prev
        rate_t = float(np.linalg.norm(p0.t - pp.t)) / dt_prev
        turned = rotation_angle_deg(p0.R, p1.R)
        moved = float(np.linalg.norm(p1.t - p0.t))
        scale = self.selector.scene_scale
        slack_r = 0.25 * self.kf_cfg.rotation_deg  # a quarter of a keyframe step
        slack_t = 0.25 * self.kf_cfg.translation_frac * scale if scale else np.inf
        if turned > 2 * rate_r * dt_gap + slack_r or moved > 2 * rate_t * dt_gap + slack_t:
            self._jumps.append((t0, t1))
            self.diag.count("pose_jumps")

    def _in_jump(self, stamp_ns: int) -> bool:
        return any(t0 < stamp_ns < t1 for t0, t1 in self._jumps)

    @guarded("dropped_image")
    def on_image(self, msg: Image) -> None:
        check_image_msg(msg)  # header and sizes only: the pixels are decoded for candidates
        self._on_frame(msgconv.stamp_to_ns(msg.header.stamp), msg, int(msg.width),
                       int(msg.height))

    @guarded("dropped_image")
    def on_compressed(self, msg: CompressedImage) -> None:
        if not len(msg.data):
            raise InputError("compressed image has no data")
        self._on_frame(msgconv.stamp_to_ns(msg.header.stamp), msg, None, None)

    def _on_frame(self, stamp_ns: int, msg, width: Optional[int],
                  height: Optional[int]) -> None:
        """Cheap part of an image callback: checks, then queue the message until its pose."""
        self.diag.count("images")
        cam = self.camera
        if cam is None:
            self.diag.count("dropped_no_camera_info")
            self.throttle.warn("noinfo", "image dropped: no valid camera_info received yet")
            return
        if stamp_ns <= self._last_image_ns:
            self.diag.count("dropped_stamp_backwards")
            self.throttle.warn("imgstamp", "image dropped: its stamp is not newer than the "
                                           "previous image's")
            return
        if width is not None and (width != cam.width or height != cam.height):
            self.diag.count("dropped_size_mismatch")
            self.throttle.warn("size", f"image {width}x{height} does not match camera_info "
                                       f"{cam.width}x{cam.height}")
            return
        self._last_image_ns = stamp_ns
        with self._lock:
            if len(self.pending) == self.pending.maxlen:
                self.diag.count("dropped_pose_late")  # the oldest waiting image falls out
                self.throttle.warn("nopose", f"image dropped: {self.pending.maxlen} images "
                                             "waiting for a newer pose (pose stream late?)")
            self.pending.append((stamp_ns, msg, cam))
        self._drain_pending()

    def _decode(self, msg, cam: CameraIntrinsics) -> np.ndarray:
        self.diag.count("images_decoded")
        if isinstance(msg, CompressedImage):
            rgb = msgconv.compressed_to_rgb(msg)
            if rgb.shape[0] != cam.height or rgb.shape[1] != cam.width:
                raise InputError(f"compressed image {rgb.shape[1]}x{rgb.shape[0]} does not "
                                 f"match camera_info {cam.width}x{cam.height}")
            return rgb
        return msgconv.image_to_rgb(msg)

    def _drain_pending(self) -> None:
        """Moves images whose pose can now be interpolated on to keyframe selection."""
        with self._select_lock:
            self._drain_pending_locked()

    def _drain_pending_locked(self) -> None:
        ready = []
        with self._lock:
            keep = collections.deque(maxlen=self.pending.maxlen)
            for stamp_ns, msg, cam in self.pending:
                pose = self.poses.lookup(stamp_ns)
                if pose is not None and self._in_jump(stamp_ns):
                    self.diag.count("dropped_pose_jump")
                    self.throttle.warn("posejump", "image dropped: the camera moved too far "
                                                   "across the pose gap around its stamp to "
                                                   "trust an interpolated pose")
                elif pose is not None:
                    ready.append((stamp_ns, msg, cam, pose))
                elif self.poses.is_too_old(stamp_ns):
                    self.diag.count("dropped_no_pose")
                    self.throttle.warn("nopose", "image dropped: no pose within "
                                                 f"{self.poses.tolerance_ns / 1e9:.3f} s on "
                                                 "both sides of its stamp")
                else:
                    keep.append((stamp_ns, msg, cam))
            self.pending = keep
        for stamp_ns, msg, cam, pose in ready:
            # the selector tests motion on the pose first and decodes only candidates
            view = View(key=str(stamp_ns), stamp_ns=stamp_ns, camera=cam, pose=pose,
                        loader=lambda m=msg, c=cam: self._decode(m, c))
            try:
                accepted = self.selector.offer(view)
            except InputError as exc:
                self.diag.count("dropped_image")
                self.throttle.warn("decode", f"image {stamp_ns} dropped: {exc}")
                continue
            if not accepted:
                for reason, n in self.selector.dropped.items():
                    self.diag.set_count(f"skipped_{reason}", n)
                continue
            self._publish_keyframe(view, msg)
            if self.selector.scene_scale and not self.sfm.scene_scale:
                # the SfM's depth guess (which earlier keyframes to match) from the scene
                # scale as soon as the selector has it, as ``ooi-seg run`` does with the
                # whole orbit's: the convergence point of the first few keyframes is a poor
                # guess (measured: a different cloud, masks IoU 0.906 vs 0.913 on the demo bag)
                self.sfm.scene_scale = self.selector.scene_scale
            try:
                self.work.put_nowait(view)
            except queue.Full:
                try:
                    self.work.get_nowait()
                    self.diag.count("dropped_backlog")
                    self.throttle.warn("backlog", "SfM is behind: dropped the oldest waiting "
                                                  "keyframe (raise keyframe spacing?)")
                except queue.Empty:
                    pass
                self.work.put_nowait(view)

    def _publish_keyframe(self, view: View, msg) -> None:
        stamp = msgconv.ns_to_stamp(view.stamp_ns)
        if isinstance(msg, CompressedImage) and msgconv.is_lossy(msg):
            self.pub_kf_lossy.publish(msg)  # before the image: the mark precedes the pixels
        if isinstance(msg, Image):  # as received: no re-encoding of the pixels
            self.pub_kf_image.publish(msg)
        else:
            self.pub_kf_image.publish(msgconv.rgb_to_image(view.get_image(), stamp,
                                                           "camera_optical"))
        self.pub_kf_info.publish(msgconv.intrinsics_to_camera_info(view.camera, stamp,
                                                                   "camera_optical"))
        self.pub_kf_pose.publish(msgconv.pose_to_pose_stamped(view.pose, stamp,
                                                              self.cfg.frame_id))
        self.diag.count("keyframes")

    # ---- SfM worker -----------------------------------------------------------------------
    def _work_loop(self) -> None:
        try:
            while not self._stop.is_set():
                self._feed_pipeline()
                if self.pipe.pending:
                    self._add_next()
        finally:
            self.pipe.close()  # ends the feature worker process

    def _feed_pipeline(self) -> None:
        """Hands waiting keyframes to the feature extraction while fewer than
        ``features_ahead`` are in flight (waits briefly for one only when none is)."""
        while self.pipe.can_submit and not self._stop.is_set():
            try:
                view = (self.work.get_nowait() if self.pipe.pending
                        else self.work.get(timeout=0.2))
            except queue.Empty:
                return
            try:
                self.pipe.submit(self._sfm_view(view))
            except Exception as exc:  # noqa: BLE001 — keep the node alive, count and report
                self.diag.count("error_sfm")
                self.throttle.warn("sfm", f"SfM failed on keyframe {view.key}: {exc}")
                continue
            self._submitted[view.key] = time.monotonic()

    def _add_next(self) -> None:
        """Adds the oldest keyframe in flight to the SfM (its features extracted ahead)."""
        t0 = time.monotonic()
        key = self.pipe.next_key
        try:
            stats = self.pipe.add_next()
        except Exception as exc:  # noqa: BLE001 — keep the node alive, count and report
            self.diag.count("error_sfm")
            self.throttle.warn("sfm", f"SfM failed on keyframe {key}: {exc}")
            self._submitted.pop(key, None)
            return
        self.keyframes_processed += 1
        self._account_map()
        self.keyframe_times.append(time.monotonic() - t0)
        self.diag.timing("keyframe", self.keyframe_times[-1])
        self.diag.timing("keyframe_median", float(np.median(self.keyframe_times)))
        t_in = self._submitted.pop(key, None)
        if t_in is not None:  # from entering the SfM (extraction) to the keyframe added
            self.diag.timing("keyframe_latency", time.monotonic() - t_in)
        if stats.get("features_wait_s") is not None:
            self.diag.timing("features_wait", float(stats["features_wait_s"]))
        self.diag.set("feature_workers", self.pipe.workers)
        failures = int(self.sfm.counts.get("feature_worker_failures", 0))
        if failures:
            self.diag.set_count("feature_worker_failures", failures)
        if self._stop.is_set():
            return  # shutting down: the publishers may be gone
        if self.keyframes_processed % self.cfg.publish_every == 0:
            try:
                self.publish_cloud()
            except Exception as exc:  # noqa: BLE001 — keep the worker alive
                self.diag.count("error_publish")
                self.throttle.warn("publish", f"publishing the cloud failed: {exc}")

    def _account_map(self) -> None:
        """Estimates the SfM map's bytes; at the budget, stops taking keyframes (logged).

        The estimate is twice the numpy arrays of each SfM keyframe (keypoints, descriptors,
        colours): the tracks' Python structures measured about as much again.
        """
        kfs = self.sfm.keyframes
        if kfs:
            kf = kfs[-1]
            self.map_bytes += 2 * sum(v.nbytes for v in vars(kf).values()
                                      if isinstance(v, np.ndarray))
        self.diag.set("sfm_map_mb", f"{self.map_bytes / 2 ** 20:.1f}")
        if self.map_bytes >= self.map_budget and not self.map_full:
            self.map_full = True
            cap = self.kf_cfg.max_keyframes
            self.kf_cfg.max_keyframes = min(cap, self.selector.accepted) if cap else \
                self.selector.accepted  # the selector refuses more
            self.diag.set_state("SfM map at its memory budget: no further keyframes")
            self.get_logger().warning(
                f"SfM map reached ~{self.map_bytes / 2 ** 20:.0f} MiB (sfm_budget_mb "
                f"{self.map_budget / 2 ** 20:.0f}) after {len(kfs)} keyframes: no further "
                "keyframes are taken (counted as skipped_max_keyframes); raise sfm_budget_mb "
                "or keyframe spacing")

    def _sfm_view(self, view: View) -> View:
        """The keyframe as SfM sees it: downscaled copy, scaled intrinsics, no full image.

        The factor is fixed by the first keyframe so that all observations share one scale.
        """
        cam = view.camera
        if self.sfm_factor is None:
            self.sfm_factor = (self.cfg.sfm_downscale if self.cfg.sfm_downscale > 0 else
                               downscale_factor(cam.width, cam.height, self.cfg.sfm_max_pixels))
            self.diag.set("sfm_downscale", self.sfm_factor)
        f = self.sfm_factor
        small = np.ascontiguousarray(downscale_rgb(view.get_image(), f))
        view.image, view.loader = None, None  # the full-size frame is published already
        return View(key=view.key, stamp_ns=view.stamp_ns, camera=downscale_camera(cam, f),
                    pose=view.pose, image=small)

    def publish_cloud(self) -> int:
        """Publishes the current cloud: points and their observations, one pair at a time
        (the worker and the ``~/publish_cloud`` service may both call this; interleaved, the
        latched observations could belong to another cloud than the latched points)."""
        with self._publish_lock:
            return self._publish_cloud_locked()

    def _publish_cloud_locked(self) -> int:
        cloud = self.sfm.cloud()
        f = self.sfm_factor or 1
        if f > 1:  # observations and errors in the source image's pixels
            cloud = dataclasses.replace(cloud, obs_xy=scale_pixels(cloud.obs_xy, f),
                                        error=np.asarray(cloud.error) * f)
        stamp = self.get_clock().now().to_msg()
        if cloud.views:
            stamp = msgconv.ns_to_stamp(cloud.views[-1].stamp_ns)
        self.pub_points.publish(msgconv.xyzrgb_to_pointcloud2(cloud.xyz, cloud.rgb, stamp,
                                                              self.cfg.frame_id))
        self.pub_obs.publish(msgconv.observations_to_pointcloud2(cloud, stamp, self.cfg.frame_id))
        self.diag.set("points", len(cloud))
        self.diag.set_state(f"{self.keyframes_processed} keyframes, {len(cloud)} points")
        return len(cloud)

    def on_publish_cloud(self, request, response):
        n = self.publish_cloud()
        response.success = True
        response.message = f"published {n} points"
        return response

    def close(self) -> None:
        self._stop.set()
        self._worker.join(timeout=5.0)


def main(args=None) -> None:
    run_node(SfmNode, args)


if __name__ == "__main__":
    main()
