"""The keyframe log: what each integrated keyframe's evidence came from, kept to re-integrate it
(METHOD section 10: re-integration against a corrected map, as BundleFusion and OVO-SLAM do).

Per keyframe: stamp, pose, intrinsics, the mask as given (its raw RGB bytes, zstd-compressed; per-frame
mask ids keep the segmenter's own colors, so re-integration associates them again) and its segments. RGB is not kept:
the object views keep the crops they need. The log is bounded by `max_bytes`: beyond it the oldest
entries are dropped and the log is no longer complete (core.follow.map_updater then does not re-integrate: a
rebuild would lose the dropped keyframes' evidence). It is saved in the snapshot (`keyframe_log.npz`)
and restored on resume.
"""

from __future__ import annotations

import io
import json
import os
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import zstandard

from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.camera import Intrinsics, validate_pose
from monovoc_ros.core.segments.segment_labels import segments_from_entries, segments_to_entries

FORMAT = "monovoc_keyframe_log"
DEFAULT_MAX_BYTES = 256 * 1024 * 1024
# Flat masks: zstd level 1 of the raw bytes is half the size of a fast PNG, and decodes 20x and encodes
# 30x faster (616x344: 4.2 KB, 0.05 ms / 0.13 ms against 7.9 KB, 1.0 ms / 4.3 ms); decoding is on
# re-integration's path for every keyframe, encoding on the live one.
_ZSTD_LEVEL = 1
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@dataclass(frozen=True)
class KeyframePoses:
    """Corrected keyframe poses from the SLAM front-end (nav_msgs/Path: one stamped pose per keyframe)."""

    poses: tuple[tuple[int, np.ndarray], ...]  # (stamp_ns, (4, 4) float64 cam_to_world), in the path's order


@dataclass(frozen=True)
class LoggedKeyframe:
    index: int
    stamp_ns: int
    cam_to_world: np.ndarray  # (4, 4) float64, corrected when the SLAM corrected it
    intrinsics: Intrinsics
    mask_blob: bytes  # encode_mask's bytes
    segments: tuple | None = None

    @property
    def nbytes(self) -> int:
        return len(self.mask_blob) + 16 * 8 + 64 + 48 * len(self.segments or ())

    def keyframe(self) -> Keyframe:
        mask = decode_mask(self.mask_blob, self.intrinsics.height, self.intrinsics.width)
        if mask is None:
            raise ValueError(f"logged keyframe {self.stamp_ns}: its mask does not decode")
        return Keyframe(self.index, self.stamp_ns, self.cam_to_world.copy(), self.intrinsics, mask, None, self.segments)


def encode_mask(mask: np.ndarray) -> bytes:
    """Lossless zstd frame of an (H, W, 3) uint8 RGB mask's bytes (the shape is the intrinsics')."""
    return zstandard.ZstdCompressor(level=_ZSTD_LEVEL).compress(np.ascontiguousarray(mask, np.uint8).tobytes())


def decode_mask(blob: bytes, height: int, width: int) -> np.ndarray | None:
    """The (H, W, 3) uint8 RGB mask of `encode_mask` (or of a PNG, as logs saved before zstd hold them);
    None when the bytes are neither, or not a mask of that size."""
    if blob[:8] == _PNG_SIGNATURE:
        bgr = cv2.imdecode(np.frombuffer(blob, np.uint8), cv2.IMREAD_COLOR)
        return None if bgr is None or bgr.shape != (height, width, 3) else np.ascontiguousarray(bgr[:, :, ::-1])
    size = height * width * 3
    try:
        raw = zstandard.ZstdDecompressor().decompress(blob, max_output_size=size)
    except zstandard.ZstdError:
        return None
    return np.frombuffer(raw, np.uint8).reshape(height, width, 3).copy() if len(raw) == size else None


