"""``sfm_node``: images + camera_info + poses in, keyframes and a growing SfM cloud out.

Subscribes (sensor-data QoS, remappable): ``image`` (sensor_msgs/Image), ``image/compressed``
(CompressedImage), ``camera_info``, ``pose`` (PoseStamped of the camera optical frame, or with
``pose_type: odometry`` nav_msgs/Odometry of the vehicle and the static ``mount_*`` transform).
Publishes: ``keyframe/image``, ``keyframe/camera_info``, ``keyframe/pose`` (stamp = the source
image's stamp), ``sfm/points`` (PointCloud2 xyz+rgb in ``frame_id``, latched) and
``sfm/observations`` (PointCloud2 rows point_index, stamp_sec, stamp_nanosec, u, v: which
keyframe saw which point where — the segmentation uses visibility), and ``diagnostics``.

SfM runs in a worker thread behind a bounded queue: when the drone produces keyframes faster
than SfM takes them, the oldest waiting keyframe is dropped and counted, never queued forever.
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
from ..sfm.keyframes import KeyframeConfig, KeyframeSelector
from .common import (ConfigParams, Diagnostics, ParamSpec, Throttle, guarded, latched_qos,
                     reliable_qos, run_node, sensor_qos)
from rclpy.node import Node


@dataclasses.dataclass
class SfmNodeConfig:
    """Parameters of the SfM node (see config/sfm_node.yaml)."""

    frame_id: str = dataclasses.field(default="map", metadata={"doc": "world frame of outputs"})
    pose_type: str = dataclasses.field(
        default="pose_stamped", metadata={"doc": "pose_stamped (optical frame) or odometry"})
    pose_tolerance_s: float = dataclasses.field(
        default=0.1, metadata={"doc": "max gap to the nearest pose sample for interpolation"})
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


SPECS = {
    "pose_type": ParamSpec("pose_stamped (optical frame) or odometry (vehicle + mount)",
                           choices=("pose_stamped", "odometry"), read_only=True),
    "pose_tolerance_s": ParamSpec("max gap to a pose sample for interpolation (s)", 0.0, 10.0),
    "pose_buffer_s": ParamSpec("seconds of pose history kept", 0.1, 600.0),
    "queue_size": ParamSpec("keyframes waiting for SfM before dropping", 1, 1000),
    "pending_images": ParamSpec("images waiting for a pose", 1, 1000),
    "publish_every": ParamSpec("publish the cloud every N keyframes", 1, 1000),
    "frame_id": ParamSpec("world frame of outputs", read_only=True),
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
        self.selector = KeyframeSelector(self.kf_cfg)
        self.sfm = IncrementalSfM(self.sfm_cfg)
        self.camera: Optional[CameraIntrinsics] = None
        self.pending: collections.deque = collections.deque(maxlen=self.cfg.pending_images)
        self.work: queue.Queue = queue.Queue(maxsize=self.cfg.queue_size)
        self._lock = threading.Lock()
        self._select_lock = threading.Lock()  # keyframe selection is stateful: one at a time
        self._last_image_ns = -1
        self.keyframes_processed = 0

        sq = sensor_qos()
        self.create_subscription(Image, "image", self.on_image, sq)
        self.create_subscription(CompressedImage, "image/compressed", self.on_compressed, sq)
        self.create_subscription(CameraInfo, "camera_info", self.on_camera_info, sq)
        if self.cfg.pose_type == "odometry":
            self.create_subscription(Odometry, "pose", self.on_odometry, sq)
        else:
            self.create_subscription(PoseStamped, "pose", self.on_pose, sq)
        rq = reliable_qos(depth=50)
        self.pub_kf_image = self.create_publisher(Image, "keyframe/image", rq)
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
        cam = msgconv.camera_info_to_intrinsics(msg)  # raises InputError on K all zeros etc.
        self.camera = cam

    @guarded("dropped_pose")
    def on_pose(self, msg: PoseStamped) -> None:
        self._add_pose(msgconv.stamp_to_ns(msg.header.stamp), msgconv.pose_from_msg(msg.pose))

    @guarded("dropped_pose")
    def on_odometry(self, msg: Odometry) -> None:
        body = msgconv.pose_from_msg(msg.pose.pose)
        cam = Pose(body.R @ self.mount.R, body.R @ self.mount.t + body.t)
        self._add_pose(msgconv.stamp_to_ns(msg.header.stamp), cam)

    def _add_pose(self, stamp_ns: int, pose: Pose) -> None:
        if not self.poses.add(stamp_ns, pose):
            self.diag.count("dropped_pose")
            self.throttle.warn("pose", f"pose at {stamp_ns} ns rejected (stamps going "
                                       "backwards or invalid); check the pose source")
            return
        self._drain_pending()

    @guarded("dropped_image")
    def on_image(self, msg: Image) -> None:
        self._on_rgb(msgconv.stamp_to_ns(msg.header.stamp), msgconv.image_to_rgb(msg))

    @guarded("dropped_image")
    def on_compressed(self, msg: CompressedImage) -> None:
        self._on_rgb(msgconv.stamp_to_ns(msg.header.stamp), msgconv.compressed_to_rgb(msg))

    def _on_rgb(self, stamp_ns: int, rgb: np.ndarray) -> None:
        self.diag.count("images")
        if self.camera is None:
            self.diag.count("dropped_no_camera_info")
            self.throttle.warn("noinfo", "image dropped: no valid camera_info received yet")
            return
        if stamp_ns <= self._last_image_ns:
            self.diag.count("dropped_stamp_backwards")
            self.throttle.warn("imgstamp", "image dropped: its stamp is not newer than the "
                                           "previous image's")
            return
        if rgb.shape[1] != self.camera.width or rgb.shape[0] != self.camera.height:
            self.diag.count("dropped_size_mismatch")
            self.throttle.warn("size", f"image {rgb.shape[1]}x{rgb.shape[0]} does not match "
                                       f"camera_info {self.camera.width}x{self.camera.height}")
            return
        self._last_image_ns = stamp_ns
        with self._lock:
            self.pending.append((stamp_ns, rgb, self.camera))
        self._drain_pending()

    def _drain_pending(self) -> None:
        """Moves images whose pose can now be interpolated on to keyframe selection."""
        with self._select_lock:
            self._drain_pending_locked()

    def _drain_pending_locked(self) -> None:
        ready = []
        with self._lock:
            keep = collections.deque(maxlen=self.pending.maxlen)
            for stamp_ns, rgb, cam in self.pending:
                pose = self.poses.lookup(stamp_ns)
                if pose is not None:
                    ready.append((stamp_ns, rgb, cam, pose))
                elif self.poses.is_too_old(stamp_ns):
                    self.diag.count("dropped_no_pose")
                    self.throttle.warn("nopose", "image dropped: no pose within "
                                                 f"{self.cfg.pose_tolerance_s} s of its stamp")
                else:
                    keep.append((stamp_ns, rgb, cam))
            self.pending = keep
        for stamp_ns, rgb, cam, pose in ready:
            view = View(key=str(stamp_ns), stamp_ns=stamp_ns, camera=cam, pose=pose, image=rgb)
            if not self.selector.offer(view):
                for reason, n in self.selector.dropped.items():
                    self.diag.counters[f"skipped_{reason}"] = n
                continue
            self._publish_keyframe(view)
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

    def _publish_keyframe(self, view: View) -> None:
        stamp = msgconv.ns_to_stamp(view.stamp_ns)
        self.pub_kf_image.publish(msgconv.rgb_to_image(view.image, stamp, "camera_optical"))
        self.pub_kf_info.publish(msgconv.intrinsics_to_camera_info(view.camera, stamp,
                                                                   "camera_optical"))
        self.pub_kf_pose.publish(msgconv.pose_to_pose_stamped(view.pose, stamp,
                                                              self.cfg.frame_id))
        self.diag.count("keyframes")

    # ---- SfM worker -----------------------------------------------------------------------
    def _work_loop(self) -> None:
        while not self._stop.is_set():
            try:
                view = self.work.get(timeout=0.2)
            except queue.Empty:
                continue
            t0 = time.monotonic()
            try:
                self.sfm.add_keyframe(view)
            except Exception as exc:  # noqa: BLE001 — keep the node alive, count and report
                self.diag.count("error_sfm")
                self.throttle.warn("sfm", f"SfM failed on keyframe {view.key}: {exc}")
                continue
            self.keyframes_processed += 1
            self.diag.timing("keyframe", time.monotonic() - t0)
            if self.keyframes_processed % self.cfg.publish_every == 0:
                self.publish_cloud()

    def publish_cloud(self) -> int:
        cloud = self.sfm.cloud()
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
