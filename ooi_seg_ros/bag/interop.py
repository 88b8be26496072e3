"""Reads a bag with independent ROS 2 bag readers and checks they agree with ours.

``ros2 bag`` and the Go ``mcap`` CLI are not installable from PyPI, so two readers that share
no code with our writer stand in for them:

- ``rosbags`` (Ternaris): its own MCAP parser, ``.msg`` parser, CDR deserialiser and rosbag2
  metadata/QoS parser; it also computes RIHS01 type hashes from the embedded definitions.
- ``mcap-ros2-support`` (Foxglove): its ``ros2msg`` schema parser and CDR decoder over the
  ``mcap`` reader (``read_ros2_messages``), what Foxglove Studio uses.

``check_bag`` decodes every message of every topic with each reader, compares the decoded
fields and the timestamps with what our ``BagReader`` (rclpy's deserialiser) gives, and checks
the file-level conventions of rosbag2's MCAP storage plugin (profile, schemas, channel
metadata, the ``rosbag2`` metadata record). Both readers are optional imports: this module is
a checking tool, the package itself does not need them.

Run it as ``python -m ooi_seg_ros.bag.interop BAG...``.
"""

from __future__ import annotations

import array
import dataclasses
import math
import os
import sys
import time
from pathlib import Path
from typing import Any, Optional, Union

import numpy as np
import yaml

from .mcap_bag import BagReader, _bag_files, canonical_qos

# QoS enum names as rmw (and rosbag2 >= version 9) spell them, by rmw's integer values.
_ENUMS = {
    "history": ("system_default", "keep_last", "keep_all", "unknown"),
    "reliability": ("system_default", "reliable", "best_effort", "unknown", "best_available"),
    "durability": ("system_default", "transient_local", "volatile", "unknown", "best_available"),
    "liveliness": ("system_default", "automatic", "manual_by_node", "manual_by_topic",
                   "unknown", "best_available"),
}


@dataclasses.dataclass
class ReaderReport:
    """What one reader made of one bag."""

    reader: str
    accepted: bool = False  # opened the bag and listed its topics
    error: str = ""  # the first exception (type: message) when it failed somewhere
    topics: dict[str, str] = dataclasses.field(default_factory=dict)  # topic -> type
    counts: dict[str, int] = dataclasses.field(default_factory=dict)  # decoded per topic
    decoded: int = 0  # messages decoded
    mismatches: list[str] = dataclasses.field(default_factory=list)  # vs our reader
    qos: dict[str, list[dict]] = dataclasses.field(default_factory=dict)  # parsed profiles
    wall_s: float = 0.0  # open + decode every message (into the reader's own objects + plain)
    cpu_s: float = 0.0


@dataclasses.dataclass
class BagCheck:
    """The result of ``check_bag``: one report per reader plus file-level problems."""

    path: str
    ours: ReaderReport
    rosbags: ReaderReport
    mcap_ros2: ReaderReport
    problems: list[str] = dataclasses.field(default_factory=list)  # convention violations

    @property
    def ok(self) -> bool:
        """Every reader accepted the bag, decoded it all, agreed with ours; no problems."""
        reps = (self.ours, self.rosbags, self.mcap_ros2)
        return (not self.problems and all(r.accepted and not r.error and not r.mismatches
                                          for r in reps)
                and all(r.counts == self.ours.counts for r in reps))

    def summary(self) -> str:
        """One line per reader."""
        lines = [f"{self.path}:"]
        for r in (self.ours, self.rosbags, self.mcap_ros2):
            state = "accepted" if r.accepted else "REJECTED"
            lines.append(f"  {r.reader:10s} {state}, {r.decoded} messages decoded, "
                         f"{len(r.mismatches)} mismatches, {r.wall_s:.2f} s "
                         f"({r.cpu_s:.2f} CPU-s)"
                         + (f"; error {r.error}" if r.error else ""))
            lines.extend(f"      {m}" for m in r.mismatches[:5])
        lines.extend(f"  problem: {p}" for p in self.problems)
        return "\n".join(lines)


