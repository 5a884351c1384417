"""What rosbag2 Jazzy writes and reads: RIHS01 `topic_type_hash` per MCAP channel, and
`monovoc record --format rosbag2 -o DIR` (metadata.yaml + .mcap) opened by rosbags as a rosbag2 bag."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml
from geometry_msgs.msg import PoseStamped
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader as Rosbag2Reader
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

import msg_adapters as ma
from monovoc_interfaces.msg import SemanticObjectArray
from monovoc_ros.bags import BagWriter, bag_info, iter_messages
from monovoc_ros.bags.schemas import type_hash, typestore
from monovoc_ros.ros_harness import ClientNode, NodeProcess, wait_for_subscribers, wait_until
from tests.rosutil import VENV, VENV_PYTHON, ros_environment

pytestmark = pytest.mark.ros

TYPES = {
    "/pose": PoseStamped,
    "/cloud": PointCloud2,
    "/objects": SemanticObjectArray,
    "/markers": MarkerArray,
}
TYPE_NAMES = {
    "/pose": "geometry_msgs/msg/PoseStamped",
    "/cloud": "sensor_msgs/msg/PointCloud2",
    "/objects": "monovoc_interfaces/msg/SemanticObjectArray",
    "/markers": "visualization_msgs/msg/MarkerArray",
}


def message(topic: str, i: int):
    stamp = 1_000_000_000 + i * 100_000_000
    if topic == "/pose":
        return ma.matrix_to_pose_stamped(np.eye(4), frame_id="map", stamp=stamp)
    if topic == "/cloud":
        points = np.arange(12, dtype=np.float32).reshape(4, 3) + i
        rgb = np.full((4, 3), 200, np.uint8)
        return ma.semantic_cloud_from_arrays(points, rgb, np.arange(4, dtype=np.uint32), np.ones(4, np.float32),
                                             frame_id="map", stamp=stamp)  # fmt: skip
    if topic == "/objects":
        return SemanticObjectArray(header=ma.make_header("map", stamp))
    return MarkerArray()


def installed_hash(type_name: str) -> str:
    """The hash rosidl generated for the type (share/<pkg>/msg/<Type>.json in the venv prefix)."""
    package, kind, name = type_name.split("/")
    hashes = json.loads((VENV / "share" / package / kind / f"{name}.json").read_text())["type_hashes"]
    return next(h["hash_string"] for h in hashes if h["type_name"] == type_name)


def test_every_channel_carries_the_rihs01_hash_of_its_type(tmp_path: Path) -> None:
    path = tmp_path / "hashes.mcap"
    with BagWriter(path) as writer:
        for i in range(2):
            for topic in TYPES:
                writer.write(topic, message(topic, i), 1_000_000_000 + i)
    with open(path, "rb") as f:  # read with the mcap library, not ours
        channels = {c.topic: c for c in make_reader(f).get_summary().channels.values()}
    for topic, type_name in TYPE_NAMES.items():
        digest = channels[topic].metadata["topic_type_hash"]
        assert digest.startswith("RIHS01_") and len(digest) == 7 + 64
        assert digest == installed_hash(type_name) == type_hash(type_name)
        # rosbags computes RIHS01 from the message definition: the same value.
        assert typestore().hash_rihs01(type_name) == digest
        assert bag_info(path).topics[topic].type_hash == digest
        assert "offered_qos_profiles" in channels[topic].metadata


def _environment(tmp_path: Path) -> dict:
    return ros_environment(tmp_path)


def test_record_format_rosbag2_writes_a_bag_directory_rosbags_opens(tmp_path: Path) -> None:
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    env = _environment(tmp_path)
    out = tmp_path / "recording"
    per_topic = 3
    total = per_topic * len(TYPES)
    args = ["-m", "monovoc_ros.cli", "record", "--format", "rosbag2", "-o", str(out), *TYPES, "--count", str(total)]
    with NodeProcess.python(args, env, name="record") as rec, ClientNode(env) as client:
        latched = QoSProfile(
            depth=5, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
        )
        publishers = {
            topic: client.node.create_publisher(cls, topic, latched if topic == "/cloud" else 10)
            for topic, cls in TYPES.items()
        }
        for publisher in publishers.values():
            wait_for_subscribers(publisher, 1, timeout=30.0, process=rec)
        endpoint_hashes = {
            topic: str(client.node.get_publishers_info_by_topic(topic)[0].topic_type_hash) for topic in TYPES
        }
        for i in range(per_topic):
            for topic, publisher in publishers.items():
                publisher.publish(message(topic, i))
        wait_until(lambda: rec.returncode is not None, 30.0, "the recorder to exit after --count messages")
        assert rec.returncode == 0, rec.describe()
        text = rec.output()
        summary = json.loads(text[text.index("{\n") : text.index("\n}") + 2])
    assert summary["total"] == total and summary["path"] == str(out)
    assert sorted(p.name for p in out.iterdir()) == ["metadata.yaml", "recording_0.mcap"]
    info = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["version"] == 9 and info["storage_identifier"] == "mcap" and info["ros_distro"] == "jazzy"
    assert info["relative_file_paths"] == ["recording_0.mcap"] and info["message_count"] == total

    with Rosbag2Reader(out) as reader:  # rosbags' rosbag2 reader: metadata.yaml + the MCAP storage plugin
        assert reader.message_count == total
        assert reader.duration > 0
        connections = {c.topic: c for c in reader.connections}
        assert sorted(connections) == sorted(TYPES)
        for topic, c in connections.items():
            assert c.msgtype == TYPE_NAMES[topic] and c.msgcount == per_topic
            assert c.digest == endpoint_hashes[topic] == installed_hash(TYPE_NAMES[topic])
            assert c.ext.serialization_format == "cdr"
        durability = {t: c.ext.offered_qos_profiles[0].durability.name for t, c in connections.items()}
        assert durability["/cloud"] == "TRANSIENT_LOCAL" and durability["/pose"] == "VOLATILE"
    # Every message decodes with only the bag's own schemas (an EMPTY typestore: the custom type too).
    decoded: dict[str, list] = {}
    with AnyReader([out], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        for connection, _, raw in reader.messages():
            decoded.setdefault(connection.topic, []).append(reader.deserialize(raw, connection.msgtype))
    assert {t: len(v) for t, v in decoded.items()} == dict.fromkeys(TYPES, per_topic)
    assert [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in decoded["/pose"]] == [
        1_000_000_000 + i * 100_000_000 for i in range(per_topic)
    ]
    assert decoded["/cloud"][0].width == 4
    # Our own reader takes the directory too (monovoc replay / bag info DIR).
    assert bag_info(out).message_count == total
    assert len(list(iter_messages(out, topics=["/objects"]))) == per_topic


def test_record_format_rosbag2_refuses_an_existing_directory(tmp_path: Path) -> None:
    env = _environment(tmp_path)
    existing = tmp_path / "taken"
    existing.mkdir()
    result = subprocess.run(
        [str(VENV_PYTHON), "-m", "monovoc_ros.cli", "record", "--format", "rosbag2", "-o", str(existing), "/x"],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 1
    assert f"monovoc record: {existing}: already exists" in result.stderr
    assert list(existing.iterdir()) == []


def test_reader_takes_only_readable_single_file_rosbag2_directories(tmp_path: Path) -> None:
    from monovoc_ros.bags import BagError
    from monovoc_ros.bags.writer import Rosbag2Writer

    with Rosbag2Writer(tmp_path / "ok") as writer:
        writer.write("/pose", message("/pose", 0), 5)
    assert bag_info(tmp_path / "ok").message_count == 1
    info = yaml.safe_load((tmp_path / "ok" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["starting_time"] == {"nanoseconds_since_epoch": 5} and info["duration"] == {"nanoseconds": 0}
    assert info["topics_with_message_count"][0]["topic_metadata"]["type_description_hash"] == type_hash(
        "geometry_msgs/msg/PoseStamped"
    )
    split = tmp_path / "split"
    split.mkdir()
    (split / "metadata.yaml").write_text(
        yaml.safe_dump({"rosbag2_bagfile_information": {"relative_file_paths": ["a_0.mcap", "a_1.mcap"]}})
    )
    with pytest.raises(BagError, match="only rosbag2 bags of one .mcap file"):
        bag_info(split)
    (split / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed")
    with pytest.raises(BagError, match="unreadable metadata.yaml"):
        bag_info(split)
