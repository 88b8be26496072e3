"""Our bags read by two independent readers: rosbags (Ternaris) and mcap_ros2 (Foxglove).

``ros2 bag`` is not installable here; these two readers share no code with our writer (their
own MCAP parsing, ``.msg`` parsing and CDR decoding), so every test below writes a real bag
with the package's own code and has both decode every message of every topic and compare it
with what we wrote.
"""

import os
import signal
import subprocess
import sys
import threading
import time
from argparse import Namespace
from pathlib import Path

import numpy as np
import pytest
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.reader import read_ros2_messages
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability, QosReliability
from sensor_msgs.msg import Image, PointCloud2
from std_msgs.msg import Float32MultiArray, String

from ooi_seg_ros import msgconv
from ooi_seg_ros.bag import BagReader, BagWriter, canonical_qos, qos_profiles, recover_bag
from ooi_seg_ros.bag.interop import check_bag, file_problems, first_difference, plain
from ooi_seg_ros.core.types import InputError

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "bags" / "demo.mcap"
DATA = ROOT.parent / "shared" / "data" / "rosbag2-recorded"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason="shared rosbag2 test bags missing")

# what `ooi-seg record` stored for publishers before (Foxy-era infinities, integer enums)
RECORDER_QOS = ("- history: 3\n  depth: 0\n  reliability: 2\n  durability: 2\n"
                "  deadline: {sec: 2147483647, nsec: 4294967295}\n"
                "  lifespan: {sec: 2147483647, nsec: 4294967295}\n  liveliness: 1\n"
                "  liveliness_lease_duration: {sec: 2147483647, nsec: 4294967295}\n"
                "  avoid_ros_namespace_conventions: false\n")


def _rosbags_read(path):
    """{topic: [(log time, decoded)]} and {topic: connection} from rosbags' AnyReader."""
    out, conns = {}, {}
    with AnyReader([Path(path)]) as r:
        for c in r.connections:
            conns[c.topic] = c
        for c, t, raw in r.messages():
            out.setdefault(c.topic, []).append((t, r.deserialize(raw, c.msgtype)))
    return out, conns


def _mcap_ros2_read(path):
    """{topic: [(log time, publish time, decoded)]} from Foxglove's read_ros2_messages."""
    out = {}
    for m in read_ros2_messages(str(path)):
        out.setdefault(m.channel.topic, []).append((m.log_time_ns, m.publish_time_ns,
                                                    m.ros_msg))
    return out


def _assert_agree(path):
    res = check_bag(path)
    assert res.ok, res.summary()
    assert res.ours.decoded == res.rosbags.decoded == res.mcap_ros2.decoded > 0
    return res


# ----------------------------------------------------------------------------- demo bag
def test_demo_bag_every_message_in_both_readers():
    res = _assert_agree(DEMO)
    assert res.ours.counts == {"/camera/image_raw": 60, "/camera/camera_info": 60,
                               "/camera/pose": 60, "/ground_truth/mask": 60,
                               "/ground_truth/ooi_points": 1}
    rb, conns = _rosbags_read(DEMO)
    assert conns["/camera/image_raw"].msgtype == "sensor_msgs/msg/Image"
    assert conns["/camera/image_raw"].msgdef.data.count("MSG: ") == 2  # Header, Time
    t, img = rb["/camera/image_raw"][0]
    rgb = img.data.reshape(img.height, img.width, 3)
    ours = msgconv.image_to_rgb(BagReader(DEMO).decode(
        "sensor_msgs/msg/Image", next(BagReader(DEMO).messages(["/camera/image_raw"]))[3]))
    assert np.array_equal(rgb, ours) and img.encoding == "rgb8"
    assert t == img.header.stamp.sec * 10**9 + img.header.stamp.nanosec
    gt = rb["/ground_truth/ooi_points"][0][1]
    assert [f.name for f in gt.fields][:3] == ["x", "y", "z"]


