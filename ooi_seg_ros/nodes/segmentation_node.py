"""``segmentation_node``: SfM cloud + keyframes in, OOI cloud, mesh and per-keyframe masks out.

Subscribes: ``sfm/points`` and ``sfm/observations`` (latched), ``keyframe/image``,
``keyframe/camera_info``, ``keyframe/pose`` (matched by exact stamp), and
``keyframe/image/compressed``: a JPEG copy there marks that keyframe's pixels as compressed
(``View.compressed``; the refinement's ``hull_graph`` acts on those; its pixels are not
used); raw keyframes whose colour measures chroma-subsampled (decoded JPEG or video,
``refine.blend_detect``) are treated the same. Runs the segmentation pipeline (the same
core code as ``ooi-seg segment``) every ``every_n_keyframes`` new keyframes and on the
``~/segment`` service (std_srvs/Trigger), driven from a worker thread; the run itself
goes to a worker *process* (``segment_worker``, ``seg.worker``) where the process may use two
cores, so that it neither waits for the GIL behind the executor and the nodes beside it nor
holds it from them. Publishes ``ooi/points``
(PointCloud2, latched), ``ooi/mesh`` (visualization_msgs/Marker TRIANGLE_LIST, latched) and
``ooi/mask`` (mono8, one per keyframe, stamp = the keyframe image's stamp; all keyframes are
re-published whenever the mesh changes), plus ``diagnostics``.

Latency. A whole run costs tens of seconds over many keyframes, most of it in the per-view
masks (refinement, hull carve), so results are published in three tiers:

- ``ooi/points`` as soon as a run's point stages are done (the pipeline's ``on_cloud``), before
  its mesh and masks; and between runs, whenever a new SfM cloud arrives, from a cheap
  *cloud-only* run of the point stages alone (``cloud_runs``; at most ``cloud_max_duty`` of the
  wall time). The cloud's stamp is the SfM cloud's (its newest keyframe).
- A *provisional* mask for every keyframe no run has covered yet, rendered from the current
  OOI cloud with the pipeline's own mask renderer (``seg.masks.render_masks``: the splatted or
  ray-cast silhouette, without the per-view refinement and hull carve), published with the
  keyframe's stamp as soon as the keyframe is complete (``provisional_masks``). Diagnostics
  say which masks are provisional (``masks_provisional``, ``provisional_mask_stamps``).
- The *final* masks of a full run, which replace the provisional ones. A run re-masks (mesh
  splat + per-view refinement) only the keyframes that need it (``incremental_final``): those
  with no final mask yet, those in whose view the coarse raw silhouette of the run's OOI cloud
  gained or lost more than ``final_refresh_change`` of the area of the one their final mask
  was made with (at ``change_check_side`` pixels, outline shifts within ``change_tolerance``
  not counted), and ``final_refresh_share`` of the rest, those whose final mask is oldest
  first, so that none is more than 1/share runs old. The others keep the final mask an
  earlier run made (it stays final) and, with ``republish_kept`` (default), it is sent again
  after the run's new masks, so that every keyframe's mask follows each mesh update (the node
  keeps final masks bit-packed for this: 1 bit per pixel of the kept keyframe image).
  Diagnostics: ``masks_new_last_run`` / ``_changed_`` / ``_rotated_`` / ``_refined_`` /
  ``_reused_last_run``, and the ``masks_reused`` counter. The ``~/segment`` service and
  ``incremental_final`` false re-mask every keyframe.

Which mask is which travels in the mask message: a provisional mask's ``header.frame_id`` is
``camera_optical_provisional``, a final one's ``camera_optical`` (``common.mask_frame_id``),
so a consumer (the training node) can keep final masks only without racing another topic.

Memory is bounded in bytes: keyframe images are kept downscaled by an integer factor derived
from their size (``image_downscale``/``image_max_pixels``) within ``image_budget_mb``; beyond
it the most redundant keyframe (camera closest to another kept one) is evicted, counted and
logged. The segmentation runs on those copies; masks are published at each keyframe's own
size: the mask made at the working size enlarged bilinearly, and for final masks its outline
placed by the received image, of which a JPEG (``mask_guide_quality``, ~0.2 MB at 1280x720)
is kept beside the smaller copy within the same budget (joint bilateral upsampling,
``seg.masks.guided_enlarge``). The worker process keeps its own copy of the smaller images
(sent once per keyframe), so image memory is about twice the budget with it.
"""

from __future__ import annotations

import collections
import dataclasses
import threading
import time
import traceback
from typing import Optional

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.duration import Duration
from rclpy.node import Node
from scipy import ndimage
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker

from .. import msgconv
from ..core.types import Capture, InputError, TriMesh, View
from ..seg.masks import render_masks
from ..core.worker import WorkerDied, usable_cores
from ..seg.pipeline import SegmentationConfig, make_config, segment
from ..seg.worker import SegmentationWorker
from .common import (KEYFRAME_STORE_SPECS, ConfigParams, Diagnostics, KeyframeAssembler,
                     ParamSpec, Throttle, downscale_camera, guarded, latched_qos,
                     mask_frame_id, reliable_qos, run_node, upscale_mask)


