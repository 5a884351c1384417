"""``monovoc_interfaces/SemanticObject`` from plain values, and back to a plain dict (for clients, JSON)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from monovoc_ros.core.evidence.palette import format_object_id, unpack_rgb
from msg_adapters.errors import AdapterError


def semantic_object(
    object_id: int,
    *,
    centroid: Sequence[float],
    bbox_min: Sequence[float],
    bbox_max: Sequence[float],
    label: str = "",
    label_source: str = "",
    description: str = "",
    score: float = 0.0,
    num_gaussians: int = 0,
    num_observations: int = 0,
):
    """A ``monovoc_interfaces.msg.SemanticObject``; color and extent are derived from the id and box.
    ``label_source``: "given", "segments", "guess" or "" (monovoc_ros.core.segments.object_labels)."""
    from geometry_msgs.msg import Point, Vector3
    from std_msgs.msg import ColorRGBA

    from monovoc_interfaces.msg import SemanticObject

    object_id = int(object_id)
    if not 0 <= object_id <= 0xFFFFFF:
        raise AdapterError(f"SemanticObject: id {object_id} is not a packed 0x00RRGGBB color")
    c = np.asarray(centroid, dtype=np.float64)
    lo, hi = np.asarray(bbox_min, dtype=np.float64), np.asarray(bbox_max, dtype=np.float64)
    if c.shape != (3,) or lo.shape != (3,) or hi.shape != (3,):
        raise AdapterError("SemanticObject: centroid, bbox_min and bbox_max must be 3-vectors")
    if not (np.isfinite(c).all() and np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise AdapterError("SemanticObject: centroid and box must be finite")
    if np.any(hi < lo):
        raise AdapterError(f"SemanticObject: bbox_max {hi.tolist()} is below bbox_min {lo.tolist()}")
    if not np.isfinite(score):
        raise AdapterError(f"SemanticObject: score {score} is not finite")
    r, g, b = (unpack_rgb(np.array([object_id]))[0] / 255.0).tolist()
    (cx, cy, cz), (x0, y0, z0), (x1, y1, z1) = c.tolist(), lo.tolist(), hi.tolist()
    return SemanticObject(
        id=object_id,
        label=str(label),
        label_source=str(label_source),
        description=str(description),
        score=float(score),
        color=ColorRGBA(r=r, g=g, b=b, a=1.0),
        centroid=Point(x=cx, y=cy, z=cz),
        bbox_min=Point(x=x0, y=y0, z=z0),
        bbox_max=Point(x=x1, y=y1, z=z1),
        extent=Vector3(x=x1 - x0, y=y1 - y0, z=z1 - z0),
        num_gaussians=int(num_gaussians),
        num_observations=int(num_observations),
    )


def semantic_object_to_dict(msg: Any) -> dict:
    """Plain Python values of a SemanticObject (any source: rclpy, mcap_ros2, rosbags)."""

    def vec(v: Any) -> list[float]:
        return [float(v.x), float(v.y), float(v.z)]

    return {
        "id": int(msg.id),
        "hex": format_object_id(msg.id),
        "label": str(msg.label),
        # Messages recorded before the field existed have none.
        "label_source": str(getattr(msg, "label_source", "")),
        "description": str(msg.description),
        "score": float(msg.score),
        "color": [float(msg.color.r), float(msg.color.g), float(msg.color.b), float(msg.color.a)],
        "centroid": vec(msg.centroid),
        "bbox_min": vec(msg.bbox_min),
        "bbox_max": vec(msg.bbox_max),
        "extent": vec(msg.extent),
        "num_gaussians": int(msg.num_gaussians),
        "num_observations": int(msg.num_observations),
    }
