"""Ctrl-C as a terminal sends it: the node gets SIGINT from the terminal and another one from `ros2 launch`
(the whole foreground process group is signalled). Signals after the first must never cut the final
snapshot short (in one of two runs the second raised KeyboardInterrupt in the worker's join: no snapshot)."""

from __future__ import annotations

import os
import signal

import pytest

from monovoc_ros.core.map_store import load_snapshot
from monovoc_ros.nodes.keyframe_publisher import KeyframePublisher
from monovoc_ros.ros_harness import (
    ClientNode,
    DiagnosticsMonitor,
    NodeProcess,
    ros_args,
    wait_for_subscribers,
    wait_until,
)
from tests.node_scene import NODE, assemble, scene_messages, small_scene
from tests.rosutil import ros_environment

pytestmark = pytest.mark.ros


def test_a_burst_of_sigint_during_shutdown_keeps_the_final_snapshot(tmp_path):
    scene, messages = small_scene(), scene_messages()
    n = len(assemble(messages))
    map_dir = tmp_path / "map"
    env = ros_environment(tmp_path)
    params = {"map_directory": str(map_dir), "save_period_s": 0.0, "diagnostics_period_s": 0.2}
    with ClientNode(env) as client:
        publisher = KeyframePublisher(client.node)
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        publisher.publish_map(scene.gaussians)
        with NodeProcess.python([*NODE, *ros_args(params)], env, name="semantic_mapper") as node:
            for pub in publisher.all_publishers():
                wait_for_subscribers(pub, timeout=30.0, process=node)
            for msgs in messages:
                publisher.publish_messages(msgs)
            diagnostics.wait_for(lambda v: v["keyframes_processed"] == str(n), 30.0, process=node)
            # SIGINT after SIGINT until the node has exited: every phase of its shutdown gets one.
            sent = 0

            def interrupted() -> bool:
                nonlocal sent
                if node.returncode is None:
                    os.kill(node.pid, signal.SIGINT)
                    sent += 1
                return node.returncode is not None

            wait_until(interrupted, 60.0, "the node to exit", interval=0.005)
            assert node.returncode == 0, node.describe()
    assert sent >= 2, sent
    assert "Traceback" not in node.output() and "KeyboardInterrupt" not in node.output()
    assert load_snapshot(map_dir).n_keyframes == n