@dataclasses.dataclass
class SegNodeConfig:
    """Parameters of the segmentation node (see config/segmentation_node.yaml)."""

    frame_id: str = dataclasses.field(default="map", metadata={"doc": "world frame of outputs"})
    method: str = dataclasses.field(
        default="ours", metadata={"doc": "segmentation preset: ours (default) or paper; "
                                         "seg.* parameters override single options"})
    every_n_keyframes: int = dataclasses.field(
        default=5, metadata={"doc": "re-segment after this many new keyframes (0 = only on "
                                    "the ~/segment service); with incremental_final a run "
                                    "costs about its new keyframes' masks, so runs can be "
                                    "frequent (10 suits incremental_final false)"})
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
    mask_guide_quality: int = dataclasses.field(
        default=90, metadata={"doc": "keyframes kept smaller than received also keep the "
                                     "received image as a JPEG of this quality, which places "
                                     "the outline of their final masks enlarged to it (joint "
                                     "bilateral upsampling; about 0.2 MB per 1280x720 "
                                     "keyframe, within image_budget_mb; 0 = none)"})
    qos_depth: int = dataclasses.field(
        default=10, metadata={"doc": "history depth of the keyframe subscriptions"})
    mask_qos_depth: int = dataclasses.field(
        default=20, metadata={"doc": "masks the middleware keeps; a burst of more waits for "
                                     "the subscribers' acknowledgements"})
    mask_stride: int = dataclasses.field(
        default=1, metadata={"doc": "publish masks for every k-th keyframe (1 = all)"})
    provisional_masks: bool = dataclasses.field(
        default=True, metadata={"doc": "publish a provisional mask for each keyframe no run "
                                       "has covered yet, rendered from the current OOI cloud "
                                       "(no refinement); a run's final mask replaces it"})
    cloud_runs: bool = dataclasses.field(
        default=True, metadata={"doc": "between full runs, run the point stages alone on "
                                       "each new SfM cloud and publish ooi/points from them"})
    provisional_refresh: bool = dataclasses.field(
        default=True, metadata={"doc": "re-render provisional masks when a newer OOI cloud "
                                       "comes (newest keyframes first, within "
                                       "refresh_max_duty; new keyframes go first)"})
    refresh_max_duty: float = dataclasses.field(
        default=0.1, metadata={"doc": "share of the wall time re-rendering provisional masks "
                                      "may take (in a one-process bench, 0.5 cost the SfM "
                                      "node frames through the shared interpreter lock)"})
    cloud_max_duty: float = dataclasses.field(
        default=0.5, metadata={"doc": "share of the wall time cloud-only runs may take: one "
                                      "of t seconds starts the next no sooner than t/duty "
                                      "after its own start"})
    incremental_final: bool = dataclasses.field(
        default=True, metadata={"doc": "automatic full runs refine the masks only of the "
                                       "keyframes that need it (new ones, changed ones, a "
                                       "rotating share); the others keep their final mask "
                                       "(false = every run re-masks every keyframe; the "
                                       "~/segment service always does)"})
    final_refresh_change: float = dataclasses.field(
        default=0.1, metadata={"doc": "with incremental_final: re-mask a keyframe when the "
                                      "coarse silhouette of the new OOI cloud in its view "
                                      "gained or lost more than this share of the area of "
                                      "the one its final mask was made with (beyond "
                                      "change_tolerance)"})
    change_tolerance: float = dataclasses.field(
        default=0.02, metadata={"doc": "outline shifts up to this share of the image's long "
                                       "side are not counted as change (the raw splat "
                                       "outline moves as the cloud gets denser)"})
    final_refresh_share: float = dataclasses.field(
        default=0.1, metadata={"doc": "with incremental_final: share of the other keyframes "
                                      "(longest-final first) re-masked each run anyway, so "
                                      "no final mask is more than 1/share runs old (0 = none)"})
    republish_kept: bool = dataclasses.field(
        default=True, metadata={"doc": "after each full run, also re-publish the final masks "
                                       "kept from earlier runs, so every keyframe's mask is "
                                       "sent again whenever the mesh changes (false = only "
                                       "the masks the run made)"})
    segment_worker: int = dataclasses.field(
        default=-1, metadata={"doc": "full runs in a worker process of their own (1), in "
                                     "this node's thread (0), or -1: a worker where the "
                                     "process may use 2+ cores. In the node's process a run "
                                     "shares the GIL with the callbacks and any node beside "
                                     "it (measured ~10x slower per mask under camera load); "
                                     "the worker keeps its own copy of the keyframe images"})
    segment_worker_nice: int = dataclasses.field(
        default=10, metadata={"doc": "the worker process runs this much below the node's CPU "
                                     "priority (0-19; 10, the usual level of a background "
                                     "job, is the only value measured): where busy processes "
                                     "outnumber the cores, the camera stream, the "
                                     "subscriptions and the SfM node come first and the "
                                     "refinement takes what is left. 30 Hz 1280x720 load "
                                     "bench, 2 cores, two runs each: frames received 79-82% "
                                     "-> 94%, keyframes dropped for SfM backlog 13-17 -> 10, "
                                     "final masks 0.922-0.925 -> 0.934-0.939 IoU, their "
                                     "latency unchanged (median 47-56 s vs 51-53 s)"})
    change_check_side: int = dataclasses.field(
        default=96, metadata={"doc": "long side in pixels of the coarse silhouettes compared "
                                     "for final_refresh_change"})


SPECS = {
    "every_n_keyframes": ParamSpec("re-segment after N new keyframes (0 = service only)", 0,
                                   100000),
    "idle_run_s": ParamSpec("re-segment after this long without input (0 = off)", 0.0, 3600.0),
    "min_keyframes": ParamSpec("keyframes before the first run", 2, 100000),
    "max_keyframes": ParamSpec("keyframes kept in memory", 2, 1000000, read_only=True),
    "mask_guide_quality": ParamSpec("JPEG quality of the received images kept to place final "
                                    "masks' outlines (0 = none)", 0, 100, read_only=True),
    "mask_stride": ParamSpec("publish masks for every k-th keyframe", 1, 1000),
    "provisional_masks": ParamSpec("provisional masks for keyframes no run covered yet"),
    "provisional_refresh": ParamSpec("re-render provisional masks from a newer OOI cloud"),
    "cloud_runs": ParamSpec("point stages alone on each new SfM cloud between full runs"),
    "cloud_max_duty": ParamSpec("share of the wall time cloud-only runs may take", 0.01, 1.0),
    "refresh_max_duty": ParamSpec("share of the wall time provisional refreshes may take",
                                  0.01, 1.0),
    "incremental_final": ParamSpec("full runs re-mask only the keyframes that need it"),
    "republish_kept": ParamSpec("re-publish kept final masks after each full run"),
    "final_refresh_change": ParamSpec("share of a coarse silhouette's area gained or lost "
                                      "that re-masks a keyframe", 0.0, 1.0),
    "final_refresh_share": ParamSpec("share of the other keyframes re-masked each run anyway",
                                     0.0, 1.0),
    "change_tolerance": ParamSpec("outline shift not counted as change (share of the long "
                                  "side)", 0.0, 0.5),
    "change_check_side": ParamSpec("long side of the coarse silhouettes compared", 16, 4096),
    **KEYFRAME_STORE_SPECS,
    "mask_qos_depth": ParamSpec("history depth of the mask publisher", 1, 10000,
                                read_only=True),
    "segment_worker": ParamSpec("full runs in a worker process (-1 = auto, 0 = none)", -1, 1,
                                read_only=True),
    "segment_worker_nice": ParamSpec("CPU priority below the node's of the worker process",
                                     0, 19, read_only=True),
    "frame_id": ParamSpec("world frame of outputs", read_only=True),
    "method": ParamSpec("segmentation preset", choices=("ours", "paper"), read_only=True),
}


