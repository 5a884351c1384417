"""Decoded ROS messages -> validated, synchronized Keyframes (or counted rejections).

The live node and offline bag processing both feed messages through `KeyframeAssembler`, so a bag
replayed into the node and the same bag read from disk produce the same keyframes. Messages are
checked and converted (msg_adapters) as they arrive; bad ones are rejected with a reason and never
reach the synchronizer or the semantic state.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

import msg_adapters as ma
from monovoc_ros.contract import BAD_MESSAGE, KEYFRAME_ROLES, POSE_MESSAGE_TYPES, SEGMENTS_ROLE
from monovoc_ros.core.evaluation.datasets import instance_palette
from monovoc_ros.core.evidence.palette import VOID_RGB, pack_rgb
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.camera import Intrinsics
from monovoc_ros.core.segments.segment_labels import SegmentLabel
from monovoc_ros.core.sync import StampEpochs, StampSynchronizer

POSE_TYPES = tuple(POSE_MESSAGE_TYPES)
_POSE_READERS = {
    "pose": ma.pose_stamped_to_matrix,
    "odometry": ma.odometry_to_matrix,
    "transform": ma.transform_stamped_to_matrix,
}
FRAME_CONVENTIONS = ("optical", "body")  # the pose is of the camera optical frame, or of a REP-103 body frame


class _VoidMask(ValueError):
    """An all-white mask: no object evidence, so not a keyframe (counted as void_mask)."""


@dataclass
class IngestConfig:
    pose_type: str = "pose"  # geometry_msgs/PoseStamped | nav_msgs/Odometry | geometry_msgs/TransformStamped
    frame_convention: str = "optical"  # "optical" (camera optical frame) or "body" (REP-103 x forward)
    sync_tolerance_s: float = 0.02
    use_image: bool = True  # the RGB image is only needed for object views; masks and poses suffice for SCD
    # Every mask waits for a SegmentArray of its stamp (the segmenter's class names of its segments).
    use_segments: bool = False
    rectified: bool = False  # CameraInfo: use P (rectified images) instead of K
    allow_distortion: bool = False
    max_pending: int = 32  # per-stream synchronizer buffer
    # A stamp more than this ahead of the node's clock is refused (stamp_future); more than this ahead of the
    # newest stamp of every other topic it is held until every topic resumes near it (a pause ended) or a later
    # message of its own topic shows it an outlier (core.sync.StampEpochs). 0 = no such check.
    max_stamp_lead_s: float = 30.0

    def __post_init__(self) -> None:
        if self.pose_type not in POSE_TYPES:
            raise ValueError(f"pose_type must be one of {POSE_TYPES}, got {self.pose_type!r}")
        if self.frame_convention not in FRAME_CONVENTIONS:
            raise ValueError(f"frame_convention must be one of {FRAME_CONVENTIONS}, got {self.frame_convention!r}")
        if not self.sync_tolerance_s >= 0:
            raise ValueError(f"sync_tolerance_s must be >= 0, got {self.sync_tolerance_s}")
        if not self.max_stamp_lead_s >= 0:
            raise ValueError(f"max_stamp_lead_s must be >= 0, got {self.max_stamp_lead_s}")


@dataclass
class Rejection:
    reason: str  # one of contract.REJECTION_REASONS
    role: str
    stamp_ns: int | None
    detail: str


# Largest image or mask decoded before any camera_info told the size to expect (4096 x 4096: 48 MB as RGB).
UNKNOWN_CAMERA_MAX_PIXELS = 4096 * 4096
MASK_MAX_SCALE = 4  # masks may be resampled copies of the camera image, up to this many times its pixels


class _SizeMismatch(ValueError):
    """An image or mask whose header disagrees with camera_info: refused before decoding (size_mismatch)."""


def _is_compressed(msg: Any) -> bool:
    return hasattr(msg, "format") and not hasattr(msg, "encoding")


def image_size(msg: Any) -> tuple[int, int]:
    """(width, height) of an Image (its fields) or CompressedImage (its PNG / JPEG header), without decoding."""
    if _is_compressed(msg):
        data = ma.buffers.bytes_view(msg.data, "CompressedImage.data")
        if data.size == 0:
            raise ma.AdapterError("CompressedImage: data is empty")
        header = ma.compressed_image_header(data, ma.compressed_image.format_codec(str(msg.format)))
        return header.width, header.height
    return int(msg.width), int(msg.height)


def image_message_to_numpy(msg: Any, max_pixels: int | None = None) -> np.ndarray:
    """sensor_msgs/Image or CompressedImage (told apart by their fields) -> NumPy."""
    if _is_compressed(msg):
        return ma.compressed_image_to_numpy(msg, max_pixels)
    if max_pixels is not None and int(msg.width) * int(msg.height) > max_pixels:
        raise ma.AdapterError(f"Image: {msg.width}x{msg.height} is more than the {max_pixels} pixels allowed here")
    return ma.image_to_numpy(msg)


def mask_from_image(array: np.ndarray) -> np.ndarray:
    """A palette mask as (H, W, 3) uint8: color masks as they are, mono8/mono16 instance-id images
    colorized with the deterministic instance palette (id 0 = void)."""
    if array.ndim == 3:
        if array.dtype != np.uint8:
            raise ma.AdapterError(
                f"mask: {8 * array.dtype.itemsize}-bit color mask; color masks must be 8-bit RGB "
                "(16-bit is only for mono16 instance ids)"
            )
        return array
    if array.dtype.kind != "u":
        raise ma.AdapterError(f"mask: instance-id images must be mono8 or mono16, got dtype {array.dtype}")
    return instance_palette(array)


def instance_segments(segments: tuple[SegmentLabel, ...]) -> tuple[SegmentLabel, ...]:
    """Segments of an instance-id mask with their ids in the colors `mask_from_image` gives those ids (0, void,
    and ids a mono16 mask cannot hold name no segment and are left out)."""
    kept = [s for s in segments if 1 <= s.id <= 0xFFFF]
    colors = pack_rgb(instance_palette(np.array([s.id for s in kept], np.int64))) if kept else []
    return tuple(SegmentLabel(int(c), s.class_name, s.score) for c, s in zip(colors, kept, strict=True))


class KeyframeAssembler:
    def __init__(self, config: IngestConfig | None = None, clock: Callable[[], int | None] | None = None) -> None:
        """``clock``: now in ns where there is one (the node's ROS time; see core.sync.StampEpochs)."""
        self.config = config or IngestConfig()
        roles = KEYFRAME_ROLES if self.config.use_image else tuple(r for r in KEYFRAME_ROLES if r != "image")
        self.roles = (*roles, SEGMENTS_ROLE) if self.config.use_segments else roles
        self.sync = StampSynchronizer(
            self.roles, "mask", int(round(self.config.sync_tolerance_s * 1e9)), self.config.max_pending
        )
        self.rejected: Counter[str] = Counter()
        self.received: Counter[str] = Counter()
        # Per role: the watermark (newest stamp that became part of a keyframe; older and equal stamps are
        # rejected) and the newest stamp accepted. Only a keyframe advances the watermark, so one outlier
        # (a far-future stamp) that never matches cannot block the messages after it.
        self._last_stamp: dict[str, int] = {}
        self._newest: dict[str, int] = {}
        self._lead_ns = int(round(self.config.max_stamp_lead_s * 1e9))
        self.epochs = StampEpochs(
            self.roles, self._lead_ns, self.config.max_pending, clock
        )  # far-future stamps: outliers or a pause
        self._camera_latest: tuple[int, int] | None = None  # size of the latest valid camera_info
        self._camera_sizes: deque[tuple[int, int]] = deque(maxlen=4)  # camera sizes of the last keyframes
        self._count = 0

    def push(self, role: str, msg: Any) -> tuple[list[Keyframe], list[Rejection]]:
        """Takes one decoded message of a role; returns the keyframes it completed and any rejection."""
        if role not in self.roles:
            return [], []
        self.received[role] += 1
        stamp = None
        try:
            stamp = ma.header_stamp_ns(msg)
            item = self._convert(role, msg)
        except ValueError as exc:
            reason = "void_mask" if isinstance(exc, _VoidMask) else BAD_MESSAGE[role]
            reason = "size_mismatch" if isinstance(exc, _SizeMismatch) else reason
            return [], [self._reject(reason, role, stamp, str(exc))]
        last = self._last_stamp.get(role)
        if last is not None and stamp <= last:
            reason = "duplicate_stamp" if stamp == last else "stamp_out_of_order"
            return [], [self._reject(reason, role, stamp, f"stamp {stamp} after {last} on {role}")]
        go, refused = self.epochs.offer(role, stamp, item, self._newest)
        rejections = [self._reject("stamp_future", h.role, h.stamp_ns, why) for h, why in refused]
        keyframes = []
        for taken in go:
            kfs, rejection = self._take(taken.role, taken.stamp_ns, taken.item)
            keyframes += kfs
            rejections += rejection
        return keyframes, rejections

    def _take(self, role: str, stamp: int, item: Any) -> tuple[list[Keyframe], list[Rejection]]:
        """A message past the stamp rules into the synchronizer."""
        rejections = []
        if self._lead_ns:
            # Waiting messages of this topic far ahead of this one were outliers (a far-future stamp that came
            # before any other topic could show it): they go, so they cannot block this topic.
            for gone in self.sync.discard_newer(role, stamp + self._lead_ns):
                detail = f"{role} stamp {gone} was {(gone - stamp) / 1e9:.3g} s ahead of a later message"
                rejections.append(self._reject("stamp_future", role, gone, detail))
        newest = self.sync.newest(role)
        if newest is not None and stamp <= newest:
            reason = "duplicate_stamp" if stamp == newest else "stamp_out_of_order"
            return [], [
                *rejections,
                self._reject(reason, role, stamp, f"stamp {stamp} after {newest} (waiting) on {role}"),
            ]
        self._newest[role] = stamp
        keyframes = []
        for pivot_stamp, parts in self.sync.push(role, stamp, (stamp, item)):
            for r, (part_stamp, _) in parts.items():
                self._last_stamp[r] = max(self._last_stamp.get(r, part_stamp), part_stamp)
            try:
                keyframes.append(self._assemble(pivot_stamp, {r: it for r, (_, it) in parts.items()}))
            except ValueError as exc:
                rejections.append(self._reject("size_mismatch", "mask", pivot_stamp, str(exc)))
        return keyframes, rejections

    def _reject(self, reason: str, role: str, stamp: int | None, detail: str) -> Rejection:
        self.rejected[reason] += 1
        return Rejection(reason, role, stamp, detail)

    def _convert(self, role: str, msg: Any) -> Any:
        if role == "pose":
            return _POSE_READERS[self.config.pose_type](msg, self.config.frame_convention)
        if role == "camera_info":
            # Validated now (size, distortion); rescaled to the mask once they are matched.
            ma.camera_info_to_intrinsics(
                msg, rectified=self.config.rectified, allow_distortion=self.config.allow_distortion
            )
            self._camera_latest = (int(msg.width), int(msg.height))
            return msg
        if role == SEGMENTS_ROLE:
            return ma.segment_array_to_labels(msg)  # ids checked as colors; instance ids mapped on assembly
        array = image_message_to_numpy(msg, self._check_size(role, msg))
        if role == "image":
            if array.ndim != 3:
                raise ma.AdapterError(f"image: expected a color image, got shape {array.shape}")
            return array
        mask = mask_from_image(array)
        if not np.any(mask != np.array(VOID_RGB, np.uint8)):
            raise _VoidMask(f"mask {mask.shape[1]}x{mask.shape[0]} is entirely void (white)")
        return mask, array.ndim == 2  # and whether its values were instance ids

    def _check_size(self, role: str, msg: Any) -> int:
        """The most pixels `msg` may decode to; raises _SizeMismatch when its header disagrees with the camera
        sizes in use (images must have one of them, masks the aspect ratio of one), before anything is decoded.

        Sizes in use: those of the last keyframes and of the latest camera_info. One bad camera_info therefore
        cannot make good images fail, and a resolution change costs one keyframe (its image comes first)."""
        sizes = {*self._camera_sizes, *([self._camera_latest] if self._camera_latest else [])}
        if not sizes:
            return UNKNOWN_CAMERA_MAX_PIXELS
        w, h = image_size(msg)
        known = ", ".join(f"{cw}x{ch}" for cw, ch in sorted(sizes))
        if role == "image" and (w, h) not in sizes:
            raise _SizeMismatch(f"image {w}x{h} disagrees with camera_info {known} (not decoded)")
        if role == "mask" and (h <= 0 or not any(abs(w / h - cw / ch) <= 0.01 * cw / ch for cw, ch in sizes)):
            raise _SizeMismatch(f"mask {w}x{h} does not have the aspect ratio of camera_info {known} (not decoded)")
        return MASK_MAX_SCALE * max(cw * ch for cw, ch in sizes)

    def _assemble(self, stamp: int, parts: dict[str, Any]) -> Keyframe:
        mask, instance_ids = parts["mask"]
        h, w = mask.shape[:2]
        info = parts["camera_info"]
        cam_w, cam_h = int(info.width), int(info.height)
        # Masks may be resampled copies of the camera image, never another aspect ratio.
        if abs(w / h - cam_w / cam_h) > 0.01 * cam_w / cam_h:
            raise ValueError(f"mask {w}x{h} does not have the aspect ratio of camera_info {cam_w}x{cam_h}")
        rgb = parts.get("image")
        if rgb is not None and rgb.shape[:2] != (cam_h, cam_w):
            raise ValueError(f"image {rgb.shape[1]}x{rgb.shape[0]} disagrees with camera_info {cam_w}x{cam_h}")
        intrinsics: Intrinsics = ma.camera_info_to_intrinsics(
            info, w, h, rectified=self.config.rectified, allow_distortion=self.config.allow_distortion
        )
        segments = parts.get(SEGMENTS_ROLE)
        if segments is not None and instance_ids:
            segments = instance_segments(segments)
        keyframe = Keyframe(self._count, stamp, parts["pose"], intrinsics, mask, rgb, segments=segments)
        self._count += 1
        if (cam_w, cam_h) in self._camera_sizes:
            self._camera_sizes.remove((cam_w, cam_h))
        self._camera_sizes.append((cam_w, cam_h))
        return keyframe
