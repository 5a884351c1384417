"""The mapping node's outputs on a real rclpy node: a publication sends the markers and SemanticObject messages
of unchanged objects again instead of building them anew, and what a subscriber receives is the same; the
semantic cloud is left out while nothing subscribes to it, and a subscriber that appears asks for it."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from monovoc_ros.core.evidence.palette import UNOBSERVED_ID
from monovoc_ros.core.mapping import SemanticMapper
from monovoc_ros.nodes.outputs import SemanticOutputs
from monovoc_ros.nodes.qos import latched_qos
from monovoc_ros.ros_harness import ClientNode, MessageCollector, wait_until
from tests.node_scene import assemble, scene_messages, small_scene
from tests.rosutil import ros_environment


def _geometry(mapper: SemanticMapper) -> dict[int, tuple]:
    return {s.id: (*s.centroid.tolist(), *s.extent.tolist()) for s in mapper.result().objects(mapper.gaussians).objects}


def test_a_publication_builds_messages_only_for_changed_objects(tmp_path: Path) -> None:
    scene = small_scene()
    keyframes = assemble(scene_messages())
    mapper = SemanticMapper(scene.gaussians)
    for kf in keyframes[:4]:
        mapper.integrate(kf)
    with ClientNode(ros_environment(tmp_path)) as client:
        outputs = SemanticOutputs(client.node, frame_id="map", labels={}, up=(0.0, 0.0, 1.0))
        n = outputs.publish(mapper, mapper.result())
        assert n > 3 and outputs.marker_cache.built == n and outputs.object_cache.built == n
        outputs.publish(mapper, mapper.result())  # nothing changed: nothing built
        assert outputs.marker_cache.built == n and outputs.object_cache.built == n

        before = _geometry(mapper)
        mapper.integrate(keyframes[4])
        after = _geometry(mapper)
        moved = sum(1 for oid, values in after.items() if before.get(oid) != values)
        assert 0 < moved < len(after)  # the keyframe changed some objects, not all
        outputs.publish(mapper, mapper.result())
        assert outputs.marker_cache.built == n + moved
        # A SemanticObject also carries the object's observation count: rebuilt for every object seen again.
        assert n + moved <= outputs.object_cache.built <= n + len(after)

        # The messages sent equal messages built afresh.
        fresh = SemanticOutputs(client.node, frame_id="map", labels={}, up=(0.0, 0.0, 1.0))
        header = {"frame_id": "map", "stamp": 7}
        result = mapper.result()
        summaries = list(result.objects(mapper.gaussians).objects)
        seen = np.ones(len(summaries), np.int64)
        labels = [None] * len(summaries)
        assert outputs._objects(summaries, seen, header, labels) == fresh._objects(summaries, seen, header, labels)


def test_the_cloud_waits_for_a_subscriber_which_then_asks_for_it(tmp_path: Path) -> None:
    from sensor_msgs.msg import PointCloud2

    from monovoc_interfaces.msg import SemanticObjectArray

    scene = small_scene()
    mapper = SemanticMapper(scene.gaussians)
    for kf in assemble(scene_messages())[:4]:
        mapper.integrate(kf)
    env = ros_environment(tmp_path)
    asked = threading.Event()
    with ClientNode(env) as host, ClientNode(env, name="viewer") as viewer:
        outputs = SemanticOutputs(
            host.node, frame_id="map", labels={}, up=(0.0, 0.0, 1.0), on_cloud_subscriber=asked.set
        )
        objects = MessageCollector()
        viewer.node.create_subscription(SemanticObjectArray, "objects", objects, latched_qos())
        wait_until(lambda: outputs.objects.get_subscription_count() == 1, 20.0, "the objects' subscriber")
        assert outputs.publish(None, None) == 0 and outputs.clouds_skipped == 1  # no map yet: no empty cloud either
        n = outputs.publish(mapper, mapper.result())
        assert n > 3 and outputs.clouds_skipped == 2  # nobody subscribes to the cloud: left out
        # The objects still go out (the empty ones of no map first, then these).
        wait_until(lambda: objects.messages and len(objects.messages[-1].objects) == n, 10.0, "the objects")
        assert not asked.is_set()

        clouds = MessageCollector()
        viewer.node.create_subscription(PointCloud2, "semantic_cloud", clouds, latched_qos())
        wait_until(asked.is_set, 20.0, "the cloud's subscriber to ask for the cloud")
        assert not clouds.messages  # none was ever sent
        outputs.publish(mapper, mapper.result())  # what the node's worker does when asked
        observed = int((mapper.result().object_ids != UNOBSERVED_ID).sum())
        # The first cloud the late subscriber gets is the current one: nothing older was latched.
        assert clouds.wait_for(1, 10.0)[0].width == observed > 0
        assert outputs.clouds_skipped == 2
