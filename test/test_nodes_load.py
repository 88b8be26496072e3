"""Nodes under load, in miniature: downscaled working copies that stay geometrically exact,
keyframe memory bounded in bytes with counted evictions, an image callback that decodes only
keyframe candidates, pose interpolation across lost pose messages, and SfM observations
published in the source image's pixels although SfM ran on a downscaled copy.

The node callbacks are called directly with real messages (no transport in between), so the
counts are exact; the transport is exercised by the pipeline and play/record tests.
"""

import time
import uuid

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter

from ooi_seg_ros import msgconv
from ooi_seg_ros.core.geometry import look_at, project
from ooi_seg_ros.core.types import CameraIntrinsics, Pose
from ooi_seg_ros.nodes.common import (Diagnostics, KeyframeAssembler, downscale_camera,
                                      downscale_factor, downscale_rgb, scale_pixels,
                                      upscale_mask)
from ooi_seg_ros.nodes.segmentation_node import SegmentationNode
from ooi_seg_ros.nodes.sfm_node import SfmNode


@pytest.fixture
def ctx():
    c = Context()
    rclpy.init(context=c)
    yield c
    rclpy.shutdown(context=c)


def _ns() -> str:
    return "/l_" + uuid.uuid4().hex[:8]


def test_downscale_factor_from_image_size():
    assert downscale_factor(320, 240, 400_000) == 1
    assert downscale_factor(1280, 720, 400_000) == 2  # 640x360
    assert downscale_factor(1920, 1080, 400_000) == 3  # 640x360
    assert downscale_factor(4000, 3000, 400_000) == 6
    assert downscale_factor(1280, 720, 0) == 1  # 0: keep full resolution


