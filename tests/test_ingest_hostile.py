"""Hostile keyframe inputs at the KeyframeAssembler (issue 9, cases 4 and 8; what the node and offline
processing share): far-future stamps, implausible cameras, 16-bit color masks."""

from __future__ import annotations

import numpy as np
import pytest

import msg_adapters as ma
from monovoc_ros.core.map.camera import Intrinsics
from monovoc_ros.ingest import KeyframeAssembler
from monovoc_ros.nodes.reorder import StampReorder
from tests.test_ingest import CAM, MS, feed, mask, messages

S = 1000 * MS
FAR = (2**31 - 1) * S  # sec = 2^31 - 1


def test_one_far_future_pose_does_not_block_later_poses():
    asm = KeyframeAssembler()
    assert len(feed(asm, messages(1 * S))[0]) == 1
    outlier = messages(FAR)["pose"]
    _, rejections = asm.push("pose", outlier)
    assert [r.reason for r in rejections] == ["stamp_future"] and "ahead of every other topic" in rejections[0].detail
    for k in range(2, 6):  # every later keyframe still goes through
        keyframes, rejections = feed(asm, messages(k * S))
        assert rejections == [] and len(keyframes) == 1, rejections


def test_a_far_future_first_message_is_dropped_by_the_next_one():
    asm = KeyframeAssembler()
    assert asm.push("pose", messages(FAR)["pose"]) == ([], [])  # nothing to compare with yet: it waits
    keyframes, rejections = feed(asm, messages(1 * S))
    assert len(keyframes) == 1 and [r.reason for r in rejections] == ["stamp_future"]
    assert rejections[0].stamp_ns == FAR and len(feed(asm, messages(2 * S))[0]) == 1


def test_watermark_moves_only_with_keyframes():
    asm = KeyframeAssembler()
    # A pose with no partners yet, then an older one of the same topic: out of order against the waiting one.
    asm.push("pose", messages(3 * S)["pose"])
    _, rejections = asm.push("pose", messages(2 * S)["pose"])
    assert [r.reason for r in rejections] == ["stamp_out_of_order"]
    assert len(feed(asm, messages(3 * S), order=("image", "camera_info", "mask"))[0]) == 1
    _, rejections = feed(asm, messages(3 * S))  # now part of a keyframe: duplicates on every topic
    assert [r.reason for r in rejections] == ["duplicate_stamp"] * 4


def test_reorder_passes_far_future_stamps_on_at_once():
    reorder = StampReorder(("mask", "pose"), max_wait_s=100.0)
    assert reorder.add("mask", messages(1 * S)["mask"]) == []
    far = messages(FAR)["pose"]
    assert reorder.add("pose", far) == [("pose", far)]  # not held at the head of the pose topic
    late = messages(1 * S)["pose"]
    assert [role for role, _ in reorder.add("pose", late)] == ["mask", "pose"]


@pytest.mark.parametrize(
    ("intrinsics", "problem"),
    [
        (Intrinsics(1e-30, 1e-30, 39.5, 29.5, 80, 60), "fx = 1e-30 is implausible for a 80 pixel wide image"),
        (Intrinsics(80.0, 1e6, 39.5, 29.5, 80, 60), "fy = 1e+06 is implausible"),
        (Intrinsics(80.0, 80.0, 39.5, 29.5, 2**32 - 1, 2**32 - 1), "exceeds 16384 pixels per side"),
        (Intrinsics(80.0, 80.0, 39.5, 29.5, 16385, 60), "exceeds 16384 pixels per side"),
    ],
)
def test_implausible_cameras_are_rejected(intrinsics, problem):
    asm = KeyframeAssembler()
    msgs = messages(1 * S)
    msgs["camera_info"] = ma.intrinsics_to_camera_info(intrinsics, stamp=1 * S)
    keyframes, rejections = feed(asm, msgs)
    assert keyframes == [] and [r.reason for r in rejections] == ["bad_camera_info"]
    assert problem in rejections[0].detail


def test_plausible_extremes_are_accepted():
    for fx in (0.05 * 80, 50.0 * 80):
        info = Intrinsics(fx, fx, 39.5, 29.5, 80, 60)
        keyframes, rejections = feed(KeyframeAssembler(), messages(1 * S, info=info))
        assert rejections == [] and len(keyframes) == 1


def test_16_bit_color_mask_gets_a_clear_reason():
    import cv2

    deep = mask().astype(np.uint16) * 257
    ok, png = cv2.imencode(".png", deep[:, :, ::-1])
    assert ok
    msgs = messages(1 * S)
    msgs["mask"].data = png.tobytes()
    keyframes, rejections = feed(KeyframeAssembler(), msgs)
    assert keyframes == [] and [r.reason for r in rejections] == ["bad_mask"]
    assert "16-bit" in rejections[0].detail and "8-bit RGB" in rejections[0].detail
    assert CAM.width == 80  # the good camera of the other cases


def test_bombs_are_refused_from_their_header_without_a_camera():
    from tests.test_node_bombs import jpeg_bomb, png_bomb

    for payload, fmt in ((png_bomb(30000, 30000), "png"), (jpeg_bomb(30000, 30000), "jpeg")):
        msg = messages(1 * S)["mask"]
        msg.format, msg.data = fmt, payload
        with pytest.raises(ma.AdapterError, match="header says 30000x30000, beyond 16384 pixels per side"):
            ma.compressed_image_to_numpy(msg)
    asm = KeyframeAssembler()  # no camera_info yet: at most UNKNOWN_CAMERA_MAX_PIXELS
    msg = messages(1 * S)["mask"]
    msg.data = png_bomb(8000, 6000)
    _, rejections = asm.push("mask", msg)
    assert [r.reason for r in rejections] == ["bad_mask"] and "8000x6000, more than the 16777216" in rejections[
        0
    ].detail


def test_offline_bag_mapping_refuses_the_maps_the_node_refuses():
    from monovoc_ros.core.follow.map_updater import map_update_refusal
    from monovoc_ros.offline import map_events
    from tests.node_scene import small_scene

    gaussians = small_scene().gaussians
    n = len(gaussians)
    empty, shrunk = gaussians.subset(np.zeros(0, np.int64)), gaussians.subset(np.arange(n // 4))
    mapper, stats = map_events([gaussians, empty, shrunk])
    assert len(mapper.gaussians) == n and stats.map_updates == 0
    assert stats.rejected == {"empty_gaussians": 1, "map_shrink": 1}
    assert map_update_refusal(gaussians, shrunk, 1.0) is None  # allowed by the operator
    assert map_update_refusal(gaussians, gaussians.subset(np.arange(n // 2 + 1)), 0.5) is None  # 50% exactly: kept
