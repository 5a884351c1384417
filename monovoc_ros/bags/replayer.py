"""Replaying a bag on live topics: recorded rate, a multiple of it, or as fast as possible without loss.

Messages are published as the bag's raw CDR bytes (no decode / encode), with each publisher's type
resolved from the schema name. Every publisher is reliable; topics recorded as transient-local (and
``*/gaussians``, the Gaussian map) are transient-local with a history deep enough for all their
messages, so a subscriber that joins late still gets the map.

No loss at the start: by default the replay waits until each of the bag's keyframe and map topics (the
node's inputs: image, mask, camera_info, pose, gaussians) has a subscriber, as a node that is still starting
(``ros2 launch`` starts both at once) would otherwise miss the first messages, and with ``fast`` all of them.
One of those topics that had no subscriber when its first message went out is reported (``unmatched``;
`monovoc replay` warns and exits with 2).

No loss with ``fast``: a reliable KEEP_LAST writer overwrites samples that are not yet acknowledged
once its history is full, so every ``depth`` messages on a topic the replay waits until they are
acknowledged, and before it returns it waits for all of them (``wait_for_all_acked``). What a
subscriber's own queue drops (a slow callback and a small ``depth``) is the subscriber's business:
give subscriptions of replayed topics a queue as deep as the burst they must absorb.

No overtaking with ``fast``: after each Gaussian map message the replay waits until a node reports on /diagnostics
that it took it (monovoc_ros.bags.map_gate: up to one diagnostics period, 1 s by default, per map), so that the
keyframes posed in it come after it (``map_gate`` in the summary); not when no node reports that within 3 s of the
start (a replay into another consumer pays those 3 s once), nor on a node given by the caller (it spins that node,
not the replay), nor while the map topic has no subscriber, nor after one map was not reported taken in time
(``maps_unconfirmed``).
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from monovoc_ros.bags import schemas
from monovoc_ros.bags.map_gate import MapGate
from monovoc_ros.bags.qos import rclpy_profile
from monovoc_ros.bags.reader import BagInfo, bag_info, iter_messages
from monovoc_ros.bags.rosnode import ros_node, spinning
from monovoc_ros.contract import KEYFRAME_ROLES, MAP_ROLE
from monovoc_ros.fastdds_profile import WRITER_HEARTBEAT_MS

STREAM_DEPTH_MAX = 100  # history of a volatile topic (unacknowledged messages in flight in fast mode)
LATCHED_DEPTH_MAX = 32  # history of a transient-local topic (what a late joiner gets)
CLOCK_TOPIC = "/clock"
DEFAULT_CLOCK_HZ = 40.0  # as ros2 bag play --clock


class ReplayError(RuntimeError):
    """The replay cannot start or finish as asked (no subscribers in time, unknown type, ...)."""


@dataclass
class ReplaySummary:
    bag: str
    messages: dict[str, int]  # per published (remapped) topic, all loops together
    seconds: float  # wall time from the first publish to the last acknowledgement
    loops: int
    bag_duration_s: float
    rate: float | None  # None when fast
    max_late_ms: float = 0.0  # worst delay behind the recorded schedule (timed replay)
    unacked: list[str] = field(default_factory=list)  # topics not fully acknowledged in time
    unmatched: list[str] = field(default_factory=list)  # expected topics without a subscriber at their first message
    interrupted: bool = False
    # --fast with a map topic: whether a node reported taking maps, so the replay waited for each (module
    # docstring); None: not looked for (a timed replay, no map topic, a node given by the caller).
    map_gate: bool | None = None
    maps_unconfirmed: int = 0  # --fast: maps no node reported taken in time (the replay stopped waiting for them)

    def as_dict(self) -> dict:
        return {
            "bag": self.bag,
            "messages": self.messages,
            "total": sum(self.messages.values()),
            "seconds": round(self.seconds, 3),
            "loops": self.loops,
            "bag_duration_s": round(self.bag_duration_s, 3),
            "rate": self.rate,
            "max_late_ms": round(self.max_late_ms, 2),
            "unacked": self.unacked,
            "unmatched": self.unmatched,
            "interrupted": self.interrupted,
            "map_gate": self.map_gate,
            "maps_unconfirmed": self.maps_unconfirmed,
        }


def parse_remaps(remaps: Iterable[str] | Mapping[str, str] | None) -> dict[str, str]:
    """``["FROM:=TO", ...]`` (or a dict) -> {FROM: TO}; names must be absolute."""
    if remaps is None:
        return {}
    items = remaps.items() if isinstance(remaps, Mapping) else (_split_remap(r) for r in remaps)
    out = {}
    for src, dst in items:
        for name in (src, dst):
            if not name.startswith("/"):
                raise ValueError(f"remap {src}:={dst}: topic names must be absolute (start with /)")
        out[src] = dst
    return out


def _split_remap(text: str) -> tuple[str, str]:
    src, sep, dst = text.partition(":=")
    if not sep or not src or not dst:
        raise ValueError(f"remap {text!r}: expected FROM:=TO")
    return src, dst


def _is_map(topic: str) -> bool:
    return topic.rsplit("/", 1)[-1] == MAP_ROLE


def expected_topics(topics: Iterable[str]) -> list[str]:
    """The topics a replay waits for by default: those of the node's keyframe and map inputs (by the
    contract's role names); for a bag without any, all of them."""
    roles = {*KEYFRAME_ROLES, MAP_ROLE}
    topics = list(topics)
    return [t for t in topics if t.rsplit("/", 1)[-1] in roles] or topics


