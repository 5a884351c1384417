"""The semantic PointCloud2 (one point per labelled Gaussian), for RViz and clients.

Fields, packed little endian in this order (point_step 24):

    x y z        float32  Gaussian mean, metres, in header.frame_id
    rgb          float32  palette color as packed 0x00RRGGBB bits reinterpreted as float32 (what
                          RViz's RGB8 color transformer reads); not a numeric value
    object_id    uint32   the object's stable id = the same packed 0x00RRGGBB palette color
                          (0xFFFFFF = void/unlabeled)
    confidence   float32  how sure the labelling is, 0..1 (e.g. the accumulated weight's share)

Reading also accepts ``rgb`` stored as UINT32, float64 positions/confidence, and any integer type
for object_id.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from monovoc_ros.contract import MAP_FRAME
from monovoc_ros.core.evidence.palette import unpack_rgb
from msg_adapters.colors import rgb_to_packed
from msg_adapters.errors import AdapterError
from msg_adapters.point_cloud import FLOAT32, FLOATS, INTEGERS, UINT32, make_cloud, read_fields, serialized_cloud

FIELDS = ("x", "y", "z", "rgb", "object_id", "confidence")


class SemanticCloud(NamedTuple):
    points: np.ndarray  # (N, 3) float32
    rgb: np.ndarray  # (N, 3) uint8
    object_ids: np.ndarray  # (N,) uint32
    confidence: np.ndarray  # (N,) float32


def semantic_cloud_from_arrays(
    points: np.ndarray,
    rgb: np.ndarray,
    object_ids: np.ndarray,
    confidence: np.ndarray,
    *,
    frame_id: str = MAP_FRAME,
    stamp: Any = 0,
):
    """A ``sensor_msgs.msg.PointCloud2`` in the semantic schema.

    ``rgb``: (N, 3) uint8, (N, 3) float in [0, 1], or (N,) packed 0x00RRGGBB integers.
    """
    return make_cloud(_columns(points, rgb, object_ids, confidence), frame_id=frame_id, stamp=stamp)


def serialized_semantic_cloud(*arrays: np.ndarray, frame_id: str = MAP_FRAME, stamp: Any = 0) -> np.ndarray:
    """The CDR bytes of `semantic_cloud_from_arrays`'s message of the same `arrays` (points, rgb, object_ids,
    confidence), (B,) uint8 (`point_cloud.serialized_cloud`)."""
    return serialized_cloud(_columns(*arrays), frame_id=frame_id, stamp=stamp)


def _columns(
    points: np.ndarray, rgb: np.ndarray, object_ids: np.ndarray, confidence: np.ndarray
) -> list[tuple[str, np.ndarray]]:
    """The semantic schema's checked columns, in order."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise AdapterError(f"SemanticCloud: points must be (N, 3), got shape {points.shape}")
    n = points.shape[0]
    if not np.all(np.isfinite(points)):
        raise AdapterError("SemanticCloud: points contain NaN or infinite values")
    packed = rgb_to_packed(rgb, "SemanticCloud.rgb")
    object_ids = np.asarray(object_ids)
    confidence = np.asarray(confidence, dtype=np.float32)
    for name, a in (("rgb", packed), ("object_ids", object_ids), ("confidence", confidence)):
        if a.shape != (n,):
            raise AdapterError(f"SemanticCloud: {name} must have shape ({n},), got {a.shape}")
    if object_ids.dtype.kind not in "ui" or (n and (object_ids.min() < 0 or object_ids.max() > 2**32 - 1)):
        raise AdapterError(f"SemanticCloud: object_ids must be integers fitting uint32, got {object_ids.dtype}")
    points = points.astype(np.float32, copy=False)
    return [
        ("x", points[:, 0]),
        ("y", points[:, 1]),
        ("z", points[:, 2]),
        ("rgb", packed.view(np.float32)),
        ("object_id", object_ids.astype(np.uint32)),
        ("confidence", confidence),
    ]


def semantic_cloud_to_arrays(msg: Any) -> SemanticCloud:
    """The arrays of a semantic PointCloud2 (copies, safe to modify)."""
    columns = read_fields(
        msg,
        {"x": FLOATS, "y": FLOATS, "z": FLOATS, "rgb": (FLOAT32, UINT32), "object_id": INTEGERS, "confidence": FLOATS},
        what="SemanticCloud",
    )
    points = np.stack([columns[k].astype(np.float32) for k in ("x", "y", "z")], axis=1)
    # Reinterpret the bits in their stored byte order: converting the float values could flush
    # these (denormal) floats to zero.
    rgb_bits = columns["rgb"]
    packed = rgb_bits.view(rgb_bits.dtype.str.replace("f", "u")).astype(np.uint32) & 0xFFFFFF
    return SemanticCloud(
        points=points,
        rgb=unpack_rgb(packed),
        object_ids=columns["object_id"].astype(np.uint32),
        confidence=columns["confidence"].astype(np.float32),
    )