# ----------------------------------------------------------------------------- record
def _publish_and_record(out, n=6):
    """A real `record` (BagRecorder) of five topics with three QoS kinds, in-process."""
    from ooi_seg_ros.nodes.bagplay import BagRecorder
    from ooi_seg_ros.nodes.common import latched_qos, reliable_qos, sensor_qos

    tag = f"/i{os.getpid()}_{time.monotonic_ns() % 10**6}"
    types = {f"{tag}/str": (String, reliable_qos()), f"{tag}/img": (Image, sensor_qos()),
             f"{tag}/pc": (PointCloud2, latched_qos()),
             f"{tag}/diag": (DiagnosticArray, reliable_qos()),
             f"{tag}/loss": (Float32MultiArray, reliable_qos())}
    sent = {t: [] for t in types}
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        node = Node("interop_pub", context=ctx)
        pubs = {t: node.create_publisher(cls, t, q) for t, (cls, q) in types.items()}
        rec = BagRecorder(str(out), list(types), context=ctx)
        ex = MultiThreadedExecutor(context=ctx)
        ex.add_node(node)
        ex.add_node(rec)
        threading.Thread(target=ex.spin, daemon=True).start()
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not (
                len(rec.subs) == len(types)
                and all(p.get_subscription_count() for p in pubs.values())):
            time.sleep(0.02)
        assert len(rec.subs) == len(types), "recorder never discovered the topics"
        for i in range(n):
            stamp = 1_700_000_000_000_000_000 + i * 1000
            rgb = (np.arange(6 * 8 * 3).reshape(6, 8, 3) * (i + 3) % 256).astype(np.uint8)
            cols = {k: np.linspace(-1, 1, 4, dtype=np.float32) * (i + 1)
                    for k in ("x", "y", "z", "f_dc_0", "opacity", "scale_0", "rot_0")}
            diag = DiagnosticArray(header=msgconv.make_header(stamp, ""), status=[
                DiagnosticStatus(level=DiagnosticStatus.WARN, name="sfm", message=f"m{i}",
                                 hardware_id="", values=[KeyValue(key="dropped",
                                                                  value=str(i))])])
            msgs = {f"{tag}/str": String(data=f"msg {i} é"),
                    f"{tag}/img": msgconv.rgb_to_image(rgb, stamp),
                    f"{tag}/pc": msgconv.fields_to_pointcloud2(cols, stamp),
                    f"{tag}/diag": diag,
                    f"{tag}/loss": Float32MultiArray(data=[float(i), 0.25, float("nan")])}
            for t, m in msgs.items():
                pubs[t].publish(m)
                sent[t].append(m)
            time.sleep(0.03)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and sum(rec.counts.values()) < n * len(types):
            time.sleep(0.02)
        rec.close()
        ex.shutdown()
        node.destroy_node()
        rec.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
    return tag, sent


def test_recorded_bag_in_both_readers(tmp_path):
    out = tmp_path / "rec.mcap"
    tag, sent = _publish_and_record(out)
    res = _assert_agree(out)
    # best-effort camera stream: the sensor_data publisher may lose one; reliable ones not
    for t in (f"{tag}/str", f"{tag}/pc", f"{tag}/diag", f"{tag}/loss"):
        assert res.ours.counts[t] == len(sent[t]), t
    rb, conns = _rosbags_read(out)
    mr = _mcap_ros2_read(out)
    # what was published is what both decode (fields, values, NaN included)
    for t in (f"{tag}/str", f"{tag}/pc", f"{tag}/diag", f"{tag}/loss"):
        want = [plain(m) for m in sent[t]]
        assert first_difference([plain(m) for _ts, m in rb[t]], want) is None, t
        assert first_difference([plain(m) for _lt, _pt, m in mr[t]], want) is None, t
    # publish time = the sender's source timestamp (rosbag2's send time), before reception
    for t in (f"{tag}/str", f"{tag}/pc"):
        times = [(lt, pt) for lt, pt, _m in mr[t]]
        assert all(0 < pt <= lt for lt, pt in times), (t, times[:3])
        assert any(pt < lt for lt, pt in times), t
    losses = [m.data for _ts, m in rb[f"{tag}/loss"]]
    assert [v[0] for v in losses] == list(range(len(sent[f"{tag}/loss"])))
    assert all(np.isnan(v[2]) for v in losses)
    assert rb[f"{tag}/diag"][2][1].status[0].values[0].value == "2"
    assert rb[f"{tag}/diag"][2][1].status[0].level == DiagnosticStatus.WARN[0]
    # QoS as the publishers offered it, parsed by rosbags' own rosbag2 QoS parser
    q = {t: c.ext.offered_qos_profiles[0] for t, c in conns.items()}
    assert q[f"{tag}/img"].reliability == QosReliability.BEST_EFFORT
    assert q[f"{tag}/pc"].durability == QosDurability.TRANSIENT_LOCAL
    assert q[f"{tag}/str"].reliability == QosReliability.RELIABLE
    assert q[f"{tag}/str"].durability == QosDurability.VOLATILE
    assert q[f"{tag}/str"].deadline.sec == 9223372036  # infinite, as rmw reports today
    # timestamps: log time = receive time, increasing (publish time: checked above)
    lt = [x[0] for x in mr[f"{tag}/str"]]
    assert lt == sorted(lt)
    assert [x[0] for x in rb[f"{tag}/str"]] == lt


