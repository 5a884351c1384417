"""Conversions between ROS 2 messages and NumPy / monovoc_ros core types.

Readers use attribute access only, so they accept rclpy messages and messages decoded from bags
(mcap_ros2's dynamic classes, rosbags' dataclasses). Writers build rclpy message classes (imported
lazily, so readers work without a ROS environment). Every conversion raises ``AdapterError`` (a
``ValueError``) naming the problem. Frame conventions and field schemas: docs/interfaces.md.
"""

from msg_adapters import buffers, compressed_image
from msg_adapters.camera_info import camera_info_to_intrinsics, has_distortion, intrinsics_to_camera_info
from msg_adapters.colors import rgb_to_packed
from msg_adapters.compressed_image import compressed_image_header, compressed_image_to_numpy, numpy_to_compressed_image
from msg_adapters.errors import AdapterError
from msg_adapters.gaussian_cloud import cloud_to_gaussian_map, gaussian_map_from_cdr, gaussian_map_to_cloud
from msg_adapters.image import image_to_numpy, numpy_to_image
from msg_adapters.markers import object_markers
from msg_adapters.message_cache import MessageCache
from msg_adapters.point_cloud import POINT_CLOUD_TYPE, point_cloud_from_cdr, prepare_point_cloud_decoder
from msg_adapters.pose import (
    R_BODY_OPTICAL,
    keyframe_poses_to_path,
    matrix_to_pose_stamped,
    matrix_to_transform_stamped,
    odometry_to_matrix,
    path_to_keyframe_poses,
    pose_stamped_to_matrix,
    pose_to_matrix,
    transform_stamped_to_matrix,
)
from msg_adapters.segments import segment_array, segment_array_to_labels
from msg_adapters.semantic_cloud import (
    SemanticCloud,
    semantic_cloud_from_arrays,
    semantic_cloud_to_arrays,
    serialized_semantic_cloud,
)
from msg_adapters.semantic_objects import semantic_object, semantic_object_to_dict
from msg_adapters.stamps import header_stamp_ns, make_header, ns_to_time, time_to_ns

__all__ = [
    "MessageCache",
    "keyframe_poses_to_path",
    "path_to_keyframe_poses",
    "R_BODY_OPTICAL",
    "AdapterError",
    "SemanticCloud",
    "camera_info_to_intrinsics",
    "cloud_to_gaussian_map",
    "buffers",
    "compressed_image",
    "compressed_image_header",
    "compressed_image_to_numpy",
    "gaussian_map_from_cdr",
    "gaussian_map_to_cloud",
    "has_distortion",
    "header_stamp_ns",
    "image_to_numpy",
    "intrinsics_to_camera_info",
    "make_header",
    "matrix_to_pose_stamped",
    "matrix_to_transform_stamped",
    "ns_to_time",
    "numpy_to_compressed_image",
    "numpy_to_image",
    "object_markers",
    "odometry_to_matrix",
    "POINT_CLOUD_TYPE",
    "point_cloud_from_cdr",
    "prepare_point_cloud_decoder",
    "pose_stamped_to_matrix",
    "pose_to_matrix",
    "rgb_to_packed",
    "segment_array",
    "segment_array_to_labels",
    "semantic_cloud_from_arrays",
    "serialized_semantic_cloud",
    "semantic_cloud_to_arrays",
    "semantic_object",
    "semantic_object_to_dict",
    "time_to_ns",
    "transform_stamped_to_matrix",
]
