"""CameraInfo <-> Intrinsics, poses <-> 4x4, Time <-> nanoseconds."""

from __future__ import annotations

import numpy as np
import pytest
import rclpy.time
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CameraInfo

from monovoc_ros.core.map.camera import Intrinsics, matrix_to_quat_wxyz, quat_wxyz_to_matrix
from msg_adapters import (
    R_BODY_OPTICAL,
    AdapterError,
    camera_info_to_intrinsics,
    has_distortion,
    header_stamp_ns,
    intrinsics_to_camera_info,
    make_header,
    matrix_to_pose_stamped,
    matrix_to_transform_stamped,
    ns_to_time,
    odometry_to_matrix,
    pose_stamped_to_matrix,
    time_to_ns,
    transform_stamped_to_matrix,
)

CAM = Intrinsics(fx=525.0, fy=520.0, cx=319.5, cy=239.5, width=640, height=480)


def _wire(msg):
    return deserialize_message(serialize_message(msg), type(msg))


def _project(intr: Intrinsics, p: np.ndarray) -> np.ndarray:
    return (intr.K @ p)[:2] / p[2]


def _random_pose(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    T = np.eye(4)
    T[:3, :3] = quat_wxyz_to_matrix(q / np.linalg.norm(q))
    T[:3, 3] = rng.uniform(-5, 5, 3)
    return T


def test_camera_info_round_trip_and_rescale() -> None:
    msg = _wire(intrinsics_to_camera_info(CAM, frame_id="cam_optical", stamp=77))
    assert msg.header.frame_id == "cam_optical" and msg.distortion_model == "plumb_bob"
    assert not has_distortion(msg)
    assert camera_info_to_intrinsics(msg) == CAM
    assert camera_info_to_intrinsics(msg, 640, 480) == CAM
    half = camera_info_to_intrinsics(msg, 320, 240)
    assert half == CAM.scaled_to(320, 240)
    assert half.fx == pytest.approx(262.5) and half.cx == pytest.approx(159.5)  # centre stays the centre


def test_distortion_is_rejected_unless_rectified_or_allowed() -> None:
    msg = intrinsics_to_camera_info(CAM)
    msg.d = [0.1, -0.05, 0.0, 0.0, 0.01]
    P = np.zeros((3, 4))
    P[:, :3] = [[500.0, 0, 310.0], [0, 500.0, 245.0], [0, 0, 1]]
    msg.p = P.reshape(-1).tolist()
    assert has_distortion(msg)
    with pytest.raises(AdapterError, match=r"non-zero distortion \(plumb_bob"):
        camera_info_to_intrinsics(msg)
    assert camera_info_to_intrinsics(msg, allow_distortion=True) == CAM  # K, distortion ignored
    rect = camera_info_to_intrinsics(msg, rectified=True)  # image_rect: P's pinhole
    assert (rect.fx, rect.fy, rect.cx, rect.cy) == (500.0, 500.0, 310.0, 245.0)


def test_roi_and_binning_describe_the_published_image() -> None:
    p = np.array([0.4, -0.3, 2.0])
    full_uv = _project(CAM, p)

    roi = intrinsics_to_camera_info(CAM)
    roi.roi.x_offset, roi.roi.y_offset, roi.roi.width, roi.roi.height = 100, 50, 320, 240
    crop = camera_info_to_intrinsics(roi)
    assert (crop.width, crop.height) == (320, 240)
    np.testing.assert_allclose(_project(crop, p), full_uv - [100, 50])

    binned = intrinsics_to_camera_info(CAM)
    binned.binning_x, binned.binning_y = 2, 4
    b = camera_info_to_intrinsics(binned)
    assert (b.width, b.height) == (320, 120)
    # Binned pixel i covers sensor pixels [i*b, (i+1)*b): centres map as (u + 0.5) / b - 0.5.
    np.testing.assert_allclose(_project(b, p), (full_uv + 0.5) / [2, 4] - 0.5)

    both = intrinsics_to_camera_info(CAM)
    both.roi.x_offset, both.roi.y_offset, both.roi.width, both.roi.height = 100, 50, 320, 240
    both.binning_x = both.binning_y = 2
    bb = camera_info_to_intrinsics(both, 80, 60)  # and rescaled to a mask resolution
    expected = ((full_uv - [100, 50] + 0.5) / 2 - 0.5 + 0.5) / 2 - 0.5
    np.testing.assert_allclose(_project(bb, p), expected)


def test_camera_info_rejects_bad_input() -> None:
    with pytest.raises(AdapterError, match="uncalibrated"):
        camera_info_to_intrinsics(CameraInfo(width=640, height=480))
    nan = intrinsics_to_camera_info(CAM)
    nan.k[0] = float("nan")
    with pytest.raises(AdapterError, match="NaN"):
        camera_info_to_intrinsics(nan)
    with pytest.raises(AdapterError, match="invalid image size 0x480"):
        camera_info_to_intrinsics(intrinsics_to_camera_info(CAM).__class__(k=CAM.K.reshape(-1).tolist(), height=480))
    roi = intrinsics_to_camera_info(CAM)
    roi.roi.x_offset, roi.roi.width, roi.roi.height = 400, 320, 240
    with pytest.raises(AdapterError, match="exceeds the 640x480 sensor"):
        camera_info_to_intrinsics(roi)
    binning = intrinsics_to_camera_info(CAM)
    binning.binning_x = 3
    with pytest.raises(AdapterError, match="not divisible by binning 3x1"):
        camera_info_to_intrinsics(binning)
    with pytest.raises(AdapterError, match="both width and height"):
        camera_info_to_intrinsics(intrinsics_to_camera_info(CAM), 320)
    skew = intrinsics_to_camera_info(CAM)
    skew.k[1] = 3.0
    with pytest.raises(AdapterError, match="not a pinhole matrix"):
        camera_info_to_intrinsics(skew)


@pytest.mark.parametrize("seed", range(3))
def test_pose_messages_round_trip(seed: int) -> None:
    T = _random_pose(np.random.default_rng(seed))
    ps = _wire(matrix_to_pose_stamped(T, frame_id="map", stamp=12_000_000_001))
    assert ps.header.frame_id == "map" and header_stamp_ns(ps) == 12_000_000_001
    np.testing.assert_allclose(pose_stamped_to_matrix(ps), T, atol=1e-12)

    ts = _wire(matrix_to_transform_stamped(T, frame_id="odom", child_frame_id="cam_optical", stamp=3))
    assert (ts.header.frame_id, ts.child_frame_id) == ("odom", "cam_optical")
    np.testing.assert_allclose(transform_stamped_to_matrix(ts), T, atol=1e-12)

    odom = Odometry(header=make_header("map", 9), child_frame_id="cam_optical")
    odom.pose.pose = ps.pose
    np.testing.assert_allclose(odometry_to_matrix(_wire(odom)), T, atol=1e-12)


def test_body_frame_convention() -> None:
    np.testing.assert_allclose(matrix_to_quat_wxyz(R_BODY_OPTICAL), [0.5, -0.5, 0.5, -0.5])
    # A camera_link (x forward, y left, z up) at the world origin, aligned with a z-up world.
    msg = PoseStamped(header=make_header("map"))
    msg.pose.orientation.w = 1.0
    T = pose_stamped_to_matrix(msg, "body")
    np.testing.assert_allclose(T[:3, 2], [1, 0, 0], atol=1e-15)  # optical z (forward) = body x
    np.testing.assert_allclose(T[:3, 0], [0, -1, 0], atol=1e-15)  # optical x (right) = -body y
    np.testing.assert_allclose(T[:3, 1], [0, 0, -1], atol=1e-15)  # optical y (down) = -body z
    np.testing.assert_allclose(pose_stamped_to_matrix(msg, "optical"), np.eye(4))
    # Writing in the body convention and reading it back gives the same optical pose.
    T = _random_pose(np.random.default_rng(5))
    body_msg = matrix_to_pose_stamped(T, frame_convention="body")
    np.testing.assert_allclose(pose_stamped_to_matrix(body_msg, "body"), T, atol=1e-12)
    tf = matrix_to_transform_stamped(T, frame_convention="body")
    np.testing.assert_allclose(transform_stamped_to_matrix(tf, "body"), T, atol=1e-12)
    assert not np.allclose(pose_stamped_to_matrix(body_msg, "optical"), T)


def test_quaternions_close_to_unit_are_normalized() -> None:
    msg = PoseStamped()
    msg.pose.orientation.w, msg.pose.orientation.z = 0.6 * 1.0005, 0.8 * 1.0005
    R = pose_stamped_to_matrix(msg)[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    msg.pose.orientation.w, msg.pose.orientation.z = 0.6 * 1.02, 0.8 * 1.02
    with pytest.raises(AdapterError, match="quaternion norm 1.02 differs from 1"):
        pose_stamped_to_matrix(msg)
    R = pose_stamped_to_matrix(msg, quat_tolerance=0.05)[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)


def test_poses_reject_bad_input() -> None:
    msg = PoseStamped()
    msg.pose.orientation.w = 0.0  # Jazzy's Quaternion defaults to w = 1
    with pytest.raises(AdapterError, match="zero quaternion"):
        pose_stamped_to_matrix(msg)
    msg.pose.orientation.w = 1.0
    msg.pose.position.y = float("nan")
    with pytest.raises(AdapterError, match="PoseStamped: translation contains NaN"):
        pose_stamped_to_matrix(msg)
    tf = TransformStamped()
    tf.transform.rotation.w = float("inf")
    with pytest.raises(AdapterError, match="TransformStamped: quaternion contains NaN or infinite"):
        transform_stamped_to_matrix(tf)
    odom = Odometry()
    odom.pose.pose.orientation.w, odom.pose.pose.orientation.x = 0.0, 0.5
    with pytest.raises(AdapterError, match="Odometry: quaternion norm 0.5"):
        odometry_to_matrix(odom)
    msg.pose.position.y = 0.0
    with pytest.raises(AdapterError, match="frame_convention must be one of"):
        pose_stamped_to_matrix(msg, "ned")
    skewed = np.eye(4)
    skewed[0, 1] = 0.3
    with pytest.raises(AdapterError, match="not orthonormal"):
        matrix_to_pose_stamped(skewed)
    with pytest.raises(AdapterError, match="NaN"):
        matrix_to_transform_stamped(np.full((4, 4), np.nan))


def test_time_conversions() -> None:
    for ns in (0, 1, 999_999_999, 1_700_000_000_123_456_789, -1, -1_500_000_000):
        t = _wire(ns_to_time(ns))
        assert time_to_ns(t) == ns and 0 <= t.nanosec < 1_000_000_000
    assert time_to_ns(Time(sec=3, nanosec=5)) == 3_000_000_005
    assert time_to_ns(rclpy.time.Time(nanoseconds=42)) == 42
    assert time_to_ns(np.int64(7)) == 7
    assert ns_to_time(rclpy.time.Time(seconds=2)).sec == 2
    with pytest.raises(AdapterError, match="nanosec=1000000000 is outside"):
        time_to_ns(Time(sec=0, nanosec=1_000_000_000))
    with pytest.raises(AdapterError, match="does not fit"):
        ns_to_time(2**31 * 1_000_000_000)
    with pytest.raises(AdapterError, match="expected a Time message"):
        time_to_ns("yesterday")
    with pytest.raises(AdapterError, match="frame_id: expected a string"):
        make_header(None)
