"""Replay and record ROS 2 topics with rosbag2-compatible MCAP bags (``ros2 bag`` is not on PyPI).

``BagPlayer`` publishes a bag's messages with their recorded timing and QoS; ``BagRecorder``
subscribes to live topics (raw, no deserialisation) and writes them as they arrive. Both are
rclpy nodes so they run in a normal executor, in-process (tests) or from the CLI.
"""

from __future__ import annotations

import sys
import threading
import time
from typing import Callable, Optional

import yaml
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..bag import BagReader, BagWriter, message_class
from ..core.types import InputError


def qos_from_offered(offered: Optional[str], default_depth: int = 10) -> QoSProfile:
    """QoS profile from rosbag2's ``offered_qos_profiles`` YAML (first profile), else reliable."""
    q = QoSProfile(depth=default_depth, reliability=ReliabilityPolicy.RELIABLE,
                   durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
    if not offered:
        return q
    try:
        profiles = yaml.safe_load(offered)
    except yaml.YAMLError:
        return q
    if not profiles or not isinstance(profiles, list) or not isinstance(profiles[0], dict):
        return q
    p = profiles[0]

    def val(key):
        v = p.get(key)
        return str(v).lower() if v is not None else ""

    rel = val("reliability")
    if rel in ("2", "best_effort"):
        q.reliability = ReliabilityPolicy.BEST_EFFORT
    dur = val("durability")
    if dur in ("1", "transient_local"):
        q.durability = DurabilityPolicy.TRANSIENT_LOCAL
    depth = p.get("depth")
    if isinstance(depth, int) and depth > 0:
        q.depth = depth
    return q


def qos_to_offered(profiles: list) -> str:
    """rosbag2-style ``offered_qos_profiles`` YAML of the publishers' QoS profiles."""
    out = []
    for prof in profiles:
        out.append({
            "history": int(prof.history), "depth": int(prof.depth),
            "reliability": int(prof.reliability), "durability": int(prof.durability),
            "deadline": {"sec": 2147483647, "nsec": 4294967295},
            "lifespan": {"sec": 2147483647, "nsec": 4294967295},
            "liveliness": int(prof.liveliness),
            "liveliness_lease_duration": {"sec": 2147483647, "nsec": 4294967295},
            "avoid_ros_namespace_conventions": False,
        })
    return yaml.safe_dump(out, sort_keys=False)


def parse_remaps(remaps: list[str]) -> dict[str, str]:
    """``a:=b`` pairs -> {a: b}."""
    out = {}
    for r in remaps or []:
        if ":=" not in r:
            raise InputError(f"remap {r!r} must look like /from:=/to")
        a, b = r.split(":=", 1)
        out[a] = b
    return out


class BagPlayer(Node):
    """Publishes a bag's messages with their original relative timing (scaled by ``rate``)."""

    def __init__(self, bag: str, rate: float = 1.0, start_s: float = 0.0, loop: bool = False,
                 topics: Optional[list[str]] = None, remap: Optional[dict[str, str]] = None,
                 progress: Optional[Callable[[str], None]] = None, **kwargs) -> None:
        super().__init__("ooi_seg_player", **kwargs)
        if rate <= 0:
            raise InputError(f"--rate must be positive, got {rate}")
        self.reader = BagReader(bag)
        infos = self.reader.topics()
        wanted = set(topics) if topics else set(infos)
        missing = sorted(wanted - set(infos))
        if missing:
            raise InputError(f"bag {bag} has no topic(s) {missing}; it has {sorted(infos)}")
        self.rate, self.start_s, self.loop = rate, start_s, loop
        self.remap = remap or {}
        self.progress = progress
        self.pubs = {}
        self.skipped: dict[str, str] = {}
        for t in sorted(wanted):
            info = infos[t]
            cls = message_class(info.type)
            if cls is None:
                self.skipped[t] = info.type
                continue
            self.pubs[t] = self.create_publisher(cls, self.remap.get(t, t),
                                                 qos_from_offered(info.qos))
        if self.skipped:
            self.get_logger().warning(
                "not replaying topics whose message types are not installed: "
                + ", ".join(f"{t} ({ty})" for t, ty in sorted(self.skipped.items())))
        self.published = 0
        self._stop = threading.Event()

    def wait_for_subscribers(self, topics: list[str], timeout_s: float) -> bool:
        """Waits until each topic's publisher has a subscriber (or the timeout passes)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if all(self.pubs[t].get_subscription_count() > 0 for t in topics if t in self.pubs):
                return True
            time.sleep(0.02)
        return False

    def stop(self) -> None:
        self._stop.set()

    def play(self) -> int:
        """Publishes everything (blocking); returns the number of messages published."""
        span = self.reader.time_span()
        t_begin = span[0] + int(self.start_s * 1e9)
        total_s = max((span[1] - t_begin) / 1e9, 1e-9)
        while True:
            wall0 = time.monotonic()
            last_print = 0.0
            msgs = self.reader.messages(topics=list(self.pubs), start_ns=t_begin)
            for topic, _type, t_ns, data in msgs:
                if self._stop.is_set():
                    return self.published
                due = wall0 + (t_ns - t_begin) / 1e9 / self.rate
                while True:
                    now = time.monotonic()
                    if now >= due or self._stop.is_set():
                        break
                    time.sleep(min(due - now, 0.05))
                self.pubs[topic].publish(data)
                self.published += 1
                if self.progress and time.monotonic() - last_print > 0.5:
                    last_print = time.monotonic()
                    self.progress(f"[play] {(t_ns - t_begin) / 1e9:7.2f} / {total_s:7.2f} s  "
                                  f"{self.published} msgs")
            if not self.loop:
                break
        if self.progress:
            self.progress(f"[play] done: {self.published} msgs\n")
        return self.published


class BagRecorder(Node):
    """Records live topics (raw bytes) into a rosbag2-compatible MCAP as they arrive.

    The file is written in place with flushed chunks, so a SIGKILL loses at most the chunk in
    progress; ``close()`` (on SIGINT/SIGTERM) finishes the file with its summary.
    """

    def __init__(self, out: str, topics: list[str], chunk_size: int = 1 << 20,
                 discovery_period_s: float = 0.5, **kwargs) -> None:
        super().__init__("ooi_seg_recorder", **kwargs)
        if not topics:
            raise InputError("name at least one topic to record")
        self.topics = [t if t.startswith("/") else "/" + t for t in topics]
        self.writer = BagWriter(out, chunk_size=chunk_size, atomic=False)
        self.subs = {}
        self.counts: dict[str, int] = {}
        self._lock = threading.Lock()
        self._closed = False
        self._timer = self.create_timer(discovery_period_s, self._discover)
        self._discover()

    def _discover(self) -> None:
        types = dict(self.get_topic_names_and_types())
        for t in self.topics:
            if t in self.subs or t not in types:
                continue
            type_name = types[t][0]
            cls = message_class(type_name)
            if cls is None:
                self.get_logger().warning(f"cannot record {t}: type {type_name} not installed")
                continue
            infos = self.get_publishers_info_by_topic(t)
            profiles = [i.qos_profile for i in infos]
            qos = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST)
            qos.reliability = (ReliabilityPolicy.BEST_EFFORT if any(
                p.reliability == ReliabilityPolicy.BEST_EFFORT for p in profiles)
                else ReliabilityPolicy.RELIABLE)
            qos.durability = (DurabilityPolicy.TRANSIENT_LOCAL if profiles and all(
                p.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in profiles)
                else DurabilityPolicy.VOLATILE)
            with self._lock:
                self.writer.add_topic(t, type_name, qos_to_offered(profiles))
            self.counts[t] = 0
            self.subs[t] = self.create_subscription(
                cls, t, lambda data, info, topic=t: self._on_msg(topic, data, info), qos,
                raw=True)
            self.get_logger().info(f"recording {t} ({type_name})")

    def _on_msg(self, topic: str, data: bytes, info: Optional[dict] = None) -> None:
        """Log time = this node's clock at reception (sim time when ``use_sim_time``), publish
        time = the sender's source timestamp from the middleware, as rosbag2 records them."""
        with self._lock:
            if self._closed:
                return
            now = self.get_clock().now().nanoseconds
            sent = int((info or {}).get("source_timestamp") or 0)
            self.writer.write(topic, data, now, sent if sent > 0 else now)
            self.counts[topic] += 1

    def close(self) -> None:
        with self._lock:
            if not self._closed:
                self._closed = True
                self.writer.close()


def stderr_progress(line: str) -> None:
    sys.stderr.write("\r" + line)
    sys.stderr.flush()
