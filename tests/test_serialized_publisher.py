"""SerializedPublisher on real rclpy nodes: the CDR bytes sent through rcl without the interpreter arrive as the
same message rclpy's own publish sends (its reference twin), on this machine through librcl (not the fallback),
and a destroyed publisher, a publish rcl refuses or bytes that are no byte array are errors, not crashes."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import msg_adapters as ma
from monovoc_ros.nodes.qos import latched_qos
from monovoc_ros.nodes.serialized_publisher import SerializedPublisher, loaded_rcl
from monovoc_ros.ros_harness import ClientNode, MessageCollector, wait_until
from tests.rosutil import ros_environment


def _cloud_arrays(n: int, seed: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    ids = rng.integers(0, 2**24, n, dtype=np.uint32)
    return rng.normal(size=(n, 3)).astype(np.float32), ids, ids, rng.uniform(0, 1, n).astype(np.float32)


def test_bytes_sent_without_the_interpreter_arrive_as_rclpy_s_message(tmp_path: Path) -> None:
    from sensor_msgs.msg import PointCloud2

    assert loaded_rcl() is not None  # Linux with rclpy's librcl: the path under test is the real one
    env = ros_environment(tmp_path)
    with ClientNode(env) as host, ClientNode(env, name="viewer") as viewer:
        released = SerializedPublisher(host.node.create_publisher(PointCloud2, "released", latched_qos(depth=3)))
        held = SerializedPublisher(
            host.node.create_publisher(PointCloud2, "held", latched_qos(depth=3)), release_interpreter=False
        )
        assert released.releases_interpreter and not held.releases_interpreter
        received = {topic: MessageCollector() for topic in ("released", "held")}
        for topic, collector in received.items():
            viewer.node.create_subscription(PointCloud2, topic, collector, latched_qos(depth=3))
        for publisher in (released, held):
            wait_until(lambda p=publisher: p.publisher.get_subscription_count() == 1, 20.0, "the subscribers")
        sent = []
        for i, n in enumerate((0, 3, 250_000)):  # the last ~6 MB: big enough for Fast DDS to fragment it
            arrays = _cloud_arrays(n, i)
            sent.append(ma.semantic_cloud_from_arrays(*arrays, frame_id="map", stamp=i + 1))
            data = ma.serialized_semantic_cloud(*arrays, frame_id="map", stamp=i + 1)
            released.publish(data)
            held.publish(data)
        for collector in received.values():
            assert collector.wait_for(3, 20.0) == sent


def test_a_destroyed_publisher_is_an_error_not_a_crash(tmp_path: Path) -> None:
    from rclpy.exceptions import InvalidHandle
    from sensor_msgs.msg import PointCloud2

    with ClientNode(ros_environment(tmp_path)) as host:
        publisher = host.node.create_publisher(PointCloud2, "gone", latched_qos())
        senders = [SerializedPublisher(publisher), SerializedPublisher(publisher, release_interpreter=False)]
        data = ma.serialized_semantic_cloud(*_cloud_arrays(10, 0), frame_id="map")
        for sender in senders:
            sender.publish(data)
            with pytest.raises(ValueError, match=r"contiguous \(B,\) uint8"):
                sender.publish(data.view(np.int8))
            with pytest.raises(ValueError, match=r"contiguous \(B,\) uint8"):
                sender.publish(data[::2])
        host.node.destroy_publisher(publisher)
        for sender in senders:  # both as rclpy's own publish refuses it
            with pytest.raises(InvalidHandle, match="destruction was requested"):
                sender.publish(data)


_REFUSED = """
import ctypes, rclpy
import msg_adapters as ma
import numpy as np
from rclpy import _rclpy_pybind11
from sensor_msgs.msg import PointCloud2
from monovoc_ros.nodes.serialized_publisher import SerializedPublisher
rclpy.init()
node = rclpy.create_node("refused")
sender = SerializedPublisher(node.create_publisher(PointCloud2, "refused", 1))
data = ma.serialized_semantic_cloud(np.zeros((1, 3)), np.zeros((1, 3), np.uint8), [1], [1.0])
sender.publish(data)
rclpy.shutdown()
try:
    sender.publish(data)
except RuntimeError as e:
    print("refused:", e)
print("error set:", bool(ctypes.CDLL(_rclpy_pybind11.__file__).rcutils_error_is_set()))
"""


def test_a_publish_rcl_refuses_raises_its_reason_and_clears_rcl_s_error_state(tmp_path: Path) -> None:
    """In a process of its own: its context is shut down while the publisher lives."""
    env = ros_environment(tmp_path)
    done = subprocess.run([sys.executable, "-c", _REFUSED], env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "refused: Failed to publish on /refused: publisher's context is invalid" in done.stdout
    assert "error set: False" in done.stdout
    assert "overwritten" not in done.stderr
