"""The benchmarks' viewer of the semantic cloud (monovoc_ros.nodes.cloud_viewer), a process of its own: it says
when it sees the cloud's publisher, and reports when each cloud arrived on the machine's monotonic clock."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

import msg_adapters as ma
from monovoc_ros.nodes.qos import latched_qos
from monovoc_ros.ros_harness import ClientNode, NodeProcess, wait_until
from tests.rosutil import ros_environment

pytestmark = pytest.mark.ros

S = 1_000_000_000


def test_the_viewer_reports_when_each_cloud_arrived(tmp_path):
    from sensor_msgs.msg import PointCloud2

    env = ros_environment(tmp_path)
    files = {k: tmp_path / f"viewer.{k}" for k in ("ready", "stop", "json")}
    args = ["-m", "monovoc_ros.nodes.cloud_viewer", "--ready-file", str(files["ready"]), "--stop-file",
            str(files["stop"]), "--out", str(files["json"])]  # fmt: skip
    points = np.zeros((3, 3), np.float32)
    with NodeProcess.python(args, env, name="cloud_viewer") as viewer, ClientNode(env) as client:
        publisher = client.node.create_publisher(PointCloud2, "/monovoc/semantic_cloud", latched_qos())
        wait_until(files["ready"].exists, 30.0, "the viewer to see the publisher", process=viewer)
        wait_until(lambda: publisher.get_subscription_count() > 0, 30.0, "the viewer's subscription", process=viewer)
        sent = {}

        def arrived() -> set[int]:
            if not files["json"].exists():
                return set()
            return {int(k) for k in json.loads(files["json"].read_text())["arrivals"]}

        for stamp in (7 * S, 8 * S):
            sent[stamp] = time.monotonic()
            msg = ma.semantic_cloud_from_arrays(points, np.zeros((3, 3), np.uint8), np.zeros(3, np.uint32),
                                               np.ones(3, np.float32), stamp=stamp)  # fmt: skip
            publisher.publish(msg)
            wait_until(lambda s=stamp: s in arrived(), 30.0, f"cloud {stamp} at the viewer", process=viewer)
        files["stop"].touch()
        wait_until(lambda: not viewer.running(), 30.0, "the viewer to end", process=None)
        assert viewer.returncode == 0, viewer.describe()
    arrivals = {int(k): v for k, v in json.loads(files["json"].read_text())["arrivals"].items()}
    assert sorted(arrivals) == [7 * S, 8 * S]
    # One clock for both processes: each cloud arrived after it was sent, within the test's time.
    for stamp, at in sent.items():
        assert at <= arrivals[stamp] < at + 30.0


def test_the_viewer_gives_up_without_a_publisher(tmp_path):
    args = ["-m", "monovoc_ros.nodes.cloud_viewer", "--ready-file", str(tmp_path / "r"), "--stop-file",
            str(tmp_path / "s"), "--out", str(tmp_path / "o.json"), "--timeout", "1"]  # fmt: skip
    with NodeProcess.python(args, ros_environment(tmp_path), name="cloud_viewer") as viewer:
        wait_until(lambda: not viewer.running(), 60.0, "the viewer to give up", process=None)
        assert viewer.returncode != 0 and "no publisher of /monovoc/semantic_cloud" in viewer.output()
    assert not (tmp_path / "r").exists()