def latched_topics(info: BagInfo) -> set[str]:
    """Topics replayed transient-local: recorded so, or the Gaussian map topic of our contract."""
    return {t.name for t in info.topics.values() if t.transient_local or _is_map(t.name)}


class _Publishers:
    def __init__(self, node: Any, info: BagInfo, selected: list[str], remap: dict[str, str]) -> None:
        classes = {}
        for topic in selected:  # every type first: fail before any publisher exists
            try:
                classes[topic] = schemas.message_class(info.topics[topic].type_name)
            except (schemas.UnknownTypeError, ValueError) as exc:
                raise ReplayError(f"{topic}: {exc}") from None
        latched = latched_topics(info)
        self.node = node
        self.out: dict[str, str] = {}
        self.pubs: dict[str, Any] = {}
        self.depth: dict[str, int] = {}
        self.unmatched: set[str] = set()  # topics whose first message went out to no subscriber
        for topic, cls in classes.items():
            transient = topic in latched
            depth = min(max(info.topics[topic].count, 1), LATCHED_DEPTH_MAX if transient else STREAM_DEPTH_MAX)
            self.out[topic] = remap.get(topic, topic)
            self.depth[topic] = depth
            profile = rclpy_profile(transient_local=transient, depth=depth)
            self.pubs[topic] = node.create_publisher(cls, self.out[topic], profile)

    def wait_matched(self, topics: Iterable[str], count: int, timeout: float, stop: threading.Event) -> None:
        deadline = time.monotonic() + timeout
        topics = list(topics)
        while True:
            lacking = [self.out[t] for t in topics if self.pubs[t].get_subscription_count() < count]
            if not lacking:
                return
            if time.monotonic() >= deadline:
                raise ReplayError(
                    f"timed out after {timeout:.1f} s waiting for {count} subscriber(s) on {lacking} "
                    "(is the node running, in the same ROS_DOMAIN_ID? --wait-subscribers 0 starts without them)"
                )
            if stop.wait(0.02):
                return

    def wait_acked(self, topics: Iterable[str], timeout: float) -> list[str]:
        from rclpy.duration import Duration

        deadline = time.monotonic() + timeout
        unacked = []
        for topic in topics:
            left = max(deadline - time.monotonic(), 0.0)
            if not self.pubs[topic].wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
                unacked.append(self.out[topic])
        return unacked

    def destroy(self) -> None:
        for pub in self.pubs.values():
            self.node.destroy_publisher(pub)