# ----------------------------------------------------------------------------- normalising
def plain(obj: Any) -> Any:
    """A tree of dict/list/bytes/str/int/float/bool of a decoded message from any reader.

    rclpy messages, rosbags dataclasses (numpy arrays) and mcap_ros2's dynamic namespaces
    (bytes for uint8[]) all map to the same tree, so decoded messages can be compared.
    uint8/byte sequences become ``bytes``; other sequences lists.
    """
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj)
    if isinstance(obj, (bytes, bytearray, memoryview)):
        return bytes(obj)
    if isinstance(obj, np.ndarray):
        if obj.dtype in (np.uint8, np.int8) and obj.ndim == 1:
            return obj.astype(np.uint8).tobytes()
        return [plain(v) for v in obj.tolist()]
    if isinstance(obj, array.array):
        return obj.tobytes() if obj.typecode in ("B", "b") else [plain(v) for v in obj]
    if isinstance(obj, (list, tuple)):
        if obj and all(isinstance(v, bytes) and len(v) == 1 for v in obj):
            return b"".join(obj)  # rclpy's byte[] is a list of 1-byte bytes
        return [plain(v) for v in obj]
    if hasattr(obj, "get_fields_and_field_types"):  # rclpy message
        # rclpy gives a scalar ``byte`` as 1-byte bytes; the other readers as an int
        return {k: (getattr(obj, k)[0] if t == "octet" else plain(getattr(obj, k)))
                for k, t in obj.get_fields_and_field_types().items()}
    if dataclasses.is_dataclass(obj):  # rosbags message
        names = [f.name for f in dataclasses.fields(obj)]
    elif hasattr(type(obj), "__slots__"):  # mcap_ros2 dynamic message
        names = list(type(obj).__slots__)
    else:
        raise TypeError(f"cannot normalise a {type(obj).__name__}")
    # fields only: ROS field names are lower case, constants upper case; "__msgtype__" etc.
    # are the readers' own bookkeeping
    return {k: plain(getattr(obj, k)) for k in names
            if not k.startswith("_") and not k.isupper()}


def _normalise_bytes(tree: Any) -> Any:
    """Empty byte-like fields compare equal whether a reader gave b'' or []."""
    if isinstance(tree, dict):
        return {k: _normalise_bytes(v) for k, v in tree.items()}
    if isinstance(tree, list):
        return b"" if not tree else [_normalise_bytes(v) for v in tree]
    return tree


def first_difference(a: Any, b: Any, path: str = "") -> Optional[str]:
    """Where two ``plain`` trees differ (NaN equals NaN), or None when they are equal."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return f"{path or '.'}: fields {sorted(a)} != {sorted(b)}"
        for k in a:
            d = first_difference(a[k], b[k], f"{path}.{k}")
            if d:
                return d
        return None
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return f"{path}: length {len(a)} != {len(b)}"
        for i, (x, y) in enumerate(zip(a, b)):
            d = first_difference(x, y, f"{path}[{i}]")
            if d:
                return d
        return None
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return None
    if type(a) is not type(b) and not (isinstance(a, (int, float)) and
                                       isinstance(b, (int, float))):
        return f"{path}: {type(a).__name__} {str(a)[:40]} != {type(b).__name__} {str(b)[:40]}"
    if a != b:
        return f"{path}: {str(a)[:60]} != {str(b)[:60]}"
    return None


# ----------------------------------------------------------------------------- readers
def _err(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}"


def read_ours(path: Union[str, Path]) -> tuple[ReaderReport, dict[str, list]]:
    """Our BagReader + rclpy deserialisation: (report, {topic: [(log, publish, plain)]})."""
    rep = ReaderReport("ours")
    out: dict[str, list] = {}
    try:
        r = BagReader(path)
        infos = r.topics()
        rep.accepted = True
        rep.topics = {t: i.type for t, i in infos.items()}
        rep.qos = {t: _load_profiles(i.qos) for t, i in infos.items()}
        for m in r.records():
            msg = r.decode(m.type, m.data, m.topic)
            out.setdefault(m.topic, []).append((m.log_time_ns, m.publish_time_ns, plain(msg)))
            rep.decoded += 1
        if r.warnings:
            rep.error = r.warnings[0]
    except Exception as exc:  # noqa: BLE001 — the report says what went wrong
        rep.error = rep.error or _err(exc)
    rep.counts = {t: len(v) for t, v in out.items()}
    return rep, out


def read_rosbags(path: Union[str, Path]) -> tuple[ReaderReport, dict[str, list], Any]:
    """rosbags' AnyReader, types from the bag's own definitions.

    Returns (report, {topic: [(log, None, plain)]}, typestore or None). rosbags gives only
    the log time of a message.
    """
    from rosbags.highlevel import AnyReader

    rep = ReaderReport("rosbags")
    out: dict[str, list] = {}
    store = None
    try:
        with AnyReader([Path(path)]) as reader:
            rep.accepted = True
            store = reader.typestore
            rep.topics = {c.topic: c.msgtype for c in reader.connections}
            rep.qos = {c.topic: [_qos_tuple_to_dict(q) for q in c.ext.offered_qos_profiles]
                       for c in reader.connections}
            for conn, t, raw in reader.messages():
                msg = reader.deserialize(raw, conn.msgtype)
                out.setdefault(conn.topic, []).append((t, None, plain(msg)))
                rep.decoded += 1
    except Exception as exc:  # noqa: BLE001 — the report says what went wrong
        rep.error = _err(exc)
    rep.counts = {t: len(v) for t, v in out.items()}
    return rep, out, store


def read_mcap_ros2(path: Union[str, Path]) -> tuple[ReaderReport, dict[str, list]]:
    """Foxglove's mcap_ros2 ``read_ros2_messages`` (log-time order)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    rep = ReaderReport("mcap_ros2")
    out: dict[str, list] = {}
    try:
        # it reads files only: a rosbag2 folder is read file by file
        files = _bag_files(Path(path))
        for fpath in files:
            with open(fpath, "rb") as f:
                reader = make_reader(f, decoder_factories=[DecoderFactory()])
                summary = reader.get_summary()
                if summary is None:
                    raise ValueError(f"{fpath.name} has no summary section (not finished)")
                rep.accepted = True
                schemas = summary.schemas
                rep.topics.update({c.topic: schemas[c.schema_id].name
                                   for c in summary.channels.values()})
                rep.qos.update({c.topic: _load_profiles(c.metadata.get("offered_qos_profiles",
                                                                       ""))
                                for c in summary.channels.values()})
                for _sch, ch, m, msg in reader.iter_decoded_messages(log_time_order=True):
                    out.setdefault(ch.topic, []).append((m.log_time, m.publish_time,
                                                         plain(msg)))
                    rep.decoded += 1
    except Exception as exc:  # noqa: BLE001 — the report says what went wrong
        rep.error = _err(exc)
    rep.counts = {t: len(v) for t, v in out.items()}
    return rep, out


