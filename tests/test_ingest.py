"""Decoded messages -> keyframes: conversion, synchronization and rejection reasons."""

from __future__ import annotations

import numpy as np
import pytest

import msg_adapters as ma
from monovoc_ros.core.map.camera import Intrinsics, pose_from_translation_quat
from monovoc_ros.ingest import IngestConfig, KeyframeAssembler

CAM = Intrinsics(80.0, 80.0, 39.5, 29.5, 80, 60)
MS = 1_000_000


def mask(h=30, w=40, color=(200, 10, 10)) -> np.ndarray:
    m = np.full((h, w, 3), 255, np.uint8)
    m[5:20, 8:30] = color
    return m


def messages(stamp: int, *, mask_array=None, image=None, pose=None, info=CAM):
    rgb = np.zeros((info.height, info.width, 3), np.uint8) if image is None else image
    T = pose_from_translation_quat([0.1, 0.2, 0.3], [1, 0, 0, 0]) if pose is None else pose
    return {
        "image": ma.numpy_to_compressed_image(rgb, "jpeg", stamp=stamp),
        "mask": ma.numpy_to_compressed_image(mask() if mask_array is None else mask_array, "png", stamp=stamp),
        "camera_info": ma.intrinsics_to_camera_info(info, stamp=stamp),
        "pose": ma.matrix_to_pose_stamped(T, stamp=stamp),
    }


def feed(asm: KeyframeAssembler, msgs: dict, order=("pose", "image", "camera_info", "mask")):
    keyframes, rejections = [], []
    for role in order:
        k, r = asm.push(role, msgs[role])
        keyframes += k
        rejections += r
    return keyframes, rejections


def test_keyframe_with_intrinsics_rescaled_to_the_mask():
    asm = KeyframeAssembler()
    kfs, rej = feed(asm, messages(100 * MS))
    assert rej == [] and len(kfs) == 1
    kf = kfs[0]
    assert kf.stamp_ns == 100 * MS and kf.index == 0
    assert kf.mask.shape == (30, 40, 3) and kf.rgb.shape == (60, 80, 3)
    assert kf.intrinsics == CAM.scaled_to(40, 30)
    np.testing.assert_allclose(kf.cam_to_world[:3, 3], [0.1, 0.2, 0.3])


def test_mono_instance_masks_are_colorized_with_void_zero():
    ids = np.zeros((30, 40), np.uint8)
    ids[2:10, 2:10] = 7
    msgs = messages(100 * MS)
    msgs["mask"] = ma.numpy_to_image(ids, "mono8", stamp=100 * MS)
    kfs, rej = feed(KeyframeAssembler(), msgs)
    assert rej == []
    m = kfs[0].mask
    assert (m[0, 0] == 255).all() and not (m[5, 5] == 255).all()


@pytest.mark.parametrize(
    ("mutate", "reason"),
    [
        (lambda m: m.update(image=ma.numpy_to_image(np.zeros((4, 4), np.uint8), "mono8", stamp=100 * MS)), "bad_image"),
        (lambda m: setattr(m["mask"], "format", "tiff"), "bad_mask"),
        (lambda m: setattr(m["pose"].pose.orientation, "w", 7.0), "bad_pose"),
        (lambda m: setattr(m["pose"].pose.position, "x", float("nan")), "bad_pose"),
        (lambda m: setattr(m["camera_info"], "k", [0.0] * 9), "bad_camera_info"),
        (
            lambda m: m.update(
                mask=ma.numpy_to_compressed_image(np.full((30, 40, 3), 255, np.uint8), "png", stamp=100 * MS)
            ),
            "void_mask",
        ),
        (
            lambda m: m.update(
                image=ma.numpy_to_compressed_image(np.zeros((600, 800, 3), np.uint8), "jpeg", stamp=100 * MS)
            ),
            "size_mismatch",
        ),
        (
            lambda m: m.update(mask=ma.numpy_to_compressed_image(mask(30, 30), "png", stamp=100 * MS)),
            "size_mismatch",
        ),
    ],
)
def test_bad_messages_are_rejected_with_a_reason(mutate, reason):
    asm = KeyframeAssembler()
    msgs = messages(100 * MS)
    mutate(msgs)
    kfs, rej = feed(asm, msgs)
    assert kfs == []
    assert [r.reason for r in rej] == [reason]
    assert asm.rejected[reason] == 1
    # The assembler keeps working: the next good keyframe goes through.
    kfs, rej = feed(asm, messages(200 * MS))
    assert len(kfs) == 1 and rej == []


