"""Keyframes a stopping node received but had no time to integrate: written beside its final snapshot
(`deferred_keyframes.npz`) and integrated first when the node resumes, so that a clean shutdown loses
nothing a robot saw. Unlike the keyframe log (core.follow.keyframe_log), which keeps what re-integration
needs, a deferred keyframe is whole: its RGB image too, for the object views. Masks and images are stored
as zstd frames of their raw bytes (lossless, and fast enough for a shutdown's few seconds).
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import zstandard

from monovoc_ros.core.follow.keyframe_log import decode_mask, encode_mask
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.camera import Intrinsics, validate_pose
from monovoc_ros.core.segments.segment_labels import segments_from_entries, segments_to_entries

FILE_NAME = "deferred_keyframes.npz"
FORMAT = "monovoc_deferred_keyframes"


def save_keyframes(path: str | os.PathLike, keyframes: Sequence[Keyframe]) -> None:
    """Writes the keyframes (in order) to `path`."""
    masks = [encode_mask(k.mask) for k in keyframes]
    images = [b"" if k.rgb is None else _encode_image(k.rgb) for k in keyframes]
    shapes = [[0, 0] if k.rgb is None else list(k.rgb.shape[:2]) for k in keyframes]
    meta = [
        {
            "index": int(k.index),
            "stamp_ns": int(k.stamp_ns),
            "intrinsics": k.intrinsics.to_dict(),
            "rgb_shape": shape,
            "segments": None if k.segments is None else segments_to_entries(k.segments),
        }
        for k, shape in zip(keyframes, shapes, strict=True)
    ]
    buf = io.BytesIO()
    np.savez(
        buf,
        format=np.array(FORMAT),
        meta=np.array(json.dumps(meta)),
        poses=np.array([k.cam_to_world for k in keyframes], np.float64).reshape(-1, 4, 4),
        mask_sizes=np.array([len(b) for b in masks], np.int64),
        masks=np.frombuffer(b"".join(masks), np.uint8),
        image_sizes=np.array([len(b) for b in images], np.int64),
        images=np.frombuffer(b"".join(images), np.uint8),
    )
    Path(path).write_bytes(buf.getvalue())


def load_keyframes(path: str | os.PathLike) -> list[Keyframe]:
    """The keyframes `save_keyframes` wrote; raises ValueError naming the file when it is not such a file."""
    try:
        with np.load(path, allow_pickle=False) as data:
            if str(data["format"]) != FORMAT:
                raise ValueError(f"not a deferred keyframe file (format {str(data['format'])!r})")
            meta = json.loads(str(data["meta"]))
            poses = data["poses"]
            masks = _split(data["masks"].tobytes(), data["mask_sizes"])
            images = _split(data["images"].tobytes(), data["image_sizes"])
        if not len(meta) == len(poses) == len(masks) == len(images):
            raise ValueError("inconsistent array lengths")
        out = []
        for m, pose, mask_blob, image_blob in zip(meta, poses, masks, images, strict=True):
            intrinsics = Intrinsics.from_dict(m["intrinsics"])
            mask = decode_mask(mask_blob, intrinsics.height, intrinsics.width)
            if mask is None:
                raise ValueError(f"keyframe {m['stamp_ns']}: its mask does not decode")
            rgb = None
            if image_blob:
                h, w = (int(v) for v in m["rgb_shape"])
                rgb = decode_mask(image_blob, h, w)  # the same lossless zstd frame of (H, W, 3) uint8
                if rgb is None:
                    raise ValueError(f"keyframe {m['stamp_ns']}: its image does not decode")
            segments = None if m["segments"] is None else segments_from_entries(m["segments"])
            pose = validate_pose(pose, what="deferred keyframe pose")
            out.append(Keyframe(int(m["index"]), int(m["stamp_ns"]), pose, intrinsics, mask, rgb, segments))
        return out
    except FileNotFoundError:
        raise
    except (ValueError, KeyError, OSError, TypeError, EOFError, zipfile.BadZipFile, zstandard.ZstdError) as exc:
        raise ValueError(f"{path}: unreadable deferred keyframes ({exc})") from exc


def _encode_image(rgb: np.ndarray) -> bytes:
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"a keyframe image must be (H, W, 3), got {rgb.shape}")
    return encode_mask(rgb)


def _split(blob: bytes, sizes: np.ndarray) -> list[bytes]:
    ends = np.cumsum(sizes)
    if len(ends) and int(ends[-1]) != len(blob):
        raise ValueError("sizes do not add up to the stored bytes")
    starts = np.concatenate([[0], ends[:-1]]).astype(np.int64)
    return [blob[int(s) : int(e)] for s, e in zip(starts, ends, strict=True)]
