"""The semantic_mapper's outputs: semantic cloud, object markers and SemanticObjectArray (worker thread).

Everything published is derived from one `SemanticResult`, so cloud, markers and objects always agree; the
objects and markers report the result's one object geometry (`SemanticResult.objects`), as do the query
answers and objects.db.
Labels follow core.segments.object_labels: labels_file, then the segmenter's class names, then what a label
provider knows (the object-query component: names restored from objects.db and the embedding model's
guesses, which exist only once objects are embedded). When those change, `republish_objects` sends the
objects and markers of the last result again with the new labels (on the worker thread, like `publish`).
The cloud holds observed Gaussians only (those with evidence and a palette label): unobserved ones have
no label to show, and leaving them out keeps the message small early in a run. Its header stamp is the
stamp of the newest integrated keyframe, so clients can tell which keyframes a cloud includes.

A publication leaves the cloud out while nothing subscribes to it (counted as `clouds_skipped`): at robot scale
it is the largest message (24 bytes a Gaussian: 24 MB at 1M), and building and serializing it took the worker
~16 ms at 1M and ~110 ms at 2M Gaussians with nobody to receive it. When a subscriber appears (the publisher's
matched event, on the executor's thread) and a cloud was left out, `on_cloud_subscriber` asks the worker for a
publication (nodes/subscribed_output.py), so a viewer that starts late still gets the current cloud, as the
transient-local QoS promises. The cloud is sent as CDR bytes without holding the interpreter
(nodes/serialized_publisher.py): a publish preempted on saturated cores no longer stalls the query service.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

import msg_adapters as ma
from monovoc_ros.core.evidence.palette import UNOBSERVED_ID
from monovoc_ros.core.mapping import SemanticMapper, SemanticResult
from monovoc_ros.core.object_geometry import ObjectSummary
from monovoc_ros.core.segments.object_labels import ObjectLabel, display, label_fields, resolve
from monovoc_ros.nodes.qos import latched_qos, output_events
from monovoc_ros.nodes.serialized_publisher import SerializedPublisher
from monovoc_ros.nodes.subscribed_output import SubscribedOutput

# fn() -> object id -> label, consulted after labels_file and segment labels (called on the worker thread).
LabelProvider = Callable[[], Mapping[int, ObjectLabel]]


class SemanticOutputs:
    """Publishers of `semantic_cloud`, `objects/markers` and `objects` (all reliable + transient-local)."""

    def __init__(
        self,
        node: Any,
        *,
        frame_id: str,
        labels: dict[int, str],
        up: tuple[float, float, float],
        on_cloud_subscriber: Callable[[], None] | None = None,
    ):
        """`on_cloud_subscriber()`: called (executor thread) when a cloud was left out and a subscriber appears;
        it should have `publish` called again soon (the node queues a publication on its worker)."""
        from sensor_msgs.msg import PointCloud2
        from visualization_msgs.msg import MarkerArray

        from monovoc_interfaces.msg import SemanticObjectArray

        self._node = node
        self.frame_id = frame_id
        self.labels = labels
        self.up = up
        self._cloud_output = SubscribedOutput(None if on_cloud_subscriber is None else lambda _: on_cloud_subscriber())
        self.cloud = node.create_publisher(
            PointCloud2, "semantic_cloud", latched_qos(), event_callbacks=self._cloud_output.events()
        )
        self._cloud_output.publisher = self.cloud
        self._cloud_bytes = SerializedPublisher(self.cloud)
        self.markers = node.create_publisher(
            MarkerArray, "objects/markers", latched_qos(), event_callbacks=output_events()
        )
        self.objects = node.create_publisher(
            SemanticObjectArray, "objects", latched_qos(), event_callbacks=output_events()
        )
        self._label_provider: LabelProvider | None = None
        # (summaries, observations, header, segment labels) of the last publication, for republish_objects.
        self._last: tuple[list[ObjectSummary], np.ndarray, dict, Mapping[int, str]] | None = None
        # The messages of objects unchanged since the last publication are sent again, not rebuilt.
        self.marker_cache: ma.MessageCache = ma.MessageCache()
        self.object_cache: ma.MessageCache = ma.MessageCache()

    def set_label_provider(self, fn: LabelProvider | None) -> None:
        """Labels of a component (see the module docstring); set before the worker starts."""
        self._label_provider = fn

    def republish_objects(self) -> int:
        """The objects and markers of the last publication again, with the labels known now (worker
        thread); returns the number of objects."""
        return 0 if self._last is None else self._publish_objects(*self._last)

    def publish(self, mapper: SemanticMapper | None, result: SemanticResult | None) -> int:
        """Publishes the cloud, then the objects and markers; returns the number of objects. The cloud goes
        first: the object geometry (main clusters, percentile boxes: ~58 ms at 140k Gaussians) is not on the
        path from a keyframe to the cloud that includes it."""
        now = self._node.get_clock().now().nanoseconds
        if mapper is None or result is None:
            header = dict(frame_id=self.frame_id, stamp=now)
            # Only for a subscriber, as any cloud: an empty one sent at start stayed the latched sample that a viewer
            # starting minutes later got first (`ros2 topic echo --once` printed an empty cloud).
            if self._cloud_output.wanted():
                empty = (
                    np.zeros((0, 3), np.float32),
                    np.zeros((0, 3), np.uint8),
                    np.zeros(0, np.uint32),
                    np.zeros(0, np.float32),
                )
                self._cloud_bytes.publish(ma.serialized_semantic_cloud(*empty, **header))
            self._last = ([], np.zeros(0, np.int64), header, {})
            return self._publish_objects(*self._last)
        header = dict(frame_id=self.frame_id, stamp=int(mapper.state.stamps_ns.max()) if mapper.n_keyframes else now)
        if self._cloud_output.wanted():
            known = np.flatnonzero(result.object_ids != UNOBSERVED_ID)
            ids = result.object_ids[known]
            # An object's id is its packed palette color: the cloud's packed rgb (result.object_rgb, unpacked).
            means, confidence = mapper.gaussians.means[known], result.confidence[known]
            self._cloud_bytes.publish(ma.serialized_semantic_cloud(means, ids, ids, confidence, **header))
        geometry = result.objects(mapper.gaussians)
        index = result.palette.index_of(geometry.ids)
        observations = np.where(index >= 0, result.palette.mask_counts[np.maximum(index, 0)], 0)
        self._last = (list(geometry.objects), observations, header, mapper.object_labels())
        return self._publish_objects(*self._last)

    @property
    def clouds_skipped(self) -> int:
        """Publications that left the cloud out: nothing subscribed to it."""
        return self._cloud_output.skipped

    def _known_labels(self) -> Mapping[int, ObjectLabel]:
        if self._label_provider is None:
            return {}
        try:
            return self._label_provider()
        except Exception as exc:  # a component's failure must not stop the map's own outputs
            self._node.get_logger().error(f"label provider failed: {type(exc).__name__}: {exc}")
            return {}

    def _publish_objects(
        self, summaries: list[ObjectSummary], observations: np.ndarray, header: dict, segments: Mapping[int, str]
    ) -> int:
        known = self._known_labels()
        labels = [resolve(s.id, self.labels, segments, known) for s in summaries]
        self.objects.publish(self._objects(summaries, observations, header, labels))
        self.markers.publish(
            ma.object_markers(
                np.array([s.id for s in summaries], np.int64),
                [display(label) for label in labels],
                np.array([s.centroid for s in summaries]).reshape(-1, 3),
                np.array([s.extent for s in summaries]).reshape(-1, 3),
                np.array([s.rgb for s in summaries], np.uint8).reshape(-1, 3),
                up=self.up,
                cache=self.marker_cache,
                **header,
            )
        )
        return len(summaries)

    def _objects(
        self, summaries: list[ObjectSummary], observations: np.ndarray, header: dict, labels: list[ObjectLabel | None]
    ) -> Any:
        from monovoc_interfaces.msg import SemanticObjectArray

        out = SemanticObjectArray(header=ma.make_header(header["frame_id"], header["stamp"]))
        self.object_cache.start()
        for s, seen, label in zip(summaries, observations.tolist(), labels, strict=True):
            name, source = label_fields(label)
            values = (name, source, s.num_gaussians, int(seen), *s.centroid.tolist(), *s.bbox_min.tolist(),
                      *s.bbox_max.tolist())  # fmt: skip

            def build(s=s, name=name, source=source, seen=seen) -> Any:
                return ma.semantic_object(
                    s.id,
                    centroid=s.centroid,
                    bbox_min=s.bbox_min,
                    bbox_max=s.bbox_max,
                    label=name,
                    label_source=source,
                    num_gaussians=s.num_gaussians,
                    num_observations=int(seen),
                )

            out.objects.append(self.object_cache.get(s.id, values, build))
        self.object_cache.finish()
        return out


def semantic_objects(matches: list) -> list:
    """SemanticObject messages of (record, score) pairs, in order."""
    return [
        ma.semantic_object(
            record.id,
            centroid=record.centroid,
            bbox_min=record.bbox_min,
            bbox_max=record.bbox_max,
            label=record.label,
            label_source=record.label_source,
            description=record.description,
            score=score,
            num_gaussians=record.num_gaussians,
            num_observations=record.num_observations,
        )
        for record, score in matches
    ]