# ----------------------------------------------------------------------------- training
@pytest.fixture(scope="module")
def training_bag(tmp_path_factory):
    """`ooi-seg train` on a tiny simulated capture (10 views, 48x36, 10 iterations)."""
    import torch
    from PIL import Image as PILImage

    from ooi_seg_ros.capture_io import write_capture
    from ooi_seg_ros.cli import train as train_cli
    from ooi_seg_ros.sim import simulate_capture

    torch.set_num_threads(1)
    tmp = tmp_path_factory.mktemp("train")
    cap = simulate_capture("aircraft", n_views=10, width=48, height=36, seed=0,
                           supersample=1).capture
    write_capture(cap, tmp / "cap")
    (tmp / "masks").mkdir()
    for v in cap.views:
        PILImage.fromarray(v.gt_mask.astype(np.uint8) * 255).save(tmp / "masks" / f"{v.key}.png")
    (tmp / "c.yaml").write_text("max_gaussians: 300\nsnapshot_every: 5\neval_every: 5\n")
    args = Namespace(input=str(tmp / "cap"), out=str(tmp / "out"), iterations=10,
                     max_gaussians=None, masks=str(tmp / "masks"), init=None, full_image=False,
                     sh_degree=None, seed=None, backend="cpu", config=str(tmp / "c.yaml"),
                     sim_views=60, sim_size="320x240", quiet=True)
    assert train_cli.run(args) == 0
    return tmp / "out"


def test_training_bag_in_both_readers(training_bag):
    from ooi_seg_ros.train.gaussians import PLY_FIELDS, load_ply

    bag = training_bag / "training.mcap"
    res = _assert_agree(bag)
    assert res.ours.counts["/train/masks"] == 10
    rb, conns = _rosbags_read(bag)
    mr = _mcap_ros2_read(bag)
    # the splats' PointCloud2 fields carry the 3DGS PLY names; the last snapshot is the PLY
    last = rb["/train/splats"][-1][1]
    names = [f.name for f in last.fields]
    assert names == [n for n in PLY_FIELDS if n not in ("nx", "ny", "nz")]
    assert {f.datatype for f in last.fields} == {7} and last.point_step == 4 * len(names)
    cols = last.data.view(np.float32).reshape(last.width, len(names))
    model = load_ply(training_bag / "splats.ply")
    assert np.array_equal(cols[:, :3], model.means.numpy().astype(np.float32))
    # the loss curve: Float32 per step, the same in both readers and in report.json
    rb_loss = [m.data for _t, m in rb["/train/loss"]]
    assert rb_loss == [m.data for _lt, _pt, m in mr["/train/loss"]] and len(rb_loss) >= 2
    assert all(np.isfinite(rb_loss))
    # masks as mono8 with their view key as frame id
    m0 = rb["/train/masks"][0][1]
    assert m0.encoding == "mono8" and set(np.unique(m0.data)) <= {0, 255}
    assert conns["/train/preview/v0"].msgtype == "sensor_msgs/msg/Image"