class KeyframeLog:
    """The logged keyframes, in order of integration; see the module docstring."""

    def __init__(self, max_bytes: int = DEFAULT_MAX_BYTES) -> None:
        if max_bytes < 0:
            raise ValueError(f"max_bytes must be >= 0, got {max_bytes}")
        self.max_bytes = int(max_bytes)
        self.entries: list[LoggedKeyframe] = []
        self.nbytes = 0
        self.dropped = 0  # entries dropped for room: re-integration cannot be exact any more
        # The pose state: True when the SLAM corrected poses since the last map update, which are then in the
        # frame of its next map already, so that update must not move them again. Saved with the log; set and
        # cleared by core.follow.map_updater only.
        self.poses_given = False

    def __len__(self) -> int:
        return len(self.entries)

    def copy(self) -> KeyframeLog:
        """The log as it is now (its entries are immutable: a new list of the same entries)."""
        out = KeyframeLog(self.max_bytes)
        out.entries = list(self.entries)
        out.nbytes, out.dropped, out.poses_given = self.nbytes, self.dropped, self.poses_given
        return out

    @property
    def complete(self) -> bool:
        return self.dropped == 0

    def add(self, keyframe: Keyframe) -> None:
        entry = LoggedKeyframe(
            keyframe.index,
            int(keyframe.stamp_ns),
            np.array(keyframe.cam_to_world, np.float64),
            keyframe.intrinsics,
            encode_mask(keyframe.mask),
            tuple(keyframe.segments) if keyframe.segments else None,
        )
        self.append(entry)

    def append(self, entry: LoggedKeyframe) -> None:
        """Logs an entry as it is (re-integration: the entry it integrated, its mask not encoded again)."""
        self.entries.append(entry)
        self.nbytes += entry.nbytes
        while self.nbytes > self.max_bytes and self.entries:
            self.nbytes -= self.entries.pop(0).nbytes
            self.dropped += 1

    def set_poses(self, given: dict[int, np.ndarray], tolerance: tuple[float, float] = (1e-3, 1e-3)) -> int:
        """Takes corrected poses (stamp -> validated (4, 4) cam_to_world) of logged keyframes (others
        ignored); returns how many moved by more than `tolerance` (metres, radians)."""
        changed = 0
        for k, entry in enumerate(self.entries):
            T = given.get(entry.stamp_ns)
            if T is None:
                continue
            changed += _pose_changed(entry.cam_to_world, T, tolerance)
            self.entries[k] = replace(entry, cam_to_world=np.array(T, np.float64))
        return changed

    def move_poses(self, move, keep=None) -> None:
        """Every pose moved by `move`, which takes them all at once ((P, 4, 4) -> (P, 4, 4) float64), but those
        of the stamps `keep(stamp_ns)` is true for."""
        rows = [k for k, entry in enumerate(self.entries) if keep is None or not keep(entry.stamp_ns)]
        if not rows:
            return
        moved = move(np.stack([self.entries[k].cam_to_world for k in rows]))
        for k, pose in zip(rows, moved, strict=True):
            self.entries[k] = replace(self.entries[k], cam_to_world=pose)

    def follow_poses(self, other: KeyframeLog) -> None:
        """Each entry takes the pose of `other`'s entry of the same stamp (a rebuild's log, when a map update
        moved the poses of the live log it re-integrates)."""
        poses = {e.stamp_ns: e.cam_to_world for e in other.entries}
        for k, entry in enumerate(self.entries):
            T = poses.get(entry.stamp_ns)
            if T is not None and T is not entry.cam_to_world:
                self.entries[k] = replace(entry, cam_to_world=T)

    def continues(self, earlier: KeyframeLog) -> None:
        """This log holds `earlier`'s entries integrated again (a re-integration swapped in): it is as complete
        as that one, and its poses are in the same frame."""
        self.dropped = earlier.dropped
        self.poses_given = earlier.poses_given

    # ---------------------------------------------------------------- files

    def save(self, path: str | os.PathLike) -> None:
        arrays = {
            "format": np.array(FORMAT),
            "stamps_ns": np.array([e.stamp_ns for e in self.entries], np.int64),
            "index": np.array([e.index for e in self.entries], np.int64),
            "poses": np.array([e.cam_to_world for e in self.entries], np.float64).reshape(-1, 4, 4),
            "intrinsics": np.array(json.dumps([e.intrinsics.to_dict() for e in self.entries])),
            "mask_sizes": np.array([len(e.mask_blob) for e in self.entries], np.int64),
            "masks": np.frombuffer(b"".join(e.mask_blob for e in self.entries), np.uint8),
            "segments": np.array(
                json.dumps([None if e.segments is None else segments_to_entries(e.segments) for e in self.entries])
            ),
            "meta": np.array(
                json.dumps({"max_bytes": self.max_bytes, "dropped": self.dropped, "poses_given": self.poses_given})
            ),
        }
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        Path(path).write_bytes(buf.getvalue())

    @classmethod
    def load(cls, path: str | os.PathLike) -> KeyframeLog:
        """Reads a file written by `save`; raises ValueError naming the file when it is not one."""
        try:
            with np.load(path, allow_pickle=False) as data:
                if str(data["format"]) != FORMAT:
                    raise ValueError(f"not a keyframe log (format {str(data['format'])!r})")
                meta = json.loads(str(data["meta"]))
                log = cls(int(meta["max_bytes"]))
                log.dropped = int(meta["dropped"])
                log.poses_given = bool(meta["poses_given"])
                segments = json.loads(str(data["segments"]))
                intrinsics = json.loads(str(data["intrinsics"]))
                # Every array is read out of the archive once: indexing `data[...]` decompresses it again.
                index, stamps, poses = data["index"], data["stamps_ns"], data["poses"]
                ends = np.cumsum(data["mask_sizes"])
                masks = data["masks"].tobytes()
                n = len(stamps)
                lengths = {len(ends), len(segments), len(intrinsics), len(poses), len(index), n}
                if len(lengths) != 1 or (n and ends[-1] != len(masks)):
                    raise ValueError("inconsistent array lengths")
                cameras: dict[str, Intrinsics] = {}  # a robot's keyframes share a few cameras
                for k in range(n):
                    key = json.dumps(intrinsics[k], sort_keys=True)
                    camera = cameras.get(key)
                    if camera is None:
                        camera = cameras[key] = Intrinsics.from_dict(intrinsics[k])
                    start = int(ends[k - 1]) if k else 0
                    log.append(
                        LoggedKeyframe(
                            int(index[k]),
                            int(stamps[k]),
                            validate_pose(poses[k], what="logged pose"),
                            camera,
                            masks[start : int(ends[k])],
                            None if segments[k] is None else segments_from_entries(segments[k]),
                        )
                    )
        except FileNotFoundError:
            raise
        except (ValueError, KeyError, OSError, TypeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: unreadable keyframe log ({exc})") from exc
        return log


def _pose_changed(a: np.ndarray, b: np.ndarray, tolerance: tuple[float, float]) -> bool:
    moved = np.linalg.norm(a[:3, 3] - b[:3, 3])
    cos = np.clip((np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2, -1.0, 1.0)
    return bool(moved > tolerance[0] or np.arccos(cos) > tolerance[1])
