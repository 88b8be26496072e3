"""rosbag2-compatible MCAP I/O: files from rosbag2 itself, byte-exact round trips, damage."""

import struct
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from sensor_msgs.msg import Image
from std_msgs.msg import String

from ooi_seg_ros import msgconv
from ooi_seg_ros.bag import QOS_PRESETS, BagReader, BagWriter, message_definition
from ooi_seg_ros.cli import main as cli_main
from ooi_seg_ros.core.types import InputError

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "rosbag2-recorded"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason="shared rosbag2 test bags missing")


@needs_data
def test_reads_rosbag2_written_file():
    r = BagReader(DATA / "only_topics.mcap")
    topics = r.topics()
    assert set(topics) == {"/rosout", "/parameter_events", "/events/write_split"}
    assert topics["/parameter_events"].count == 7
    assert topics["/events/write_split"].type == "rosbag2_interfaces/msg/WriteSplitEvent"
    assert "reliability: 1" in topics["/rosout"].qos
    assert not r.warnings
    msgs = list(r.messages())
    assert len(msgs) == 7 and all(m[0] == "/parameter_events" for m in msgs)
    ev = r.decode(msgs[0][1], msgs[0][3], msgs[0][0])
    assert type(ev).__name__ == "ParameterEvent" and ev.node == "/introspection_client"
    # a type the wheels do not install decodes from the definition embedded in the file
    cdr = b"\x00\x01\x00\x00" + struct.pack("<I", 4) + b"a.m\x00" + struct.pack("<I", 4) + \
        b"b.m\x00"
    split = r.decode("rosbag2_interfaces/msg/WriteSplitEvent", cdr, "/events/write_split")
    assert split.closed_file == "a.m" and split.opened_file == "b.m"
    with pytest.raises(InputError, match="not installed"):
        r.decode("rosbag2_interfaces/msg/WriteSplitEvent", cdr)


@needs_data
def test_reads_rosbag2_directory():
    r = BagReader(DATA / "talker")
    topics = r.topics()
    assert topics["/topic"].type == "std_msgs/msg/String" and topics["/topic"].count == 10
    texts = [r.decode(ty, d, t).data for t, ty, _, d in r.messages(topics=["/topic"])]
    assert texts[0] == "Hello, world! 0" and len(texts) == 10
    t0, t1 = r.time_span()
    assert t1 - t0 == 4531096768
    late = list(r.messages(start_ns=t0 + 2_000_000_000))
    assert 0 < len(late) < 20 and all(m[2] >= t0 + 2_000_000_000 for m in late)


@needs_data
def test_definition_format_matches_rosbag2():
    with open(DATA / "only_topics.mcap", "rb") as f:
        theirs = make_reader(f).get_summary().schemas[2].data.decode()
    ours = message_definition("rcl_interfaces/msg/ParameterEvent")
    sep = [ln for ln in theirs.splitlines() if ln.startswith("MSG: ") or ln.startswith("====")]
    assert [ln for ln in ours.splitlines() if ln.startswith("MSG: ") or ln.startswith("====")] \
        == sep
    img = message_definition("sensor_msgs/msg/Image")
    assert "\n" + "=" * 80 + "\nMSG: std_msgs/Header\n" in img
    assert "MSG: builtin_interfaces/Time" in img
    assert message_definition("no_such_pkg/msg/Thing") is None


def _write_demo(path, n=5, chunk_size=1 << 20, atomic=True):
    with BagWriter(path, chunk_size=chunk_size, atomic=atomic) as w:
        w.add_topic("/chatter", "std_msgs/msg/String", "sensor_data")
        w.add_topic("/img", "sensor_msgs/msg/Image")
        for i in range(n):
            w.write("/chatter", String(data=f"msg {i}"), 1000 + 10 * i)
            rgb = np.full((4, 6, 3), i, np.uint8)
            w.write("/img", msgconv.rgb_to_image(rgb, 1000 + 10 * i), 1000 + 10 * i + 5)
    return path


