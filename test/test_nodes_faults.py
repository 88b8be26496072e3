"""Node parameters and faults: config files match the declared parameters, bad parameter
values are refused with a reason, malformed messages are dropped and counted while the node
keeps running."""

import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
import rclpy
import yaml
from geometry_msgs.msg import PoseStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image

from ooi_seg_ros import msgconv
from ooi_seg_ros.core.geometry import look_at
from ooi_seg_ros.core.types import CameraIntrinsics
from ooi_seg_ros.nodes.common import sensor_qos
from ooi_seg_ros.nodes.segmentation_node import SegmentationNode
from ooi_seg_ros.nodes.sfm_node import SfmNode
from ooi_seg_ros.nodes.training_node import TrainingNode

CONFIG = Path(__file__).resolve().parents[1] / "config"


@pytest.fixture
def ctx():
    c = Context()
    rclpy.init(context=c)
    yield c
    rclpy.shutdown(context=c)


def _make(cls, ctx, overrides=()):
    extra = [Parameter("record_path", value="none")] if cls is TrainingNode else []
    return cls(context=ctx, namespace="/f_" + uuid.uuid4().hex[:8],
               parameter_overrides=list(overrides) + extra)


@pytest.mark.parametrize("cls,name", [(SfmNode, "sfm_node"),
                                      (SegmentationNode, "segmentation_node"),
                                      (TrainingNode, "training_node")])
def test_config_files_match_declared_parameters(ctx, cls, name):
    data = yaml.safe_load((CONFIG / f"{name}.yaml").read_text())[name]["ros__parameters"]
    overrides = [Parameter(k, value=v) for k, v in data.items() if k != "record_path"]
    node = _make(cls, ctx, overrides)
    try:
        for k in data:
            assert node.has_parameter(k), f"{name}.yaml sets undeclared parameter {k}"
        # every parameter has a description
        for k in node._parameters:
            if k not in ("use_sim_time", "start_type_description_service"):
                assert node.describe_parameter(k).description, k
        # the commented stage options are real parameters too
        for line in (CONFIG / f"{name}.yaml").read_text().splitlines():
            line = line.strip()
            if line.startswith("# ") and ": " in line and "." in line.split(":")[0]:
                assert node.has_parameter(line[2:].split(":")[0]), line
    finally:
        close = getattr(node, "close", None)
        if close:
            close()
        node.destroy_node()


def test_bad_parameter_values_are_refused(ctx):
    node = _make(SegmentationNode, ctx)
    try:
        res = node.set_parameters([Parameter("every_n_keyframes", value=-3)])
        assert not res[0].successful and "range" in res[0].reason
        res = node.set_parameters([Parameter("mask_stride", value="two")])
        assert not res[0].successful
        res = node.set_parameters([Parameter("every_n_keyframes", value=7)])
        assert res[0].successful and node.cfg.every_n_keyframes == 7
    finally:
        node.destroy_node()


def _wait(pred, timeout=10.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.02)
    return False


def test_sfm_node_drops_malformed_messages_and_keeps_running(ctx):
    node = _make(SfmNode, ctx)
    ns = node.get_namespace()
    feeder = Node("feeder", context=ctx, namespace=ns)
    pub_info = feeder.create_publisher(CameraInfo, "camera_info", sensor_qos())
    pub_pose = feeder.create_publisher(PoseStamped, "pose", sensor_qos())
    pub_img = feeder.create_publisher(Image, "image", sensor_qos())
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(feeder)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()
    c = node.diag.counters
    try:
        assert _wait(lambda: pub_img.get_subscription_count() > 0)
        cam = CameraIntrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
        # CameraInfo with K all zeros
        bad_info = msgconv.intrinsics_to_camera_info(cam, msgconv.ns_to_stamp(1), "cam")
        bad_info.k = [0.0] * 9
        pub_info.publish(bad_info)
        assert _wait(lambda: c.get("dropped_camera_info", 0) == 1)
        # an image before any valid camera_info
        rgb = np.zeros((48, 64, 3), np.uint8)
        pub_img.publish(msgconv.rgb_to_image(rgb, msgconv.ns_to_stamp(10), "cam"))
        assert _wait(lambda: c.get("dropped_no_camera_info", 0) == 1)
        pub_info.publish(msgconv.intrinsics_to_camera_info(cam, msgconv.ns_to_stamp(1), "cam"))
        assert _wait(lambda: node.camera is not None)
        # NaN pose
        p = msgconv.pose_to_pose_stamped(look_at(np.array([3.0, 0, 1]), np.zeros(3)),
                                         msgconv.ns_to_stamp(100), "map")
        p.pose.orientation.w = float("nan")
        pub_pose.publish(p)
        assert _wait(lambda: c.get("dropped_pose", 0) == 1)
        # wrong step, empty data, unsupported encoding
        img = msgconv.rgb_to_image(rgb, msgconv.ns_to_stamp(200), "cam")
        img.step = 10
        pub_img.publish(img)
        empty = msgconv.rgb_to_image(rgb, msgconv.ns_to_stamp(201), "cam")
        empty.data = b""
        pub_img.publish(empty)
        enc = msgconv.rgb_to_image(rgb, msgconv.ns_to_stamp(202), "cam")
        enc.encoding = "32FC1"
        pub_img.publish(enc)
        assert _wait(lambda: c.get("dropped_image", 0) == 3)
        # good image, then one whose stamp goes backwards
        pub_img.publish(msgconv.rgb_to_image(rgb, msgconv.ns_to_stamp(300), "cam"))
        assert _wait(lambda: c.get("images", 0) == 2)
        pub_img.publish(msgconv.rgb_to_image(rgb, msgconv.ns_to_stamp(250), "cam"))
        assert _wait(lambda: c.get("dropped_stamp_backwards", 0) == 1)
        # still alive: diagnostics are published and report the drops as a warning
        snap = node.diag.snapshot()
        assert snap["counters"]["dropped_image"] == 3
        node.diag.publish()
    finally:
        ex.shutdown()
        spin.join(timeout=5)
        node.close()
        node.destroy_node()
        feeder.destroy_node()