# ----------------------------------------------------------------------------- SIGKILL
_KILLED_WRITER = """
import os, signal, sys
from std_msgs.msg import String
from ooi_seg_ros.bag import BagWriter
w = BagWriter(sys.argv[1], chunk_size=300, atomic=False)
w.add_topic("/chatter", "std_msgs/msg/String", "sensor_data")
w.add_topic("/img", "sensor_msgs/msg/Image")
from ooi_seg_ros import msgconv
import numpy as np
for i in range(60):
    w.write("/chatter", String(data=f"message {i}"), 1000 + 10 * i, 2000 + 10 * i, i)
    if i % 10 == 0:
        w.write("/img", msgconv.rgb_to_image(np.full((2, 3, 3), i, np.uint8), 1000 + 10 * i),
                1000 + 10 * i + 5)
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_sigkilled_writer_rejected_by_both_then_recovered(tmp_path):
    """A writer killed with SIGKILL: ours reads up to its last chunk; rosbags and mcap_ros2
    reject the file (no footer); ``recover_bag`` makes a finished copy both read in full."""
    p = tmp_path / "killed.mcap"
    proc = subprocess.run([sys.executable, "-c", _KILLED_WRITER, str(p)], cwd=ROOT,
                          capture_output=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()
    r = BagReader(p)
    assert r.truncated and "ooi-seg recover" in r.warnings[0]
    ours = list(r.records())
    assert 40 <= len(ours) < 66  # all but the chunk in progress
    with pytest.raises(Exception, match="magic"):
        with AnyReader([p]):
            pass
    with pytest.raises(Exception):
        list(read_ros2_messages(str(p)))
    fixed = tmp_path / "fixed.mcap"
    assert recover_bag(p, fixed) == len(ours)
    res = _assert_agree(fixed)
    assert res.rosbags.decoded == len(ours)
    mr = _mcap_ros2_read(fixed)
    got = mr["/chatter"]
    assert [m.data for _lt, _pt, m in got] == [f"message {i}" for i in range(len(got))]
    want = [(1000 + 10 * i, 2000 + 10 * i) for i in range(len(got))]
    assert [(lt, pt) for lt, pt, _m in got] == want
    with open(fixed, "rb") as f:
        seqs = [m.sequence for _s, ch, m in make_reader(f).iter_messages()
                if ch.topic == "/chatter"]
    assert seqs == list(range(len(got)))
    with pytest.raises(InputError, match="itself"):
        recover_bag(fixed, fixed)


@pytest.mark.slow
def test_sigkilled_record_process(tmp_path):
    """`ooi-seg record` killed with SIGKILL while a publisher runs: recovered, both readers
    decode every message ours reads from the damaged file."""
    out = tmp_path / "rec.mcap"
    topic = f"/k{os.getpid()}_{time.monotonic_ns() % 10**6}"
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    rec = subprocess.Popen([sys.executable, "-m", "ooi_seg_ros.cli", "record", "--out",
                            str(out), "--chunk-size", "512", topic], cwd=ROOT, env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        node = Node("interop_kill_pub", context=ctx)
        pub = node.create_publisher(String, topic, 10)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not pub.get_subscription_count():
            time.sleep(0.05)
        assert pub.get_subscription_count(), "recorder never subscribed"
        for i in range(150):
            pub.publish(String(data=f"msg {i}"))
            time.sleep(0.005)
        time.sleep(1.0)
    finally:
        rec.send_signal(signal.SIGKILL)
        rec.wait(timeout=30)
        rclpy.shutdown(context=ctx)
    r = BagReader(out)
    assert r.truncated
    n = sum(1 for _ in r.records())
    assert n >= 100
    fixed = tmp_path / "fixed.mcap"
    # as a user would: the CLI subcommand the reader's warning names
    proc = subprocess.run([sys.executable, "-m", "ooi_seg_ros.cli", "recover", str(out),
                           "--out", str(fixed)], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert f"wrote {fixed}: {n} messages" in proc.stdout
    res = _assert_agree(fixed)
    assert res.mcap_ros2.counts[topic] == n
    missing = subprocess.run([sys.executable, "-m", "ooi_seg_ros.cli", "recover",
                              str(tmp_path / "nope.mcap"), "--out", str(fixed)], cwd=ROOT,
                             capture_output=True, text=True, timeout=120)
    assert missing.returncode == 1 and "does not exist" in missing.stderr


# ----------------------------------------------------------------------------- QoS layout
def test_qos_written_in_rosbag2_version_9_layout(tmp_path):
    """Jazzy's rosbag2 (metadata version 9) reads QoS enums by name: an integer there reads
    as "unknown". Whatever QoS text a caller gives, the file holds the version 9 layout in
    the channels and a YAML list in the rosbag2 record; rosbags parses it back exactly."""
    p = tmp_path / "q.mcap"
    with BagWriter(p) as w:
        w.add_topic("/rec", "std_msgs/msg/String", RECORDER_QOS)
        w.add_topic("/lat", "std_msgs/msg/String", "transient_local")
        w.add_topic("/named", "std_msgs/msg/String",
                    "- {history: keep_all, depth: 0, reliability: best_effort, "
                    "durability: volatile}")
        for i, t in enumerate(("/rec", "/lat", "/named")):
            w.write(t, String(data=t), 100 + i)
    assert file_problems(p) == []
    with open(p, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        chans = {c.topic: c.metadata for c in reader.get_summary().channels.values()}
        meta = yaml.safe_load([m for m in reader.iter_metadata()
                               if m.name == "rosbag2"][0].metadata["serialized_metadata"])
    rec = yaml.safe_load(chans["/rec"]["offered_qos_profiles"])[0]
    assert rec["history"] == "unknown" and rec["reliability"] == "best_effort"
    assert rec["deadline"] == {"sec": 9223372036, "nsec": 854775807}
    assert meta["version"] == 9
    listed = {t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"]
              for t in meta["topics_with_message_count"]}
    assert listed["/lat"] == [yaml.safe_load(chans["/lat"]["offered_qos_profiles"])[0]]
    assert listed["/lat"][0]["durability"] == "transient_local"
    _rb, conns = _rosbags_read(p)
    assert conns["/named"].ext.offered_qos_profiles[0].reliability == \
        QosReliability.BEST_EFFORT
    assert conns["/lat"].ext.offered_qos_profiles[0].durability == \
        QosDurability.TRANSIENT_LOCAL
    # the version 8 layout (integers) is one call away, e.g. to compare with older bags
    assert qos_profiles(chans["/lat"]["offered_qos_profiles"], 8)[0]["durability"] == 1
    assert canonical_qos(canonical_qos(RECORDER_QOS, 8)) == canonical_qos(RECORDER_QOS)
    with pytest.raises(InputError, match="integers"):
        BagWriter(tmp_path / "bad.mcap").add_topic("/t", "std_msgs/msg/String",
                                                   "- {depth: many}")


# ----------------------------------------------------------------------------- their bags
@needs_data
def test_rosbag2_written_files_read_the_same():
    """Files written by rosbag2 / the Go mcap tool: both readers agree with ours."""
    res = check_bag(DATA / "only_topics.mcap")
    assert res.ok, res.summary()
    assert res.ours.counts == {"/parameter_events": 7}
    res = check_bag(DATA / "talker" / "talker.mcap")
    assert not any(r.mismatches or r.error for r in (res.ours, res.rosbags, res.mcap_ros2))
    assert res.ours.counts == res.rosbags.counts == {"/topic": 10, "/rosout": 10}
    # the Go tool wrote no rosbag2 record; only that is missing
    assert res.problems == ["no 'rosbag2' metadata record (ros2 bag info reads it)"]
    # the folder: its metadata.yaml's QoS (deadline 0) differ from the file's channels
    # (Foxy infinities), so rosbags matches no connection and yields nothing; ours and
    # mcap_ros2 read all 20
    res = check_bag(DATA / "talker")
    assert res.ours.decoded == res.mcap_ros2.decoded == 20 and res.rosbags.decoded == 0
    # and our reader gives the folder's QoS from its metadata.yaml, as ros2 bag play uses
    # them and rosbags reports them
    qos = BagReader(DATA / "talker").topics()["/topic"].qos
    assert yaml.safe_load(qos)[0]["deadline"] == {"sec": 0, "nsec": 0}
    assert [q["deadline"] for q in res.rosbags.qos["/topic"]] == [{"sec": 0, "nsec": 0}]


def test_checks_catch_a_definition_that_does_not_match(tmp_path):
    """The checks have teeth: a schema that does not describe the data is caught, and a
    definition that is not the installed one gets no (wrong) installed type hash."""
    from std_msgs.msg import Float32

    from ooi_seg_ros.bag import message_definition, type_hash

    wrong = message_definition("std_msgs/msg/Float32").replace("float32", "float64")
    p = tmp_path / "wrong.mcap"
    with BagWriter(p) as w:
        w.add_topic("/f", "std_msgs/msg/Float32", definition=wrong)
        w.write("/f", Float32(data=1.5), 10)
    with open(p, "rb") as f:
        (ch,) = make_reader(f).get_summary().channels.values()
    assert "topic_type_hash" not in ch.metadata
    res = check_bag(p)
    assert not res.ok and (res.rosbags.error or res.rosbags.mismatches)
    assert res.mcap_ros2.error or res.mcap_ros2.mismatches
    q = tmp_path / "wrong_hash.mcap"
    with BagWriter(q) as w:
        w.add_topic("/f", "std_msgs/msg/Float32", definition=wrong,
                    type_hash=type_hash("std_msgs/msg/Float32"))
        w.write("/f", Float32(data=1.5), 10)
    assert any("topic_type_hash" in x for x in check_bag(q).problems)


def test_other_version_of_a_type_decodes_by_its_own_definition(tmp_path):
    """A bag from another version of a type (its hash is not the installed one) is decoded by
    the definition it carries, as the independent readers do, not by the installed class."""
    from std_msgs.msg import Float32

    other = "float32 value\n"  # same bytes on the wire, another field name
    p = tmp_path / "other.mcap"
    with BagWriter(p) as w:
        w.add_topic("/f", "std_msgs/msg/Float32", definition=other,
                    type_hash="RIHS01_" + "ab" * 32)
        w.write("/f", Float32(data=1.5), 10)
    r = BagReader(p)
    (m,) = list(r.records())
    assert r.decode(m.type, m.data, m.topic).value == 1.5
    assert r.decode(m.type, m.data).data == 1.5  # without the topic: the installed class
    (rb,) = _rosbags_read(p)[0]["/f"]
    assert rb[1].value == 1.5


def test_training_node_recording_in_both_readers(tmp_path):
    """The training node's own recording (inputs and outputs, written while it runs)."""
    import uuid

    from rclpy.parameter import Parameter
    from std_srvs.srv import Trigger

    from ooi_seg_ros.nodes.common import mask_frame_id
    from ooi_seg_ros.nodes.training_node import TrainingNode

    r = BagReader(DEMO)
    names = {"/camera/camera_info": 0, "/camera/pose": 1, "/camera/image_raw": 2,
             "/ground_truth/mask": 3}
    demo = [[], [], [], []]
    for topic, ty, _t, data in r.messages(topics=list(names)):
        demo[names[topic]].append(r.decode(ty, data))
    bag = tmp_path / "node.mcap"
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        ns = "/tb_" + uuid.uuid4().hex[:8]
        node = TrainingNode(context=ctx, namespace=ns, parameter_overrides=[
            Parameter("record_path", value=str(bag)), Parameter("stable_updates", value=1),
            Parameter("train.iterations", value=3), Parameter("train.eval_every", value=0),
            Parameter("train.snapshot_every", value=0),
            Parameter("train.max_gaussians", value=300)])
        try:
            for info, pose, img, gt in list(zip(*demo))[:8]:
                node.on_kf_info(info)
                node.on_kf_pose(pose)
                node.on_kf_image(img)
                node.on_mask(msgconv.mask_to_image(msgconv.image_to_mask(gt), gt.header.stamp,
                                                   mask_frame_id(False)))
            xyz = np.random.default_rng(0).normal(scale=0.2, size=(200, 3))
            cloud = msgconv.xyzrgb_to_pointcloud2(xyz, None, demo[2][7].header.stamp)
            node.on_ooi_points(cloud)
            node.on_ooi_points(cloud)
            assert node.on_train_srv(Trigger.Request(), Trigger.Response()).success
            assert node.wait_idle(120) and node.runs == 1
        finally:
            node.close()
            node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
    res = _assert_agree(bag)
    assert res.ours.counts[f"{ns}/keyframe/image"] == 8
    assert res.ours.counts[f"{ns}/splats"] >= 1
    (_t, splats), *_ = _rosbags_read(bag)[0][f"{ns}/splats"]
    assert [f.name for f in splats.fields][:4] == ["x", "y", "z", "f_dc_0"]