def test_out_of_order_and_duplicate_stamps_are_rejected():
    asm = KeyframeAssembler()
    assert len(feed(asm, messages(200 * MS))[0]) == 1
    kfs, rej = feed(asm, messages(200 * MS))
    assert kfs == [] and {r.reason for r in rej} == {"duplicate_stamp"}
    kfs, rej = feed(asm, messages(100 * MS))
    assert kfs == [] and {r.reason for r in rej} == {"stamp_out_of_order"}
    assert len(feed(asm, messages(300 * MS))[0]) == 1


def test_tolerance_and_optional_image():
    asm = KeyframeAssembler(IngestConfig(sync_tolerance_s=0.005, use_image=False))
    msgs = messages(100 * MS)
    msgs["pose"] = ma.matrix_to_pose_stamped(np.eye(4), stamp=103 * MS)
    kfs, _ = feed(asm, msgs, order=("pose", "camera_info", "mask"))
    assert len(kfs) == 1 and kfs[0].rgb is None
    msgs = messages(200 * MS)
    msgs["pose"] = ma.matrix_to_pose_stamped(np.eye(4), stamp=208 * MS)  # beyond 5 ms
    kfs, _ = feed(asm, msgs, order=("camera_info", "mask", "pose"))
    assert kfs == [] and asm.sync.stats.unmatched["mask"] == 1


def test_body_frame_convention_and_pose_types():
    T = pose_from_translation_quat([1, 2, 3], [1, 0, 0, 0])
    asm = KeyframeAssembler(IngestConfig(pose_type="transform", frame_convention="body"))
    msgs = messages(100 * MS)
    msgs["pose"] = ma.matrix_to_transform_stamped(T, stamp=100 * MS, frame_convention="body")
    kfs, rej = feed(asm, msgs)
    assert rej == []
    np.testing.assert_allclose(kfs[0].cam_to_world, T, atol=1e-12)
    with pytest.raises(ValueError, match="pose_type"):
        IngestConfig(pose_type="tf")


def test_segments_wait_for_their_mask_and_follow_instance_ids():
    from monovoc_ros.core.evaluation.datasets import instance_palette
    from monovoc_ros.core.evidence.palette import pack_rgb
    from monovoc_ros.core.segments.segment_labels import SegmentLabel

    asm = KeyframeAssembler(IngestConfig(use_segments=True))
    assert asm.roles[-1] == "segments"
    chair = SegmentLabel(int(pack_rgb(np.array([200, 10, 10], np.uint8))), "chair", 0.8)
    msgs = messages(100 * MS)
    kfs, rej = feed(asm, msgs)  # no segments yet: the mask waits
    assert kfs == [] and rej == []
    kfs, rej = asm.push("segments", ma.segment_array([chair], stamp=100 * MS))
    assert rej == [] and len(kfs) == 1 and kfs[0].segments == (chair,)

    # A mono16 instance mask: segment ids are instance ids and become the colors the mask is given.
    ids = np.zeros((30, 40), np.uint16)
    ids[2:10, 2:10] = 300
    msgs = messages(200 * MS)
    msgs["mask"] = ma.numpy_to_image(ids, "mono16", stamp=200 * MS)
    named = [SegmentLabel(300, "lamp", 1.0), SegmentLabel(70000, "ghost", 1.0)]  # 70000: no mono16 id
    msgs["segments"] = ma.segment_array(named, stamp=200 * MS)
    kfs, rej = feed(asm, msgs, order=("pose", "image", "camera_info", "segments", "mask"))
    assert rej == [] and len(kfs) == 1
    color = int(pack_rgb(instance_palette(np.array([300])))[0])
    assert kfs[0].segments == (SegmentLabel(color, "lamp", 1.0),)
    assert int(pack_rgb(kfs[0].mask[5, 5])) == color


@pytest.mark.parametrize(
    ("class_name", "score", "segment_id"), [("", 1.0, 5), ("chair", 1.5, 5), ("chair", 1.0, 0xFFFFFF)]
)
def test_bad_segments_are_rejected_and_their_mask_never_completes(class_name, score, segment_id):
    from monovoc_interfaces.msg import Segment, SegmentArray

    asm = KeyframeAssembler(IngestConfig(use_segments=True))
    bad = SegmentArray(header=ma.make_header("", 100 * MS), segments=[Segment(id=segment_id, class_name=class_name,
                                                                              score=score)])  # fmt: skip
    kfs, rej = asm.push("segments", bad)
    assert kfs == [] and [r.reason for r in rej] == ["bad_segments"]
    kfs, rej = feed(asm, messages(100 * MS))
    assert kfs == [] and rej == []
    assert asm.rejected["bad_segments"] == 1
