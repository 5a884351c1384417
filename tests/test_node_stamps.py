"""One far-future stamp against the live node (issue 9, case 4): a single valid pose stamped
sec = 2^31 - 1 made every later pose `stamp_out_of_order` until a reset. Now it is rejected against the
other topics (stamp_future) and every later keyframe is integrated."""

from __future__ import annotations

import copy

import pytest

import msg_adapters as ma
from monovoc_ros.nodes.keyframe_publisher import KeyframePublisher
from monovoc_ros.ros_harness import ClientNode, DiagnosticsMonitor, NodeProcess, ros_args, wait_for_subscribers
from tests.node_scene import NODE, scene_messages, small_scene
from tests.rosutil import ros_environment

pytestmark = pytest.mark.ros


def test_a_far_future_pose_does_not_block_mapping(tmp_path):
    scene, messages = small_scene(), scene_messages()
    outlier = copy.deepcopy(messages[3]["pose"])
    outlier.header.stamp = ma.ns_to_time((2**31 - 1) * 1_000_000_000)
    env = ros_environment(tmp_path)
    params = {"publish_rate_hz": 0.0, "diagnostics_period_s": 0.2}
    with (
        NodeProcess.python([*NODE, *ros_args(params)], env, name="semantic_mapper") as node,
        ClientNode(env) as client,
    ):
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        publisher = KeyframePublisher(client.node)
        for pub in publisher.all_publishers():
            wait_for_subscribers(pub, timeout=20.0, process=node)
        publisher.publish_map(scene.gaussians)
        for msgs in messages[:3]:
            publisher.publish_messages(msgs)
        diagnostics.wait_for(lambda v: v["keyframes_processed"] == "3", 20.0, process=node)
        publisher.publishers["pose"].publish(outlier)
        diagnostics.wait_for(lambda v: v["rejected.stamp_future"] == "1", 10.0, process=node)
        for msgs in messages[3:8]:
            publisher.publish_messages(msgs)
        done = diagnostics.wait_for(lambda v: v["keyframes_processed"] == "8", 20.0, process=node)
        node.wait_for_output("ahead of every other topic", 10.0)
        node.check_running()
    assert done["rejected.stamp_out_of_order"] == "0" and done["rejected_total"] == "1"
