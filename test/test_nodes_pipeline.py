"""Launch-free integration test: the three nodes in-process, fed the bundled demo bag.

Real rclpy nodes in their own Context and executor; the bag's messages go through real
publishers; the assertions are on what the nodes publish: an OOI cloud, a mask for every
keyframe with the keyframe's stamp and an IoU against the bag's ground truth, splats, and a
training recording that reads back.
"""

import os
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_srvs.srv import Trigger

from ooi_seg_ros import msgconv
from ooi_seg_ros.bag import BagReader
from ooi_seg_ros.nodes.common import latched_qos, reliable_qos, sensor_qos
from ooi_seg_ros.nodes.segmentation_node import SegmentationNode
from ooi_seg_ros.nodes.sfm_node import SfmNode
from ooi_seg_ros.nodes.training_node import TrainingNode

DEMO = Path(__file__).resolve().parents[1] / "bags" / "demo.mcap"
N_VIEWS = int(os.environ.get('OOI_IT_VIEWS', 60))  # the whole demo orbit


def _wait(pred, timeout=120.0, period=0.05):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(period)
    return False


def _load_demo(n_views):
    r = BagReader(str(DEMO))
    msgs = {"info": [], "pose": [], "image": [], "gt": []}
    names = {"/camera/camera_info": "info", "/camera/pose": "pose",
             "/camera/image_raw": "image", "/ground_truth/mask": "gt"}
    for topic, ty, _t, data in r.messages(topics=list(names)):
        msgs[names[topic]].append(r.decode(ty, data))
    for k in msgs:
        msgs[k] = msgs[k][:n_views]
    return msgs


