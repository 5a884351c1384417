"""Recording live topics into an MCAP bag (what ``ros2 bag record -s mcap`` does; there is no rosbag2 here).

Each topic is subscribed raw (CDR bytes, nothing decoded) once it has a publisher, with its type
taken from the graph and a QoS adapted to the publishers like rosbag2 does: reliable unless some
publisher is best-effort, transient-local when every publisher is (so a latched map is recorded
even if it was published before the recorder started). Channels carry the publishers' offered QoS.

Output: one ``.mcap`` file (``bag_format="mcap"``) or a rosbag2 bag directory (``"rosbag2"``:
``metadata.yaml`` + ``<name>_0.mcap``, what ``ros2 bag record -s mcap -o DIR`` writes).

Log time: the receive time (``log_time="receive"``, as rosbag2), or the message's header stamp
(``"header"``; read from the CDR without decoding, receive time for types without a header) which
makes a recording of a replay line up with the source bag.
"""

from __future__ import annotations

import contextlib
import os
import struct
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from monovoc_ros.bags import schemas
from monovoc_ros.bags.qos import offered_from_endpoint, rclpy_profile
from monovoc_ros.bags.rosnode import ros_node, spinning
from monovoc_ros.bags.writer import BagWriter, Rosbag2Writer

LOG_TIMES = ("receive", "header")
BAG_FORMATS = ("mcap", "rosbag2")
SUBSCRIPTION_DEPTH = 1000  # raw callbacks only append to the writer; this absorbs a --fast replay's bursts
CHUNK_SIZE = 1024 * 1024  # a recorder killed hard loses at most its current (unwritten) chunk
_POLL_S = 0.05


@dataclass
class RecordSummary:
    path: str
    messages: dict[str, int]
    seconds: float
    size_bytes: int
    missing: list[str] = field(default_factory=list)  # topics that never had a publisher
    interrupted: bool = False

    def as_dict(self) -> dict:
        return {
            "path": self.path,
            "messages": self.messages,
            "total": sum(self.messages.values()),
            "seconds": round(self.seconds, 3),
            "size_bytes": self.size_bytes,
            "missing": self.missing,
            "interrupted": self.interrupted,
        }


def _absolute(topic: str) -> str:
    return topic if topic.startswith("/") else "/" + topic


def header_stamp_from_cdr(data: bytes) -> int | None:
    """The header stamp of a CDR message whose first field is ``std_msgs/Header`` (sec, nanosec first)."""
    if len(data) < 12:
        return None
    little = data[1] & 1  # encapsulation id 0x0001 = CDR little endian, 0x0000 = big endian
    sec, nanosec = struct.unpack("<iI" if little else ">iI", data[4:12])
    return sec * 1_000_000_000 + nanosec if sec >= 0 else None


def _has_header(cls: type) -> bool:
    fields = cls.get_fields_and_field_types()
    return bool(fields) and next(iter(fields.values())) == "std_msgs/Header"


class _Recorder:
    def __init__(self, node: Any, writer: BagWriter, log_time: str, stop: threading.Event, count: int | None) -> None:
        self.node = node
        self.writer = writer
        self.log_time = log_time
        self.stop = stop
        self.count = count
        self.lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self.total = 0
        self.subscriptions: dict[str, Any] = {}

    def try_subscribe(self, topic: str, types: dict[str, list[str]]) -> str | None:
        """Subscribes when the topic has a publisher; returns its type name then."""
        if topic not in types or self.node.count_publishers(topic) == 0:
            return None
        type_name = schemas.normalize_type_name(types[topic][0])
        cls = schemas.message_class(type_name)
        schemas.message_definition(type_name)  # fail now, not in a callback, if no schema can be built
        infos = self.node.get_publishers_info_by_topic(topic)
        offered = [offered_from_endpoint(i.qos_profile) for i in infos]
        reliable = all(q.reliable for q in offered)
        transient = bool(offered) and all(q.transient_local for q in offered)
        with self.lock:
            self.writer.add_topic(topic, type_name, offered)
        header = _has_header(cls)
        self.subscriptions[topic] = self.node.create_subscription(
            cls,
            topic,
            lambda data, t=topic, h=header: self._on_message(t, data, h),
            rclpy_profile(reliable=reliable, transient_local=transient, depth=SUBSCRIPTION_DEPTH),
            raw=True,
        )
        return type_name

    def _on_message(self, topic: str, data: bytes, has_header: bool) -> None:
        received = self.node.get_clock().now().nanoseconds
        log_time = received
        if self.log_time == "header" and has_header:
            log_time = header_stamp_from_cdr(data) or received
        with self.lock:
            if self.stop.is_set() or self.writer.finished:
                return
            self.writer.write(topic, data, log_time, publish_time_ns=received)
            self.counts[topic] += 1
            self.total += 1
            if self.count is not None and self.total >= self.count:
                self.stop.set()