def _no_message(info: BagInfo) -> str:
    """Why a bag without messages has none."""
    if not info.finished:
        return "no complete message: an unfinished bag (its recording stopped, or the file was cut, in its first chunk)"
    return "the bag holds no message"


def replay(
    path: str | os.PathLike,
    *,
    rate: float = 1.0,
    fast: bool = False,
    clock: bool = False,
    clock_hz: float = DEFAULT_CLOCK_HZ,
    remap: Iterable[str] | Mapping[str, str] | None = None,
    topics: Iterable[str] | None = None,
    wait_subscribers: int | None = None,
    wait_timeout: float = 30.0,
    ack_timeout: float = 30.0,
    loop: bool = False,
    hold: float = 0.0,
    stop_event: threading.Event | None = None,
    node: Any = None,
    on_started: Callable[[], None] | None = None,
    on_done: Callable[[ReplaySummary], None] | None = None,
    on_published: Callable[[str, int], None] | None = None,
) -> ReplaySummary:
    """Publishes the bag's messages (see the module docstring); returns what was published.

    ``rate``: multiple of the recorded rate (ignored with ``fast``). ``topics``: only these bag topics.
    ``wait_subscribers``: before starting, wait until every replayed topic has that many subscribers
    (``wait_timeout``, then ReplayError); None (the default): one on each `expected_topics`; 0: no wait.
    ``hold``: seconds to keep the publishers (and the latched map) alive after the last message.
    ``stop_event``: set it to stop early (Ctrl-C in the main thread does the same). ``node``: publish
    from this node instead of an own one in a new context.
    ``on_started()``: called when publishing starts; ``on_done(summary)``: when it ends, before ``hold``;
    ``on_published(topic, log_time_ns)``: after each message was published (bag topic; a latency's origin).
    """
    if not fast and not rate > 0:
        raise ValueError(f"rate must be > 0, got {rate}")
    stop = stop_event or threading.Event()
    info = bag_info(path)
    selected = list(info.topics) if topics is None else list(topics)
    unknown = [t for t in selected if t not in info.topics]
    if unknown:
        raise ReplayError(f"{path}: no topic(s) {unknown} in the bag (it has {sorted(info.topics)})")
    selected = [t for t in selected if info.topics[t].count > 0]
    if not selected:  # replaying nothing and exiting 0 would pass for a replay
        raise ReplayError(f"{path}: {_no_message(info) if info.message_count == 0 else 'no message on those topics'}")
    remaps = parse_remaps(remap)
    summary = ReplaySummary(str(path), {}, 0.0, 0, info.duration_s, None if fast else rate)
    counts: Counter[str] = Counter()
    gate: MapGate | None = None
    with (
        ros_node("monovoc_replay", node, writer_heartbeat_ms=WRITER_HEARTBEAT_MS) as ros,
        contextlib.ExitStack() as own,
    ):
        pubs = _Publishers(ros, info, selected, remaps)
        clock_pub = _ClockPublisher(ros) if clock else None
        try:
            if wait_subscribers is None:
                pubs.wait_matched(expected_topics(selected), 1, wait_timeout, stop)
            elif wait_subscribers > 0:
                pubs.wait_matched(selected, wait_subscribers, wait_timeout, stop)
            if fast and node is None and any(_is_map(t) for t in selected):
                gate = MapGate(ros)
                own.enter_context(spinning(ros))
                gate = gate if gate.found(stop) else None
                summary.map_gate = gate is not None
            if on_started is not None:
                on_started()
            start = time.monotonic()
            try:
                while not stop.is_set():
                    late = _play_once(
                        Path(path), selected, pubs, clock_pub, counts, fast, rate, clock_hz, stop, on_published, gate
                    )
                    summary.max_late_ms = max(summary.max_late_ms, late)
                    summary.loops += 1
                    if not loop:
                        break
            except KeyboardInterrupt:
                summary.interrupted = True
            summary.interrupted = summary.interrupted or stop.is_set()
            # Ctrl-C: acknowledge briefly, do not hang the user's terminal.
            summary.unacked = pubs.wait_acked(selected, 1.0 if summary.interrupted else ack_timeout)
            summary.seconds = time.monotonic() - start
            summary.messages = {pubs.out[t]: counts[t] for t in selected}
            summary.unmatched = [pubs.out[t] for t in expected_topics(selected) if t in pubs.unmatched]
            summary.maps_unconfirmed = gate.missed if gate is not None else 0
            if on_done is not None:
                on_done(summary)
            if hold > 0 and not summary.interrupted:
                try:
                    stop.wait(hold)
                except KeyboardInterrupt:
                    summary.interrupted = True
        finally:
            pubs.destroy()
            if clock_pub is not None:
                clock_pub.destroy()
    return summary


