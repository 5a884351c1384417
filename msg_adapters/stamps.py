"""Time stamps: ``builtin_interfaces/Time`` <-> integer nanoseconds, and headers.

Every ``stamp`` argument of this package accepts an int (nanoseconds), a ``builtin_interfaces/Time``
(rclpy, mcap_ros2 or rosbags; anything with ``sec`` and ``nanosec``) or an ``rclpy.time.Time``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from msg_adapters.errors import AdapterError

_NS = 1_000_000_000
_INT32 = (-(2**31), 2**31 - 1)


def time_to_ns(stamp: Any) -> int:
    """Nanoseconds of a Time message (``sec`` * 1e9 + ``nanosec``), or of an ``rclpy.time.Time``."""
    if isinstance(stamp, (int, np.integer)) and not isinstance(stamp, bool):
        return int(stamp)
    if hasattr(stamp, "nanoseconds") and not hasattr(stamp, "sec"):
        return int(stamp.nanoseconds)
    try:
        sec, nanosec = int(stamp.sec), int(stamp.nanosec)
    except (AttributeError, TypeError, ValueError):
        raise AdapterError(f"stamp: expected a Time message or int nanoseconds, got {type(stamp).__name__}") from None
    if not 0 <= nanosec < _NS:
        raise AdapterError(f"stamp: nanosec={nanosec} is outside [0, 1e9)")
    return sec * _NS + nanosec


def ns_to_time(ns: Any):
    """A ``builtin_interfaces.msg.Time`` for integer nanoseconds (or any accepted stamp)."""
    from builtin_interfaces.msg import Time

    ns = time_to_ns(ns)
    sec, nanosec = divmod(ns, _NS)
    if not _INT32[0] <= sec <= _INT32[1]:
        raise AdapterError(f"stamp: {ns} ns does not fit builtin_interfaces/Time (int32 seconds)")
    return Time(sec=sec, nanosec=nanosec)


def make_header(frame_id: str, stamp: Any = 0):
    """A ``std_msgs.msg.Header`` with ``frame_id`` and ``stamp``."""
    from std_msgs.msg import Header

    if not isinstance(frame_id, str):
        raise AdapterError(f"frame_id: expected a string, got {type(frame_id).__name__}")
    return Header(frame_id=frame_id, stamp=ns_to_time(stamp))


def header_stamp_ns(msg: Any) -> int:
    """Nanoseconds of ``msg.header.stamp``."""
    try:
        return time_to_ns(msg.header.stamp)
    except AttributeError:
        raise AdapterError(f"{type(msg).__name__} has no header.stamp") from None