@pytest.mark.parametrize("version", [8, 9])
def test_bag_written_by_rosbags_reads_in_ours(tmp_path, version):
    """The reverse direction: a rosbag2 folder written by rosbags' own writer (MCAP storage,
    metadata version 8 or 9 with its QoS layout) reads in ours with the same values, and
    its QoS reach `play` as written."""
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
    from rosbags.interfaces import Qos, QosHistory, QosLiveliness, QosTime
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from ooi_seg_ros.nodes.bagplay import qos_from_offered

    ts = get_typestore(Stores.ROS2_JAZZY)
    inf = QosTime(9223372036, 854775807)

    def qos(rel, dur):
        return [Qos(QosHistory.KEEP_LAST, 7, rel, dur, inf, inf, QosLiveliness.AUTOMATIC, inf,
                    False)]

    Img, Hdr, Time = (ts.types[n] for n in ("sensor_msgs/msg/Image", "std_msgs/msg/Header",
                                            "builtin_interfaces/msg/Time"))
    Str = ts.types["std_msgs/msg/String"]
    folder = tmp_path / f"rb{version}"
    with Writer(folder, version=version, storage_plugin=StoragePlugin.MCAP) as w:
        ci = w.add_connection("/img", "sensor_msgs/msg/Image", typestore=ts,
                              offered_qos_profiles=qos(QosReliability.BEST_EFFORT,
                                                       QosDurability.VOLATILE))
        cs = w.add_connection("/str", "std_msgs/msg/String", typestore=ts,
                              offered_qos_profiles=qos(QosReliability.RELIABLE,
                                                       QosDurability.TRANSIENT_LOCAL))
        for i in range(4):
            px = np.full(2 * 3 * 3, i, np.uint8)
            img = Img(Hdr(Time(1, i), "cam"), 2, 3, "rgb8", 0, 9, px)
            w.write(ci, 100 + i, ts.serialize_cdr(img, "sensor_msgs/msg/Image"))
            w.write(cs, 100 + i, ts.serialize_cdr(Str(f"s{i}"), "std_msgs/msg/String"))
    meta = yaml.safe_load((folder / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == version
    for path in (folder, next(folder.glob("*.mcap"))):
        r = BagReader(path)
        topics = r.topics()
        assert {t: i.count for t, i in topics.items()} == {"/img": 4, "/str": 4}
        got = [(m.topic, m.log_time_ns, r.decode(m.type, m.data, m.topic)) for m in r.records()]
        imgs = [m for t, _lt, m in got if t == "/img"]
        assert [msgconv.image_to_rgb(m)[0, 0, 0] for m in imgs] == [0, 1, 2, 3]
        assert [m.header.stamp.nanosec for m in imgs] == [0, 1, 2, 3]
        assert [m.data for t, _lt, m in got if t == "/str"] == ["s0", "s1", "s2", "s3"]
        q_img, q_str = qos_from_offered(topics["/img"].qos), qos_from_offered(topics["/str"].qos)
        assert q_img.reliability == ReliabilityPolicy.BEST_EFFORT and q_img.depth == 7
        assert q_str.durability == DurabilityPolicy.TRANSIENT_LOCAL
    res = check_bag(folder)
    assert not any(r.mismatches or r.error for r in (res.ours, res.rosbags, res.mcap_ros2))
