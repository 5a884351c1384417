"""Generic ``sensor_msgs/PointCloud2`` field access with NumPy structured views (no per-point loops)."""

from __future__ import annotations

import functools
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from monovoc_ros.core.clipped_text import clipped
from msg_adapters.buffers import byte_array, bytes_view
from msg_adapters.errors import AdapterError
from msg_adapters.stamps import make_header

# sensor_msgs/PointField datatype constants.
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
DATATYPE_NAMES = {
    INT8: "INT8", UINT8: "UINT8", INT16: "INT16", UINT16: "UINT16",
    INT32: "INT32", UINT32: "UINT32", FLOAT32: "FLOAT32", FLOAT64: "FLOAT64",
}  # fmt: skip
_DATATYPE_CODES = {INT8: "i1", UINT8: "u1", INT16: "i2", UINT16: "u2", INT32: "i4", UINT32: "u4",
                   FLOAT32: "f4", FLOAT64: "f8"}  # fmt: skip
_NUMPY_TO_DATATYPE = {np.dtype(code): dt for dt, code in _DATATYPE_CODES.items()}
FLOATS = (FLOAT32, FLOAT64)
INTEGERS = (INT8, UINT8, INT16, UINT16, INT32, UINT32)


POINT_CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
# Characters of a field's name: a name, not a payload (errors quote names; a node logs them).
MAX_FIELD_NAME = 1024
# Field names an error lists, each cut to this many characters: a cloud may carry thousands of fields.
_LISTED_NAMES, _LISTED_CHARS = 16, 40


