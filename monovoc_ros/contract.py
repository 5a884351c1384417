"""The topic contract between bags, replay, offline mapping and the live node (docs/interfaces.md has the
schemas): namespace, roles, frames, metadata keys, and the names under which bad input is counted.

Under a namespace (default ``/monovoc``): ``image`` (CompressedImage jpeg/png or Image rgb8), ``mask``
(lossless palette mask: CompressedImage png or Image rgb8), ``camera_info`` (of the image's resolution,
no distortion), ``pose`` (PoseStamped, camera optical frame to ``map``), optionally ``segments``
(monovoc_interfaces/SegmentArray: the segmenter's class names of the mask's segments) and ``gaussians`` (the Gaussian
map PointCloud2, transient-local). A keyframe's four messages share one header stamp; in bags the MCAP
log time equals the header stamp.
"""

from __future__ import annotations

import importlib

DEFAULT_NAMESPACE = "/monovoc"
CAMERA_FRAME = "camera_optical_frame"
MAP_FRAME = "map"
# Where every node publishes its diagnostics (absolute, as diagnostic_aggregator expects); `monovoc replay --fast`
# reads the mapping node's count of maps taken there (bags/map_gate.py).
DIAGNOSTICS_TOPIC = "/diagnostics"
KEYFRAME_ROLES = ("image", "mask", "camera_info", "pose")
# Optional keyframe input (node parameter use_segments): a segmenter's class names for the mask's segments,
# one SegmentArray per mask with the mask's stamp (empty when it named nothing).
SEGMENTS_ROLE = "segments"
MAP_ROLE = "gaussians"
# Optional input: the SLAM's corrected keyframe trajectory (nav_msgs/Path, each pose stamped with its
# keyframe's stamp); a moved keyframe starts a re-integration of the keyframe log (core.session).
KEYFRAME_POSES_ROLE = "keyframe_poses"
KEYFRAME_POSES_TYPE = "nav_msgs/msg/Path"
ROLES = (*KEYFRAME_ROLES, SEGMENTS_ROLE, MAP_ROLE, KEYFRAME_POSES_ROLE)
# Message types ("package/msg/Type"): the image and the mask in either transport (node parameters
# image_transport / mask_transport), the pose in one of three forms (pose_type).
IMAGE_MESSAGE_TYPES = {"compressed": "sensor_msgs/msg/CompressedImage", "raw": "sensor_msgs/msg/Image"}
POSE_MESSAGE_TYPES = {
    "pose": "geometry_msgs/msg/PoseStamped",
    "odometry": "nav_msgs/msg/Odometry",
    "transform": "geometry_msgs/msg/TransformStamped",
}
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
SEGMENTS_TYPE = "monovoc_interfaces/msg/SegmentArray"
MAP_TYPE = "sensor_msgs/msg/PointCloud2"
# Why a message did not become part of a keyframe, as counted in diagnostics and offline reports.
BAD_MESSAGE = {
    "image": "bad_image",
    "mask": "bad_mask",
    "camera_info": "bad_camera_info",
    "pose": "bad_pose",
    SEGMENTS_ROLE: "bad_segments",
    KEYFRAME_POSES_ROLE: "bad_keyframe_poses",
}
REJECTION_REASONS = (
    *BAD_MESSAGE.values(),
    "size_mismatch",
    "void_mask",
    "stamp_out_of_order",
    "duplicate_stamp",
    "stamp_future",
)
LABELS_METADATA = "monovoc_labels"  # JSON list of {color: [r, g, b], class_name, ...} (Sequence.labels())
SOURCE_METADATA = "monovoc_source"  # JSON: where the bag came from, formats, time offset
MAP_LEAD_NS = 1_000_000  # a map message is logged 1 ms before the keyframe it precedes


def keyframe_types(
    image: str = "compressed", mask: str = "compressed", pose: str = "pose", *, segments: bool = False
) -> dict[str, str]:
    """Role -> message type of the keyframe inputs, for the given image / mask transports and pose type (and
    the optional segments input)."""
    types = {
        "image": IMAGE_MESSAGE_TYPES[image],
        "mask": IMAGE_MESSAGE_TYPES[mask],
        "camera_info": CAMERA_INFO_TYPE,
        "pose": POSE_MESSAGE_TYPES[pose],
    }
    if segments:
        types[SEGMENTS_ROLE] = SEGMENTS_TYPE
    return types


def message_class(type_name: str) -> type:
    """The rclpy class of a ``package/msg/Type`` name."""
    package, _, name = type_name.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), name)


def topic_names(namespace: str = DEFAULT_NAMESPACE) -> dict[str, str]:
    """Role -> topic, e.g. ``{"image": "/monovoc/image", ..., "gaussians": "/monovoc/gaussians"}``."""
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return {role: f"{ns}/{role}" for role in ROLES}