def record(
    out_path: str | os.PathLike,
    topics: Iterable[str],
    *,
    duration: float | None = None,
    count: int | None = None,
    log_time: str = "receive",
    stop_event: threading.Event | None = None,
    compression: str = "zstd",
    node: Any = None,
    on_subscribed: Callable[[str, str], None] | None = None,
    on_ready: Callable[[], None] | None = None,
    bag_format: str = "mcap",
) -> RecordSummary:
    """Records ``topics`` into ``out_path`` until ``duration`` seconds, ``count`` messages in all,
    ``stop_event`` or Ctrl-C; the bag is finalized in every case.

    ``on_ready()`` is called once the node is up, ``on_subscribed(topic, type_name)`` as each topic gets
    subscribed. ``node``: a node
    that its owner spins (else an own node in a new context, spun here). ``bag_format``: "mcap" (``out_path``
    is the file) or "rosbag2" (``out_path`` is the bag directory); either must not exist yet.
    """
    if log_time not in LOG_TIMES:
        raise ValueError(f"log_time must be one of {LOG_TIMES}, got {log_time!r}")
    if bag_format not in BAG_FORMATS:
        raise ValueError(f"bag_format must be one of {BAG_FORMATS}, got {bag_format!r}")
    wanted = list(dict.fromkeys(_absolute(t) for t in topics))
    if not wanted:
        raise ValueError("record: no topics given")
    if bag_format == "mcap" and os.path.lexists(out_path):  # a recording is not to be had again: never replaced
        raise ValueError(f"{out_path}: already exists (a recording goes to a new file)")
    stop = stop_event or threading.Event()
    interrupted = False
    start = time.monotonic()
    writer_type = Rosbag2Writer if bag_format == "rosbag2" else BagWriter
    writer = writer_type(out_path, compression=compression, canonical=False, chunk_size=CHUNK_SIZE)
    try:
        with ros_node("monovoc_record", node) as ros:
            recorder = _Recorder(ros, writer, log_time, stop, count)
            spin = spinning(ros) if node is None else contextlib.nullcontext()
            with spin:
                try:
                    if on_ready is not None:
                        on_ready()
                    _subscribe_loop(recorder, wanted, stop, start, duration, on_subscribed)
                except KeyboardInterrupt:
                    interrupted = True
                with recorder.lock:
                    writer.finish()
                for sub in recorder.subscriptions.values():
                    ros.destroy_subscription(sub)
    finally:
        writer.finish()
    return RecordSummary(
        path=str(out_path),
        messages={t: recorder.counts[t] for t in wanted if t in recorder.subscriptions},
        seconds=time.monotonic() - start,
        size_bytes=writer.path.stat().st_size,
        missing=[t for t in wanted if t not in recorder.subscriptions],
        interrupted=interrupted,
    )


def _subscribe_loop(recorder: _Recorder, wanted: list[str], stop, start: float, duration, on_subscribed) -> None:
    pending = list(wanted)
    while not stop.is_set():
        if duration is not None and time.monotonic() - start >= duration:
            return
        if pending:
            types = dict(recorder.node.get_topic_names_and_types())
            for topic in list(pending):
                type_name = recorder.try_subscribe(topic, types)
                if type_name is not None:
                    pending.remove(topic)
                    if on_subscribed is not None:
                        on_subscribed(topic, type_name)
        stop.wait(_POLL_S)
