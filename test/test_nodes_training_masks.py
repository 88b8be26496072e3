"""The training node trains on final masks only.

``ooi/mask`` carries the segmentation node's provisional masks (header.frame_id ending in
``_provisional``) and its final ones. The segmentation node's own mask publisher labels them;
the training node records both, never trains on a provisional mask, auto-starts only once
every kept keyframe has a final mask, and ``~/train`` says how many keyframes it left out.
Real nodes in their own context, real messages (the demo bag's keyframes and ground-truth
masks), callbacks called directly.
"""

import uuid
from pathlib import Path

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from ooi_seg_ros import msgconv
from ooi_seg_ros.bag import BagReader
from ooi_seg_ros.nodes.common import mask_frame_id, mask_is_provisional
from ooi_seg_ros.nodes.segmentation_node import SegmentationNode
from ooi_seg_ros.nodes.training_node import TrainingNode

DEMO = Path(__file__).resolve().parents[1] / "bags" / "demo.mcap"


@pytest.fixture
def ctx():
    c = Context()
    rclpy.init(context=c)
    yield c
    rclpy.shutdown(context=c)


@pytest.fixture(scope="module")
def demo():
    """(camera_info, pose, image, gt mask) messages of the first 8 views of the demo bag."""
    r = BagReader(str(DEMO))
    names = {"/camera/camera_info": 0, "/camera/pose": 1, "/camera/image_raw": 2,
             "/ground_truth/mask": 3}
    out = [[], [], [], []]
    for topic, ty, _t, data in r.messages(topics=list(names)):
        out[names[topic]].append(r.decode(ty, data))
    return list(zip(*[o[:8] for o in out]))


def _stamp(msg):
    return msgconv.stamp_to_ns(msg.header.stamp)


def _mask_msg(gt_msg, provisional: bool):
    return msgconv.mask_to_image(msgconv.image_to_mask(gt_msg), gt_msg.header.stamp,
                                 mask_frame_id(provisional))


def _trainer(ctx, overrides=()):
    return TrainingNode(context=ctx, namespace="/tm_" + uuid.uuid4().hex[:8],
                        parameter_overrides=[
                            Parameter("record_path", value="none"),
                            Parameter("stable_updates", value=1),
                            Parameter("train.iterations", value=3),
                            Parameter("train.eval_every", value=0),
                            Parameter("train.snapshot_every", value=0),
                            Parameter("train.max_gaussians", value=500)] + list(overrides))


def _feed(node, demo):
    for info, pose, img, _gt in demo:
        node.on_kf_info(info)
        node.on_kf_pose(pose)
        node.on_kf_image(img)
    # the same OOI cloud twice: stable
    xyz = np.random.default_rng(0).normal(scale=0.2, size=(300, 3))
    cloud = msgconv.xyzrgb_to_pointcloud2(xyz, None, demo[-1][2].header.stamp)
    node.on_ooi_points(cloud)
    node.on_ooi_points(cloud)


def _srv(node):
    return node.on_train_srv(Trigger.Request(), Trigger.Response())


def test_segmentation_node_labels_its_masks(ctx, demo):
    """Provisional masks go out with the provisional frame, a run's masks with the plain one,
    and a provisional mask is never published after a keyframe's final mask."""
    node = SegmentationNode(context=ctx, namespace="/tm_" + uuid.uuid4().hex[:8],
                            parameter_overrides=[Parameter("every_n_keyframes", value=0),
                                                 Parameter("provisional_masks", value=False),
                                                 Parameter("cloud_runs", value=False)])
    try:
        sent = []
        node.pub_mask.publish = sent.append
        for info, pose, img, _gt in demo[:2]:
            node.on_kf_info(info)
            node.on_kf_pose(pose)
            node.on_kf_image(img)
        s0, s1 = _stamp(demo[0][2]), _stamp(demo[1][2])
        full = {s: (node.assembler.full_cameras[s], node.assembler.factors[s]) for s in (s0, s1)}
        m = msgconv.image_to_mask(demo[0][3])
        assert node._publish_mask(m, s0, full[s0], provisional_from=1)
        assert node._publish_mask(m, s1, full[s1])
        assert not node._publish_mask(m, s1, full[s1], provisional_from=2)  # final already
        assert [(_stamp(x), mask_is_provisional(x)) for x in sent] == [(s0, True), (s1, False)]
        assert sent[0].header.frame_id == "camera_optical_provisional"
        assert sent[1].header.frame_id == "camera_optical"
        assert node.provisional_stamps() == [s0]
    finally:
        node.destroy_node()


def test_auto_start_waits_for_final_masks(ctx, demo):
    node = _trainer(ctx, [Parameter("auto_start", value=True),
                          Parameter("min_keyframes", value=4)])
    try:
        _feed(node, demo)
        assert node.ooi_is_stable()
        for *_x, gt in demo:  # provisional masks for every keyframe: no start
            node.on_mask(_mask_msg(gt, True))
        assert node.runs == 0 and not node._busy.locked()
        assert node.mask_counts() == (0, 8, 0)
        assert node.diag.values["masks_provisional"] == "8"
        for *_x, gt in demo[:7]:  # final masks for 7 of 8 (more than min_keyframes): no start
            node.on_mask(_mask_msg(gt, False))
        assert node.runs == 0 and not node._busy.locked()
        assert node.mask_counts() == (7, 1, 0)
        # a provisional mask never replaces a final one
        node.on_mask(_mask_msg(demo[0][3], True))
        assert node.mask_counts() == (7, 1, 0)
        assert node.diag.counters["masks_provisional_ignored"] == 1
        node.on_mask(_mask_msg(demo[7][3], False))  # the last final mask: training starts
        assert node._busy.locked() or node.runs == 1
        assert node.wait_idle(120)
        assert node.runs == 1, node.last_error if hasattr(node, "last_error") else None
        assert len(node.result.train_keys) + len(node.result.heldout_keys) == 8
    finally:
        node.close()
        node.destroy_node()


def test_train_service_uses_final_masks_and_says_what_it_left_out(ctx, demo):
    node = _trainer(ctx, [Parameter("min_keyframes", value=4)])
    try:
        _feed(node, demo)
        for *_x, gt in demo:
            node.on_mask(_mask_msg(gt, True))
        res = _srv(node)
        assert not res.success
        assert "0 keyframes with final masks" in res.message
        assert "8 with a provisional mask only" in res.message, res.message
        finals = demo[:5]
        for *_x, gt in finals:
            node.on_mask(_mask_msg(gt, False))
        res = _srv(node)
        assert res.success, res.message
        assert "5 keyframes with final masks" in res.message
        assert "3 with a provisional mask only, 0 without a mask" in res.message, res.message
        assert node.wait_idle(120)
        assert node.runs == 1
        used = set(node.result.train_keys) | set(node.result.heldout_keys)
        views = {v.key: v.stamp_ns for v in node.keyframes.values()}
        assert sorted(views[k] for k in used) == sorted(_stamp(img) for _i, _p, img, _g in finals)
    finally:
        node.close()
        node.destroy_node()
