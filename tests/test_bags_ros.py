"""`monovoc replay` and `monovoc record` with real rclpy processes on loopback."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, CompressedImage, PointCloud2
from test_bags_convert import assert_same_map, moved, small_scene

import msg_adapters as ma
from monovoc_ros.bags import bag_info, iter_messages, record, replay, sequence_to_bag, topic_names
from monovoc_ros.bags.schemas import canonical_cdr
from monovoc_ros.ros_harness import (
    FOREIGN_ROS_VARIABLES,
    ClientNode,
    HarnessError,
    KeyframePublishTimes,
    MessageCollector,
    NodeProcess,
    cloud_latencies_ms,
    first_cloud_at,
    wait_until,
)
from tests.rosutil import REPO, ros_environment

pytestmark = pytest.mark.ros

TOPICS = topic_names()
TYPES = {
    "image": CompressedImage,
    "mask": CompressedImage,
    "camera_info": CameraInfo,
    "pose": PoseStamped,
    "gaussians": PointCloud2,
}


@pytest.fixture(scope="module")
def scene():
    return small_scene()


@pytest.fixture(scope="module")
def bag(scene, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("ros") / "scene.mcap"
    sequence_to_bag(scene, path, map_updates={3: moved(scene.gaussians)})
    return path


def qos(role: str):
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    durability = DurabilityPolicy.TRANSIENT_LOCAL if role == "gaussians" else DurabilityPolicy.VOLATILE
    return QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=durability)


def replay_process(bag: Path, env: dict, *args: str) -> NodeProcess:
    return NodeProcess.python(["-m", "monovoc_ros.cli", "replay", str(bag), *args], env, name="replay")


def finish(process: NodeProcess, timeout: float = 60.0) -> dict:
    """Waits for the process to exit with 0; returns the JSON summary it printed."""
    try:
        wait_until(lambda: process.returncode is not None, timeout, f"{process.name} to exit")
    except HarnessError:
        # Interrupted, the recorder prints what it received per topic: whether a message was lost, and where.
        process.stop()
        raise AssertionError(f"{process.name} did not exit within {timeout} s\n{process.describe()}") from None
    assert process.returncode == 0, process.describe()
    return printed_summary(process)


def printed_summary(process: NodeProcess) -> dict:
    text = process.output()
    return json.loads(text[text.index("{\n") : text.index("\n}") + 2])


def bag_messages(bag: Path, role: str) -> list:
    return [m.decode() for m in iter_messages(bag, topics=[TOPICS[role]])]


def test_replay_fast_delivers_every_message_and_remaps(bag: Path, tmp_path: Path) -> None:
    env = ros_environment(tmp_path)
    counts = {t.name: t.count for t in bag_info(bag).topics.values()}
    with ClientNode(env) as client:
        received = {role: MessageCollector() for role in TYPES}
        for role, cls in TYPES.items():
            name = "/cam/image" if role == "image" else TOPICS[role]
            client.node.create_subscription(cls, name, received[role], qos(role))
        old_name = MessageCollector()
        client.node.create_subscription(CompressedImage, TOPICS["image"], old_name, qos("image"))
        args = ["--fast", "--wait-subscribers", "1", "--remap", "/monovoc/image:=/cam/image"]
        with replay_process(bag, env, *args) as p:
            summary = finish(p)
        assert summary["messages"]["/cam/image"] == counts[TOPICS["image"]] and not summary["unacked"]
        assert "deprecated" not in p.output()  # the command's arguments are not taken for rcl remap rules
        for role in TYPES:
            received[role].wait_for(counts[TOPICS[role]], timeout=10.0)
        time.sleep(0.2)  # nothing more may arrive (no duplicates)
        assert {role: len(c.messages) for role, c in received.items()} == {r: counts[TOPICS[r]] for r in TYPES}
        assert not old_name.messages
    for got, ref in zip(received["mask"].messages, bag_messages(bag, "mask"), strict=True):
        assert ma.header_stamp_ns(got) == ma.header_stamp_ns(ref)
        np.testing.assert_array_equal(ma.compressed_image_to_numpy(got), ma.compressed_image_to_numpy(ref))
    maps = [ma.cloud_to_gaussian_map(m) for m in received["gaussians"].messages]
    for got, ref in zip(maps, bag_messages(bag, "gaussians"), strict=True):
        assert_same_map(got, ma.cloud_to_gaussian_map(ref))


def test_replay_fast_waits_by_default_for_subscribers_that_come_late(bag: Path, tmp_path: Path) -> None:
    """Plain `monovoc replay --fast` started before anything subscribes (a node still starting) waits for
    one subscriber on each keyframe and map topic, then loses nothing (it sent 0 of 60 to a node before)."""
    env = ros_environment(tmp_path)
    counts = {t.name: t.count for t in bag_info(bag).topics.values()}
    with replay_process(bag, env, "--fast") as p, ClientNode(env) as client:
        # Each subscription is created while the replay is already waiting: they match one by one.
        received = {}
        for role, cls in TYPES.items():
            assert p.returncode is None and '"total"' not in p.output()  # still waiting, nothing published
            received[role] = MessageCollector()
            client.node.create_subscription(cls, TOPICS[role], received[role], qos(role))
        summary = finish(p)
        for role in TYPES:
            received[role].wait_for(counts[TOPICS[role]], timeout=10.0)
    assert summary["unmatched"] == [] and summary["unacked"] == []
    assert {role: len(c.messages) for role, c in received.items()} == {r: counts[TOPICS[r]] for r in TYPES}


class _Arrivals:
    def __init__(self) -> None:
        self.times: list[float] = []
        self.values: list[int] = []

    def __call__(self, msg) -> None:
        self.times.append(time.monotonic())
        self.values.append(ma.time_to_ns(msg.clock) if isinstance(msg, Clock) else ma.header_stamp_ns(msg))


def test_replay_keeps_the_recorded_rate_and_publishes_clock(bag: Path, tmp_path: Path) -> None:
    env = ros_environment(tmp_path)
    info = bag_info(bag)
    masks, clock = _Arrivals(), _Arrivals()
    with ClientNode(env) as client:
        client.node.create_subscription(CompressedImage, TOPICS["mask"], masks, qos("mask"))
        client.node.create_subscription(PoseStamped, TOPICS["pose"], MessageCollector(), qos("pose"))
        client.node.create_subscription(Clock, "/clock", clock, qos("clock"))
        args = ["--rate", "0.5", "--clock", "--wait-subscribers", "1", "--topics", TOPICS["mask"], TOPICS["pose"]]
        with replay_process(bag, env, *args) as p:
            summary = finish(p)
    assert set(summary["messages"]) == {TOPICS["mask"], TOPICS["pose"]}
    # Keyframes are 0.1 s apart in the bag: 0.2 s at half rate.
    stamps = [m.log_time_ns for m in iter_messages(bag, topics=[TOPICS["mask"]])]
    assert masks.values == stamps
    # The pacing is the replayer's: it reports how far behind its schedule it ever published (the gaps
    # between arrivals here also carry this process's own scheduling, which a loaded machine stretches).
    assert summary["max_late_ms"] < 80, summary
    assert summary["seconds"] >= 1.0, summary  # never ahead of it: 6 masks 0.2 s apart, then the acks
    # /clock: bag time, never backwards, at ~40 Hz of wall time in between.
    assert len(clock.values) >= 25
    assert np.all(np.diff(clock.values) >= 0)
    assert info.start_ns <= clock.values[0] and clock.values[-1] <= info.end_ns


def test_late_subscriber_gets_the_latched_map_and_ctrl_c_exits_cleanly(scene, bag: Path, tmp_path: Path) -> None:
    env = ros_environment(tmp_path)
    with replay_process(bag, env, "--rate", "4", "--hold", "60", "--wait-subscribers", "0") as p:
        p.wait_for_output('"total"', timeout=30.0)  # playback over; the publishers are held
        with ClientNode(env) as client:
            maps = MessageCollector()
            client.node.create_subscription(PointCloud2, TOPICS["gaussians"], maps, qos("gaussians"))
            maps.wait_for(2, timeout=10.0, process=p)
        assert p.stop() == 2, p.describe()  # the keyframes went out to no one: said loudly, exit code 2
    assert "Traceback" not in p.output()
    assert "WARNING: no subscriber on" in p.output() and TOPICS["mask"] in p.output()
    assert_same_map(ma.cloud_to_gaussian_map(maps.messages[0]), scene.gaussians)
    assert_same_map(ma.cloud_to_gaussian_map(maps.messages[-1]), moved(scene.gaussians))


def _use_ros_env(env: dict, monkeypatch) -> None:
    # In-process replay/record create their own context: it reads these from the process environment.
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOG_DIR", "HOME"):
        monkeypatch.setenv(key, env[key])
    for key in FOREIGN_ROS_VARIABLES:
        monkeypatch.delenv(key, raising=False)


def test_record_a_replay_gives_the_same_bag(bag: Path, tmp_path: Path, monkeypatch) -> None:
    env = ros_environment(tmp_path)
    _use_ros_env(env, monkeypatch)
    out = tmp_path / "recorded.mcap"
    total = bag_info(bag).message_count
    args = ["-m", "monovoc_ros.cli", "record", "-o", str(out), *bag_info(bag).topics]
    with NodeProcess.python([*args, "--count", str(total), "--log-time", "header"], env, name="record") as rec:
        rec.wait_for_output("monovoc record: recording", timeout=30.0)
        sent: list[tuple[str, int, float]] = []
        keyframes = KeyframePublishTimes()

        def published(topic: str, log_time_ns: int) -> None:
            sent.append((topic, log_time_ns, time.monotonic()))
            keyframes(topic, log_time_ns)

        summary = replay(bag, fast=True, wait_subscribers=1, wait_timeout=30.0, on_published=published)
        assert sum(summary.messages.values()) == total and not summary.unacked
        recorded = finish(rec, timeout=30.0)
    # on_published heard every message once, in the bag's order; a keyframe's time is its last message's.
    assert [(t, ns) for t, ns, _ in sent] == [(m.topic, m.log_time_ns) for m in iter_messages(bag)]
    masks = [m.log_time_ns for m in iter_messages(bag, [TOPICS["mask"]])]
    assert sorted(keyframes.at) == masks
    for stamp, at in keyframes.at.items():
        mine = [t for topic, ns, t in sent if ns == stamp and topic in keyframes.topics]
        later = [t for _, ns, t in sent if ns > stamp]
        assert len(mine) == 4 and max(mine) <= at <= min(later, default=at)
    assert recorded["total"] == total and not recorded["missing"]
    source, copy = bag_info(bag), bag_info(out)
    assert {t.name: (t.type_name, t.count) for t in copy.topics.values()} == {
        t.name: (t.type_name, t.count) for t in source.topics.values()
    }
    assert copy.topics[TOPICS["gaussians"]].transient_local and not copy.topics[TOPICS["mask"]].transient_local
    for topic, info in source.topics.items():
        a = [(m.log_time_ns, canonical_cdr(m.data, info.type_name)) for m in iter_messages(bag, [topic])]
        b = [(m.log_time_ns, canonical_cdr(m.data, info.type_name)) for m in iter_messages(out, [topic])]
        assert a == b, topic
    with AnyReader([out], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        assert reader.message_count == total
        for connection, _, raw in reader.messages(connections=reader.connections[:1]):
            reader.deserialize(raw, connection.msgtype)


def test_cloud_latencies_count_from_each_keyframes_publication() -> None:
    published = {100: 10.0, 200: 10.5, 300: 11.0, 400: 11.5}
    # Stamp 100 arrives alone, 200 is first held by the cloud of 300, 400 by no cloud; 900 is the node's own.
    arrivals = {100: 10.08, 300: 11.2, 900: 10.9}
    assert np.allclose(cloud_latencies_ms(published, arrivals), [80.0, 700.0, 200.0])
    assert cloud_latencies_ms({}, arrivals) == [] and cloud_latencies_ms(published, {}) == []
    # The first cloud holding a keyframe came at 10.08: keyframes published from then on are the running ones.
    assert first_cloud_at(published, arrivals) == 10.08 and first_cloud_at(published, {900: 10.9}) is None
    assert np.allclose(cloud_latencies_ms(published, arrivals, after=10.08), [700.0, 200.0])


def test_record_stops_on_ctrl_c_and_on_duration(tmp_path: Path, monkeypatch) -> None:
    env = ros_environment(tmp_path)
    _use_ros_env(env, monkeypatch)
    out = tmp_path / "interrupted.mcap"
    with NodeProcess.python(["-m", "monovoc_ros.cli", "record", "-o", str(out), "/nobody/publishes"], env) as rec:
        rec.wait_for_output("monovoc record: recording", timeout=30.0)
        assert rec.stop() == 0, rec.describe()
    summary = printed_summary(rec)
    assert summary["interrupted"] and summary["missing"] == ["/nobody/publishes"]
    assert bag_info(out).message_count == 0  # a finalized, readable (empty) bag
    stop = threading.Event()
    start = time.monotonic()
    result = record(tmp_path / "timed.mcap", ["/nobody/either"], duration=0.3, stop_event=stop)
    assert 0.3 <= time.monotonic() - start < 5.0 and result.missing == ["/nobody/either"]
    assert bag_info(tmp_path / "timed.mcap").message_count == 0
    # A file it cannot write (its folder would be a file): one line, exit code 1, before waiting for any topic.
    (tmp_path / "a_file").write_text("in the way")
    nowhere = tmp_path / "a_file" / "out.mcap"
    failed = subprocess.run([sys.executable, "-m", "monovoc_ros.cli", "record", "-o", str(nowhere), "/x"], env=env,
                            capture_output=True, text=True, timeout=60)  # fmt: skip
    assert failed.returncode == 1 and failed.stderr.startswith("monovoc record: ") and "Traceback" not in failed.stderr
    # A bag that exists is never replaced (it replaced a 9 MB recording with an empty one and said nothing).
    kept = (tmp_path / "timed.mcap").read_bytes()
    with pytest.raises(ValueError, match="already exists"):
        record(tmp_path / "timed.mcap", ["/nobody/either"], duration=0.1)
    assert (tmp_path / "timed.mcap").read_bytes() == kept


def test_replay_errors(bag: Path, tmp_path: Path, monkeypatch) -> None:
    from monovoc_ros.bags.replayer import ReplayError, parse_remaps

    assert parse_remaps(["/a:=/b", "/c:=/d"]) == {"/a": "/b", "/c": "/d"}
    with pytest.raises(ValueError, match="FROM:=TO"):
        parse_remaps(["/a=/b"])
    with pytest.raises(ValueError, match="absolute"):
        parse_remaps(["a:=/b"])
    with pytest.raises(ValueError, match="rate"):
        replay(bag, rate=0.0)
    with pytest.raises(ReplayError, match="/nope"):
        replay(bag, topics=["/nope"])
    # A bag cut inside its first chunk has no complete message: said, not "replayed" with nothing sent.
    cut = tmp_path / "cut.mcap"
    cut.write_bytes((REPO / "bags" / "synthetic_room.mcap").read_bytes()[:100_000])  # its first chunk: 6.6 MB
    with pytest.raises(ReplayError, match="unfinished bag"):
        replay(cut)
    # Nothing published: exit code 3 (NOT_STARTED), on which the launch file ends the launch. In a process of its own:
    # the command installs its signal handlers.
    from monovoc_ros.commands.replay import NOT_STARTED

    for path in (cut, tmp_path / "no_such.mcap"):
        failed = subprocess.run([sys.executable, "-m", "monovoc_ros.cli", "replay", str(path)], capture_output=True,
                                text=True, timeout=60)  # fmt: skip
        assert failed.returncode == NOT_STARTED == 3, failed.stderr
        assert failed.stderr.startswith("monovoc replay: ") and "Traceback" not in failed.stderr
    _use_ros_env(ros_environment(tmp_path), monkeypatch)
    start = time.monotonic()
    with pytest.raises(ReplayError, match="1 subscriber"):
        replay(bag, topics=[TOPICS["mask"]], wait_subscribers=1, wait_timeout=0.3)
    assert time.monotonic() - start < 5.0


def test_the_short_writer_heartbeat_is_in_place_when_the_participant_is_created(tmp_path, monkeypatch):
    """Fast DDS reads its profile when a context's first node creates the participant (not at init): the
    replay's own node and the harness's ClientNode are created with the 50 ms heartbeat profile in the
    environment, and it is gone afterwards (a fast replay beside a client ended 3 s late without it)."""
    import rclpy

    from monovoc_ros.bags.rosnode import ros_node
    from monovoc_ros.fastdds_profile import WRITER_HEARTBEAT_MS

    env = ros_environment(tmp_path)
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOG_DIR", "HOME"):
        monkeypatch.setenv(key, env[key])
    monkeypatch.delenv("FASTRTPS_DEFAULT_PROFILES_FILE", raising=False)
    monkeypatch.delenv("RMW_IMPLEMENTATION", raising=False)
    profiles: list[str] = []
    create_node = rclpy.create_node

    def recording(*args, **kwargs):
        path = os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE")
        profiles.append(Path(path).read_text() if path else "")
        return create_node(*args, **kwargs)

    monkeypatch.setattr(rclpy, "create_node", recording)
    with ros_node("monovoc_replay_probe", writer_heartbeat_ms=WRITER_HEARTBEAT_MS):
        assert "FASTRTPS_DEFAULT_PROFILES_FILE" not in os.environ
    with ClientNode(env):
        assert "FASTRTPS_DEFAULT_PROFILES_FILE" not in os.environ
    heartbeat = f"<nanosec>{WRITER_HEARTBEAT_MS * 1_000_000}</nanosec>"
    assert len(profiles) == 2 and all(heartbeat in p for p in profiles), profiles
