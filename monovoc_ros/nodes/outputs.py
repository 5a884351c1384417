"""The semantic_mapper's outputs: semantic cloud, object markers and SemanticObjectArray (worker thread).

Everything published is derived from one `SemanticResult`, so cloud, markers and objects always agree; the
objects and markers report the result's one object geometry (`SemanticResult.objects`), as do the query
answers and objects.db.
The cloud holds observed Gaussians only (those with evidence and a palette label): unobserved ones have
no label to show, and leaving them out keeps the message small early in a run. Its header stamp is the
stamp of the newest integrated keyframe, so clients can tell which keyframes a cloud includes.
"""

from __future__ import annotations

from typing import Any

import numpy as np

import msg_adapters as ma
from monovoc_ros.core.mapping import SemanticMapper, SemanticResult
from monovoc_ros.core.objects import ObjectSummary
from monovoc_ros.core.palette import UNOBSERVED_ID
from monovoc_ros.nodes.qos import latched_qos


class SemanticOutputs:
    """Publishers of `semantic_cloud`, `objects/markers` and `objects` (all reliable + transient-local)."""

    def __init__(self, node: Any, *, frame_id: str, labels: dict[int, str], up: tuple[float, float, float]):
        from sensor_msgs.msg import PointCloud2
        from visualization_msgs.msg import MarkerArray

        from monovoc_interfaces.msg import SemanticObjectArray

        self._node = node
        self.frame_id = frame_id
        self.labels = labels
        self.up = up
        self.cloud = node.create_publisher(PointCloud2, "semantic_cloud", latched_qos())
        self.markers = node.create_publisher(MarkerArray, "objects/markers", latched_qos())
        self.objects = node.create_publisher(SemanticObjectArray, "objects", latched_qos())

    def publish(self, mapper: SemanticMapper | None, result: SemanticResult | None) -> int:
        """Publishes the cloud, then the objects and markers; returns the number of objects. The cloud goes
        first: the object geometry (main clusters, percentile boxes: ~58 ms at 140k Gaussians) is not on the
        path from a keyframe to the cloud that includes it."""
        now = self._node.get_clock().now().nanoseconds
        if mapper is None or result is None:
            header = dict(frame_id=self.frame_id, stamp=now)
            empty = (
                np.zeros((0, 3), np.float32),
                np.zeros((0, 3), np.uint8),
                np.zeros(0, np.uint32),
                np.zeros(0, np.float32),
            )
            self.cloud.publish(ma.semantic_cloud_from_arrays(*empty, **header))
            return self._publish_objects([], np.zeros(0, np.int64), header, self.labels)
        known = result.object_ids != UNOBSERVED_ID
        header = dict(frame_id=self.frame_id, stamp=int(mapper.state.stamps_ns.max()) if mapper.n_keyframes else now)
        self.cloud.publish(
            ma.semantic_cloud_from_arrays(
                mapper.gaussians.means[known],
                result.object_rgb()[known],
                result.object_ids[known],
                result.confidence[known],
                **header,
            )
        )
        labels = {**mapper.object_labels(), **self.labels}  # labels_file first, then segment labels
        geometry = result.objects(mapper.gaussians)
        index = result.palette.index_of(geometry.ids)
        observations = np.where(index >= 0, result.palette.mask_counts[np.maximum(index, 0)], 0)
        return self._publish_objects(list(geometry.objects), observations, header, labels)

    def _publish_objects(
        self, summaries: list[ObjectSummary], observations: np.ndarray, header: dict, labels: dict[int, str]
    ) -> int:
        self.objects.publish(self._objects(summaries, observations, header, labels))
        self.markers.publish(
            ma.object_markers(
                np.array([s.id for s in summaries], np.int64),
                [labels.get(s.id, "") for s in summaries],
                np.array([s.centroid for s in summaries]).reshape(-1, 3),
                np.array([s.extent for s in summaries]).reshape(-1, 3),
                np.array([s.rgb for s in summaries], np.uint8).reshape(-1, 3),
                up=self.up,
                **header,
            )
        )
        return len(summaries)

    def _objects(
        self, summaries: list[ObjectSummary], observations: np.ndarray, header: dict, labels: dict[int, str]
    ) -> Any:
        from monovoc_interfaces.msg import SemanticObjectArray

        out = SemanticObjectArray(header=ma.make_header(header["frame_id"], header["stamp"]))
        for s, seen in zip(summaries, observations.tolist(), strict=True):
            out.objects.append(
                ma.semantic_object(
                    s.id,
                    centroid=s.centroid,
                    bbox_min=s.bbox_min,
                    bbox_max=s.bbox_max,
                    label=labels.get(s.id, ""),
                    num_gaussians=s.num_gaussians,
                    num_observations=int(seen),
                )
            )
        return out