@pytest.mark.slow
def test_nodes_on_demo_bag(tmp_path, capsys):
    demo = _load_demo(N_VIEWS)
    gt = {msgconv.stamp_to_ns(m.header.stamp): msgconv.image_to_mask(m) for m in demo["gt"]}
    ns = "/it_" + uuid.uuid4().hex[:8]
    ctx = Context()
    rclpy.init(context=ctx)
    common = [Parameter("use_sim_time", value=False)]
    sfm = SfmNode(context=ctx, namespace=ns, parameter_overrides=common + [
        Parameter("keyframes.translation_frac", value=0.0),
        Parameter("queue_size", value=100)])
    seg = SegmentationNode(context=ctx, namespace=ns, parameter_overrides=common + [
        Parameter("every_n_keyframes", value=0)])
    bag_path = tmp_path / "training.mcap"
    trn = TrainingNode(context=ctx, namespace=ns, parameter_overrides=common + [
        Parameter("record_path", value=str(bag_path)),
        Parameter("train.iterations", value=40),
        Parameter("train.max_gaussians", value=3000),
        Parameter("train.eval_every", value=0),
        Parameter("train.snapshot_every", value=20)])
    feeder = Node("feeder", context=ctx, namespace=ns)
    pub_info = feeder.create_publisher(CameraInfo, "camera_info", sensor_qos())
    pub_pose = feeder.create_publisher(PoseStamped, "pose", sensor_qos())
    pub_img = feeder.create_publisher(Image, "image", sensor_qos())
    got = {"ooi": [], "mask": [], "splats": []}
    feeder.create_subscription(PointCloud2, "ooi/points", got["ooi"].append, latched_qos())
    feeder.create_subscription(Image, "ooi/mask", got["mask"].append, reliable_qos(depth=200))
    feeder.create_subscription(PointCloud2, "splats", got["splats"].append, latched_qos())
    ex = MultiThreadedExecutor(num_threads=4, context=ctx)
    for n in (sfm, seg, trn, feeder):
        ex.add_node(n)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()
    try:
        assert _wait(lambda: pub_img.get_subscription_count() > 0
                     and pub_info.get_subscription_count() > 0, 20)
        for info, pose, img in zip(demo["info"], demo["pose"], demo["image"]):
            before = sfm.diag.counters.get("images", 0)
            pub_info.publish(info)
            pub_pose.publish(pose)
            time.sleep(0.01)
            pub_img.publish(img)
            assert _wait(lambda: sfm.diag.counters.get("images", 0) > before, 10), \
                "sfm_node did not receive an image"
        sel = sfm.selector
        assert _wait(lambda: sel.accepted + sum(sel.dropped.values()) == N_VIEWS, 30), \
            sel.report()
        n_kf = sfm.selector.accepted
        assert n_kf >= N_VIEWS * 0.8, sfm.selector.report()
        assert _wait(lambda: sfm.keyframes_processed + sfm.diag.counters.get("error_sfm", 0)
                     >= n_kf, 600), "SfM did not finish the keyframes"
        assert sfm.diag.counters.get("error_sfm", 0) == 0
        assert _wait(lambda: len(seg.keyframes) == n_kf and seg._points_msg is not None, 60), \
            (len(seg.keyframes), n_kf, seg._points_msg is not None, seg.diag.snapshot(),
             sfm.diag.snapshot())

        # before any full run: provisional masks from the cloud-only runs' OOI cloud
        assert _wait(lambda: len({msgconv.stamp_to_ns(m.header.stamp) for m in got["mask"]})
                     >= n_kf or seg.last_error, 300), \
            f"{len(got['mask'])} provisional masks, {seg.diag.snapshot()}"
        assert seg.last_error is None, seg.last_error
        assert got["ooi"] and seg.runs == 0
        assert sorted(seg.provisional_stamps()) == sorted(seg.keyframes)
        # the training node tells the provisional masks apart: nothing to train on yet
        assert _wait(lambda: len(trn.provisional) >= n_kf, 60), trn.diag.snapshot()
        tcli = feeder.create_client(Trigger, f"{ns}/training_node/train")
        assert tcli.wait_for_service(timeout_sec=10)
        fut = tcli.call_async(Trigger.Request())
        assert _wait(fut.done, 30) and not fut.result().success, fut.result()
        assert f"{n_kf} with a provisional mask only" in fut.result().message, fut.result()

        # the ~/segment service of the segmentation node
        cli = feeder.create_client(Trigger, f"{ns}/segmentation_node/segment")
        assert cli.wait_for_service(timeout_sec=10)
        fut = cli.call_async(Trigger.Request())
        assert _wait(fut.done, 30) and fut.result().success, fut.result()
        sc = seg.diag.counters
        assert _wait(lambda: (seg.runs >= 1 and not seg._busy.locked())
                     or sc.get("error_segmentation"), 600), \
            f"{len(got['mask'])} masks, {len(got['ooi'])} clouds, {seg.diag.snapshot()}"
        assert seg.last_error is None, seg.last_error
        assert sc.get("error_segmentation", 0) == 0
        assert seg.provisional_stamps() == []  # the run replaced every provisional mask
        sent = (sc.get("masks_published", 0) + sc.get("masks_provisional_published", 0)
                + sc.get("masks_provisional_refreshed", 0))
        assert _wait(lambda: len(got["mask"]) == sent, 60), (len(got["mask"]), sent)

        ooi_xyz, _ = msgconv.pointcloud2_to_xyzrgb(got["ooi"][-1])
        assert len(ooi_xyz) > 20
        by_stamp = {}
        for m in got["mask"]:  # in publication order: provisional ones, then the run's
            by_stamp.setdefault(msgconv.stamp_to_ns(m.header.stamp), []).append(m)
        assert sorted(by_stamp) == sorted(seg.keyframes)  # masks for every keyframe, stamped
        assert sc.get("masks_published") == n_kf  # one final mask per keyframe
        final = [ms[-1] for ms in by_stamp.values()]
        prov = [ms[-2] for ms in by_stamp.values() if len(ms) >= 2]  # latest provisional

        def mean_iou(msgs):
            ious, recs = [], []
            for m in msgs:
                pred = msgconv.image_to_mask(m)
                g = gt[msgconv.stamp_to_ns(m.header.stamp)]
                ious.append((pred & g).sum() / max((pred | g).sum(), 1))
                recs.append((pred & g).sum() / max(g.sum(), 1))
            return np.mean(ious), np.min(ious), len(ious), np.mean(recs)

        iou, iou_min, n, rec = mean_iou(final)
        p_iou, p_min, p_n, _ = mean_iou(prov)
        # the segmentation issue's bar (IoU >= 0.90, recall >= 0.97), on the real SfM cloud
        # the nodes built: measured 0.913 / 0.978 (BENCHMARKS, session 10)
        bar = float(os.environ.get("OOI_IT_IOU", 0.90))
        bar_recall = float(os.environ.get("OOI_IT_RECALL", 0.97))
        with capsys.disabled():  # the measured figure belongs in the test output, pass or fail
            print(f"\n[nodes pipeline] mean mask IoU {iou:.3f} (min {iou_min:.3f}), recall "
                  f"{rec:.3f} over {n} keyframes; bar {bar:.2f} / {bar_recall:.2f}. Latest "
                  f"provisional masks before the run: {p_iou:.3f} (min {p_min:.3f}) over {p_n}")
        assert iou >= bar and rec >= bar_recall, f"mean IoU {iou:.3f}, recall {rec:.3f}"

        # training on the ~/train service
        assert _wait(lambda: len(trn.masks) >= n_kf and trn.ooi_xyz is not None, 60)
        fut = tcli.call_async(Trigger.Request())
        assert _wait(fut.done, 30) and fut.result().success, fut.result()
        assert _wait(lambda: got["splats"] or trn.diag.counters.get("error_training"), 900)
        assert got["splats"], (trn.diag.snapshot(), getattr(trn, "last_error", None))
        fields = [f.name for f in got["splats"][-1].fields]
        for name in ("x", "y", "z", "f_dc_0", "f_dc_2", "f_rest_0", "opacity", "scale_0",
                     "rot_3"):
            assert name in fields
        assert trn.wait_idle(60)
    finally:
        ex.shutdown(timeout_sec=5)
        spin.join(timeout=5)
        for n in (sfm, seg, trn, feeder):
            close = getattr(n, "close", None)
            if close:
                close()
            n.destroy_node()
        rclpy.shutdown(context=ctx)

    rec = BagReader(str(bag_path))
    topics = rec.topics()
    assert topics[f"{ns}/splats"].count >= 2  # snapshots + final
    assert topics[f"{ns}/ooi/mask"].count >= n_kf
    assert topics[f"{ns}/keyframe/image"].count == n_kf
    last = [d for _t, _ty, _ts, d in rec.messages(topics=[f"{ns}/splats"])][-1]
    cloud = rec.decode("sensor_msgs/msg/PointCloud2", last)
    assert cloud.width * cloud.height == len(trn.result.model)
