"""``visualization_msgs/MarkerArray`` of semantic objects, for RViz.

The array starts with one DELETEALL marker with an empty namespace (RViz 2 then clears every marker
of the display, while a named namespace would clear only that one), so objects that disappeared
are removed; then per
object a translucent CUBE (namespace ``<ns>/boxes``) at the centroid, sized by the axis-aligned
extent, in the palette color, and a white TEXT_VIEW_FACING label (namespace ``<ns>/labels``)
above the box along ``up``. Both use the object id (the packed palette color, < 2^24) as marker
id, so an object keeps its markers across updates.

``up`` is the map frame's up direction: (0, 0, 1) for REP-103 frames (z up); a SLAM world frame
that is the first camera's optical frame has y down, so pass (0, -1, 0) there.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from monovoc_ros.contract import MAP_FRAME
from monovoc_ros.core.evidence.palette import format_object_id, unpack_rgb
from msg_adapters.colors import rgb_to_packed
from msg_adapters.errors import AdapterError
from msg_adapters.message_cache import MessageCache
from msg_adapters.stamps import make_header

_INT32_MAX = 2**31 - 1


def object_markers(
    ids: Sequence[int] | np.ndarray,
    labels: Sequence[str],
    centroids: np.ndarray,
    extents: np.ndarray,
    rgb: np.ndarray,
    *,
    frame_id: str = MAP_FRAME,
    stamp: Any = 0,
    namespace: str = "monovoc",
    alpha: float = 0.4,
    text_height: float = 0.12,
    min_extent: float = 0.01,
    up: Sequence[float] = (0.0, 0.0, 1.0),
    cache: MessageCache | None = None,
):
    """A ``visualization_msgs.msg.MarkerArray``: DELETEALL, then a CUBE and a TEXT per object.

    ``rgb``: (N, 3) uint8, (N, 3) float in [0, 1], or (N,) packed. An empty label shows the id as hex.
    Extents are clamped to ``min_extent`` (RViz does not draw zero-size cubes). ``cache``: the markers of an
    object whose values did not change since the last call with it are reused, their header set anew: an array
    returned before shares them (publish it before the next call, as the mapping node does).
    """
    from geometry_msgs.msg import Point, Pose, Quaternion, Vector3
    from std_msgs.msg import ColorRGBA
    from visualization_msgs.msg import Marker, MarkerArray

    ids = np.asarray(ids)
    n = ids.shape[0] if ids.ndim == 1 else -1
    if ids.ndim != 1 or (n and ids.dtype.kind not in "ui"):
        raise AdapterError(f"object_markers: ids must be a 1-D integer array, got {ids.dtype} shape {ids.shape}")
    if n and (ids.min() < 0 or ids.max() > _INT32_MAX):
        raise AdapterError("object_markers: ids must fit a non-negative int32 marker id")
    if np.unique(ids).size != n:
        raise AdapterError("object_markers: ids must be unique")
    labels = list(labels)
    centroids = np.asarray(centroids, dtype=np.float64).reshape(-1, 3) if n else np.zeros((0, 3))
    extents = np.asarray(extents, dtype=np.float64).reshape(-1, 3) if n else np.zeros((0, 3))
    colors = unpack_rgb(rgb_to_packed(rgb, "object_markers.rgb")) if n else np.zeros((0, 3), np.uint8)
    for name, count in (("labels", len(labels)), ("centroids", len(centroids)), ("extents", len(extents)),
                        ("rgb", len(colors))):  # fmt: skip
        if count != n:
            raise AdapterError(f"object_markers: {name} has {count} entries for {n} ids")
    if not (np.all(np.isfinite(centroids)) and np.all(np.isfinite(extents))):
        raise AdapterError("object_markers: centroids and extents must be finite")
    if np.any(extents < 0):
        raise AdapterError("object_markers: extents must be non-negative")
    if not 0.0 <= alpha <= 1.0:
        raise AdapterError(f"object_markers: alpha {alpha} outside [0, 1]")
    up_dir = np.asarray(up, dtype=np.float64)
    if up_dir.shape != (3,) or not np.isfinite(up_dir).all() or np.linalg.norm(up_dir) == 0:
        raise AdapterError(f"object_markers: up must be a non-zero 3-vector, got {up}")
    up_dir = up_dir / np.linalg.norm(up_dir)

    header = make_header(frame_id, stamp)
    identity = Quaternion(w=1.0, x=0.0, y=0.0, z=0.0)
    out = MarkerArray()
    out.markers.append(Marker(header=header, ns="", id=0, action=Marker.DELETEALL))
    sizes = np.maximum(extents, min_extent)
    # Half the box's size along `up`, plus half a line of text, so the label sits just above it.
    lift = 0.5 * np.abs(sizes) @ np.abs(up_dir) + 0.75 * text_height
    label_pos = centroids + lift[:, None] * up_dir
    rgbf = (colors.astype(np.float64) / 255.0).tolist()
    # Python floats: rclpy messages store whatever they are given.
    rows = zip(ids.tolist(), labels, centroids.tolist(), sizes.tolist(), label_pos.tolist(), rgbf, strict=True)
    cache = cache if cache is not None else MessageCache()
    cache.start()
    for oid, label, centre, size, label_at, color in rows:

        def build(oid=oid, label=label, centre=centre, size=size, label_at=label_at, color=color) -> tuple:
            (cx, cy, cz), (sx, sy, sz), (lx, ly, lz), (r, g, b) = centre, size, label_at, color
            box = Marker(header=header, ns=f"{namespace}/boxes", id=oid, type=Marker.CUBE, action=Marker.ADD)
            box.pose = Pose(position=Point(x=cx, y=cy, z=cz), orientation=identity)
            box.scale = Vector3(x=sx, y=sy, z=sz)
            box.color = ColorRGBA(r=r, g=g, b=b, a=float(alpha))
            text = Marker(header=header, ns=f"{namespace}/labels", id=oid, type=Marker.TEXT_VIEW_FACING)
            text.action = Marker.ADD
            text.pose = Pose(position=Point(x=lx, y=ly, z=lz), orientation=identity)
            text.scale = Vector3(x=0.0, y=0.0, z=float(text_height))
            text.color = ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0)
            text.text = str(label) or format_object_id(oid)
            return box, text

        values = (namespace, float(alpha), float(text_height), str(label), *centre, *size, *label_at, *color)
        box, text = cache.get(oid, values, build)
        box.header = text.header = header
        out.markers += [box, text]
    cache.finish()
    return out