class _Points:
    """An OOI cloud as ``on_cloud`` reads it (from the worker: coordinates and colours)."""

    def __init__(self, xyz: np.ndarray, rgb: np.ndarray) -> None:
        self.xyz, self.rgb = xyz, rgb


class _PointStagesDone(Exception):
    """Raised from ``segment``'s ``on_cloud`` to end a cloud-only run after the point stages."""


def _raise_done() -> None:
    raise _PointStagesDone


def _silhouette_change(old: np.ndarray, new: np.ndarray, tol_px: int) -> float:
    """Area the silhouette gained or lost, beyond ``tol_px`` pixels from the other one, as a
    share of the old silhouette's area (1.0 when the old one was empty and the new is not)."""
    st = np.ones((2 * tol_px + 1, 2 * tol_px + 1), bool) if tol_px > 0 else None
    grow = (lambda m: ndimage.binary_dilation(m, st)) if st is not None else (lambda m: m)
    moved = int((new & ~grow(old)).sum() + (old & ~grow(new)).sum())
    area = int(old.sum())
    return moved / area if area else float(moved > 0)


@dataclasses.dataclass
class _OoiCloud:
    """The OOI cloud masks are rendered from, and what it came from."""

    xyz: np.ndarray  # [N, 3] float64, map frame
    cloud_seq: int  # sequence number of the SfM cloud message it was segmented from
    stamp_ns: int  # that SfM cloud's stamp (its newest keyframe)
    source: str  # "run N" (point stages of full run N) or "cloud-only"


OBS_WAIT_S = 2.0  # s a run waits for the observations published with its SfM cloud
MAX_LOSSY_MARKS = 10_000  # JPEG keyframe marks kept (the newest stamps)
LIVE_REFINE_UPSAMPLE = 1  # refine.upsample of the live node (see __init__)
LIVE_REFINE_MAX_SIDE = 256  # px, without the worker process; see SegmentationNode.__init__