@pytest.mark.parametrize("f", [2, 3])
def test_downscaled_camera_and_image_agree(f):
    cam = CameraIntrinsics(97, 61, 80.0, 82.0, 47.3, 29.8)
    small = downscale_camera(cam, f)
    assert (small.width, small.height) == (97 // f, 61 // f)
    # a bright f x f block of the source is one bright pixel of the copy, at its own centre
    img = np.zeros((61, 97, 3), np.uint8)
    i, j = 7, 11
    img[f * i:f * i + f, f * j:f * j + f] = 255
    out = downscale_rgb(img, f)
    assert out.shape == (61 // f, 97 // f, 3)
    assert tuple(np.argwhere(out[..., 0] == 255)[0]) == (i, j)
    centre_src = np.array([[f * j + (f - 1) / 2, f * i + (f - 1) / 2]])
    assert np.allclose((centre_src + 0.5) / f - 0.5, [[j, i]])
    # a 3D point projects to the same place in both cameras, up to the pixel scale
    pose = look_at(np.array([0.0, -4.0, 1.0]), np.zeros(3))
    pts = np.array([[0.3, 0.2, 0.1], [-0.5, 0.1, 0.4]])
    uv_full, _ = project(pts, cam, pose)
    uv_small, _ = project(pts, small, pose)
    assert np.allclose(scale_pixels(uv_small, f), uv_full, atol=1e-4)


def test_upscale_mask_is_smooth_and_sized():
    m = np.zeros((10, 16), bool)
    m[2:5, 3:9] = True
    up = upscale_mask(m, 3, 50, 31)  # source 50x31 kept at 16x10 (remainder cropped)
    assert up.shape == (31, 50)
    # the blocks' own pixels (source 9..26 x 6..14), outline within a pixel of theirs
    assert up[7:14, 10:26].all() and not up[:5].any() and not up[:, :8].any()
    assert abs(int(up.sum()) - 9 * 18) <= 2 * (9 + 18)
    assert upscale_mask(m, 1, 16, 10) is m
    # a diagonal edge enlarged: no factor-sized steps (each row's edge moves ~1 px per row)
    d = np.tri(20, 20, dtype=bool)
    edge = upscale_mask(d, 4, 80, 80).argmin(axis=1)
    assert np.abs(np.diff(edge[8:72])).max() <= 2


def _kf(assembler, stamp, pose, size=(48, 64)):
    cam = CameraIntrinsics(size[1], size[0], 50.0, 50.0, size[1] / 2 - 0.5, size[0] / 2 - 0.5)
    rgb = np.full(size + (3,), stamp % 251, np.uint8)
    assembler.add(stamp, "info", cam)
    assembler.add(stamp, "pose", pose)
    return assembler.add(stamp, "image", rgb)


def test_diagnostics_publish_while_counters_appear_in_another_thread(ctx):
    """The diagnostics timer iterates the counters while worker threads add new keys (the
    SfM node's skipped_<reason>, now through ``set_count`` under the lock). A smoke test:
    the unlocked writes it replaced did not fail it either (the window is a few bytecodes),
    the fix rests on every write taking the lock."""
    import threading

    node = Node("diag", context=ctx, namespace=_ns())
    try:
        diag = Diagnostics(node, period_s=3600.0)
        stop = threading.Event()

        def add():
            for i in range(300):
                if stop.is_set():
                    return
                diag.set_count(f"skipped_{i}", i)
                diag.count(f"dropped_{i}")
                time.sleep(0.0005)

        t = threading.Thread(target=add)
        t.start()
        published = 0
        try:
            while t.is_alive():
                diag.publish()
                published += 1
        finally:
            stop.set()
            t.join()
        snap = diag.snapshot()["counters"]
        assert published > 10 and len(snap) == 600 and snap["skipped_299"] == 299
    finally:
        node.destroy_node()


def test_keyframe_memory_is_bounded_in_bytes(ctx):
    node = Node("asm", context=ctx, namespace=_ns())
    try:
        diag = Diagnostics(node)
        evicted = []
        one = 24 * 32 * 3  # a 64x48 image kept at half size
        asm = KeyframeAssembler(diag, max_keyframes=1000, max_bytes=5 * one, downscale=2,
                                evict_policy="oldest", on_evict=evicted.append)
        for k in range(12):
            assert _kf(asm, 100 + k, look_at(np.array([4.0, 0.1 * k, 1.0]), np.zeros(3)))
        assert len(asm) == 5 and asm.nbytes == 5 * one
        assert list(asm.keyframes) == list(range(107, 112))  # oldest went first
        assert evicted == list(range(100, 107))
        assert diag.counters["dropped_keyframe_budget"] == 7
        v = asm.keyframes[111]
        assert v.image.shape == (24, 32, 3) and v.camera.width == 32
        assert asm.full_cameras[111].width == 64 and asm.factors[111] == 2
    finally:
        node.destroy_node()


def test_kept_guides_count_in_the_budget_and_go_with_their_keyframe(ctx):
    """Keyframes kept smaller keep a JPEG of the received image (to place final masks'
    outlines); its bytes count in the budget and leave with the keyframe."""
    node = Node("asmg", context=ctx, namespace=_ns())
    try:
        diag = Diagnostics(node)
        one = 24 * 32 * 3
        asm = KeyframeAssembler(diag, max_keyframes=1000, max_bytes=4 * one, downscale=2,
                                evict_policy="oldest", guide_quality=90)
        for k in range(6):
            assert _kf(asm, 100 + k, look_at(np.array([4.0, 0.1 * k, 1.0]), np.zeros(3)))
        assert sorted(asm.guides) == sorted(asm.keyframes) and len(asm) < 4
        assert asm.nbytes == len(asm) * one + sum(len(g) for g in asm.guides.values())
        g = asm.guide(105)
        assert g.shape == (48, 64, 3) and np.abs(g.astype(int) - 105).max() <= 2
        assert asm.guide(100) is None  # evicted
        full = KeyframeAssembler(diag, max_keyframes=10, downscale=1, guide_quality=95)
        assert _kf(full, 7, look_at(np.array([4.0, 0.0, 1.0]), np.zeros(3)))
        assert full.guides == {} and full.guide(7) is None  # kept whole: nothing to place
        off = KeyframeAssembler(diag, max_keyframes=10, downscale=2)
        assert _kf(off, 7, look_at(np.array([4.0, 0.0, 1.0]), np.zeros(3)))
        assert off.guides == {} and off.nbytes == one
    finally:
        node.destroy_node()


def test_redundant_keyframe_is_evicted_first(ctx):
    node = Node("asm2", context=ctx, namespace=_ns())
    try:
        diag = Diagnostics(node)
        one = 48 * 64 * 3
        asm = KeyframeAssembler(diag, max_keyframes=1000, max_bytes=4 * one, downscale=1)
        # an orbit of four views, then one almost where the second was
        angles = [0, 90, 180, 270]
        for k, a in enumerate(angles):
            c = 4 * np.array([np.cos(np.radians(a)), np.sin(np.radians(a)), 0.3])
            _kf(asm, 10 + k, look_at(c, np.zeros(3)))
        c = 4 * np.array([np.cos(np.radians(92)), np.sin(np.radians(92)), 0.3])
        _kf(asm, 20, look_at(c, np.zeros(3)))
        assert list(asm.keyframes) == [10, 12, 13, 20]  # the older of the near pair went
        assert diag.counters["dropped_keyframe_budget"] == 1
    finally:
        node.destroy_node()


def test_mismatched_keyframe_is_dropped_and_counted(ctx):
    node = Node("asm3", context=ctx, namespace=_ns())
    try:
        diag = Diagnostics(node)
        asm = KeyframeAssembler(diag, max_keyframes=10)
        cam = CameraIntrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
        asm.add(5, "info", cam)
        asm.add(5, "pose", Pose.identity())
        assert not asm.add(5, "image", np.zeros((40, 64, 3), np.uint8))
        assert len(asm) == 0 and diag.counters["dropped_keyframe_size_mismatch"] == 1
    finally:
        node.destroy_node()


def _orbit_pose(k: int, n: int) -> Pose:
    a = 2 * np.pi * k / n
    return look_at(np.array([4 * np.cos(a), 4 * np.sin(a), 1.5]), np.zeros(3))


def test_sfm_node_decodes_candidates_only_and_bridges_lost_poses(ctx):
    node = SfmNode(context=ctx, namespace=_ns(), parameter_overrides=[
        Parameter("keyframes.rotation_deg", value=20.0)])
    try:
        cam = CameraIntrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
        node.on_camera_info(msgconv.intrinsics_to_camera_info(cam, msgconv.ns_to_stamp(0)))
        rng = np.random.default_rng(0)
        period = 33_333_333  # 30 Hz
        n = 90
        lost = set(range(20, 24)) | {50, 51}  # bursts of 4 and 2 lost pose messages
        for k in range(n):
            stamp = 10 ** 9 + k * period
            pose = _orbit_pose(k, 240)  # 1.5 degrees per frame
            if k not in lost:
                node.on_pose(msgconv.pose_to_pose_stamped(pose, stamp, "map"))
            rgb = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
            node.on_image(msgconv.rgb_to_image(rgb, stamp, "cam"))
        node.on_pose(msgconv.pose_to_pose_stamped(_orbit_pose(n, 240), 10 ** 9 + n * period,
                                                  "map"))
        c = node.diag.counters
        assert c["images"] == n
        assert c.get("dropped_no_pose", 0) == 0, c  # lost poses were bridged
        assert node.pose_tolerance_ns() == 5 * period  # (pose_max_lost + 1) periods
        seen = node.selector.seen
        assert seen == n
        # only frames that passed the motion test were decoded (for the blur test)
        decoded = c["images_decoded"]
        assert decoded == node.selector.accepted + node.selector.dropped.get("blurry", 0)
        assert decoded < n / 2, (decoded, node.selector.report())
        # a gap longer than the tolerance is not bridged: counted, not guessed
        s0 = 10 ** 9 + (n + 20) * period
        node.on_image(msgconv.rgb_to_image(np.zeros((48, 64, 3), np.uint8), s0, "cam"))
        node.on_pose(msgconv.pose_to_pose_stamped(_orbit_pose(n + 30, 240), s0 + 10 * period,
                                                  "map"))
        assert c["dropped_no_pose"] == 1
        # nor is a short gap across which the camera jumped (half a keyframe step or more)
        s1 = s0 + 11 * period
        node.on_image(msgconv.rgb_to_image(np.zeros((48, 64, 3), np.uint8), s1, "cam"))
        node.on_pose(msgconv.pose_to_pose_stamped(_orbit_pose(n + 50, 240), s1 + period,
                                                  "map"))
        assert c["dropped_pose_jump"] == 1
    finally:
        node.close()
        node.destroy_node()


def test_sfm_node_forwards_jpeg_keyframes_on_the_compressed_topic(ctx):
    """A keyframe that came as JPEG goes out raw on ``keyframe/image`` (as before) and
    unchanged on ``keyframe/image/compressed`` (the segmentation's mark); png does not."""
    from ooi_seg_ros.core.types import View

    node = SfmNode(context=ctx, namespace=_ns())
    try:
        sent = {"raw": [], "jpeg": []}
        node.pub_kf_image.publish = sent["raw"].append
        node.pub_kf_lossy.publish = sent["jpeg"].append
        cam = CameraIntrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
        rgb = np.zeros((48, 64, 3), np.uint8)
        for k, fmt in enumerate(("jpeg", "png")):
            stamp = 10 ** 9 + k
            msg = msgconv.rgb_to_compressed(rgb, stamp, fmt=fmt)
            view = View(str(stamp), stamp, cam, _orbit_pose(k, 12), rgb)
            node._publish_keyframe(view, msg)
        assert len(sent["raw"]) == 2 and [m.format for m in sent["jpeg"]] == ["jpeg"]
        assert msgconv.stamp_to_ns(sent["jpeg"][0].header.stamp) == 10 ** 9
    finally:
        node.close()
        node.destroy_node()


@pytest.mark.slow
def test_sfm_on_downscaled_copies_publishes_source_pixels(ctx):
    from ooi_seg_ros.sim import simulate_capture

    # 16 views (22.5 deg apart): 8 left only two pairs with matches and ~50 points, too
    # few for a test that must not depend on the CPU's SIFT rounding
    cap = simulate_capture("aircraft", n_views=16, width=640, height=480, seed=0,
                           supersample=1).capture
    node = SfmNode(context=ctx, namespace=_ns(), parameter_overrides=[
        Parameter("sfm_max_pixels", value=80_000),  # 640x480 -> factor 2 (320x240)
        Parameter("keyframes.translation_frac", value=0.0),
        Parameter("queue_size", value=100)])
    try:
        for k, v in enumerate(cap.views):
            stamp = 10 ** 9 + k * 10 ** 8
            node.on_camera_info(msgconv.intrinsics_to_camera_info(v.camera, stamp))
            node.on_pose(msgconv.pose_to_pose_stamped(v.pose, stamp, "map"))
            node.on_image(msgconv.rgb_to_image(v.get_image(), stamp, "cam"))
        deadline = time.monotonic() + 120
        # frames pass a queue and the selector in other threads: wait for all of them
        while ((node.keyframes_processed < node.selector.accepted or node.selector.accepted < 12
                or node.work.qsize()) and time.monotonic() < deadline):
            time.sleep(0.1)
        assert node.sfm_factor == 2
        assert node.keyframes_processed == node.selector.accepted >= 12
        assert all(kf.view.image is None for kf in node.sfm.keyframes)  # no pixels kept
        assert all(kf.view.camera.width == 320 for kf in node.sfm.keyframes)
        got = []
        node.pub_obs.publish = got.append  # capture what would go on the wire
        node.pub_points.publish = got.append
        node.publish_cloud()
        # the worker may publish its last keyframe's cloud at the same time: pairs go out
        # whole (the node's publish lock) and no keyframe is left, so the last pair is it
        assert len(got) in (2, 4)
        pts_msg, obs_msg = got[-2:]
        views = list(cap.views)
        for k, v in enumerate(views):
            v.stamp_ns = 10 ** 9 + k * 10 ** 8
        cloud = msgconv.pointcloud2_to_sfm_cloud(pts_msg, obs_msg, views)
        assert len(cloud) > 150  # 364 measured (300 if the scene scale came late)
        err = []
        for i in range(len(cloud)):
            for vi, xy in zip(*cloud.observations(i)):
                p, _ = project(cloud.xyz[i:i + 1], views[vi].camera, views[vi].pose)
                err.append(np.linalg.norm(p[0] - xy))
        # observations are in the 640x480 source pixels: reprojection agrees there
        assert np.median(err) < 1.5, np.median(err)
    finally:
        node.close()
        node.destroy_node()


def _blank_keyframes(node, n: int, n_orbit: int) -> list:
    """Feeds ``n`` black 160x120 keyframes on an ``n_orbit``-view orbit to a segmentation
    node's keyframe topics; returns their views (no image)."""
    from ooi_seg_ros.core.types import View

    cam = CameraIntrinsics(160, 120, 120.0, 120.0, 79.5, 59.5)
    views = []
    for k in range(n):
        stamp = 10 ** 9 + k * 10 ** 8
        pose = _orbit_pose(k, n_orbit)
        node.on_kf_info(msgconv.intrinsics_to_camera_info(cam, stamp))
        node.on_kf_pose(msgconv.pose_to_pose_stamped(pose, stamp, "map"))
        node.on_kf_image(msgconv.rgb_to_image(np.zeros((120, 160, 3), np.uint8), stamp))
        views.append(View(key=str(stamp), stamp_ns=stamp, camera=cam, pose=pose))
    return views


def test_segmentation_node_keeps_downscaled_keyframes_within_budget(ctx):
    node = SegmentationNode(context=ctx, namespace=_ns(), parameter_overrides=[
        Parameter("every_n_keyframes", value=0), Parameter("image_max_pixels", value=10_000),
        Parameter("image_budget_mb", value=3 * 80 * 60 * 3 / 2 ** 20),
        Parameter("mask_guide_quality", value=0)])  # (their bytes count too: tested above)
    try:
        _blank_keyframes(node, 6, 6)  # kept at 80x60
        assert len(node.keyframes) == 3
        assert node.diag.counters["dropped_keyframe_budget"] == 3
        assert all(v.image.shape == (60, 80, 3) for v in node.keyframes.values())
    finally:
        node.destroy_node()


def test_segmentation_node_marks_keyframes_that_came_as_jpeg(ctx):
    """A JPEG copy on ``keyframe/image/compressed`` (as the SfM node forwards one) marks that
    keyframe's view ``compressed`` for the refinement; png copies and the others stay
    lossless."""
    node = SegmentationNode(context=ctx, namespace=_ns(), parameter_overrides=[
        Parameter("every_n_keyframes", value=0)])
    try:
        views = _blank_keyframes(node, 3, 12)
        img = np.zeros((120, 160, 3), np.uint8)
        node.on_kf_lossy(msgconv.rgb_to_compressed(img, views[1].stamp_ns, fmt="jpeg"))
        node.on_kf_lossy(msgconv.rgb_to_compressed(img, views[2].stamp_ns, fmt="png"))
        node.on_points(msgconv.xyzrgb_to_pointcloud2(np.zeros((4, 3)), np.zeros((4, 3),
                                                     np.uint8), msgconv.ns_to_stamp(10 ** 9)))
        got = {v.stamp_ns: v.compressed for v in node._inputs(observations=False)[0]}
        assert got == {views[0].stamp_ns: False, views[1].stamp_ns: True,
                       views[2].stamp_ns: False}
    finally:
        node.destroy_node()


def test_segmentation_run_takes_the_observations_of_its_own_cloud(ctx, monkeypatch):
    """Observations index the points of their own SfM cloud: a run started by a points
    message waits for the observations with its stamp, and without them (late or another
    cloud's) goes on without observations, counted -- never with the wrong cloud's."""
    import threading

    from ooi_seg_ros.core.types import SfmCloud
    from ooi_seg_ros.nodes import segmentation_node as segmod

    monkeypatch.setattr(segmod, "OBS_WAIT_S", 0.5)
    node = SegmentationNode(context=ctx, namespace=_ns(), parameter_overrides=[
        Parameter("every_n_keyframes", value=0)])
    try:
        views = _blank_keyframes(node, 3, 12)
        assert len(node.keyframes) == 3

        def cloud_msgs(n, stamp_ns):  # n points, each seen by keyframes 0 and 1
            c = SfmCloud(np.random.default_rng(n).normal(size=(n, 3)),
                         np.full((n, 3), 100, np.uint8), np.zeros(n),
                         np.arange(0, 2 * n + 1, 2, dtype=np.int64),
                         np.tile(np.array([0, 1], np.int32), n),
                         np.full((2 * n, 2), 10.0, np.float32), views)
            st = msgconv.ns_to_stamp(stamp_ns)
            return msgconv.xyzrgb_to_pointcloud2(c.xyz, c.rgb, st), \
                msgconv.observations_to_pointcloud2(c, st)

        # no observations ever received: no wait, none used
        pts, obs = cloud_msgs(5, 10 ** 9)
        node.on_points(pts)
        assert node._inputs()[2].obs_ptr[-1] == 0
        # the previous cloud's observations only: wait, then none used and counted
        node.on_obs(obs)
        pts2, obs2 = cloud_msgs(8, 2 * 10 ** 9)
        node.on_points(pts2)
        cloud = node._inputs()[2]
        assert len(cloud) == 8 and cloud.obs_ptr[-1] == 0
        assert node.diag.counters["cloud_without_observations"] == 1
        # its own observations arriving while the run waits: used
        threading.Timer(0.1, node.on_obs, args=(obs2,)).start()
        cloud = node._inputs()[2]
        assert cloud.obs_ptr[-1] == 16 and np.all(cloud.track_lengths() == 2)
        assert node.diag.counters["cloud_without_observations"] == 1
    finally:
        node.destroy_node()


def _demo_keyframes(n):
    """(camera_info, pose, image, gt mask) messages of the first n views of the demo bag."""
    from pathlib import Path

    from ooi_seg_ros.bag import BagReader

    r = BagReader(str(Path(__file__).resolve().parents[1] / "bags" / "demo.mcap"))
    names = {"/camera/camera_info": 0, "/camera/pose": 1, "/camera/image_raw": 2,
             "/ground_truth/mask": 3}
    out = [[], [], [], []]
    for topic, ty, _t, data in r.messages(topics=list(names)):
        out[names[topic]].append(r.decode(ty, data))
    return list(zip(*[o[:n] for o in out]))


@pytest.mark.slow
def test_segmentation_on_downscaled_keyframes_publishes_full_size_masks(ctx):
    """The node segments 1/2-size copies and publishes masks at the keyframes' own size, for
    every keyframe, close to the full-resolution run's IoU against the ground truth."""
    from ooi_seg_ros.core.types import View
    from ooi_seg_ros.sfm.incremental import IncrementalSfM

    kfs = _demo_keyframes(16)
    views = []
    for info, pose, img, _gt in kfs:
        views.append(View(key="", stamp_ns=msgconv.stamp_to_ns(img.header.stamp),
                          camera=msgconv.camera_info_to_intrinsics(info),
                          pose=msgconv.pose_from_msg(pose.pose), image=msgconv.image_to_rgb(img)))
    sfm = IncrementalSfM()
    for v in views:
        sfm.add_keyframe(v)
    cloud = sfm.cloud()
    stamp = msgconv.ns_to_stamp(views[-1].stamp_ns)
    pts = msgconv.sfm_cloud_to_pointcloud2(cloud, stamp)
    obs = msgconv.observations_to_pointcloud2(cloud, stamp)
    gt = {msgconv.stamp_to_ns(g.header.stamp): msgconv.image_to_mask(g) for *_x, g in kfs}
    results = {}
    for f in (1, 2):
        node = SegmentationNode(context=ctx, namespace=_ns(), parameter_overrides=[
            Parameter("every_n_keyframes", value=0), Parameter("image_downscale", value=f)])
        try:
            for info, pose, img, _gt in kfs:
                node.on_kf_info(info)
                node.on_kf_pose(pose)
                node.on_kf_image(img)
            node.on_points(pts)
            node.on_obs(obs)
            masks = {}
            node.pub_mask.publish = lambda m: masks.__setitem__(  # what goes on the wire
                msgconv.stamp_to_ns(m.header.stamp), msgconv.image_to_mask(m))
            assert node._busy.acquire(blocking=False)
            node._run()  # synchronously; releases _busy
            assert node.last_error is None, node.last_error
            assert sorted(masks) == sorted(gt)
            assert all(m.shape == (240, 320) for m in masks.values())
            if f == 2:
                assert all(v.image.shape == (120, 160, 3) for v in node.keyframes.values())
                assert sorted(node.assembler.guides) == sorted(gt)  # final outlines placed
                # a kept final mask sent again (republish_kept) is the one published, bit
                # for bit, without placing its outline again
                assert sorted(node._final_full) == sorted(gt)
                node.assembler.guide = None  # not called again
                s0 = sorted(gt)[3]
                first = masks.pop(s0)
                small = np.zeros((120, 160), bool)
                full = (node.assembler.full_cameras[s0], node.assembler.factors[s0])
                assert node._publish_mask(small, s0, full, again=True)
                assert np.array_equal(masks[s0], first)
            results[f] = masks
        finally:
            node.destroy_node()

    def iou(a, b):
        return (a & b).sum() / max((a | b).sum(), 1)

    full = np.mean([iou(results[1][k], gt[k]) for k in gt])
    half = np.mean([iou(results[2][k], gt[k]) for k in gt])
    agree = np.mean([iou(results[1][k], results[2][k]) for k in gt])
    print(f"IoU vs ground truth: full-size keyframes {full:.3f}, 1/2-size {half:.3f}; "
          f"masks agree {agree:.3f}")
    # 160x120 working copies are far below the default (which keeps 320x240 whole); the
    # check is that the path is exact (sizes, stamps, coordinates), not that tiny copies cost
    # nothing. At 1280x720 -> 640x360 the IoU is unchanged (BENCHMARKS.md, nodes section).
    # absolute quality on 16 views is the segmentation's business (it moved 0.67 -> 0.41 with
    # its own changes while this test stood); the node's part is to lose little to the copies
    assert half >= full - 0.1 and agree > 0.6, (full, half, agree)


def test_training_masks_are_kept_bit_packed():
    from ooi_seg_ros.nodes.training_node import _mask_at

    rng = np.random.default_rng(1)
    m = rng.random((61, 97)) > 0.5
    bits = np.packbits(m, axis=None)
    assert bits.nbytes == (61 * 97 + 7) // 8  # 1/8 of the bool mask
    assert np.array_equal(_mask_at(bits, m.shape, 1), m)
    block = np.zeros((8, 8), bool)
    block[:2, :2] = True  # a quarter of the top-left 4x4 block, all of the next one down
    block[4:8, :4] = True
    half = _mask_at(np.packbits(block, axis=None), block.shape, 4)
    assert half.tolist() == [[False, False], [True, False]]


@pytest.mark.slow
def test_segmentation_node_reruns_when_input_goes_idle(ctx):
    """After the last keyframes of a flight (fewer than every_n_keyframes), the node segments
    again by itself once its input has been idle for idle_run_s."""
    from rclpy.executors import SingleThreadedExecutor
    import threading

    from ooi_seg_ros.core.types import View
    from ooi_seg_ros.sfm.incremental import IncrementalSfM

    kfs = _demo_keyframes(12)
    views = [View(key="", stamp_ns=msgconv.stamp_to_ns(img.header.stamp),
                  camera=msgconv.camera_info_to_intrinsics(info),
                  pose=msgconv.pose_from_msg(pose.pose), image=msgconv.image_to_rgb(img))
             for info, pose, img, _gt in kfs]
    sfm = IncrementalSfM()
    for v in views:
        sfm.add_keyframe(v)
    cloud = sfm.cloud()
    stamp = msgconv.ns_to_stamp(views[-1].stamp_ns)
    node = SegmentationNode(context=ctx, namespace=_ns(), parameter_overrides=[
        Parameter("every_n_keyframes", value=100), Parameter("min_keyframes", value=8),
        Parameter("idle_run_s", value=0.5)])
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()
    try:
        node.on_points(msgconv.sfm_cloud_to_pointcloud2(cloud, stamp))
        node.on_obs(msgconv.observations_to_pointcloud2(cloud, stamp))
        for info, pose, img, _gt in kfs:
            node.on_kf_info(info)
            node.on_kf_pose(pose)
            node.on_kf_image(img)
        newest = max(node.keyframes)
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and (node.last_run_newest_ns != newest
                                               or node._busy.locked()):
            time.sleep(0.1)
        assert node.last_error is None, node.last_error
        assert node.last_run_newest_ns == newest  # a run covered the last keyframes
        assert node.runs >= 2  # the first at min_keyframes, then the idle one
    finally:
        ex.shutdown()
        spin.join(timeout=5)
        node.destroy_node()


@pytest.mark.slow
def test_sfm_map_stops_growing_at_its_byte_budget(ctx):
    from ooi_seg_ros.sim import simulate_capture

    cap = simulate_capture("aircraft", n_views=6, width=160, height=120, seed=0,
                           supersample=1).capture
    node = SfmNode(context=ctx, namespace=_ns(), parameter_overrides=[
        Parameter("sfm_budget_mb", value=0.01),  # below one keyframe's features
        Parameter("keyframes.translation_frac", value=0.0)])
    try:
        def feed(k, v):
            stamp = 10 ** 9 + k * 10 ** 8
            node.on_camera_info(msgconv.intrinsics_to_camera_info(v.camera, stamp))
            node.on_pose(msgconv.pose_to_pose_stamped(v.pose, stamp, "map"))
            node.on_image(msgconv.rgb_to_image(v.get_image(), stamp, "cam"))

        feed(0, cap.views[0])
        deadline = time.monotonic() + 60
        while node.keyframes_processed < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert node.map_full and node.map_bytes > 0
        for k, v in enumerate(cap.views[1:], start=1):
            feed(k, v)
        assert node.selector.accepted == 1
        assert node.selector.dropped["max_keyframes"] == len(cap.views) - 1
    finally:
        node.close()
        node.destroy_node()