def test_written_file_is_rosbag2_shaped(tmp_path):
    p = _write_demo(tmp_path / "demo.mcap")
    with open(p, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        s = reader.get_summary()
        assert {sc.encoding for sc in s.schemas.values()} == {"ros2msg"}
        for ch in s.channels.values():
            assert ch.message_encoding == "cdr"
            assert yaml.safe_load(ch.metadata["offered_qos_profiles"])[0]["history"] == \
                "keep_last"  # rosbag2 metadata version 9: rmw enum names
            assert ch.metadata["topic_type_hash"].startswith("RIHS01_")
        assert {ci.compression for ci in s.chunk_indexes} == {"zstd"}
        meta = [m for m in reader.iter_metadata() if m.name == "rosbag2"]
    assert len(meta) == 1 and meta[0].metadata["ros_distro"] == "jazzy"
    info = yaml.safe_load(meta[0].metadata["serialized_metadata"])
    assert info["message_count"] == 10 and info["storage_identifier"] == "mcap"
    counts = {t["topic_metadata"]["name"]: t["message_count"]
              for t in info["topics_with_message_count"]}
    assert counts == {"/chatter": 5, "/img": 5}
    assert info["duration"]["nanoseconds"] == 45


def test_round_trip_bytes_and_rewrite_identical(tmp_path):
    a = _write_demo(tmp_path / "a" / "bag.mcap")
    r = BagReader(a)
    recs = list(r.records())
    assert [m.data for m in recs if m.topic == "/chatter"] == \
        [bytes(msgconv_serialize(String(data=f"msg {i}"))) for i in range(5)]
    back = r.decode("sensor_msgs/msg/Image", recs[1].data)
    assert isinstance(back, Image) and msgconv.image_to_rgb(back)[0, 0, 0] == 0
    b = tmp_path / "b" / "bag.mcap"
    with BagWriter(b) as w:
        for t, info in r.topics().items():
            w.add_topic(t, info.type, info.qos)
        for m in recs:
            w.write(m.topic, m.data, m.log_time_ns, m.publish_time_ns, m.sequence)
    assert a.read_bytes() == b.read_bytes()


def msgconv_serialize(msg):
    from rclpy.serialization import serialize_message
    return serialize_message(msg)


def test_atomic_write_leaves_no_complete_looking_file(tmp_path):
    p = tmp_path / "x.mcap"
    w = BagWriter(p)
    w.add_topic("/chatter", "std_msgs/msg/String")
    w.write("/chatter", String(data="a"), 1)
    assert not p.exists() and (tmp_path / "x.mcap.part").exists()
    w.close()
    assert p.exists() and not (tmp_path / "x.mcap.part").exists()
    q = tmp_path / "y.mcap"
    with pytest.raises(RuntimeError):
        with BagWriter(q) as w2:
            w2.add_topic("/chatter", "std_msgs/msg/String")
            raise RuntimeError("boom")
    assert not q.exists() and not (tmp_path / "y.mcap.part").exists()


def test_truncated_file_reads_complete_chunks(tmp_path):
    p = _write_demo(tmp_path / "rec.mcap", n=40, chunk_size=256, atomic=False)
    full = len(list(BagReader(p).messages()))
    cut = tmp_path / "cut.mcap"
    data = p.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.3)])
    r = BagReader(cut)
    assert r.truncated and "truncated" in r.warnings[0]
    got = list(r.messages())
    assert 0 < len(got) < full
    times = [m[2] for m in got]
    assert times == sorted(times)
    assert r.topics()["/chatter"].count + r.topics()["/img"].count == len(got)


