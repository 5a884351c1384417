"""Any ``Sequence`` (synthetic scene, plain / NICE-SLAM / HI-SLAM2 folders) -> a ROS 2 MCAP bag.

The bag follows the topic contract of ``topics``: the Gaussian map once, 1 ms before the first keyframe,
then per keyframe pose, camera_info, image and mask under one header stamp (MCAP log and publish time
equal to it). Optional map updates are logged 1 ms before the keyframe they precede. The sequence's
palette labels go into the metadata record ``monovoc_labels``, conversion settings into
``monovoc_source``. Output is deterministic: the same sequence and options give the same bytes.

Stamps: a sequence whose first stamp is below 1 s (the synthetic scene and plain folders without
stamps.txt start at 0) is shifted by ``time_offset_ns`` = 1 s, so no header stamp is zero and the map's
log time (first stamp - 1 ms) is not negative. The offset is recorded in ``monovoc_source``.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import msg_adapters as ma
from monovoc_ros.bags.qos import OfferedQos
from monovoc_ros.bags.writer import BagWriter
from monovoc_ros.contract import (
    CAMERA_FRAME,
    DEFAULT_NAMESPACE,
    LABELS_METADATA,
    MAP_FRAME,
    MAP_LEAD_NS,
    SEGMENTS_ROLE,
    SOURCE_METADATA,
    topic_names,
)
from monovoc_ros.core.evaluation.datasets import Sequence
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.gaussians import GaussianMap

RGB_FORMATS = ("jpeg", "png", "raw")
MASK_FORMATS = ("png", "raw", "none")  # none: a camera-only bag (image, camera_info, pose, map) for the segmenter
MIN_START_NS = 1_000_000_000
DEFAULT_JPEG_QUALITY = 95
# Publisher QoS recorded with the channels (what replay offers): everything reliable, the map latched.
MAP_QOS = OfferedQos(reliable=True, transient_local=True, depth=1)
STREAM_QOS = OfferedQos(reliable=True, transient_local=False, depth=10)

MapUpdates = Mapping[int, GaussianMap] | Iterable[tuple[int, GaussianMap]]


@dataclass
class ConvertReport:
    path: Path
    keyframes: int
    messages: dict[str, int]  # per topic
    map_messages: int
    time_offset_ns: int
    size_bytes: int
    seconds: float
    skipped: list[str] = field(default_factory=list)  # what the sequence could not provide

    def summary(self) -> dict:
        return {
            "path": str(self.path),
            "keyframes": self.keyframes,
            "messages": self.messages,
            "map_messages": self.map_messages,
            "time_offset_ns": self.time_offset_ns,
            "size_bytes": self.size_bytes,
            "size_mb": round(self.size_bytes / 1e6, 2),
            "seconds": round(self.seconds, 2),
            "skipped": self.skipped,
        }


def default_time_offset(first_stamp_ns: int) -> int:
    """0 for real clock stamps; 1 s for sequences that count from 0 (see the module docstring)."""
    return 0 if first_stamp_ns >= MIN_START_NS else MIN_START_NS


def _image_message(rgb: np.ndarray, fmt: str, stamp: int, jpeg_quality: int):
    if fmt == "raw":
        return ma.numpy_to_image(rgb, "rgb8", frame_id=CAMERA_FRAME, stamp=stamp)
    return ma.numpy_to_compressed_image(rgb, fmt, frame_id=CAMERA_FRAME, stamp=stamp, jpeg_quality=jpeg_quality)


def _mask_message(mask: np.ndarray, fmt: str, stamp: int):
    if fmt == "raw":
        return ma.numpy_to_image(mask, "rgb8", frame_id=CAMERA_FRAME, stamp=stamp)
    return ma.numpy_to_compressed_image(mask, "png", frame_id=CAMERA_FRAME, stamp=stamp)


def camera_info_intrinsics(keyframe: Keyframe):
    """Intrinsics for the image's resolution (the mask's when there is no image)."""
    k = keyframe.intrinsics
    if keyframe.rgb is None:
        return k
    h, w = keyframe.rgb.shape[:2]
    return k if (w, h) == (k.width, k.height) else k.scaled_to(w, h)


def _normalize_updates(map_updates: MapUpdates | None, n: int) -> dict[int, GaussianMap]:
    items = map_updates.items() if isinstance(map_updates, Mapping) else (map_updates or ())
    updates: dict[int, GaussianMap] = {}
    for k, gmap in items:
        k = int(k)
        if not 1 <= k < n:
            raise ValueError(f"map update before keyframe {k}: must be in 1..{n - 1} (the first map precedes 0)")
        if not isinstance(gmap, GaussianMap):
            raise TypeError(f"map update before keyframe {k}: expected a GaussianMap, got {type(gmap).__name__}")
        updates[k] = gmap
    return updates


def sequence_to_bag(
    sequence: Sequence,
    out_path: str | os.PathLike,
    *,
    rgb_format: str = "jpeg",
    mask_format: str = "png",
    namespace: str = DEFAULT_NAMESPACE,
    max_keyframes: int | None = None,
    map_updates: MapUpdates | None = None,
    include_map: bool = True,
    jpeg_quality: int = DEFAULT_JPEG_QUALITY,
    time_offset_ns: int | None = None,
    compression: str = "zstd",
    progress: bool = False,
    segments: bool | None = None,
) -> ConvertReport:
    """Writes ``sequence`` as a bag at ``out_path`` (atomically: a partial file never has the final name).

    ``segments``: write a SegmentArray beside every mask (the keyframes' segment class names); None = when
    the first keyframe has segments.

    ``map_updates``: ``{k: GaussianMap}`` or ``[(k, map), ...]``: a map message logged 1 ms before keyframe
    ``k`` (1 <= k < number of keyframes written), e.g. a moved or densified map halfway, for tests.
    """
    if rgb_format not in RGB_FORMATS:
        raise ValueError(f"rgb_format must be one of {RGB_FORMATS}, got {rgb_format!r}")
    if mask_format not in MASK_FORMATS:
        raise ValueError(f"mask_format must be one of {MASK_FORMATS}, got {mask_format!r}")
    n = len(sequence) if max_keyframes is None else min(len(sequence), int(max_keyframes))
    if n < 1:
        raise ValueError(f"{sequence.name}: no keyframes to write")
    updates = _normalize_updates(map_updates, n)
    stamps = np.asarray(sequence.stamps_ns[:n], dtype=np.int64)
    offset = default_time_offset(int(stamps[0])) if time_offset_ns is None else int(time_offset_ns)
    if int(stamps[0]) + offset - MAP_LEAD_NS < 0:
        raise ValueError(f"time_offset_ns={offset}: the first stamp would be below {MAP_LEAD_NS} ns")
    topics = topic_names(namespace)
    out_path = Path(out_path)
    tmp_path = out_path.with_name(f".{out_path.name}.partial")
    skipped: list[str] = []
    start = time.perf_counter()

    gaussians = sequence.load_gaussians() if include_map else None
    if include_map and gaussians is None:
        skipped.append("gaussians (the sequence has no Gaussian map)")
    try:
        with BagWriter(tmp_path, compression=compression) as writer:
            writer.add_json_metadata(LABELS_METADATA, sequence.labels())
            writer.add_json_metadata(
                SOURCE_METADATA,
                {
                    "sequence": sequence.name,
                    "keyframes": n,
                    "rgb_format": rgb_format,
                    "mask_format": mask_format,
                    "jpeg_quality": jpeg_quality if rgb_format == "jpeg" else None,
                    "namespace": namespace,
                    "time_offset_ns": offset,
                    "gaussians": None if gaussians is None else len(gaussians),
                    "map_updates": sorted(updates),
                },
            )
            map_messages = 0

            def write_map(gmap: GaussianMap, stamp: int) -> None:
                msg = ma.gaussian_map_to_cloud(gmap, frame_id=MAP_FRAME, stamp=stamp)
                writer.write(topics["gaussians"], msg, stamp, qos=MAP_QOS)

            if gaussians is not None:
                write_map(gaussians, int(stamps[0]) + offset - MAP_LEAD_NS)
                map_messages += 1
            iterator = range(n)
            if progress:
                from tqdm import tqdm

                iterator = tqdm(iterator, desc=f"bag {out_path.name}", unit="kf", file=sys.stderr)
            for i in iterator:
                stamp = int(stamps[i]) + offset
                if i in updates:
                    write_map(updates[i], stamp - MAP_LEAD_NS)
                    map_messages += 1
                kf = sequence.keyframe(i)
                if int(kf.stamp_ns) + offset != stamp:
                    raise ValueError(f"{sequence.name}: keyframe {i} stamp {kf.stamp_ns} != stamps_ns[{i}]")
                pose = ma.matrix_to_pose_stamped(kf.cam_to_world, frame_id=MAP_FRAME, stamp=stamp)
                writer.write(topics["pose"], pose, stamp, qos=STREAM_QOS)
                info = ma.intrinsics_to_camera_info(camera_info_intrinsics(kf), frame_id=CAMERA_FRAME, stamp=stamp)
                writer.write(topics["camera_info"], info, stamp, qos=STREAM_QOS)
                if kf.rgb is not None:
                    image = _image_message(kf.rgb, rgb_format, stamp, jpeg_quality)
                    writer.write(topics["image"], image, stamp, qos=STREAM_QOS)
                elif "image" not in " ".join(skipped):
                    skipped.append("image (the sequence has no RGB images)")
                if mask_format == "none":  # what a robot with only a camera records: the segmenter makes masks
                    continue
                if i == 0:
                    with_segments = kf.segments is not None if segments is None else segments
                if with_segments:  # one per mask, empty when the segmenter named nothing in it
                    names = ma.segment_array(kf.segments or (), frame_id=CAMERA_FRAME, stamp=stamp)
                    writer.write(topics[SEGMENTS_ROLE], names, stamp, qos=STREAM_QOS)
                writer.write(topics["mask"], _mask_message(kf.mask, mask_format, stamp), stamp, qos=STREAM_QOS)
            counts = dict(writer.counts)
        os.replace(tmp_path, out_path)
    finally:
        tmp_path.unlink(missing_ok=True)
    return ConvertReport(
        path=out_path,
        keyframes=n,
        messages=counts,
        map_messages=map_messages,
        time_offset_ns=offset,
        size_bytes=out_path.stat().st_size,
        seconds=time.perf_counter() - start,
        skipped=skipped,
    )
