"""Poses: ``geometry_msgs/PoseStamped``, ``TransformStamped``, ``nav_msgs/Odometry`` <-> 4x4.

The 4x4 is camera-to-world (``T_wc``, float64) in the OpenCV optical camera frame, as everywhere in
monovoc_ros. ``frame_convention`` says which frame the message's pose is of:

- ``"optical"``: the camera's optical frame (x right, y down, z forward), as SLAM systems publish
  and as REP-103 ``*_optical_frame`` TFs are. Used as is.
- ``"body"``: a REP-103 body frame (x forward, y left, z up) at the camera, e.g. ``camera_link``.
  Converted by right-multiplying the fixed rotation ``R_BODY_OPTICAL`` (the optical axes expressed in
  the body frame; quaternion wxyz (0.5, -0.5, 0.5, -0.5), i.e. rpy (-pi/2, 0, -pi/2)).

The world frame is the message's ``header.frame_id``; for TransformStamped and Odometry the camera
frame is ``child_frame_id`` (a TransformStamped maps child coordinates into the parent frame).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from monovoc_ros.contract import CAMERA_FRAME, MAP_FRAME
from monovoc_ros.core.follow.keyframe_log import KeyframePoses
from monovoc_ros.core.map.camera import matrix_to_quat_wxyz, quat_wxyz_to_matrix, validate_pose
from msg_adapters.errors import AdapterError
from msg_adapters.stamps import make_header, time_to_ns

R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
_T_BODY_OPTICAL = np.eye(4)
_T_BODY_OPTICAL[:3, :3] = R_BODY_OPTICAL
FRAME_CONVENTIONS = ("optical", "body")
DEFAULT_QUAT_TOLERANCE = 1e-3


def _check_convention(frame_convention: str) -> None:
    if frame_convention not in FRAME_CONVENTIONS:
        raise AdapterError(f"frame_convention must be one of {FRAME_CONVENTIONS}, got {frame_convention!r}")


def _matrix(translation: Any, rotation: Any, what: str, frame_convention: str, quat_tolerance: float) -> np.ndarray:
    _check_convention(frame_convention)
    try:
        t = np.array([translation.x, translation.y, translation.z], dtype=np.float64)
        q = np.array([rotation.w, rotation.x, rotation.y, rotation.z], dtype=np.float64)
    except (AttributeError, TypeError, ValueError) as e:
        raise AdapterError(f"{what}: not a position/orientation ({e})") from None
    if not np.all(np.isfinite(t)):
        raise AdapterError(f"{what}: translation contains NaN or infinite values: {t.tolist()}")
    if not np.all(np.isfinite(q)):
        raise AdapterError(f"{what}: quaternion contains NaN or infinite values: {q.tolist()}")
    norm = float(np.linalg.norm(q))
    if norm == 0.0:
        raise AdapterError(f"{what}: zero quaternion (orientation not set?)")
    if abs(norm - 1.0) > quat_tolerance:
        raise AdapterError(f"{what}: quaternion norm {norm:.6g} differs from 1 by more than {quat_tolerance:g}")
    T = np.eye(4)
    T[:3, :3] = quat_wxyz_to_matrix(q / norm)
    T[:3, 3] = t
    return T @ _T_BODY_OPTICAL if frame_convention == "body" else T


def pose_to_matrix(
    pose: Any, frame_convention: str = "optical", *, quat_tolerance: float = DEFAULT_QUAT_TOLERANCE
) -> np.ndarray:
    """4x4 of a ``geometry_msgs/Pose`` (``position``, ``orientation``)."""
    return _matrix(pose.position, pose.orientation, "Pose", frame_convention, quat_tolerance)


def pose_stamped_to_matrix(
    msg: Any, frame_convention: str = "optical", *, quat_tolerance: float = DEFAULT_QUAT_TOLERANCE
) -> np.ndarray:
    """Camera-to-world 4x4 of a ``geometry_msgs/PoseStamped`` (world = ``header.frame_id``)."""
    return _matrix(msg.pose.position, msg.pose.orientation, "PoseStamped", frame_convention, quat_tolerance)


def transform_stamped_to_matrix(
    msg: Any, frame_convention: str = "optical", *, quat_tolerance: float = DEFAULT_QUAT_TOLERANCE
) -> np.ndarray:
    """Camera-to-world 4x4 of a ``geometry_msgs/TransformStamped`` (parent = world, child = camera)."""
    tf = msg.transform
    return _matrix(tf.translation, tf.rotation, "TransformStamped", frame_convention, quat_tolerance)


def odometry_to_matrix(
    msg: Any, frame_convention: str = "optical", *, quat_tolerance: float = DEFAULT_QUAT_TOLERANCE
) -> np.ndarray:
    """Camera-to-world 4x4 of a ``nav_msgs/Odometry`` pose (world = ``header.frame_id``)."""
    pose = msg.pose.pose
    return _matrix(pose.position, pose.orientation, "Odometry", frame_convention, quat_tolerance)


def _translation_quat(T: np.ndarray, frame_convention: str) -> tuple[np.ndarray, np.ndarray]:
    _check_convention(frame_convention)
    try:
        T = validate_pose(T, what="camera-to-world pose")
    except ValueError as e:
        raise AdapterError(str(e)) from None
    if frame_convention == "body":
        T = T @ _T_BODY_OPTICAL.T
    return T[:3, 3], matrix_to_quat_wxyz(T[:3, :3])


def matrix_to_pose_stamped(
    T: np.ndarray, *, frame_id: str = MAP_FRAME, stamp: Any = 0, frame_convention: str = "optical"
):
    """A ``geometry_msgs.msg.PoseStamped`` of a camera-to-world 4x4 (``frame_convention`` of the output)."""
    from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion

    t, q = _translation_quat(T, frame_convention)
    pose = Pose(
        position=Point(x=float(t[0]), y=float(t[1]), z=float(t[2])),
        orientation=Quaternion(w=float(q[0]), x=float(q[1]), y=float(q[2]), z=float(q[3])),
    )
    return PoseStamped(header=make_header(frame_id, stamp), pose=pose)


def matrix_to_transform_stamped(
    T: np.ndarray,
    *,
    frame_id: str = MAP_FRAME,
    child_frame_id: str = CAMERA_FRAME,
    stamp: Any = 0,
    frame_convention: str = "optical",
):
    """A ``geometry_msgs.msg.TransformStamped`` parent ``frame_id`` <- child ``child_frame_id``."""
    from geometry_msgs.msg import Quaternion, Transform, TransformStamped, Vector3

    t, q = _translation_quat(T, frame_convention)
    tf = Transform(
        translation=Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
        rotation=Quaternion(w=float(q[0]), x=float(q[1]), y=float(q[2]), z=float(q[3])),
    )
    return TransformStamped(header=make_header(frame_id, stamp), child_frame_id=child_frame_id, transform=tf)


def path_to_keyframe_poses(
    msg: Any, frame_convention: str = "optical", *, quat_tolerance: float = DEFAULT_QUAT_TOLERANCE
) -> KeyframePoses:
    """The corrected keyframe poses of a ``nav_msgs/Path`` (each pose stamped with its keyframe's stamp)."""
    poses = []
    for k, stamped in enumerate(msg.poses):
        try:
            T = pose_stamped_to_matrix(stamped, frame_convention, quat_tolerance=quat_tolerance)
        except AdapterError as exc:
            raise AdapterError(f"Path pose {k}: {exc}") from None
        poses.append((time_to_ns(stamped.header.stamp), T))
    return KeyframePoses(tuple(poses))


def keyframe_poses_to_path(poses: KeyframePoses, *, frame_id: str = MAP_FRAME, stamp: Any = 0):
    """A ``nav_msgs.msg.Path`` of corrected keyframe poses (what a SLAM publishes after a loop closure)."""
    from nav_msgs.msg import Path

    return Path(
        header=make_header(frame_id, stamp),
        poses=[matrix_to_pose_stamped(T, frame_id=frame_id, stamp=int(s)) for s, T in poses.poses],
    )