def test_bad_inputs_raise_input_error(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        BagReader(tmp_path / "missing.mcap")
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an mcap file at all" * 10)
    with pytest.raises(InputError, match="not a readable MCAP"):
        BagReader(junk)
    empty_dir = tmp_path / "empty"
    empty_dir.mkdir()
    with pytest.raises(InputError, match="no .mcap"):
        BagReader(empty_dir)
    p = _write_demo(tmp_path / "ok.mcap", n=1)
    with pytest.raises(InputError, match="/camera/image_raw"):
        BagReader(p).require_topics(["/camera/image_raw"])
    with pytest.raises(InputError, match="preset"):
        BagWriter(tmp_path / "q.mcap").add_topic("/t", "std_msgs/msg/String", "fast please")
    w = BagWriter(tmp_path / "n.mcap")
    with pytest.raises(InputError, match="not installed"):
        w.add_topic("/t", "no_such_pkg/msg/Thing")
    with pytest.raises(InputError, match="add_topic"):
        w.write("/u", b"\x00\x01\x00\x00", 5)
    w.abort()
    assert set(QOS_PRESETS) == {"sensor_data", "reliable", "transient_local"}


@needs_data
def test_info_cli(tmp_path, capsys):
    assert cli_main(["info", str(DATA / "talker")]) == 0
    out = capsys.readouterr().out
    assert "/topic" in out and "std_msgs/msg/String" in out and "4.531 s" in out
    p = _write_demo(tmp_path / "d.mcap", n=2)
    assert cli_main(["info", str(p)]) == 0
    out = capsys.readouterr().out
    assert "6x4 rgb8" in out
    assert cli_main(["info", str(tmp_path / "nope.mcap")]) == 1


def test_unclosed_in_place_writer_is_readable_up_to_last_chunk(tmp_path):
    """What a SIGKILL-ed recorder leaves: flushed chunks, no summary."""
    p = tmp_path / "live.mcap"
    w = BagWriter(p, chunk_size=200, atomic=False)
    w.add_topic("/chatter", "std_msgs/msg/String")
    for i in range(50):
        w.write("/chatter", String(data=f"message number {i}"), 10 + i)
    r = BagReader(p)  # the writer is still open: nothing after the last full chunk
    got = [r.decode(ty, d).data for _, ty, _, d in r.messages()]
    assert r.truncated and 0 < len(got) <= 50
    assert got == [f"message number {i}" for i in range(len(got))]
    w.close()
    assert len(list(BagReader(p).messages())) == 50 and not BagReader(p).truncated


def test_serialize_zeroes_padding_and_matches_rclpy():
    """rclpy leaves CDR alignment padding uninitialised; bag bytes must not depend on it."""
    from rclpy.serialization import deserialize_message, serialize_message

    from ooi_seg_ros.bag.mcap_bag import serialize
    from ooi_seg_ros.core.types import CameraIntrinsics
    msgs = [msgconv.rgb_to_image(np.zeros((3, 5, 3), np.uint8), 5),
            msgconv.intrinsics_to_camera_info(CameraIntrinsics(8, 6, 5, 5, 3, 2), 7),
            msgconv.xyzrgb_to_pointcloud2(np.ones((4, 3)), np.zeros((4, 3), np.uint8), 3)]
    for m in msgs:
        outs = set()
        for _ in range(5):
            _junk = [serialize_message(String(data="x" * k)) for k in range(1, 60)]
            outs.add(serialize(m))
        assert len(outs) == 1 and _junk
        data = outs.pop()
        assert len(data) == len(serialize_message(m))
        assert serialize_message(deserialize_message(data, type(m))).__len__() == len(data)
        assert deserialize_message(data, type(m)) == m
    # the Image padding after is_bigendian (bytes 50, 51) is zero
    assert serialize(msgs[0])[50:52] == b"\x00\x00"


def test_corrupted_chunk_and_foreign_storage(tmp_path):
    p = _write_demo(tmp_path / "c.mcap", n=10)
    data = bytearray(p.read_bytes())
    with open(p, "rb") as f:
        ci = make_reader(f).get_summary().chunk_indexes[0]
    mid = ci.chunk_start_offset + ci.chunk_length // 2
    data[mid:mid + 16] = b"\xff" * 16
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError, match="damaged|mcap recover"):
        list(BagReader(bad).messages())
    d = tmp_path / "sqlite_bag"
    d.mkdir()
    (d / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": {
        "storage_identifier": "sqlite3", "relative_file_paths": ["x.db3"]}}))
    with pytest.raises(InputError, match="ros2 bag convert"):
        BagReader(d)
    (d / "metadata.yaml").write_text("rosbag2_bagfile_information: [oops")
    with pytest.raises(InputError, match="metadata"):
        BagReader(d)
