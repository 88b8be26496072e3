"""ooi-seg play / record: in-process with real rclpy nodes, and across processes."""

import os
import signal
import subprocess
import sys
import threading
import time
import uuid

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from std_msgs.msg import String

from ooi_seg_ros.bag import BagReader, BagWriter
from ooi_seg_ros.nodes.bagplay import BagPlayer, BagRecorder, qos_from_offered


def _topic() -> str:
    return "/t_" + uuid.uuid4().hex[:10]


def _make_bag(path, topic, n=20, dt_ns=10_000_000):
    from rclpy.serialization import serialize_message
    with BagWriter(str(path)) as w:
        w.add_topic(topic, "std_msgs/msg/String", "reliable")
        for i in range(n):
            w.write(topic, serialize_message(String(data=f"msg {i}")), 1_000_000_000 + i * dt_ns)


@pytest.fixture
def ctx():
    c = Context()
    rclpy.init(context=c)
    yield c
    rclpy.shutdown(context=c)


def _wait(pred, timeout=10.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.02)
    return False


def test_play_into_record_roundtrip(tmp_path, ctx):
    topic = _topic()
    src = tmp_path / "src.mcap"
    out = tmp_path / "rec.mcap"
    _make_bag(src, topic)
    player = BagPlayer(str(src), rate=2.0, context=ctx)
    recorder = BagRecorder(str(out), [topic], context=ctx)
    ex = MultiThreadedExecutor(context=ctx)
    ex.add_node(player)
    ex.add_node(recorder)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()
    try:
        assert _wait(lambda: topic in recorder.subs), "recorder never discovered the topic"
        assert player.wait_for_subscribers([topic], 10.0)
        assert player.play() == 20
        assert _wait(lambda: recorder.counts.get(topic) == 20)
    finally:
        recorder.close()
        ex.shutdown()
        player.destroy_node()
        recorder.destroy_node()
    src_data = [d for _t, _ty, _ts, d in BagReader(str(src)).messages()]
    rec = BagReader(str(out))
    assert rec.topics()[topic].type == "std_msgs/msg/String"
    assert [d for _t, _ty, _ts, d in rec.messages()] == src_data  # byte for byte
    # the recorded QoS is what the player offered (reliable)
    assert qos_from_offered(rec.topics()[topic].qos).reliability == 1


def test_player_rejects_missing_topic(tmp_path, ctx):
    from ooi_seg_ros.core.types import InputError
    src = tmp_path / "src.mcap"
    _make_bag(src, _topic(), n=2)
    with pytest.raises(InputError, match="no topic"):
        BagPlayer(str(src), topics=["/nope"], context=ctx)


def _cli(*args):
    return [sys.executable, "-m", "ooi_seg_ros.cli", *args]


@pytest.mark.slow
def test_play_and_record_across_processes_with_sigint(tmp_path):
    """`ooi-seg record` in one process, `ooi-seg play` in another, over loopback; SIGINT
    finishes the recording and it reads back complete."""
    topic = _topic()
    src = tmp_path / "src.mcap"
    out = tmp_path / "rec.mcap"
    _make_bag(src, topic, n=30)
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    rec = subprocess.Popen(_cli("record", "--out", str(out), topic), env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        time.sleep(1.0)
        play = subprocess.run(_cli("play", str(src), "--wait-for-subscribers", "15"), env=env,
                              capture_output=True, text=True, timeout=120)
        assert play.returncode == 0, play.stderr
        time.sleep(1.0)
    finally:
        rec.send_signal(signal.SIGINT)
        out_text = rec.communicate(timeout=30)[0]
    assert rec.returncode == 0, out_text
    assert "recorded 30 messages" in out_text, out_text
    r = BagReader(str(out))
    assert r.topics()[topic].count == 30


@pytest.mark.slow
def test_record_survives_sigkill_up_to_last_chunk(tmp_path):
    """After SIGKILL the recording is readable up to its last finished chunk."""
    topic = _topic()
    src = tmp_path / "src.mcap"
    out = tmp_path / "rec.mcap"
    _make_bag(src, topic, n=200, dt_ns=2_000_000)
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    rec = subprocess.Popen(_cli("record", "--out", str(out), "--chunk-size", "512", topic),
                           env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(1.0)
        play = subprocess.run(_cli("play", str(src), "--wait-for-subscribers", "15"), env=env,
                              capture_output=True, text=True, timeout=120)
        assert play.returncode == 0, play.stderr
        time.sleep(1.0)
    finally:
        rec.send_signal(signal.SIGKILL)
        rec.wait(timeout=30)
    r = BagReader(str(out))
    assert r.truncated  # no footer: the process never finished the file
    got = [r.decode(ty, d).data for _t, ty, _ts, d in r.messages(topics=[topic])]
    assert len(got) >= 150  # everything but the last unfinished chunk (512-byte chunks)
    # (CDR from the middleware may carry trailing alignment padding: compare decoded messages)
    assert got == [f"msg {i}" for i in range(len(got))]
