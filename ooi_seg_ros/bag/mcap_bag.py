"""Read and write ROS 2 bags as MCAP files the way rosbag2 (storage plugin ``mcap``) does.

A file written here has the ``ros2`` profile, one ``ros2msg`` schema per type with the full
concatenated definition, ``cdr`` channels carrying ``offered_qos_profiles`` and
``topic_type_hash`` metadata, zstd-compressed chunks, and the ``rosbag2`` metadata record
(``serialized_metadata`` YAML, ``ros_distro``) at the end, so ``ros2 bag info/play`` accept it.
The file says rosbag2 metadata version 9 (Jazzy) and holds QoS in that version's layout: rmw
enum names in the channels, a YAML list in the record (rosbag2 parses both by the version).
``interop`` checks files against two independent readers; ``recover_bag`` finishes a file
whose writer was killed.

Reading accepts an ``.mcap`` file or a rosbag2 bag folder (``metadata.yaml`` + files). A file
without a summary (recorder killed, file cut short) is read record by record up to the damage,
and ``BagReader.warnings`` says so.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path
from typing import Any, Iterator, NamedTuple, Optional, Union

import numpy as np
import yaml

from ..core.types import InputError
from . import msgdefs

log = logging.getLogger(__name__)

_INF_SEC, _INF_NSEC = 9223372036, 854775807  # RMW_DURATION_INFINITE
# rosbag2 metadata version written: 9 (Jazzy) stores QoS enums as rmw names ("reliable"), and
# the topic list's offered_qos_profiles as a YAML list, not a string. A reader takes the
# version from the file and parses the channels' QoS accordingly, so the two must agree: an
# integer enum in a version 9 file reads as "unknown" in rosbag2.
ROSBAG2_VERSION = 9


# rmw's enum names by integer value (rosbag2 writes the names from metadata version 9 on).
_QOS_ENUMS = {
    "history": ("system_default", "keep_last", "keep_all", "unknown"),
    "reliability": ("system_default", "reliable", "best_effort", "unknown", "best_available"),
    "durability": ("system_default", "transient_local", "volatile", "unknown", "best_available"),
    "liveliness": ("system_default", "automatic", "manual_by_node", "manual_by_topic",
                   "unknown", "best_available"),
}
# "Infinite" durations that pre-Galactic rmw implementations reported; rosbag2 reads them as
# RMW_DURATION_INFINITE, so they are written as that.
_OLD_INFINITE = {(2147483647, 4294967295), (2147483647, 2147483647)}


def _qos_enum(key: str, value: Any, version: int) -> Any:
    """One QoS policy value as an rmw name (version >= 9) or its integer (version <= 8)."""
    names = _QOS_ENUMS[key]
    if isinstance(value, bool) or value is None:
        value = 0 if value is None else int(value)
    if isinstance(value, int):
        idx = value if 0 <= value < len(names) else names.index("unknown")
    else:
        s = str(value).strip().lower()
        if s.isdigit():
            idx = int(s) if int(s) < len(names) else names.index("unknown")
        else:
            idx = names.index(s) if s in names else names.index("unknown")
    return names[idx] if version >= 9 else idx


def _qos_time(value: Any) -> dict:
    """A ``{sec, nsec}`` duration; old infinities become RMW_DURATION_INFINITE."""
    if not isinstance(value, dict):
        return {"sec": _INF_SEC, "nsec": _INF_NSEC}
    sec, nsec = int(value.get("sec", _INF_SEC)), int(value.get("nsec", _INF_NSEC))
    if (sec, nsec) in _OLD_INFINITE:
        sec, nsec = _INF_SEC, _INF_NSEC
    return {"sec": sec, "nsec": nsec}


def qos_profiles(qos: str, version: int = ROSBAG2_VERSION) -> list[dict]:
    """The profiles of an ``offered_qos_profiles`` YAML in rosbag2's layout for ``version``.

    Enums become rmw names (version >= 9, as Jazzy's rosbag2 writes and reads them) or
    integers (version <= 8); keys come in rosbag2's order; missing fields get rosbag2's
    defaults (keep_last 0, infinite durations).
    """
    parsed = yaml.safe_load(qos) if qos else []
    out = []
    for p in parsed or []:
        p = p if isinstance(p, dict) else {}
        out.append({
            "history": _qos_enum("history", p.get("history", 1), version),
            "depth": int(p.get("depth", 0) or 0),
            "reliability": _qos_enum("reliability", p.get("reliability", 1), version),
            "durability": _qos_enum("durability", p.get("durability", 2), version),
            "deadline": _qos_time(p.get("deadline")),
            "lifespan": _qos_time(p.get("lifespan")),
            "liveliness": _qos_enum("liveliness", p.get("liveliness", 1), version),
            "liveliness_lease_duration": _qos_time(p.get("liveliness_lease_duration")),
            "avoid_ros_namespace_conventions": bool(p.get("avoid_ros_namespace_conventions",
                                                          False)),
        })
    return out


def canonical_qos(qos: str, version: int = ROSBAG2_VERSION) -> str:
    """``offered_qos_profiles`` text as rosbag2 writes it into an MCAP channel (see
    ``qos_profiles``); "" for no profiles."""
    profiles = qos_profiles(qos, version)
    if not profiles:
        return ""
    return yaml.safe_dump(profiles, sort_keys=False, default_flow_style=False).rstrip("\n")


# The presets in rosbag2's current layout (metadata version 9): rmw enum names.
QOS_PRESETS = {
    "sensor_data": canonical_qos("- {history: 1, depth: 5, reliability: 2, durability: 2}"),
    "reliable": canonical_qos("- {history: 1, depth: 10, reliability: 1, durability: 2}"),
    "transient_local": canonical_qos("- {history: 1, depth: 1, reliability: 1, durability: 1}"),
}


def resolve_qos(qos: Optional[str]) -> str:
    """An ``offered_qos_profiles`` string from a preset name, a YAML string or None."""
    if qos is None or qos == "":
        return QOS_PRESETS["reliable"]
    if qos in QOS_PRESETS:
        return QOS_PRESETS[qos]
    try:
        parsed = yaml.safe_load(qos)
    except yaml.YAMLError as exc:
        raise InputError(f"QoS {qos[:40]!r} is neither a preset {sorted(QOS_PRESETS)} nor "
                         f"valid YAML: {exc}") from exc
    if not isinstance(parsed, list) or not all(isinstance(p, dict) for p in parsed):
        raise InputError(f"QoS {qos[:40]!r} must be a preset {sorted(QOS_PRESETS)} or a YAML "
                         "list of profiles (rosbag2 offered_qos_profiles)")
    try:
        return canonical_qos(qos)
    except (TypeError, ValueError, AttributeError) as exc:
        raise InputError(f"QoS {qos[:40]!r} has a value rosbag2 cannot hold ({exc}); depth "
                         "and durations must be integers") from exc


@dataclasses.dataclass
class TopicInfo:
    """What a bag says about one topic."""

    name: str
    type: str
    count: int = 0
    qos: str = ""  # offered_qos_profiles YAML ("" when the bag has none)
    serialization_format: str = "cdr"
    type_hash: str = ""
    schema_encoding: str = ""
    schema: bytes = b""  # the embedded definition (ros2msg text)


class BagMessage(NamedTuple):
    """One stored message with everything needed to write it again unchanged."""

    topic: str
    type: str
    log_time_ns: int
    data: bytes
    publish_time_ns: int
    sequence: int


class _FlushingStream:
    """File wrapper that flushes to the OS after each write the MCAP writer makes.

    The MCAP writer buffers a whole chunk in memory and writes it in one go, so flushing here
    puts every finished chunk on disk (what a SIGKILL-ed recorder leaves readable).
    """

    def __init__(self, f) -> None:
        self._f = f

    def write(self, b) -> int:
        n = self._f.write(b)
        self._f.flush()
        return n

    def tell(self) -> int:
        return self._f.tell()

    def flush(self) -> None:
        self._f.flush()


class BagWriter:
    """Writes a rosbag2-compatible MCAP file; use as a context manager or call ``close()``."""

    def __init__(self, path: Union[str, Path], compression: str = "zstd",
                 chunk_size: int = 1 << 20, atomic: bool = True,
                 ros_distro: str = "jazzy") -> None:
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)  # written as given (name it *.mcap for other tools)
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE, "": CompressionType.NONE}.get(compression)
        if comp is None:
            raise InputError(f"compression {compression!r} is not one of zstd, lz4, none")
        if chunk_size <= 0:
            raise InputError(f"chunk_size must be positive, got {chunk_size}")
        self.atomic = atomic
        self.ros_distro = ros_distro
        self._target = self.path.with_name(self.path.name + ".part") if atomic else self.path
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._file = open(self._target, "wb")
        except OSError as exc:
            raise InputError(f"cannot write bag {self._target}: {exc}; check the folder "
                             "exists and is writable") from exc
        stream: Any = self._file if atomic else _FlushingStream(self._file)
        self._writer = Writer(stream, chunk_size=chunk_size, compression=comp)
        self._writer.start(profile="ros2", library="ooi_seg_ros")
        self._schemas: dict[str, int] = {}
        self._hashes: dict[str, str] = {}  # type -> RIHS01 hash of its schema ("" unknown)
        self._channels: dict[str, int] = {}
        self.topics: dict[str, TopicInfo] = {}
        self._t0: Optional[int] = None
        self._t1: Optional[int] = None
        self._closed = False

    def __enter__(self) -> "BagWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None and self.atomic:
            self.abort()
        else:
            self.close()

    def add_topic(self, topic: str, type_name: str, qos: Optional[str] = None,
                  definition: Optional[str] = None, type_hash: Optional[str] = None) -> None:
        """Declares a topic (idempotent for the same type).

        ``definition`` overrides the schema text (e.g. copied from another bag); by default it
        is built from the installed ``.msg`` files, and a type that is not installed needs it.
        ``type_hash`` (RIHS01) goes with it when known; otherwise the installed type's hash is
        written only when the definition is the installed one (readers check the hash against
        the definition, so a wrong one is worse than none).
        """
        if topic in self.topics:
            if self.topics[topic].type != type_name:
                raise InputError(f"topic {topic} already added with type "
                                 f"{self.topics[topic].type}, not {type_name}")
            return
        msgdefs.split_type(type_name)  # validates the form
        if type_name not in self._schemas:
            text = definition if definition is not None else msgdefs.message_definition(type_name)
            if text is None:
                raise InputError(f"message type {type_name} is not installed (no .msg under "
                                 "share/); install its interface package or pass definition=")
            self._schemas[type_name] = self._writer.register_schema(
                name=type_name, encoding="ros2msg", data=text.encode("utf-8"))
            installed = definition is None or definition == msgdefs.message_definition(type_name)
            self._hashes[type_name] = (msgdefs.type_hash(type_name) or "") if installed else ""
        qos_s = resolve_qos(qos)  # in rosbag2's layout for the version this file declares
        meta = {"offered_qos_profiles": qos_s}
        thash = self._hashes[type_name] if type_hash is None else type_hash
        if thash:
            meta["topic_type_hash"] = thash
        self._channels[topic] = self._writer.register_channel(
            topic=topic, message_encoding="cdr", schema_id=self._schemas[type_name],
            metadata=meta)
        self.topics[topic] = TopicInfo(topic, type_name, 0, qos_s, "cdr", thash, "ros2msg")

    def write(self, topic: str, msg: Any, log_time_ns: int,
              publish_time_ns: Optional[int] = None, sequence: int = 0) -> None:
        """Writes one message (a ROS message object or its CDR bytes) to a declared topic."""
        if self._closed:
            raise InputError(f"bag {self.path} is already closed")
        if topic not in self._channels:
            if isinstance(msg, (bytes, bytearray, memoryview)):
                raise InputError(f"topic {topic} was not added; call add_topic() first")
            cls = type(msg)
            self.add_topic(topic, _type_name_of(cls))
        if isinstance(msg, (bytes, bytearray, memoryview)):
            data = bytes(msg)
        else:
            data = serialize(msg)
        t = int(log_time_ns)
        self._writer.add_message(self._channels[topic], log_time=t, data=data,
                                 publish_time=int(t if publish_time_ns is None
                                                  else publish_time_ns),
                                 sequence=int(sequence))
        self.topics[topic].count += 1
        self._t0 = t if self._t0 is None else min(self._t0, t)
        self._t1 = t if self._t1 is None else max(self._t1, t)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """An MCAP metadata record (string key/values), e.g. capture details."""
        if name == "rosbag2":
            raise InputError("the rosbag2 metadata record is written by close()")
        self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()})

    def _metadata_yaml(self) -> str:
        """rosbag2's ``serialized_metadata`` (bag information) for this file."""
        t0 = self._t0 if self._t0 is not None else _INF_SEC * 10**9 + _INF_NSEC
        dur = (self._t1 - self._t0) if self._t0 is not None else 0
        n = sum(t.count for t in self.topics.values())
        info = {
            "version": ROSBAG2_VERSION, "storage_identifier": "mcap",
            "duration": {"nanoseconds": dur}, "starting_time": {"nanoseconds_since_epoch": t0},
            "message_count": n,
            "topics_with_message_count": [
                {"topic_metadata": {"name": t.name, "type": t.type, "serialization_format": "cdr",
                                    "offered_qos_profiles": qos_profiles(t.qos),
                                    "type_description_hash": t.type_hash},
                 "message_count": t.count}
                for t in sorted(self.topics.values(), key=lambda x: x.name)],
            "compression_format": "", "compression_mode": "",
            "relative_file_paths": [self.path.name],
            "files": [{"path": self.path.name, "starting_time": {"nanoseconds_since_epoch": t0},
                       "duration": {"nanoseconds": dur}, "message_count": n}],
            "custom_data": None, "ros_distro": self.ros_distro,
        }
        return yaml.safe_dump(info, sort_keys=False, default_flow_style=False)

    def close(self) -> None:
        """Finishes the file (metadata record + summary) and, if atomic, moves it in place."""
        if self._closed:
            return
        self._closed = True
        self._writer.add_metadata("rosbag2", {"serialized_metadata": self._metadata_yaml(),
                                              "ros_distro": self.ros_distro})
        self._writer.finish()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        if self.atomic:
            os.replace(self._target, self.path)

    def abort(self) -> None:
        """Drops an atomic write (removes ``<path>.part``); a non-atomic file is finished."""
        if self._closed:
            return
        if not self.atomic:
            self.close()
            return
        self._closed = True
        self._file.close()
        try:
            os.remove(self._target)
        except OSError:
            pass


def _as_plain(msg: Any) -> Any:
    """A dict tree of an rclpy message that mcap_ros2's CDR encoder accepts."""
    import array

    out = {}
    for name, ftype in msg.get_fields_and_field_types().items():
        v = getattr(msg, name)
        if hasattr(v, "get_fields_and_field_types"):
            v = _as_plain(v)
        elif isinstance(v, np.ndarray):
            v = v.tobytes() if v.dtype == np.uint8 else v.tolist()
        elif isinstance(v, array.array):
            v = v if v.typecode == "B" else v.tolist()
        elif isinstance(v, list):
            if v and hasattr(v[0], "get_fields_and_field_types"):
                v = [_as_plain(x) for x in v]
            elif v and isinstance(v[0], bytes):
                v = b"".join(v)
        elif isinstance(v, bytes) and len(v) == 1 and ftype == "octet":
            v = v[0]
        out[name] = v
    return out


_ENCODERS: dict[str, Any] = {}


def serialize(msg: Any) -> bytes:
    """CDR bytes of an rclpy message with zeroed alignment padding (deterministic).

    ``rclpy.serialization.serialize_message`` leaves alignment padding uninitialised, so the
    same message can give different bytes; a bag written twice from the same capture must be
    identical, so messages are encoded from their definition (mcap_ros2) and checked against
    rclpy's length. Falls back to rclpy's bytes when the encoder cannot handle a type.
    """
    from rclpy.serialization import serialize_message

    ref = serialize_message(msg)
    tname = _type_name_of(type(msg))
    enc = _ENCODERS.get(tname)
    if enc is None:
        from mcap_ros2._dynamic import serialize_dynamic
        text = msgdefs.message_definition(tname)
        enc = _ENCODERS[tname] = (serialize_dynamic(tname, text)[tname] if text else False)
    if enc:
        try:
            data = bytes(enc(_as_plain(msg)))
        except (ValueError, TypeError, KeyError, NotImplementedError, AttributeError):
            data = b""
        if len(data) == len(ref):
            return data
    return bytes(ref)


def _type_name_of(cls) -> str:
    """"pkg/msg/Name" of a generated rclpy message class."""
    mod = cls.__module__.split(".")  # e.g. sensor_msgs.msg._image
    return f"{mod[0]}/msg/{cls.__name__}"


def message_class(type_name: str):
    """The installed rclpy message class of a type, or None when it is not installed."""
    import importlib
    try:
        pkg, name = msgdefs.split_type(type_name)
    except InputError:
        return None
    try:
        mod = importlib.import_module(f"{pkg}.msg")
    except ImportError:
        return None
    return getattr(mod, name, None)


def _folder_topic_qos(path: Path) -> dict[str, str]:
    """{topic: offered_qos_profiles text} from a rosbag2 folder's ``metadata.yaml``.

    ``ros2 bag play`` of a folder takes the topics' QoS from there, not from the files'
    channels (the two can differ, e.g. in bags written by other tools). Version 9 stores a
    YAML list, older versions a string; both come back as text. {} when there is none.
    """
    meta = path / "metadata.yaml"
    if not path.is_dir() or not meta.is_file():
        return {}
    try:
        info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
        out = {}
        for t in info.get("topics_with_message_count") or []:
            tm = t["topic_metadata"]
            q = tm.get("offered_qos_profiles")
            if isinstance(q, list):
                q = yaml.safe_dump(q, sort_keys=False, default_flow_style=False).rstrip("\n")
            if isinstance(q, str) and q:
                out[tm["name"]] = q
        return out
    except (yaml.YAMLError, KeyError, TypeError, AttributeError):
        return {}  # _bag_files has said what is wrong with the file


def _bag_files(path: Path) -> list[Path]:
    """The MCAP files of a bag path (file or rosbag2 folder), InputError when there are none."""
    if not path.exists():
        raise InputError(f"bag {path} does not exist; give an .mcap file or a rosbag2 folder")
    if path.is_file():
        return [path]
    meta = path / "metadata.yaml"
    files: list[Path] = []
    if meta.is_file():
        try:
            info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
            storage = info.get("storage_identifier", "mcap")
            rel = info.get("relative_file_paths") or []
        except (yaml.YAMLError, KeyError, TypeError, AttributeError) as exc:
            raise InputError(f"{meta} is not a rosbag2 metadata file ({exc}); remove it or "
                             "re-create it with `ros2 bag reindex`") from exc
        if info.get("compression_mode") == "FILE" and info.get("compression_format"):
            raise InputError(f"bag {path} is file-compressed ({info['compression_format']}); "
                             "run `ros2 bag decompress` (or zstd -d) on it first")
        if storage != "mcap":
            raise InputError(f"bag {path} uses storage {storage!r}; convert it to MCAP with "
                             "`ros2 bag convert` (only mcap is read)")
        files = [path / r for r in rel if (path / r).is_file()]
    if not files:
        files = sorted(path.glob("*.mcap"))
    if not files:
        raise InputError(f"{path} holds no .mcap file; give an .mcap file or a rosbag2 folder")
    return files


class _FileIndex:
    """Schemas, channels and statistics of one MCAP file (from its summary or a scan)."""

    def __init__(self, path: Path) -> None:
        from mcap.reader import make_reader

        self.path = path
        self.truncated = False
        self.error = ""
        self.schemas: dict[int, Any] = {}
        self.channels: dict[int, Any] = {}
        self.counts: dict[int, int] = {}
        self.t0: Optional[int] = None
        self.t1: Optional[int] = None
        summary = None
        try:
            with open(path, "rb") as f:
                summary = make_reader(f).get_summary()
        except Exception as exc:  # noqa: BLE001 — mcap raises many types for broken files
            self.error = f"{type(exc).__name__}: {exc}"
        if summary is not None and summary.statistics is not None:
            self.schemas = dict(summary.schemas)
            self.channels = dict(summary.channels)
            st = summary.statistics
            self.counts = dict(st.channel_message_counts)
            if st.message_count:
                self.t0, self.t1 = st.message_start_time, st.message_end_time
            if self.counts and sum(self.counts.values()) != st.message_count:
                self._scan()  # statistics that do not add up (seen in rosbag2 files)
        else:
            self._scan()

    def _scan(self) -> None:
        """Reads the file record by record (no summary needed), stopping at damage."""
        self.counts = {}
        self.t0 = self.t1 = None
        for rec in self.records():
            cid = rec.channel_id
            self.counts[cid] = self.counts.get(cid, 0) + 1
            t = rec.log_time
            self.t0 = t if self.t0 is None else min(self.t0, t)
            self.t1 = t if self.t1 is None else max(self.t1, t)

    def records(self) -> Iterator[Any]:
        """Message records in file order via the streaming reader; notes truncation."""
        from mcap.records import Channel, Message, Schema
        from mcap.stream_reader import StreamReader

        with open(self.path, "rb") as f:
            it = StreamReader(f, record_size_limit=1 << 31, validate_crcs=True).records
            while True:
                try:
                    rec = next(it)
                except StopIteration:
                    return
                except Exception as exc:  # noqa: BLE001 — damaged data ends the readable part
                    self.truncated = True
                    self.error = f"{type(exc).__name__}: {exc}"
                    return
                if isinstance(rec, Schema):
                    self.schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    self.channels[rec.id] = rec
                elif isinstance(rec, Message):
                    yield rec


class BagReader:
    """Reads a ROS 2 MCAP bag (``.mcap`` file or rosbag2 folder) without needing ROS running."""

    def __init__(self, path: Union[str, Path]) -> None:
        self.path = Path(path)
        self.files = _bag_files(self.path)
        self.warnings: list[str] = []
        self._idx: list[_FileIndex] = []
        for f in self.files:
            try:
                idx = _FileIndex(f)
            except OSError as exc:
                raise InputError(f"cannot read bag file {f}: {exc}") from exc
            if not idx.channels and idx.error:
                raise InputError(f"{f} is not a readable MCAP file ({idx.error}); re-record it "
                                 "or repair it with `mcap recover`")
            if idx.truncated or idx.error:
                msg = (f"{f.name} has no valid summary/footer (truncated or damaged: "
                       f"{idx.error}); read {sum(idx.counts.values())} messages up to the "
                       "damage. Other readers (rosbags, Foxglove, ros2 bag) reject such a "
                       "file: repair it with `ooi-seg recover FILE --out FIXED.mcap` (the same "
                       "as `python -m ooi_seg_ros.bag.recover`, or `mcap recover`)")
                self.warnings.append(msg)
                log.warning(msg)
            self._idx.append(idx)
        self._decoders: dict[int, Any] = {}
        self._folder_qos = _folder_topic_qos(self.path)
        self._topic_cache: Optional[dict[str, TopicInfo]] = None

    @property
    def truncated(self) -> bool:
        """True when some file could only be read up to damage."""
        return bool(self.warnings)

    def topics(self) -> dict[str, TopicInfo]:
        """{topic: TopicInfo} over all files (topics without messages included)."""
        out: dict[str, TopicInfo] = {}
        for idx in self._idx:
            for cid, ch in idx.channels.items():
                sch = idx.schemas.get(ch.schema_id)
                tname = sch.name if sch is not None else ""
                info = out.get(ch.topic)
                if info is None:
                    info = out[ch.topic] = TopicInfo(
                        ch.topic, tname, 0, ch.metadata.get("offered_qos_profiles", ""),
                        ch.message_encoding, ch.metadata.get("topic_type_hash", ""),
                        sch.encoding if sch is not None else "",
                        bytes(sch.data) if sch is not None else b"")
                info.count += idx.counts.get(cid, 0)
        for topic, qos in self._folder_qos.items():
            if topic in out:
                out[topic].qos = qos
        return out

    def time_span(self) -> tuple[int, int]:
        """(first, last) message log time in ns; (0, 0) for a bag without messages."""
        t0 = [i.t0 for i in self._idx if i.t0 is not None]
        t1 = [i.t1 for i in self._idx if i.t1 is not None]
        return (min(t0), max(t1)) if t0 else (0, 0)

    def metadata(self, name: str) -> Optional[dict[str, str]]:
        """The last MCAP metadata record called ``name`` in the bag, or None."""
        from mcap.reader import make_reader

        found = None
        for idx in self._idx:
            if idx.truncated or idx.error:
                continue
            try:
                with open(idx.path, "rb") as f:
                    for m in make_reader(f).iter_metadata():
                        if m.name == name:
                            found = dict(m.metadata)
            except Exception:  # noqa: BLE001 — optional information
                continue
        return found

    def require_topics(self, topics: list[str]) -> None:
        """InputError naming the missing topics and the ones the bag has."""
        have = self.topics()
        missing = [t for t in topics if t not in have]
        if missing:
            raise InputError(f"bag {self.path} has no topic(s) {missing}; it has "
                             f"{sorted(have)} (pass the right topic names)")

    def records(self, topics: Optional[list[str]] = None, start_ns: Optional[int] = None,
                end_ns: Optional[int] = None) -> Iterator[BagMessage]:
        """Every message (log-time order per file) with publish time and sequence."""
        from mcap.reader import make_reader

        want = set(topics) if topics is not None else None
        for idx in self._idx:
            def keep(ch, t) -> bool:
                return ((want is None or ch.topic in want)
                        and (start_ns is None or t >= start_ns)
                        and (end_ns is None or t < end_ns))
            if idx.truncated or idx.error:
                for m in idx.records():
                    ch = idx.channels[m.channel_id]
                    if keep(ch, m.log_time):
                        yield self._bag_message(idx, ch, m)
                continue
            with open(idx.path, "rb") as f:
                reader = make_reader(f, validate_crcs=True)
                try:
                    for _sch, ch, m in reader.iter_messages(
                            topics=list(want) if want is not None else None,
                            starting_at=start_ns, ending_before=end_ns, log_time_order=True):
                        yield self._bag_message(idx, ch, m)
                except Exception as exc:  # noqa: BLE001 — a chunk damaged after the summary
                    raise InputError(f"{idx.path} is damaged ({type(exc).__name__}: {exc}); "
                                     "repair it with `mcap recover`") from exc

    @staticmethod
    def _bag_message(idx: _FileIndex, ch, m) -> BagMessage:
        sch = idx.schemas.get(ch.schema_id)
        return BagMessage(ch.topic, sch.name if sch is not None else "", m.log_time,
                          bytes(m.data), m.publish_time, m.sequence)

    def messages(self, topics: Optional[list[str]] = None, start_ns: Optional[int] = None,
                 end_ns: Optional[int] = None) -> Iterator[tuple[str, str, int, bytes]]:
        """(topic, type, log_time_ns, CDR bytes) in log-time order."""
        for r in self.records(topics, start_ns, end_ns):
            yield r.topic, r.type, r.log_time_ns, r.data

    def decode(self, type_name: str, data: bytes, topic: Optional[str] = None) -> Any:
        """A message object from CDR bytes.

        The installed rclpy class when there is one and the bag's type hash for ``topic`` (if
        it has one) is the installed type's; otherwise a dynamic object decoded from the
        definition embedded in the bag (needs ``topic``), so a bag recorded with another
        version of a type decodes by its own definition instead of into garbage. InputError
        if neither works.
        """
        cls = message_class(type_name)
        if cls is not None and topic is not None:
            if self._topic_cache is None:
                self._topic_cache = self.topics()
            info = self._topic_cache.get(topic)
            if (info is not None and info.type_hash and info.schema
                    and info.type_hash != (msgdefs.type_hash(type_name) or info.type_hash)):
                cls = None  # another version of the type: use the bag's own definition
        if cls is not None:
            from rclpy.serialization import deserialize_message
            try:
                return deserialize_message(data, cls)
            except Exception as exc:  # noqa: BLE001 — rclpy raises generic errors
                raise InputError(f"cannot decode a {type_name} message ({exc}); the bag's "
                                 "data does not match the installed type") from exc
        info = self.topics().get(topic) if topic else None
        if info is None or info.schema_encoding != "ros2msg" or not info.schema:
            raise InputError(f"type {type_name} is not installed and the bag carries no ros2msg "
                             "definition for it; install its interface package to decode it")
        from mcap.records import Schema
        from mcap_ros2.decoder import DecoderFactory

        key = hash((type_name, info.schema))
        dec = self._decoders.get(key)
        if dec is None:
            dec = DecoderFactory().decoder_for(
                "cdr", Schema(id=0, name=type_name, encoding="ros2msg", data=info.schema))
            self._decoders[key] = dec
        try:
            return dec(data)
        except Exception as exc:  # noqa: BLE001 — dynamic decoder errors
            raise InputError(f"cannot decode {type_name} on {topic} from its embedded "
                             f"definition ({exc})") from exc


def recover_bag(src: Union[str, Path], dst: Union[str, Path]) -> int:
    """Rewrites a bag cut short (recorder killed, disk full) as a finished file; returns the
    number of messages kept.

    Readers that need the summary and footer (rosbags, Foxglove's mcap_ros2 reader,
    ``ros2 bag``) reject a file that lacks them; everything up to the damage is copied here,
    byte for byte per message (log/publish time and sequence kept), with each topic's
    schema text and QoS, and the file's other metadata records. It is what ``mcap recover``
    does, for a ROS 2 bag.
    """
    from mcap.records import Channel, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    src, dst = Path(src), Path(dst)
    if src.resolve() == dst.resolve():
        raise InputError(f"recover {src} into a new file, not over itself")
    files = _bag_files(src)
    schemas: dict[tuple[int, int], Any] = {}
    channels: dict[tuple[int, int], Any] = {}
    n = 0
    with BagWriter(dst) as w:
        for k, fpath in enumerate(files):
            with open(fpath, "rb") as f:
                it = StreamReader(f, record_size_limit=1 << 31, validate_crcs=True).records
                while True:
                    try:
                        rec = next(it)
                    except StopIteration:
                        break
                    except Exception as exc:  # noqa: BLE001 — damage ends the readable part
                        log.warning("%s: stopped at damage (%s: %s) after %d messages",
                                    fpath.name, type(exc).__name__, exc, n)
                        break
                    if isinstance(rec, Schema):
                        schemas[(k, rec.id)] = rec
                    elif isinstance(rec, Channel):
                        channels[(k, rec.id)] = rec
                    elif isinstance(rec, Metadata) and rec.name != "rosbag2":
                        w.add_metadata(rec.name, dict(rec.metadata))
                    elif isinstance(rec, Message):
                        ch = channels.get((k, rec.channel_id))
                        if ch is None:
                            continue  # a message before its channel: not valid MCAP
                        if ch.topic not in w.topics:
                            sch = schemas.get((k, ch.schema_id))
                            if sch is None or sch.encoding != "ros2msg":
                                raise InputError(f"{fpath}: topic {ch.topic} has no ros2msg "
                                                 "schema; it is not a ROS 2 bag")
                            w.add_topic(ch.topic, sch.name,
                                        ch.metadata.get("offered_qos_profiles") or None,
                                        definition=bytes(sch.data).decode("utf-8"),
                                        type_hash=ch.metadata.get("topic_type_hash", ""))
                        w.write(ch.topic, bytes(rec.data), rec.log_time, rec.publish_time,
                                rec.sequence)
                        n += 1
    return n
