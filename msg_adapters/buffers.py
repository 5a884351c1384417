"""Byte payloads of messages from any source, as NumPy arrays without needless copies.

A ``uint8[]`` field is an ``array.array('B')`` in rclpy messages, ``bytes`` (or a list) in messages
decoded by mcap_ros2, and a NumPy array in messages decoded by rosbags.
"""

from __future__ import annotations

import array
from collections.abc import Sequence

import numpy as np

from msg_adapters.errors import AdapterError


def bytes_view(data: object, what: str = "data") -> np.ndarray:
    """A 1-D uint8 array over ``data`` (a view when the buffer allows it; may be read-only)."""
    if isinstance(data, np.ndarray):
        if data.dtype.itemsize == 1 and data.ndim == 1:
            # Callers index with byte strides (as_strided): the buffer must be contiguous.
            return np.ascontiguousarray(data).view(np.uint8)
        raise AdapterError(f"{what}: expected a 1-D byte array, got {data.dtype} with shape {data.shape}")
    if isinstance(data, (bytes, bytearray, memoryview, array.array)):
        try:
            return np.frombuffer(data, dtype=np.uint8)
        except (ValueError, TypeError) as e:
            raise AdapterError(f"{what}: not a byte buffer ({e})") from None
    if isinstance(data, Sequence) and not isinstance(data, str):
        try:
            return np.asarray(data, dtype=np.uint8).reshape(-1)
        except (ValueError, TypeError, OverflowError) as e:
            raise AdapterError(f"{what}: not a sequence of bytes ({e})") from None
    raise AdapterError(f"{what}: unsupported payload type {type(data).__name__}")


def byte_array(nbytes: int) -> array.array:
    """A zeroed ``array.array('B')`` of ``nbytes`` to fill in place through ``np.frombuffer`` (a writable view):
    a message's uint8[] field built without `to_byte_array`'s copy of a filled NumPy array."""
    return array.array("B", b"\0") * nbytes


def to_byte_array(a: np.ndarray) -> array.array:
    """The bytes of ``a`` (C order) as an ``array.array('B')``, which rclpy's uint8[] setters take without
    per-element checks (a message built with ``check_fields=True`` keeps it as it is; unchecked, the setter copies
    it once more: `byte_array` for big payloads)."""
    out = array.array("B")
    out.frombytes(memoryview(np.ascontiguousarray(a)).cast("B"))
    return out
