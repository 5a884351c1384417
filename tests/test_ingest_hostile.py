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
    assert asm.push("pose", outlier) == ([], [])  # held: a lone outlier or the first message after a pause
    keyframes, rejections = feed(asm, messages(2 * S))  # the next pose shows it an outlier
    assert len(keyframes) == 1 and [r.reason for r in rejections] == ["stamp_future"]
    assert rejections[0].stamp_ns == FAR and "ahead of a later one" in rejections[0].detail
    for k in range(3, 6):  # every later keyframe still goes through
        keyframes, rejections = feed(asm, messages(k * S))
        assert rejections == [] and len(keyframes) == 1, rejections
    assert asm.epochs.epochs == 0 and asm.epochs.held == 0


@pytest.mark.parametrize("gap_s", [100, 3600, 30 * 24 * 3600])
def test_streams_that_resume_after_a_pause_are_integrated(gap_s):
    """A robot that stood still, a restarted SLAM or a later bag: every topic resumes far ahead of the
    stamps the pause froze. The first messages are held until every topic agrees; nothing is lost."""
    asm = KeyframeAssembler()
    for k in range(1, 4):
        assert len(feed(asm, messages(k * S))[0]) == 1
    made = []
    for k in range(4, 8):
        keyframes, rejections = feed(asm, messages(gap_s * S + k * S))
        assert rejections == [], rejections
        made.append(len(keyframes))
    # The first resumed keyframe waits for the second (a stream, not one keyframe), then both go on.
    assert made == [0, 2, 1, 1] and asm.epochs.epochs == 1 and sum(asm.rejected.values()) == 0


def test_one_whole_keyframe_stamped_in_the_future_blocks_nothing():
    """Every topic of one keyframe with the same bad stamp (a camera's header copied by the segmenter and the
    SLAM) agrees with itself, but one keyframe is not a resumed stream: it is held, then refused."""
    asm = KeyframeAssembler()
    assert len(feed(asm, messages(1 * S))[0]) == 1
    assert feed(asm, messages(10**6 * S)) == ([], [])  # held on every topic
    keyframes, rejections = feed(asm, messages(2 * S))
    assert len(keyframes) == 1 and [r.reason for r in rejections] == ["stamp_future"] * 4
    for k in range(3, 6):
        assert len(feed(asm, messages(k * S))[0]) == 1
    assert asm.epochs.epochs == 0 and asm.epochs.held == 0


def test_messages_held_behind_a_late_topics_epoch_are_refused_not_kept():
    """Three topics resume, the fourth only 45 s later: what the others sent before the last 30 s can never
    be matched; it is refused when the epoch opens, and nothing stays held."""
    asm = KeyframeAssembler()
    assert len(feed(asm, messages(1 * S))[0]) == 1
    gap = 1000 * S
    for k in range(20):  # image, camera_info and mask every 5 s for 95 s, no pose
        feed(asm, messages(gap + 5 * k * S), order=("image", "camera_info", "mask"))
    keyframes = []
    for k in range(16, 20):  # the pose resumes 80 s later
        keyframes += asm.push("pose", messages(gap + 5 * k * S)["pose"])[0]
    assert len(keyframes) == 4 and asm.epochs.epochs == 1 and asm.epochs.held == 0
    assert asm.rejected["stamp_future"] == 3 * 10  # the first 50 s of three topics: behind the epoch


def test_a_lone_far_future_message_after_a_pause_is_still_an_outlier():
    asm = KeyframeAssembler()
    assert len(feed(asm, messages(1 * S))[0]) == 1
    asm.push("mask", messages(FAR)["mask"])  # held
    assert feed(asm, messages(100 * S)) == ([], [])  # the streams resume 99 s later, far from the outlier
    keyframes, rejections = feed(asm, messages(101 * S))
    assert len(keyframes) == 2 and [r.reason for r in rejections] == ["stamp_future"]
    assert asm.epochs.epochs == 1 and rejections[0].stamp_ns == FAR


def test_a_far_future_stamp_is_refused_at_once_against_the_clock():
    now = 10 * S
    asm = KeyframeAssembler(clock=lambda: now)
    assert len(feed(asm, messages(1 * S))[0]) == 1
    _, rejections = asm.push("pose", messages(now + 31 * S)["pose"])
    assert [r.reason for r in rejections] == ["stamp_future"] and "31 s ahead of this host's clock" in rejections[
        0
    ].detail
    assert feed(asm, messages(now + 28 * S)) == ([], [])  # a pause within the clock: an epoch
    keyframes, rejections = feed(asm, messages(now + 29 * S))
    assert len(keyframes) == 2 and rejections == [] and asm.epochs.epochs == 1
    unknown = KeyframeAssembler(clock=lambda: None)  # sim time before the first /clock: no clock rule
    assert unknown.push("pose", messages(FAR)["pose"]) == ([], [])


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


def test_reorder_holds_a_far_future_stamp_aside_until_its_topic_shows_it_an_outlier():
    reorder = StampReorder(("mask", "pose"), max_wait_s=100.0)
    assert reorder.add("mask", messages(1 * S)["mask"]) == []
    far = messages(FAR)["pose"]
    assert reorder.add("pose", far) == []  # held aside, not at the head of the pose topic
    late = messages(1 * S)["pose"]
    out = reorder.add("pose", late)
    assert out[0] == ("pose", far) and [role for role, _ in out[1:]] == ["mask", "pose"]


def test_reorder_takes_streams_that_resume_after_a_pause_in_stamp_order():
    reorder = StampReorder(("mask", "pose"), max_wait_s=100.0)
    reorder.add("mask", messages(1 * S)["mask"])
    assert [r for r, _ in reorder.add("pose", messages(1 * S)["pose"])] == ["mask", "pose"]
    gap = 3600 * S
    assert reorder.add("pose", messages(gap + 2 * S)["pose"]) == []  # held: alone so far ahead
    assert reorder.add("pose", messages(gap + 3 * S)["pose"]) == []
    out = reorder.add("mask", messages(gap + 2 * S)["mask"])  # every topic agrees: a new epoch
    assert [(r, ma.header_stamp_ns(m)) for r, m in out] == [("mask", gap + 2 * S), ("pose", gap + 2 * S)]
    assert reorder.epochs.epochs == 1 and len(reorder) == 1  # pose gap + 3 s waits for its mask


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