def _qos_tuple_to_dict(q) -> dict:
    """A rosbags Qos named tuple as a dict with rmw's enum names."""
    return {"history": q.history.name.lower(), "depth": int(q.depth),
            "reliability": q.reliability.name.lower(),
            "durability": q.durability.name.lower(),
            "deadline": {"sec": q.deadline.sec, "nsec": q.deadline.nsec},
            "lifespan": {"sec": q.lifespan.sec, "nsec": q.lifespan.nsec},
            "liveliness": q.liveliness.name.lower(),
            "liveliness_lease_duration": {"sec": q.liveliness_lease_duration.sec,
                                          "nsec": q.liveliness_lease_duration.nsec},
            "avoid_ros_namespace_conventions": bool(q.avoid_ros_namespace_conventions)}


def _load_profiles(text: Any) -> list[dict]:
    """Profiles of an offered_qos_profiles value (YAML text or list) with enum names."""
    if not text:
        return []
    profiles = yaml.safe_load(text) if isinstance(text, str) else text
    out = []
    for p in profiles or []:
        q = dict(p)
        for key, names in _ENUMS.items():
            v = q.get(key)
            if isinstance(v, int) and 0 <= v < len(names):
                q[key] = names[v]
        out.append(q)
    return out


# ----------------------------------------------------------------------------- checks
def _compare(rep: ReaderReport, theirs: dict[str, list], ours: dict[str, list],
             with_publish: bool) -> None:
    """Adds to ``rep.mismatches`` every topic/message where ``theirs`` differs from ours."""
    for topic in sorted(set(ours) | set(theirs)):
        a, b = ours.get(topic, []), theirs.get(topic, [])
        if len(a) != len(b):
            rep.mismatches.append(f"{topic}: {len(b)} messages, ours {len(a)}")
            continue
        # same log time within a topic keeps file order in every reader
        a = sorted(a, key=lambda x: x[0])
        b = sorted(b, key=lambda x: x[0])
        for i, (x, y) in enumerate(zip(a, b)):
            if x[0] != y[0]:
                rep.mismatches.append(f"{topic}[{i}]: log time {y[0]} != ours {x[0]}")
                break
            if with_publish and x[1] != y[1]:
                rep.mismatches.append(f"{topic}[{i}]: publish time {y[1]} != ours {x[1]}")
                break
            d = first_difference(_normalise_bytes(x[2]), _normalise_bytes(y[2]))
            if d:
                rep.mismatches.append(f"{topic}[{i}] {d}")
                break


