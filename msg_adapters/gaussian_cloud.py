"""``sensor_msgs/PointCloud2`` <-> ``GaussianMap``: the Gaussian map topic's schema.

One point per Gaussian, fields (names matter, order and offsets do not when reading):

    x y z                     float32  mean, metres, in header.frame_id
    scale_0 scale_1 scale_2   float32  ACTIVATED scales (metres, > 0), not the PLY's log-scales
    rot_w rot_x rot_y rot_z   float32  rotation quaternion (w, x, y, z); normalized on reading
    opacity                   float32  ACTIVATED opacity in [0, 1], not the PLY's logit
    f_dc_0 f_dc_1 f_dc_2      float32  RAW SH degree-0 coefficients: color = 0.5 + SH_C0 * f_dc
                                       (as in the PLY); optional as a group (absent: no colors)
    id                        uint32   stable per-Gaussian id from the SLAM front-end; optional
                                       (absent: the map has no stable ids)

Reading also accepts float64 for the float fields, any integer type for ``id``, point_step and
row padding, and big-endian data. Written clouds are little endian, packed in the order above
(point_step 60 with colors and ids), height 1.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from monovoc_ros.contract import MAP_FRAME
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.map.ply import SH_C0
from msg_adapters.errors import AdapterError
from msg_adapters.point_cloud import FLOATS, INTEGERS, make_cloud, point_cloud_from_cdr, read_fields
from msg_adapters.stamps import header_stamp_ns

POSITION_FIELDS = ("x", "y", "z")
SCALE_FIELDS = ("scale_0", "scale_1", "scale_2")
ROTATION_FIELDS = ("rot_w", "rot_x", "rot_y", "rot_z")
COLOR_FIELDS = ("f_dc_0", "f_dc_1", "f_dc_2")
REQUIRED_FIELDS = POSITION_FIELDS + SCALE_FIELDS + ROTATION_FIELDS + ("opacity",)
_ID_MAX = 2**32 - 1


_F32 = np.dtype(np.float32)


def _stack(columns: dict[str, np.ndarray], names: tuple[str, ...]) -> np.ndarray:
    """(N, len(names)) float32 of the named columns (views of the points). When they lie side by side in every
    point as native float32 (as every writer packs x y z, the scales, the rotation), one strided copy of them
    all: at 1M points half the time of a copy per column."""
    first = columns[names[0]]
    start = first.__array_interface__["data"][0]
    adjacent = all(
        columns[name].dtype == _F32
        and columns[name].strides == first.strides
        and columns[name].__array_interface__["data"][0] == start + 4 * i
        for i, name in enumerate(names)
    )
    if adjacent:
        side_by_side = np.lib.stride_tricks.as_strided(first, (first.shape[0], len(names)), (first.strides[0], 4))
        return np.array(side_by_side, dtype=np.float32)
    out = np.empty((first.shape[0], len(names)), dtype=np.float32)
    for i, name in enumerate(names):
        out[:, i] = columns[name]
    return out


def _finite(a: np.ndarray, names: tuple[str, ...], what: str) -> None:
    finite = np.isfinite(a)
    if finite.all():
        return
    rows, cols = np.nonzero(~finite)
    fields = sorted({names[c] for c in cols})
    raise AdapterError(
        f"GaussianCloud: {rows.size} NaN/inf values in {what} fields {fields} (first at point {rows[0]})"
    )


def cloud_to_gaussian_map(msg: Any) -> GaussianMap:
    """The GaussianMap of a Gaussian PointCloud2 (schema in the module docstring)."""
    floats = {name: FLOATS for name in REQUIRED_FIELDS}
    optional = {name: FLOATS for name in COLOR_FIELDS}
    optional["id"] = INTEGERS
    columns = read_fields(msg, floats, optional, what="GaussianCloud")
    present_colors = [name for name in COLOR_FIELDS if name in columns]
    if present_colors and len(present_colors) != len(COLOR_FIELDS):
        missing = [name for name in COLOR_FIELDS if name not in columns]
        raise AdapterError(f"GaussianCloud: color fields must come as a group; missing {missing}")

    means = _stack(columns, POSITION_FIELDS)
    _finite(means, POSITION_FIELDS, "position")
    scales = _stack(columns, SCALE_FIELDS)
    _finite(scales, SCALE_FIELDS, "scale")
    if scales.size and scales.min() <= 0:
        raise AdapterError(
            f"GaussianCloud: scales must be activated (metres, > 0); min is {scales.min():g} (log-scales sent?)"
        )
    quats = _stack(columns, ROTATION_FIELDS)
    _finite(quats, ROTATION_FIELDS, "rotation")
    zero = (quats[:, 0] == 0) & (quats[:, 1] == 0) & (quats[:, 2] == 0) & (quats[:, 3] == 0)  # 3x any(axis=1)
    if zero.any():
        raise AdapterError(f"GaussianCloud: {int(zero.sum())} zero quaternions (first at point {int(np.argmax(zero))})")
    opacities = np.asarray(columns["opacity"], dtype=np.float32)
    _finite(opacities[:, None], ("opacity",), "opacity")
    if opacities.size and (opacities.min() < 0 or opacities.max() > 1):
        raise AdapterError(
            f"GaussianCloud: opacity must be activated (0..1); range is [{opacities.min():g}, {opacities.max():g}] "
            "(logits sent?)"
        )
    colors = None
    if present_colors:
        f_dc = _stack(columns, COLOR_FIELDS)
        _finite(f_dc, COLOR_FIELDS, "color")
        colors = 0.5 + np.float32(SH_C0) * f_dc
    ids = None
    if "id" in columns:
        ids = np.asarray(columns["id"], dtype=np.int64)
    try:
        return GaussianMap(means, scales, quats, opacities, colors=colors, ids=ids, stamp_ns=_stamp_ns(msg))
    except ValueError as e:
        raise AdapterError(f"GaussianCloud: {e}") from None


MAX_FRAME_ID = 1024  # characters of a map's frame_id (a name, not a payload: the map reader's header carries it)


def gaussian_map_from_cdr(data: bytes | memoryview) -> tuple[GaussianMap, str]:
    """A Gaussian map topic's serialized message (a raw subscription's bytes, a bag's record) -> the map (stamped
    with its header's, ``GaussianMap.stamp_ns``) and its header's frame_id: ``point_cloud_from_cdr``, then
    ``cloud_to_gaussian_map``, as the node, its map reader and offline mapping all read it. Raises AdapterError."""
    msg = point_cloud_from_cdr(data)
    frame_id = str(msg.header.frame_id)
    if len(frame_id) > MAX_FRAME_ID:
        raise AdapterError(f"GaussianCloud: frame_id of {len(frame_id)} characters (at most {MAX_FRAME_ID})")
    return cloud_to_gaussian_map(msg), frame_id


def _stamp_ns(msg: Any) -> int:
    """The map's stamp (GaussianMap.stamp_ns): the header's, 0 (unknown) when it has none or a negative one."""
    return max(0, header_stamp_ns(msg)) if hasattr(msg, "header") else 0


def gaussian_map_to_cloud(gmap: GaussianMap, *, frame_id: str = MAP_FRAME, stamp: Any = None, include_ids: bool = True):
    """A ``sensor_msgs.msg.PointCloud2`` of ``gmap`` (f_dc when it has colors, id when it has ids), stamped
    ``stamp`` (None: the map's own, ``gmap.stamp_ns``)."""
    columns: list[tuple[str, np.ndarray]] = []
    for names, values in ((POSITION_FIELDS, gmap.means), (SCALE_FIELDS, gmap.scales), (ROTATION_FIELDS, gmap.quats)):
        columns += [(name, values[:, i]) for i, name in enumerate(names)]
    columns.append(("opacity", gmap.opacities))
    if gmap.colors is not None:
        f_dc = (gmap.colors - np.float32(0.5)) / np.float32(SH_C0)
        columns += [(name, f_dc[:, i]) for i, name in enumerate(COLOR_FIELDS)]
    if include_ids and gmap.ids is not None:
        if gmap.ids.size and (gmap.ids.min() < 0 or gmap.ids.max() > _ID_MAX):
            raise AdapterError(f"GaussianCloud: ids must fit uint32; range is [{gmap.ids.min()}, {gmap.ids.max()}]")
        columns.append(("id", gmap.ids.astype(np.uint32)))
    if not np.all(np.isfinite(gmap.means)):
        raise AdapterError("GaussianCloud: map has NaN/inf positions")
    return make_cloud(columns, frame_id=frame_id, stamp=gmap.stamp_ns if stamp is None else stamp)