class _ClockPublisher:
    def __init__(self, node: Any) -> None:
        from rosgraph_msgs.msg import Clock

        self._cls = Clock
        self.node = node
        # Reliable, depth 1: matches best-effort clock subscribers (rclcpp::ClockQoS) and reliable ones.
        self.pub = node.create_publisher(Clock, CLOCK_TOPIC, rclpy_profile(depth=1))

    def publish(self, stamp_ns: int) -> None:
        from builtin_interfaces.msg import Time

        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        self.pub.publish(self._cls(clock=Time(sec=sec, nanosec=nanosec)))

    def destroy(self) -> None:
        self.node.destroy_publisher(self.pub)


def _play_once(
    path: Path,
    selected: list[str],
    pubs: _Publishers,
    clock_pub: _ClockPublisher | None,
    counts: Counter,
    fast: bool,
    rate: float,
    clock_hz: float,
    stop: threading.Event,
    on_published: Callable[[str, int], None] | None = None,
    gate: MapGate | None = None,
) -> float:
    """One pass over the bag; returns the worst lateness behind the schedule in ms. `gate`: --fast waits for each
    map to be taken (module docstring)."""
    first_ns: int | None = None
    wall0 = 0.0
    worst_late = 0.0
    since_ack: Counter[str] = Counter()
    clock_period = 1.0 / clock_hz if clock_hz > 0 else None
    for message in iter_messages(path, topics=selected):
        if stop.is_set():
            break
        if first_ns is None:
            first_ns, wall0 = message.log_time_ns, time.monotonic()
        if not fast:
            target = wall0 + (message.log_time_ns - first_ns) / 1e9 / rate
            _wait_until(target, stop, clock_pub, clock_period, first_ns, wall0, rate)
            if stop.is_set():
                break
            worst_late = max(worst_late, (time.monotonic() - target) * 1e3)
        if clock_pub is not None:
            clock_pub.publish(message.log_time_ns)
        topic = message.topic
        if not counts[topic] and pubs.pubs[topic].get_subscription_count() == 0:
            pubs.unmatched.add(topic)
        publisher = pubs.pubs[topic]
        gated = gate is not None and not gate.missed and _is_map(topic) and publisher.get_subscription_count() > 0
        before = gate.counts() if gated else None
        publisher.publish(message.data)
        if on_published is not None:
            on_published(topic, message.log_time_ns)
        counts[topic] += 1
        since_ack[topic] += 1
        if before is not None:
            gate.wait_taken(before, stop)
        if fast and since_ack[topic] >= pubs.depth[topic]:
            # The history is full of possibly unacknowledged samples: the next write could drop one.
            pubs.wait_acked([topic], 30.0)
            since_ack[topic] = 0
    return worst_late


def _wait_until(
    target: float,
    stop: threading.Event,
    clock_pub: _ClockPublisher | None,
    clock_period: float | None,
    first_ns: int,
    wall0: float,
    rate: float,
) -> None:
    while True:
        now = time.monotonic()
        if now >= target or stop.is_set():
            return
        step = target - now
        if clock_pub is not None and clock_period is not None:
            step = min(step, clock_period)
        if stop.wait(step):
            return
        if clock_pub is not None and time.monotonic() < target:
            clock_pub.publish(first_ns + int((time.monotonic() - wall0) * rate * 1e9))
