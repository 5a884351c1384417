"""mask_ids per_frame in the live node: the bundled per-frame bag (every mask renumbered, each with the
segmenter's class names on `segments`) replayed into semantic_mapper gives the same objects and labels as
`monovoc map --bag ... --mask-ids per-frame`."""

from __future__ import annotations

import numpy as np
import pytest

import msg_adapters as ma
from monovoc_ros.bags import bag_events, bag_info, iter_messages, topic_names
from monovoc_ros.bags.bundled import PER_FRAME_BAG, bundled_bag, make_per_frame_bag
from monovoc_ros.cli import main
from monovoc_ros.core.evidence.palette import UNOBSERVED_ID
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map_store import load_snapshot
from monovoc_ros.nodes.qos import latched_qos
from monovoc_ros.ros_harness import ClientNode, DiagnosticsMonitor, MessageCollector, NodeProcess, ros_args, wait_until
from tests.node_scene import NODE
from tests.rosutil import ros_environment
from tests.test_bags_ros import finish, replay_process

pytestmark = pytest.mark.ros


def _pose(message) -> tuple[tuple, np.ndarray]:
    msg = message.decode()
    p, q = msg.pose.position, msg.pose.orientation
    header = (msg.header.frame_id, msg.header.stamp.sec, msg.header.stamp.nanosec)
    return header, np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w])


def test_per_frame_bag_is_reproducible(tmp_path):
    """The committed bag is what the code makes: every message byte for byte, but for the poses' last
    bits (the trajectory's trigonometry and small matrix products round differently on another CPU's
    SIMD paths of numpy and OpenBLAS: 4 of 20 poses differed in 1-4 bytes between two machines)."""
    path = make_per_frame_bag(tmp_path).path
    assert bag_info(path).topics == bag_info(bundled_bag(PER_FRAME_BAG)).topics  # types, hashes, QoS, counts
    made = list(iter_messages(path))
    committed = list(iter_messages(bundled_bag(PER_FRAME_BAG)))
    assert [(m.topic, m.log_time_ns) for m in made] == [(m.topic, m.log_time_ns) for m in committed]
    pose_topic = topic_names()["pose"]
    for a, b in zip(made, committed, strict=True):
        if a.topic == pose_topic:
            (header_a, pose_a), (header_b, pose_b) = _pose(a), _pose(b)
            assert header_a == header_b
            np.testing.assert_allclose(pose_a, pose_b, rtol=0, atol=1e-12)
        else:
            assert a.data == b.data, a.topic


def test_live_node_on_the_per_frame_bag_matches_offline_mapping(tmp_path):
    from sensor_msgs.msg import PointCloud2

    from monovoc_interfaces.msg import SemanticObjectArray

    bag = bundled_bag(PER_FRAME_BAG)
    out = tmp_path / "map"
    assert main(["map", "--bag", str(bag), "-o", str(out), "--quiet", "--mask-ids", "per-frame"]) == 0
    mapper = load_snapshot(out)
    expected = mapper.result()
    keyframes = [e for e in bag_events(bag) if isinstance(e, Keyframe)]
    last = keyframes[-1].stamp_ns
    assert len(mapper.associator.issued) >= 15

    env = ros_environment(tmp_path)
    labels = mapper.object_labels()
    assert len(labels) >= 15 and "sofa" in labels.values()  # the bag's segment names reached the objects
    params = {"publish_rate_hz": 0.0, "mask_ids": "per_frame", "use_segments": True, "diagnostics_period_s": 0.2}
    with (
        NodeProcess.python([*NODE, *ros_args(params)], env, name="semantic_mapper") as node,
        ClientNode(env) as client,
    ):
        clouds, objects = MessageCollector(), MessageCollector()
        client.node.create_subscription(PointCloud2, "/monovoc/semantic_cloud", clouds, latched_qos())
        client.node.create_subscription(SemanticObjectArray, "/monovoc/objects", objects, latched_qos())
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        with replay_process(bag, env, "--fast", "--wait-subscribers", "1") as replay:
            finish(replay)
        done = diagnostics.wait_for(lambda v: v["keyframes_processed"] == str(len(keyframes)), 60.0, process=node)
        assert done["keyframes_dropped"] == "0" and done["rejected_total"] == "0"
        wait_until(lambda: any(ma.header_stamp_ns(m) == last for m in clouds.messages), 20.0, "the final cloud",
                   process=node)  # fmt: skip
        wait_until(lambda: objects.messages and ma.header_stamp_ns(objects.messages[-1]) == last, 20.0, "objects")
        cloud = next(m for m in clouds.messages if ma.header_stamp_ns(m) == last)
        final = objects.messages[-1]

    known = expected.object_ids != UNOBSERVED_ID
    got = ma.semantic_cloud_to_arrays(cloud)
    np.testing.assert_array_equal(got.object_ids, expected.object_ids[known])
    np.testing.assert_allclose(got.confidence, expected.confidence[known])
    ids = sorted(o.id for o in final.objects)
    assert ids == sorted(set(expected.object_ids[known].tolist())) and len(ids) >= 15
    assert set(ids) <= set(mapper.associator.issued)
    assert {o.id: o.label for o in final.objects} == {i: labels.get(i, "") for i in ids}