@functools.cache
def _typestore():
    """rosbags' stock Jazzy typestore (PointCloud2 needs no registration; monovoc_ros.bags.schemas has the one that
    registers the project's own types, which msg_adapters does not import)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def point_cloud_from_cdr(data: bytes | memoryview) -> Any:
    """The ``sensor_msgs/PointCloud2`` of a raw subscription's serialized message (CDR with its 4-byte
    encapsulation header), for the readers here: rosbags' decoder, whose ``data`` is a read-only view of ``data``,
    where rclpy's deserializing copies the payload twice (a 1M-Gaussian map, 57 MB: ~120 ms in process; the whole
    take of such a map, DDS's reassembly included, ~50 ms of CPU less: docs/results.md). Raises AdapterError for
    bytes that are no PointCloud2. Stricter than rclpy in a few ways (docs/robustness.md): XCDR2 or other
    encapsulations than plain CDR, four or more trailing bytes, and strings that are not UTF-8 are refused."""
    try:
        # A memoryview: rosbags slices off the encapsulation header, which on bytes copies the payload.
        return _typestore().deserialize_cdr(memoryview(data), POINT_CLOUD_TYPE)
    except MemoryError:
        raise
    except Exception as e:  # rosbags' SerdeError, and whatever else hostile bytes may raise
        raise AdapterError(f"PointCloud2: not a serialized PointCloud2 ({type(e).__name__}: {e})") from None


def prepare_point_cloud_decoder() -> None:
    """Builds the decoder now (rosbags' typestore and the type's generated code: ~0.1-0.2 s), so that a node's first
    map does not pay for it."""
    _typestore().get_msgdef(POINT_CLOUD_TYPE)


def read_fields(
    msg: Any,
    required: dict[str, Sequence[int]],
    optional: dict[str, Sequence[int]] | None = None,
    *,
    what: str = "PointCloud2",
) -> dict[str, np.ndarray]:
    """Columns of the named fields, one (N,) array each (native byte order, stored dtype).

    ``required`` / ``optional`` map field names to the PointField datatypes accepted for them.
    Optional fields that are absent are left out of the result. Arrays may be read-only views of
    the message buffer: copy before writing.
    """
    optional = optional or {}
    fields: dict[str, Any] = {}
    for f in msg.fields:
        name = str(f.name)
        if len(name) > MAX_FIELD_NAME:
            raise AdapterError(f"{what}: a field name of {len(name)} characters (at most {MAX_FIELD_NAME})")
        if name in fields and (name in required or name in optional):
            raise AdapterError(f"{what}: field {name!r} appears more than once")
        fields.setdefault(name, f)
    missing = [name for name in required if name not in fields]
    if missing:
        raise AdapterError(f"{what}: missing required fields {missing} (has {_listed(list(fields))})")

    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    n = height * width
    byteorder = ">" if bool(msg.is_bigendian) else "<"
    names, formats, offsets = [], [], []
    for name, allowed in list(required.items()) + list(optional.items()):
        if name not in fields:
            continue
        f = fields[name]
        datatype, offset, count = int(f.datatype), int(f.offset), int(f.count)
        if datatype not in _DATATYPE_CODES:
            raise AdapterError(f"{what}: field {name!r} has unknown datatype {datatype}")
        if datatype not in allowed:
            want = " or ".join(DATATYPE_NAMES[d] for d in allowed)
            raise AdapterError(f"{what}: field {name!r} has datatype {DATATYPE_NAMES[datatype]}, expected {want}")
        if count != 1:
            raise AdapterError(f"{what}: field {name!r} has count {count}, expected 1")
        dtype = np.dtype(byteorder + _DATATYPE_CODES[datatype])
        if offset < 0 or offset + dtype.itemsize > point_step:
            raise AdapterError(f"{what}: field {name!r} at offset {offset} does not fit point_step {point_step}")
        names.append(name)
        formats.append(dtype)
        offsets.append(offset)

    if n == 0:
        return {name: np.empty(0, dtype=fmt.newbyteorder("=")) for name, fmt in zip(names, formats, strict=True)}
    row_bytes = width * point_step
    if row_step < row_bytes:
        raise AdapterError(f"{what}: row_step {row_step} is smaller than width * point_step = {row_bytes}")
    data = bytes_view(msg.data, f"{what}.data")
    needed = row_step * (height - 1) + row_bytes
    if data.size < needed:
        raise AdapterError(f"{what}: data has {data.size} bytes, {width}x{height} points need {needed}")
    # A header that lies about the layout is refused even where the lie would be harmless to read.
    if data.size > row_step * height or (height == 1 and row_step not in (row_bytes, data.size)):
        raise AdapterError(
            f"{what}: row_step {row_step} x height {height} does not describe {data.size} bytes of data "
            f"(width {width} x point_step {point_step} = {row_bytes} per row)"
        )
    if height == 1 or row_step == row_bytes:
        packed = data[: n * point_step]
    else:  # rows padded beyond width * point_step: gather them (one copy)
        rows = np.lib.stride_tricks.as_strided(data, shape=(height, row_bytes), strides=(row_step, 1))
        packed = np.ascontiguousarray(rows).reshape(-1)
    layout = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})
    points = packed.view(layout)
    return {name: points[name] for name in names}


def _listed(names: list[str]) -> str:
    """`names` for an error message, bounded: the first _LISTED_NAMES, each cut to _LISTED_CHARS characters."""
    shown = [clipped(n, _LISTED_CHARS) for n in names[:_LISTED_NAMES]]
    more = f" and {len(names) - _LISTED_NAMES} more" if len(names) > _LISTED_NAMES else ""
    return f"{shown}{more}"


def make_cloud(columns: Iterable[tuple[str, np.ndarray]], *, frame_id: str, stamp: Any = 0, is_dense: bool = True):
    """An unordered (height 1) little-endian ``sensor_msgs.msg.PointCloud2`` with packed fields in the given order."""
    return _with_points(*_cloud_without_points(columns, frame_id, stamp, is_dense))


def serialized_cloud(
    columns: Iterable[tuple[str, np.ndarray]], *, frame_id: str, stamp: Any = 0, is_dense: bool = True
) -> np.ndarray:
    """The CDR bytes (with their encapsulation header) that rclpy's `serialize_message` makes of `make_cloud`'s
    message, as a (B,) uint8 array with the points written in place: for `SerializedPublisher`, which hands them
    to rcl without the interpreter (a message object costs one more copy of its points, rclpy's C message, and
    holds the interpreter while it is made). Only the small rest of the message is serialized by rclpy: with no
    points it ends with their length (uint32 0) and `is_dense` (one byte), no padding recorded after them (XCDR1 as
    rmw_fastrtps writes it); a middleware that serializes otherwise gets the whole message serialized by rclpy."""
    from rclpy.serialization import serialize_message

    msg, columns, dtype = _cloud_without_points(columns, frame_id, stamp, is_dense)
    head = serialize_message(msg)
    start = points_offset(head)
    if start is None:
        return np.frombuffer(serialize_message(_with_points(msg, columns, dtype)), np.uint8)
    out = np.empty(start + msg.row_step + 1, np.uint8)
    out[: start - 4] = np.frombuffer(head, np.uint8, start - 4)
    out[start - 4 : start] = np.array([msg.row_step], np.uint32).view(np.uint8)  # host order, as rclpy writes
    _fill(out[start : start + msg.row_step].view(dtype), columns)
    out[-1] = head[-1]
    return out


def points_offset(head: bytes) -> int | None:
    """Where the points go in `head`, the CDR of a PointCloud2 without points (its last 5 bytes: a uint32 0, the
    points' length, and is_dense), or None when `head` does not end so or records padding after it."""
    start = len(head) - 1
    if len(head) < 9 or head[2:4] != b"\0\0" or head[start - 4 : start] != b"\0\0\0\0" or head[-1] not in (0, 1):
        return None
    return start


def _cloud_without_points(
    columns: Iterable[tuple[str, np.ndarray]], frame_id: str, stamp: Any, is_dense: bool
) -> tuple[Any, list[tuple[str, np.ndarray]], np.dtype]:
    """`make_cloud`'s message without its points, the checked columns and the packed dtype of a point."""
    from sensor_msgs.msg import PointCloud2, PointField

    columns = [(name, np.asarray(values)) for name, values in columns]
    n = columns[0][1].shape[0] if columns else 0
    layout = []
    for name, values in columns:
        if values.ndim != 1 or values.shape[0] != n:
            raise AdapterError(f"PointCloud2: column {name!r} has shape {values.shape}, expected ({n},)")
        if values.dtype.newbyteorder("=") not in _NUMPY_TO_DATATYPE:
            raise AdapterError(f"PointCloud2: column {name!r} has unsupported dtype {values.dtype}")
        layout.append((name, values.dtype.newbyteorder("<")))
    dtype = np.dtype(layout)
    fields = [
        PointField(
            name=name,
            offset=dtype.fields[name][1],
            datatype=_NUMPY_TO_DATATYPE[dtype.fields[name][0].newbyteorder("=")],
            count=1,
        )
        for name, _ in columns
    ]
    # check_fields: the setter keeps an array.array('B') as it is (unchecked, it copies whatever it is given).
    msg = PointCloud2(header=make_header(frame_id, stamp), height=1, width=n, fields=fields, check_fields=True)
    msg.is_bigendian = False
    msg.point_step = dtype.itemsize
    msg.row_step = msg.point_step * n
    msg.is_dense = bool(is_dense)
    return msg, columns, dtype


def _with_points(msg: Any, columns: list[tuple[str, np.ndarray]], dtype: np.dtype) -> Any:
    """`msg` with its points. They are written straight into the message's bytes: filling a NumPy array, copying
    its bytes into an array.array, then rclpy's setter copying that again, held the interpreter for two copies of
    ~24 MB at 1M."""
    data = byte_array(msg.row_step)
    _fill(np.frombuffer(data, dtype=dtype), columns)
    msg.data = data
    return msg


def _fill(points: np.ndarray, columns: list[tuple[str, np.ndarray]]) -> None:
    """Writes each column into its field of `points` (N,) of the packed dtype."""
    for name, values in columns:
        points[name] = values