def file_problems(path: Union[str, Path], store: Any = None) -> list[str]:
    """Where a finished MCAP file departs from what rosbag2's MCAP storage plugin writes.

    Checks the ``ros2`` profile, ``ros2msg`` schemas named ``pkg/msg/Name``, ``cdr`` channels
    with ``offered_qos_profiles`` in the layout the file's own metadata version declares,
    the ``rosbag2`` metadata record against the summary, and (with a rosbags typestore built
    from the file) each ``topic_type_hash`` against the hash of the embedded definition and,
    for a bag that says it is from Jazzy, against the hash of rosbags' own Jazzy types.
    """
    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_typestore

    jazzy = get_typestore(Stores.ROS2_JAZZY)

    problems: list[str] = []
    with open(path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        summary = reader.get_summary()
        records = [m for m in reader.iter_metadata() if m.name == "rosbag2"]
    if header.profile != "ros2":
        problems.append(f"profile {header.profile!r}, not 'ros2'")
    if summary is None:
        return problems + ["no summary section"]
    for s in summary.schemas.values():
        parts = s.name.split("/")
        if s.encoding != "ros2msg":
            problems.append(f"schema {s.name}: encoding {s.encoding!r}, not 'ros2msg'")
        if len(parts) != 3 or parts[1] != "msg":
            problems.append(f"schema name {s.name!r} is not pkg/msg/Name")
    version = None
    meta = None
    if not records:
        problems.append("no 'rosbag2' metadata record (ros2 bag info reads it)")
    else:
        try:
            meta = yaml.safe_load(records[-1].metadata["serialized_metadata"])
            version = int(meta["version"])
        except (KeyError, TypeError, ValueError, yaml.YAMLError) as exc:
            problems.append(f"rosbag2 metadata record unreadable: {_err(exc)}")
    for c in summary.channels.values():
        if c.message_encoding != "cdr":
            problems.append(f"{c.topic}: message encoding {c.message_encoding!r}, not 'cdr'")
        text = c.metadata.get("offered_qos_profiles")
        if text is None:
            problems.append(f"{c.topic}: channel has no offered_qos_profiles")
        elif version is not None:
            problems.extend(f"{c.topic}: {p}" for p in _qos_layout_problems(text, version))
        thash = c.metadata.get("topic_type_hash", "")
        sch = summary.schemas.get(c.schema_id)
        if store is not None and thash and sch is not None:
            try:
                have = store.hash_rihs01(sch.name)
            except Exception as exc:  # noqa: BLE001 — report, do not stop
                problems.append(f"{c.topic}: rosbags cannot hash {sch.name}: {_err(exc)}")
            else:
                if have != thash:
                    problems.append(f"{c.topic}: topic_type_hash {thash} != {have} computed "
                                    "from the embedded definition")
        if (thash and sch is not None and sch.name in jazzy.fielddefs
                and (meta or {}).get("ros_distro") == "jazzy"):
            if jazzy.hash_rihs01(sch.name) != thash:
                problems.append(f"{c.topic}: topic_type_hash {thash} is not Jazzy's "
                                f"{jazzy.hash_rihs01(sch.name)} for {sch.name}")
    if meta is not None:
        problems.extend(_metadata_problems(meta, summary, version))
    return problems


def _qos_layout_problems(value: Any, version: int) -> list[str]:
    """rosbag2 <= 8: a YAML string with integer enums; >= 9: enum names (rmw spelling)."""
    try:
        profiles = yaml.safe_load(value) if isinstance(value, str) else value
    except yaml.YAMLError as exc:
        return [f"offered_qos_profiles is not YAML ({exc})"]
    if not isinstance(profiles, list):
        return ["offered_qos_profiles is not a list of profiles"]
    out = []
    for p in profiles:
        for key, names in _ENUMS.items():
            v = p.get(key) if isinstance(p, dict) else None
            if version >= 9 and v not in names:
                out.append(f"QoS {key} {v!r} is not an rmw name, as metadata version "
                           f"{version} needs (rosbag2 would read it as unknown)")
            elif version < 9 and not isinstance(v, int):
                out.append(f"QoS {key} {v!r} is not an integer, as version {version} needs")
    return out


def _metadata_problems(meta: dict, summary, version: Optional[int]) -> list[str]:
    """The rosbag2 record's counts, times and topics against the MCAP summary."""
    out = []
    st = summary.statistics
    counts = {}
    for cid, n in (st.channel_message_counts if st else {}).items():
        ch = summary.channels.get(cid)
        if ch is not None:
            counts[ch.topic] = counts.get(ch.topic, 0) + n
    topics = {}
    for t in meta.get("topics_with_message_count") or []:
        tm = t.get("topic_metadata", {})
        topics[tm.get("name")] = t.get("message_count")
        q = tm.get("offered_qos_profiles")
        if version is not None and version >= 9 and isinstance(q, str):
            out.append(f"rosbag2 record: {tm.get('name')} offered_qos_profiles is a string; "
                       "version 9 stores a YAML list")
        if version is not None and version < 9 and not isinstance(q, str):
            out.append(f"rosbag2 record: {tm.get('name')} offered_qos_profiles is not a "
                       f"string, as version {version} needs")
        if q is not None and version is not None:
            out.extend(f"rosbag2 record: {tm.get('name')} {p}"
                       for p in _qos_layout_problems(q, version))
    channel_topics = {c.topic for c in summary.channels.values()}
    if set(topics) != channel_topics:
        out.append(f"rosbag2 record topics {sorted(topics)} != channels {sorted(channel_topics)}")
    for t, n in topics.items():
        if counts.get(t, 0) != n:
            out.append(f"rosbag2 record: {t} count {n} != {counts.get(t, 0)} in the file")
    if st is not None and meta.get("message_count") != st.message_count:
        out.append(f"rosbag2 record message_count {meta.get('message_count')} != "
                   f"{st.message_count}")
    if st is not None and st.message_count:
        t0 = (meta.get("starting_time") or {}).get("nanoseconds_since_epoch")
        dur = (meta.get("duration") or {}).get("nanoseconds")
        if t0 != st.message_start_time or dur != st.message_end_time - st.message_start_time:
            out.append(f"rosbag2 record start/duration {t0}/{dur} != file "
                       f"{st.message_start_time}/{st.message_end_time - st.message_start_time}")
    return out


def _timed(fn, path):
    """fn(path) with its wall and CPU seconds put into the report (first item)."""
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn(path)
    out[0].wall_s, out[0].cpu_s = time.perf_counter() - w0, time.process_time() - c0
    return out


def check_bag(path: Union[str, Path]) -> BagCheck:
    """Reads ``path`` with our reader and both independent readers and compares them."""
    path = Path(path)
    ours_rep, ours = _timed(read_ours, path)
    rb_rep, rb, store = _timed(read_rosbags, path)
    mr_rep, mr = _timed(read_mcap_ros2, path)
    _compare(rb_rep, rb, ours, with_publish=False)
    _compare(mr_rep, mr, ours, with_publish=True)
    # the QoS each reader parsed is the one we report (mcap_ros2 reads a folder's files, not
    # its metadata.yaml, which is where a folder's QoS come from)
    for rep in (rb_rep, mr_rep) if path.is_file() else (rb_rep,):
        for topic, profiles in ours_rep.qos.items():
            theirs = [canonical_qos_dict(p) for p in rep.qos.get(topic, [])]
            if rep.accepted and theirs != [canonical_qos_dict(p) for p in profiles]:
                rep.mismatches.append(f"{topic}: QoS {theirs} != ours "
                                      f"{[canonical_qos_dict(p) for p in profiles]}")
    problems: list[str] = []
    if path.is_file():
        try:
            problems = file_problems(path, store)
        except Exception as exc:  # noqa: BLE001 — a damaged file is reported, not raised
            problems = [f"cannot read the file's summary: {_err(exc)}"]
    return BagCheck(str(path), ours_rep, rb_rep, mr_rep, problems)


def canonical_qos_dict(p: dict) -> dict:
    """A profile with enum names and Foxy-era infinities mapped as rosbag2 reads them."""
    return yaml.safe_load(canonical_qos(yaml.safe_dump([p]), 9))[0]


def main(argv: Optional[list[str]] = None) -> int:
    """``python -m ooi_seg_ros.bag.interop BAG...``: 0 when every bag reads the same."""
    paths = sys.argv[1:] if argv is None else argv
    if not paths:
        print("usage: python -m ooi_seg_ros.bag.interop BAG [BAG...]", file=sys.stderr)
        return 2
    ok = True
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    for p in paths:
        res = check_bag(p)
        print(res.summary())
        ok &= res.ok
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