class SegmentationNode(Node):
    """Keeps the keyframes and the latest cloud, segments on demand or every N keyframes.

    Two worker threads: the full run (``_run``: point stages, mesh, masks, refinement) and the
    fast path (``_fast_loop``: provisional masks of new keyframes, cloud-only runs), so that a
    keyframe arriving during a long run still gets a mask and the OOI cloud follows the SfM
    cloud within the point stages' cost.
    """

    def __init__(self, **kwargs) -> None:
        super().__init__("segmentation_node", **kwargs)
        self.cfg = SegNodeConfig()
        ConfigParams(self, self.cfg, specs=SPECS)
        self.seg_cfg: SegmentationConfig = make_config(self.cfg.method)
        self._use_worker = bool(self.cfg.segment_worker if self.cfg.segment_worker >= 0
                                else usable_cores() >= 2)
        if not self._use_worker:
            # full runs in this process: GrabCut on crops reduced to 256 px (the preset allows
            # 400). In the 30 Hz 1280x720 load bench the 400-px crops made in-process runs 2-3x
            # longer and the SfM node dropped keyframes; 256 kept 60/60 (BENCHMARKS, Nodes,
            # session 6). With the worker process 400 px kept up (60/60, final-mask IoU 0.925
            # against 0.876 at 256; session 7). Parameter seg.refine.max_side overrides.
            self.seg_cfg.refine.max_side = min(self.seg_cfg.refine.max_side,
                                               LIVE_REFINE_MAX_SIDE)
        # live: GrabCut on the crop as it is, not enlarged (the preset's refine.upsample 2). In
        # the 30 Hz 1280x720 load bench (working size 640x360) enlarged crops doubled the full
        # runs (29 -> 73 s) and the final masks' latency (median 51 -> 97 s), and at 640x360
        # they gain nothing (stool 0.926 -> 0.924; BENCHMARKS session 25). Parameter
        # seg.refine.upsample overrides.
        self.seg_cfg.refine.upsample = LIVE_REFINE_UPSAMPLE
        ConfigParams(self, self.seg_cfg, prefix="seg.")
        self.diag = Diagnostics(self)
        self.throttle = Throttle(self)
        self._lock = threading.Lock()
        self._obs_arrived = threading.Condition(self._lock)  # on_obs -> a run waiting for it
        self._cloud_pub_lock = threading.Lock()  # ooi/points: newest-wins check + publish
        self.assembler = KeyframeAssembler.from_config(self.diag, self.cfg, self.throttle.warn)
        self.keyframes = self.assembler.keyframes  # {stamp_ns: View}, capture order
        self._points_msg: Optional[PointCloud2] = None
        self._obs_msg: Optional[PointCloud2] = None
        self._points_seq = 0  # SfM cloud messages received
        self._new_since_run = 0
        self._busy = threading.Lock()
        self.runs = 0
        self.last_result = None
        self.last_error: Optional[str] = None
        # fast path state (under self._lock)
        self._ooi: Optional[_OoiCloud] = None  # newest OOI cloud published
        self._mesh = None  # mesh of the last full run (mask renderer for masks.mode "mesh")
        self._final: set[int] = set()  # keyframes whose latest mask is a full run's
        # keyframe -> (run number, coarse silhouette of the OOI cloud) its final mask came from
        self._final_src: dict[int, tuple[int, np.ndarray]] = {}
        # final masks bit-packed ({stamp: (bits, shape)}) for republish_kept
        self._final_bits: dict[int, tuple[np.ndarray, tuple]] = {}
        # the same enlarged to keyframes kept smaller (as published: its outline placed by
        # the received image), so that republishing does not place it again
        self._final_full: dict[int, tuple[np.ndarray, tuple]] = {}
        self._provisional: dict[int, int] = {}  # keyframe -> cloud seq its mask came from
        self._refresh_next_t = 0.0  # monotonic time before which no provisional mask refresh
        self._cloud_claimed = 0  # newest SfM cloud seq a run has taken up (full or cloud-only)
        self._cloud_next_t = 0.0  # monotonic time before which no cloud-only run starts
        self._fast_lock = threading.Lock()  # one fast step at a time
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.cloud_runs = 0
        self._worker: Optional[SegmentationWorker] = None  # started with the first full run
        self.diag.set("segment_worker", "yes" if self._use_worker else "no")
        self.cloud_run_times: collections.deque = collections.deque(maxlen=100)  # s, completed

        rq = reliable_qos(depth=self.cfg.qos_depth)
        self._lossy: set[int] = set()  # stamps of keyframes that came as JPEG
        self.create_subscription(Image, "keyframe/image", self.on_kf_image, rq)
        self.create_subscription(CompressedImage, "keyframe/image/compressed", self.on_kf_lossy,
                                 rq)
        self.create_subscription(CameraInfo, "keyframe/camera_info", self.on_kf_info, rq)
        self.create_subscription(PoseStamped, "keyframe/pose", self.on_kf_pose, rq)
        self.create_subscription(PointCloud2, "sfm/points", self.on_points, latched_qos())
        self.create_subscription(PointCloud2, "sfm/observations", self.on_obs, latched_qos())
        self.pub_points = self.create_publisher(PointCloud2, "ooi/points", latched_qos())
        self.pub_mesh = self.create_publisher(Marker, "ooi/mesh", latched_qos())
        self.pub_mask = self.create_publisher(Image, "ooi/mask",
                                              reliable_qos(depth=self.cfg.mask_qos_depth))
        self._mask_pub_lock = threading.Lock()  # masks come from two threads
        self._mask_batch = 0  # masks published since the subscribers last acknowledged all
        self.create_service(Trigger, "~/segment", self.on_segment_srv)
        self._last_input = time.monotonic()
        self.last_run_newest_ns: Optional[int] = None  # newest keyframe of the last run
        self.create_timer(0.5, self._on_idle_timer)
        self._fast = threading.Thread(target=self._fast_loop, daemon=True)
        self._fast.start()
        self.diag.set("masks_provisional", 0)
        self.diag.set_state("waiting for keyframes and the SfM cloud")

    # ---- inputs -------------------------------------------------------------------------
    def _part(self, stamp_ns: int, key: str, value) -> None:
        if self.assembler.add(stamp_ns, key, value):
            with self._lock:  # a repeated keyframe replaces the old one: its mask is stale
                self._final.discard(stamp_ns)
                self._final_src.pop(stamp_ns, None)
                self._final_bits.pop(stamp_ns, None)
                self._final_full.pop(stamp_ns, None)
            self._new_since_run += 1
            self._last_input = time.monotonic()
            self._wake.set()  # a provisional mask for it
        self._maybe_run()

    @guarded("dropped_keyframe_image")
    def on_kf_image(self, msg: Image) -> None:
        self._part(msgconv.stamp_to_ns(msg.header.stamp), "image", msgconv.image_to_rgb(msg))

    @guarded("dropped_keyframe_image")
    def on_kf_lossy(self, msg: CompressedImage) -> None:
        """Marks the keyframe with this stamp as JPEG pixels (the pixels come raw)."""
        if msgconv.is_lossy(msg):
            with self._lock:
                self._lossy.add(msgconv.stamp_to_ns(msg.header.stamp))
                if len(self._lossy) > 4 * MAX_LOSSY_MARKS:  # marks of long-gone keyframes
                    self._lossy = set(sorted(self._lossy)[-MAX_LOSSY_MARKS:])

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
        with self._lock:
            self._points_msg = msg
            self._points_seq += 1
        self._last_input = time.monotonic()
        self._wake.set()  # a cloud-only run for it
        self._maybe_run()

    @guarded("dropped_cloud")
    def on_obs(self, msg: PointCloud2) -> None:
        with self._lock:
            self._obs_msg = msg
            self._obs_arrived.notify_all()

    def _observations_for(self, points: PointCloud2) -> Optional[PointCloud2]:
        """The observations message published with ``points`` (same header stamp).

        The SfM node publishes the points, then their observations; a run started by the
        points message waits up to ``OBS_WAIT_S`` for the pair. Observations index the points
        of their own cloud, so another cloud's would attach to the wrong points: without the
        pair the run goes on without observations (counted as ``cloud_without_observations``).
        No wait when no observations were ever received (a source publishing points only).
        """
        want = points.header.stamp
        deadline = time.monotonic() + OBS_WAIT_S
        with self._lock:
            while True:
                obs = self._obs_msg
                if obs is None:
                    return None
                if obs.header.stamp == want:
                    return obs
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._obs_arrived.wait(left)
        self.diag.count("cloud_without_observations")
        self.throttle.warn("obs", "segment: no observations with the SfM cloud's stamp "
                                  f"{msgconv.stamp_to_ns(want)} within {OBS_WAIT_S:g} s: "
                                  "running without per-point visibility")
        return None

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

    def trigger(self, all_masks: bool = False) -> bool:
        """Starts a segmentation run in the background unless one is running.

        ``all_masks``: re-mask every keyframe even with ``incremental_final``.
        """
        if not self._busy.acquire(blocking=False):
            return False
        self._new_since_run = 0
        threading.Thread(target=self._run, args=(all_masks,), daemon=True).start()
        return True

    def _inputs(self, observations: bool = True) -> Optional[tuple]:
        """(views, {stamp: (full camera, factor)}, SfmCloud, cloud seq, cloud stamp) of now.

        The cloud's observations come in source pixels; they are scaled to the kept
        (downscaled) views (``observations=False``: none; the point stages do not use them).
        None when the SfM cloud or two keyframes are missing.
        """
        with self.assembler.lock:
            views = list(self.assembler.keyframes.values())
            full = {v.stamp_ns: (self.assembler.full_cameras[v.stamp_ns],
                                 self.assembler.factors[v.stamp_ns]) for v in views}
        with self._lock:
            points, seq = self._points_msg, self._points_seq
            for v in views:
                v.compressed = v.stamp_ns in self._lossy
        if points is None or len(views) < 2:
            return None
        obs = self._observations_for(points) if observations else None
        cloud = msgconv.pointcloud2_to_sfm_cloud(points, obs, views)
        if len(cloud.obs_xy) and any(f > 1 for _c, f in full.values()):
            f = np.array([full[v.stamp_ns][1] for v in views], np.float64)
            cloud.obs_xy = ((cloud.obs_xy + 0.5) / f[cloud.obs_view, None]
                            - 0.5).astype(np.float32)
            cloud.error = np.asarray(cloud.error) / float(np.median(f))
        return views, full, cloud, seq, msgconv.stamp_to_ns(points.header.stamp)

    def _publish_cloud(self, xyz: np.ndarray, rgb: np.ndarray, seq: int, stamp_ns: int,
                       source: str) -> bool:
        """Publishes ``ooi/points`` unless a newer SfM cloud's OOI went out already.

        The check, the update and the publish are one step (``_cloud_pub_lock``): the full
        run and the fast cloud-only run both call this, and an older cloud published after
        a newer one would stay latched."""
        with self._cloud_pub_lock:
            with self._lock:
                if self._ooi is not None and self._ooi.cloud_seq > seq:
                    return False
                self._ooi = _OoiCloud(np.asarray(xyz, np.float64), seq, stamp_ns, source)
            self.pub_points.publish(msgconv.xyzrgb_to_pointcloud2(
                xyz, rgb, msgconv.ns_to_stamp(stamp_ns), self.cfg.frame_id))
        self.diag.count("ooi_cloud_updates")
        self.diag.set("ooi_cloud", f"{len(xyz)} points from the SfM cloud of {stamp_ns} "
                                   f"({source})")
        self._wake.set()  # keyframes still without a mask can get one now
        return True

    def _run(self, all_masks: bool = False) -> None:
        try:
            t0 = time.monotonic()
            got = self._inputs()
            if got is None:
                self.throttle.warn("segnodata", "segment: need the SfM cloud and >= 2 keyframes")
                return
            views, full, cloud, seq, cloud_stamp = got
            with self._lock:
                self._cloud_claimed = max(self._cloud_claimed, seq)
            capture = Capture(views=views, source="ros")
            run_no = self.runs + 1
            self.diag.set_state(f"segmenting {len(cloud)} points over {len(views)} keyframes")
            got_cloud = []

            def on_cloud(ooi) -> None:
                got_cloud.append(ooi)
                self.diag.timing("segment_cloud", time.monotonic() - t0)
                self._publish_cloud(ooi.xyz, ooi.rgb, seq, cloud_stamp, f"run {run_no}")

            worker = self._get_worker()

            keys, sil, prepass_s = None, None, None
            if self.cfg.incremental_final and not all_masks:
                # the point stages first (deterministic: the same OOI cloud as the run's), to
                # choose the keyframes whose masks this run makes
                t_pts = time.monotonic()
                if worker is not None:
                    xyz, rgb = self._in_worker(worker.point_stages, views, cloud, self.seg_cfg)
                    on_cloud(_Points(xyz, rgb))
                else:
                    try:
                        segment(capture, cloud, self.seg_cfg,
                                on_cloud=lambda ooi: (on_cloud(ooi), _raise_done()))
                    except _PointStagesDone:
                        pass
                prepass_s = time.monotonic() - t_pts
                self.diag.timing("segment_points_prepass", prepass_s)
                keys, sil = self._keys_to_mask(views, got_cloud[0].xyz)
                if not keys:  # every keyframe keeps its final mask (final_refresh_share 0)
                    self.runs += 1
                    self.last_run_newest_ns = max(v.stamp_ns for v in views)
                    self.diag.set("masks_refined_last_run", 0)
                    self.diag.set("masks_reused_last_run", len(views))
                    self.diag.count("masks_reused", len(views))
                    self.diag.set_state(f"run {self.runs}: no keyframe needed a new mask")
                    return
            # the final masks of the keyframes this run does not re-mask (what the hull
            # additions need of them instead of refining them again)
            ctx = self._context_masks(views, keys) if keys is not None else None
            if worker is not None:
                result = self._in_worker(worker.segment, views, cloud, self.seg_cfg,
                                         mask_keys=keys, context_masks=ctx)
                if keys is None:
                    on_cloud(result.ooi_cloud)
            else:
                result = segment(capture, cloud, self.seg_cfg,
                                 on_cloud=None if keys is not None else on_cloud,
                                 mask_keys=keys, context_masks=ctx)
            self.last_result = result
            self.runs += 1
            self.last_run_newest_ns = max(v.stamp_ns for v in views)
            self.diag.timing("segment", time.monotonic() - t0)
            if sil is None:
                sil = self._coarse_silhouettes(views, result.ooi_cloud.xyz)
            self._publish(result, views, full, cloud_stamp, sil)
            reused = len(views) - len(result.masks)
            self.diag.set("masks_refined_last_run", len(result.masks))
            self.diag.set("masks_reused_last_run", reused)
            self.diag.count("masks_reused", reused)
            st = result.params.get("stability") if hasattr(result, "params") else None
            if st and st.get("draws"):
                # how close the OOI choice is (seg/stability.py): re-runs that chose otherwise
                self.diag.set("ooi_stability_flips_last_run", f"{st['flips']} of {st['draws']}")
            for w in getattr(result, "warnings", []) or []:
                self.throttle.warn("segwarn:" + w[:40], f"segmentation: {w}")
            d = self.diag.values
            why = (f" (new {d.get('masks_new_last_run')}, changed "
                   f"{d.get('masks_changed_last_run')}, rotated "
                   f"{d.get('masks_rotated_last_run')})" if keys is not None else "")
            stages = ", ".join(f"{k} {v:.1f}" for k, v in result.timings.items())
            if prepass_s is not None:
                stages = f"point stages first {prepass_s:.1f}, " + stages
            plane_s = (result.params.get("refine") or {}).get("plane_check_s")
            if plane_s is not None:
                stages += f" (plane check {plane_s:.1f})"
            for k, v in result.timings.items():
                self.diag.timing(f"segment_{k}", v)
            self.get_logger().info(
                f"run {self.runs}: masked {len(result.masks)} of {len(views)} keyframes{why}, "
                f"kept {reused} final masks of earlier runs; {time.monotonic() - t0:.1f} s "
                f"[{stages}]")
            self.diag.set_state(f"run {self.runs}: {len(result.ooi_cloud)} OOI points, "
                                f"{len(result.masks)} masks made, {reused} final masks of "
                                f"earlier runs kept")
        except Exception as exc:  # noqa: BLE001 — the node keeps running
            self.diag.count("error_segmentation")
            self.last_error = traceback.format_exc()
            self.throttle.warn("segfail", f"segmentation failed: {type(exc).__name__}: {exc}")
        finally:
            self._busy.release()

    def _context_masks(self, views: list[View], keys: list[str]) -> dict:
        """{key: final mask} (working size) of the kept keyframes not in ``keys``."""
        keyset = set(keys)
        with self._lock:
            bits = {v.key: self._final_bits.get(v.stamp_ns) for v in views
                    if v.key not in keyset}
        return {k: np.unpackbits(b[0], count=int(np.prod(b[1]))).reshape(b[1]).astype(bool)
                for k, b in bits.items() if b is not None}

    def _get_worker(self) -> Optional[SegmentationWorker]:
        """The full runs' worker process (started on first use); None = run in this thread."""
        if not self._use_worker:
            return None
        if self._worker is None or not self._worker.alive:
            if self._worker is not None:
                self._worker.close(timeout=1.0)
            try:
                self._worker = SegmentationWorker(nice=int(self.cfg.segment_worker_nice))
                self.diag.set("segment_worker_nice", self._worker.nice)
            except OSError as exc:  # no interpreter to start, no processes left
                self._worker_failed(exc)
                return None
        return self._worker

    def _worker_failed(self, exc: BaseException) -> None:
        self.diag.count("segment_worker_failures")
        self.throttle.warn("segworker", f"segmentation worker process failed ({exc}); full "
                                        f"runs go on in the node's own thread")
        self._use_worker = False
        self.diag.set("segment_worker", f"failed: {exc}")

    def _in_worker(self, fn, *args, **kwargs):
        """``fn`` (a ``SegmentationWorker`` method); if the worker dies, the same call in this
        thread (and every later run: counted, logged)."""
        try:
            return fn(*args, **kwargs)
        except WorkerDied as exc:
            if self._stop.is_set():  # closed under a running job: the node is going
                raise
            self._worker_failed(exc)
        views, cloud, cfg = args
        capture = Capture(views=views, source="ros")
        if fn.__name__ == "point_stages":
            from ..seg.worker import point_stages
            ooi = point_stages(capture, cloud, cfg)
            return ooi.xyz, ooi.rgb
        return segment(capture, cloud, cfg, **kwargs)

    def _publish_mask(self, mask: np.ndarray, stamp_ns: int, full: tuple,
                      provisional_from: Optional[int] = None, again: bool = False) -> bool:
        """Publishes one keyframe's mask at its own size and records whether it is final.

        ``provisional_from`` (the sequence number of the SfM cloud whose OOI cloud it was
        rendered from) marks a provisional mask; it is dropped when the keyframe has a final
        mask already or was evicted. The check and the publication happen under one lock, so
        a provisional mask never goes out after the final one of the same keyframe.
        ``again``: the keyframe's kept final mask sent again (``republish_kept``): the
        enlarged mask published before is reused, not enlarged again.
        """
        cam, f = full
        final = provisional_from is None
        with self._lock:
            kept = self._final_full.get(stamp_ns) if again and f > 1 else None
        if kept is not None:  # ``again``: the kept final mask, as published before
            mask = np.unpackbits(kept[0], count=int(np.prod(kept[1]))).reshape(kept[1])
            mask = mask.astype(bool)
        else:
            # a final mask's outline is placed by the received image (provisional ones are
            # quick previews: enlarged only)
            guide = self.assembler.guide(stamp_ns) if final and f > 1 else None
            mask = upscale_mask(np.asarray(mask, bool), f, cam.width, cam.height, guide=guide)
            if final and f > 1:
                with self._lock:
                    self._final_full[stamp_ns] = (np.packbits(mask), mask.shape)
        msg = msgconv.mask_to_image(mask, msgconv.ns_to_stamp(stamp_ns),
                                    mask_frame_id(provisional_from is not None))
        with self._mask_pub_lock:
            if self._mask_batch >= self.cfg.mask_qos_depth:
                # the middleware keeps only mask_qos_depth masks: let the subscribers catch
                # up rather than overwrite masks they have not acknowledged yet
                if not self.pub_mask.wait_for_all_acked(Duration(seconds=10.0)):
                    self.diag.count("mask_ack_timeouts")
                    self.throttle.warn("maskack", "a mask subscriber did not acknowledge "
                                                  "within 10 s; it may miss masks")
                self._mask_batch = 0
            with self._lock:
                if provisional_from is None:
                    self._provisional.pop(stamp_ns, None)
                    self._final.add(stamp_ns)
                elif stamp_ns in self._final or stamp_ns not in self.keyframes:
                    return False  # a run covered it meanwhile, or it was evicted
                else:
                    self._provisional[stamp_ns] = provisional_from
            self.pub_mask.publish(msg)
            self._mask_batch += 1
        return True

    def _publish(self, result, views: list[View], full: dict, cloud_stamp: int,
                 sil: dict) -> None:
        """Publishes the run's mesh and the masks it made, then (``republish_kept``) the final
        masks of earlier runs that keyframes it did not re-mask keep."""
        stamp = msgconv.ns_to_stamp(cloud_stamp)
        if result.mesh is not None and not result.mesh.is_empty:
            self.pub_mesh.publish(msgconv.mesh_to_marker(result.mesh, stamp, self.cfg.frame_id))
        with self._lock:
            self._mesh = result.mesh
        for i, v in enumerate(views):
            if i % self.cfg.mask_stride:
                continue
            mask = result.masks.get(v.key)
            if mask is None:
                with self._lock:
                    kept = v.stamp_ns in self._final
                if not kept:
                    self.diag.count("masks_missing")
                continue
            mask = np.asarray(mask, bool)
            if self._publish_mask(mask, v.stamp_ns, full[v.stamp_ns]):
                with self._lock:
                    self._final_src[v.stamp_ns] = (self.runs, sil.get(v.stamp_ns))
                    self._final_bits[v.stamp_ns] = (np.packbits(mask), mask.shape)
            self.diag.count("masks_published")
        if self.cfg.republish_kept:
            # the kept final masks after the new ones: every keyframe's mask follows the mesh
            for i, v in enumerate(views):
                if i % self.cfg.mask_stride or v.key in result.masks:
                    continue
                with self._lock:
                    bits = self._final_bits.get(v.stamp_ns)
                if bits is None:
                    continue
                mask = np.unpackbits(bits[0], count=int(np.prod(bits[1]))).reshape(bits[1])
                if self._publish_mask(mask.astype(bool), v.stamp_ns, full[v.stamp_ns],
                                      again=True):
                    self.diag.count("masks_republished")
        self._report_provisional()

    def _coarse_silhouettes(self, views: list[View], xyz: np.ndarray) -> dict:
        """{stamp: bool [h, w]} the raw point silhouette of ``xyz`` in each view at
        ``change_check_side`` pixels on the long side (the pipeline's own splat renderer,
        no refinement): what tells whether a view's mask would change."""
        small = []
        for v in views:
            f = max(1, int(round(max(v.camera.width, v.camera.height)
                                 / self.cfg.change_check_side)))
            small.append(View(v.key, v.stamp_ns, downscale_camera(v.camera, f), v.pose))
        mcfg = dataclasses.replace(self.seg_cfg.masks, hull_consistency=False, mode="points")
        empty = TriMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int32))
        masks, _p = render_masks(small, mcfg, empty, np.asarray(xyz, np.float64))
        return {v.stamp_ns: masks[v.key] for v in small}

    def _keys_to_mask(self, views: list[View], xyz: np.ndarray) -> tuple[list[str], dict]:
        """Keys of the keyframes this run re-masks: those without a final mask, those whose
        coarse silhouette changed by more than ``final_refresh_change`` since their final
        mask was made, and ``final_refresh_share`` of the rest, longest-final first; and the
        coarse silhouettes of ``xyz`` ({stamp: mask}) it compared."""
        sil = self._coarse_silhouettes(views, xyz)
        tol = int(round(self.cfg.change_tolerance * self.cfg.change_check_side))
        with self._lock:
            src = {v.stamp_ns: self._final_src.get(v.stamp_ns) for v in views
                   if v.stamp_ns in self._final}
        new, changed, rest = [], [], []
        for i, v in enumerate(views):
            if i % self.cfg.mask_stride:
                continue  # no mask is published for it
            old = src.get(v.stamp_ns)
            if old is None or old[1] is None or old[1].shape != sil[v.stamp_ns].shape:
                new.append(v)
                continue
            change = _silhouette_change(old[1], sil[v.stamp_ns], tol)
            (changed if change > self.cfg.final_refresh_change else rest).append((old[0], v))
        n_rot = int(np.ceil(self.cfg.final_refresh_share * len(rest))) if rest else 0
        rest.sort(key=lambda rv: rv[0])  # stable: oldest run first, then capture order
        rotated = [v for _r, v in rest[:n_rot]]
        self.diag.set("masks_new_last_run", len(new))
        self.diag.set("masks_changed_last_run", len(changed))
        self.diag.set("masks_rotated_last_run", len(rotated))
        keys = [v.key for v in new] + [v.key for _r, v in changed] + [v.key for v in rotated]
        return keys, sil

    # ---- fast path: provisional masks and cloud-only runs -----------------------------------
    def _fast_loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(timeout=0.5)
            self._wake.clear()
            if self._stop.is_set():
                break
            try:
                self.fast_step()
            except Exception as exc:  # noqa: BLE001 — the worker keeps running
                self.diag.count("error_fast_path")
                self.last_error = traceback.format_exc()
                self.throttle.warn("fastfail", f"provisional mask / cloud-only run failed: "
                                               f"{type(exc).__name__}: {exc}")

    def fast_step(self) -> None:
        """Provisional masks for keyframes without one, then a cloud-only run if one is due.

        Called by the fast-path thread whenever a keyframe or an SfM cloud arrives (and every
        0.5 s); tests call it directly.
        """
        with self._fast_lock:
            self._provisional_step()
            if self._cloud_step():
                self._provisional_step()

    def _provisional_step(self) -> int:
        """Renders and publishes a provisional mask for every kept keyframe that has no mask,
        newest first; then, when due, re-renders provisional masks made from an older OOI
        cloud (early clouds from few keyframes are poor), newest first, yielding to new
        keyframes and spending at most ``refresh_max_duty`` of the wall time on it."""
        if not self.cfg.provisional_masks:
            return 0
        with self._lock:
            ooi, mesh = self._ooi, self._mesh
        if ooi is None or len(ooi.xyz) == 0:
            return 0
        with self.assembler.lock:
            kept = [(v, (self.assembler.full_cameras[s], self.assembler.factors[s]))
                    for s, v in reversed(self.assembler.keyframes.items())]
        with self._lock:
            new = [(v, f) for v, f in kept
                   if v.stamp_ns not in self._final and v.stamp_ns not in self._provisional]
            stale = [(v, f) for v, f in kept
                     if self._provisional.get(v.stamp_ns, ooi.cloud_seq) < ooi.cloud_seq]
        if not self.cfg.provisional_refresh or time.monotonic() < self._refresh_next_t:
            stale = []
        if not new and not stale:
            return 0
        mcfg = dataclasses.replace(self.seg_cfg.masks, hull_consistency=False)
        if mcfg.mode == "mesh" and (mesh is None or mesh.is_empty):
            mcfg.mode = "points"  # as the pipeline does without a mesh
        if mesh is None:
            mesh = TriMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int32))
        done = 0
        for refresh, todo in ((False, new), (True, stale)):
            t_start = time.monotonic()
            for v, full in todo:
                if refresh and self._wake.is_set():
                    break  # a new keyframe or cloud came: it goes first (next step)
                t0 = time.monotonic()
                masks, _p = render_masks([v], mcfg, mesh, ooi.xyz)
                if self._publish_mask(masks[v.key], v.stamp_ns, full,
                                      provisional_from=ooi.cloud_seq):
                    done += 1
                    self.diag.count("masks_provisional_refreshed" if refresh
                                    else "masks_provisional_published")
                    self.diag.timing("provisional_mask", time.monotonic() - t0)
            if refresh and todo:
                self._refresh_next_t = t_start + (time.monotonic() - t_start) \
                    / self.cfg.refresh_max_duty
        self._report_provisional()
        return done

    def _cloud_step(self) -> bool:
        """A cloud-only run on the newest SfM cloud if no run took it up and one is due."""
        if not self.cfg.cloud_runs or time.monotonic() < self._cloud_next_t:
            return False
        with self._lock:
            due = self._points_seq > self._cloud_claimed
        if not due or len(self.keyframes) < self.cfg.min_keyframes:
            return False
        t0 = time.monotonic()
        got = self._inputs(observations=False)
        if got is None:
            return False
        views, _full, cloud, seq, cloud_stamp = got
        with self._lock:
            if seq <= self._cloud_claimed:
                return False
            self._cloud_claimed = seq
        published = []

        def on_cloud(ooi) -> None:
            published.append(
                self._publish_cloud(ooi.xyz, ooi.rgb, seq, cloud_stamp, "cloud-only"))
            raise _PointStagesDone

        try:
            segment(Capture(views=views, source="ros"), cloud, self.seg_cfg, on_cloud=on_cloud)
        except _PointStagesDone:
            self.cloud_run_times.append(time.monotonic() - t0)
            self.diag.timing("cloud_run_median", float(np.median(self.cloud_run_times)))
        except InputError as exc:  # e.g. too few points yet: the full run will say so too
            self.diag.count("cloud_runs_failed")
            self.throttle.warn("cloudrun", f"cloud-only run: {exc}")
        dt = time.monotonic() - t0
        self._cloud_next_t = t0 + dt / self.cfg.cloud_max_duty
        self.cloud_runs += 1
        self.diag.count("cloud_runs")
        self.diag.timing("cloud_run", dt)
        return bool(published and published[0])

    def _report_provisional(self) -> None:
        with self.assembler.lock:
            kept = set(self.assembler.keyframes)
        with self._lock:
            for s in [s for s in self._provisional if s not in kept]:
                del self._provisional[s]  # evicted keyframes
            self._final &= kept
            for s in [s for s in self._final_src if s not in kept]:
                del self._final_src[s]
            for s in [s for s in self._final_bits if s not in kept]:
                del self._final_bits[s]
            for s in [s for s in self._final_full if s not in kept]:
                del self._final_full[s]
            prov = sorted(self._provisional)
        self.diag.set("masks_provisional", len(prov))
        shown = ",".join(str(s) for s in prov[-10:])
        self.diag.set("provisional_mask_stamps",
                      (f"+{len(prov) - 10} older," if len(prov) > 10 else "") + shown)

    def provisional_stamps(self) -> list[int]:
        """Keyframes whose latest published mask is provisional (no run covered them yet)."""
        with self._lock:
            return sorted(s for s in self._provisional if s in self.keyframes)

    def close(self) -> None:
        """Stops the fast-path thread (a running full segmentation is a daemon thread) and
        the worker process."""
        self._stop.set()
        self._wake.set()
        if self._fast.is_alive() and self._fast is not threading.current_thread():
            self._fast.join(timeout=10.0)
        worker, self._worker = self._worker, None
        if worker is not None:
            worker.close(timeout=5.0)

    def destroy_node(self) -> None:
        self.close()
        super().destroy_node()

    def on_segment_srv(self, request, response):
        if self._points_msg is None or len(self.keyframes) < 2:
            response.success = False
            response.message = (f"not ready: cloud={'yes' if self._points_msg else 'no'}, "
                                f"keyframes={len(self.keyframes)} (need the SfM cloud and >= 2)")
            return response
        started = self.trigger(all_masks=True)
        response.success = started
        response.message = "segmentation started" if started else "a run is already in progress"
        return response


def main(args=None) -> None:
    run_node(SegmentationNode, args)


if __name__ == "__main__":
    main()
