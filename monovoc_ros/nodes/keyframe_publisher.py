"""Publishes keyframes and Gaussian maps on the semantic_mapper's topic contract (tests, benchmarks, simulators).

The contract (docs/interfaces.md; the bags of monovoc_ros.bags use it too): in one namespace, `image`
(CompressedImage jpeg), `mask` (CompressedImage png: lossless), `camera_info`, `pose` (PoseStamped, optical
frame) sharing one header stamp per keyframe, and `gaussians` (PointCloud2, reliable + transient-local).
`keyframe_messages` builds the four messages of a keyframe without ROS publishing, so a test can feed the
very same message objects to an offline KeyframeAssembler and to the live node.
"""

from __future__ import annotations

from typing import Any

import msg_adapters as ma
from monovoc_ros.contract import (
    CAMERA_FRAME,
    DEFAULT_NAMESPACE,
    MAP_FRAME,
    MAP_ROLE,
    MAP_TYPE,
    SEGMENTS_ROLE,
    keyframe_types,
    message_class,
)
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.nodes.qos import input_qos, latched_qos

ROLE_ORDER = ("pose", "camera_info", "image", SEGMENTS_ROLE, "mask")  # the mask (the synchronizer's pivot) last


def keyframe_messages(
    keyframe: Keyframe,
    *,
    stamp_ns: int | None = None,
    frame_id: str = MAP_FRAME,
    camera_frame: str = CAMERA_FRAME,
    image_format: str = "jpeg",
) -> dict[str, Any]:
    """role -> message for one keyframe (mask as PNG; camera_info for the mask's resolution unless the RGB
    image is larger, in which case for the RGB's, as a camera driver would publish it)."""
    stamp = keyframe.stamp_ns if stamp_ns is None else stamp_ns
    intrinsics = keyframe.intrinsics
    if keyframe.rgb is not None and keyframe.rgb.shape[:2] != keyframe.mask.shape[:2]:
        intrinsics = intrinsics.scaled_to(keyframe.rgb.shape[1], keyframe.rgb.shape[0])
    msgs = {
        "pose": ma.matrix_to_pose_stamped(keyframe.cam_to_world, frame_id=frame_id, stamp=stamp),
        "camera_info": ma.intrinsics_to_camera_info(intrinsics, frame_id=camera_frame, stamp=stamp),
        "mask": ma.numpy_to_compressed_image(keyframe.mask, "png", frame_id=camera_frame, stamp=stamp),
    }
    if keyframe.rgb is not None:
        msgs["image"] = ma.numpy_to_compressed_image(keyframe.rgb, image_format, frame_id=camera_frame, stamp=stamp)
    if keyframe.segments is not None:
        msgs[SEGMENTS_ROLE] = ma.segment_array(keyframe.segments, frame_id=camera_frame, stamp=stamp)
    return msgs


class KeyframePublisher:
    """Publishers for the node's inputs, created on `node` (any rclpy node, e.g. a test's client node)."""

    def __init__(
        self, node: Any, namespace: str = DEFAULT_NAMESPACE, *, depth: int = 1000, segments: bool = False
    ) -> None:
        ns = namespace.rstrip("/")
        # Deep writer history: a reliable writer drops unacknowledged samples beyond its depth.
        qos = input_qos(depth)
        self.publishers = {
            role: node.create_publisher(message_class(t), f"{ns}/{role}", qos)
            for role, t in keyframe_types(segments=segments).items()
        }
        self.gaussians = node.create_publisher(message_class(MAP_TYPE), f"{ns}/{MAP_ROLE}", latched_qos())

    def all_publishers(self) -> list[Any]:
        return [*self.publishers.values(), self.gaussians]

    def publish_messages(self, msgs: dict[str, Any], order: tuple[str, ...] = ROLE_ORDER) -> None:
        """Publishes the messages of one keyframe; a segments message needs ``segments=True``."""
        unknown = set(msgs) - set(self.publishers)
        if unknown:
            raise ValueError(f"no publisher for {sorted(unknown)} (KeyframePublisher(..., segments=True)?)")
        for role in order:
            if role in msgs:
                self.publishers[role].publish(msgs[role])

    def publish_map(self, gaussians: GaussianMap, *, stamp_ns: int | None = None, frame_id: str = MAP_FRAME) -> Any:
        """Publishes `gaussians` stamped `stamp_ns` (None: the map's own stamp)."""
        msg = ma.gaussian_map_to_cloud(gaussians, frame_id=frame_id, stamp=stamp_ns)
        self.gaussians.publish(msg)
        return msg
