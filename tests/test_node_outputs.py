"""The mapping node's outputs on a real rclpy node: a publication sends the markers and SemanticObject messages
of unchanged objects again instead of building them anew, and what a subscriber receives is the same."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from monovoc_ros.core.mapping import SemanticMapper
from monovoc_ros.nodes.outputs import SemanticOutputs
from monovoc_ros.ros_harness import ClientNode
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
