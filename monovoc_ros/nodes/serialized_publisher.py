"""Publishing a message already serialized (CDR bytes) without holding the interpreter.

Why: rclpy's `Publisher.publish` keeps the interpreter lock through `rcl_publish` (converting the message, serializing
it, handing it to the middleware), as does `publish` of bytes (`publish_raw`, which first copies them into a
string). At 1M Gaussians the semantic cloud is ~14 MB: 5-7 ms of publish on an idle machine, 60-230 ms when the
thread is preempted on two saturated cores, during which no query is answered (docs/results.md, issue 25).

So the bytes go to `rcl_publish_serialized_message` of the librcl the process already has (the same copy as
rclpy's bindings, found in /proc/self/maps), called through ctypes, which lets go of the interpreter for the call.
The publisher stays rclpy's (its QoS, events, subscription count); only the call that sends differs. Where that
library is not found (not Linux, a build that links rcl statically) the bytes go through rclpy's `publish`.
"""

from __future__ import annotations

import ctypes
import functools
from pathlib import Path
from typing import Any

import numpy as np

RCL_LIBRARY = "librcl.so"


class _Allocator(ctypes.Structure):
    """rcutils_allocator_t: unused by publishing (nothing is allocated or freed in the message)."""

    _fields_ = [
        ("allocate", ctypes.c_void_p),
        ("deallocate", ctypes.c_void_p),
        ("reallocate", ctypes.c_void_p),
        ("zero_allocate", ctypes.c_void_p),
        ("state", ctypes.c_void_p),
    ]


class _SerializedMessage(ctypes.Structure):
    """rcl_serialized_message_t (rcutils_uint8_array_t), over a buffer it does not own."""

    _fields_ = [
        ("buffer", ctypes.c_void_p),
        ("buffer_length", ctypes.c_size_t),
        ("buffer_capacity", ctypes.c_size_t),
        ("allocator", _Allocator),
    ]


@functools.cache
def loaded_rcl_publish() -> Any | None:
    """`rcl_publish_serialized_message` of the librcl loaded with rclpy's bindings, or None where none is found."""
    import rclpy.impl.implementation_singleton  # noqa: F401  (loads rclpy's bindings, and with them librcl)

    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError:
        return None
    paths = {line.split(maxsplit=5)[5] for line in maps.splitlines() if line.endswith("/" + RCL_LIBRARY)}
    if len(paths) != 1:  # none, or two copies: which one made the publisher is unknown
        return None
    try:
        fn = ctypes.CDLL(paths.pop()).rcl_publish_serialized_message
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_void_p, ctypes.POINTER(_SerializedMessage), ctypes.c_void_p]
    fn.restype = ctypes.c_int
    return fn


class SerializedPublisher:
    """Sends CDR bytes (with their encapsulation header, as `rclpy.serialization.serialize_message` makes them) on
    an rclpy publisher of the matching type."""

    def __init__(self, publisher: Any, *, release_interpreter: bool = True) -> None:
        """`release_interpreter` False: always rclpy's `publish` (the reference the tests hold the other against)."""
        self.publisher = publisher
        self._rcl_publish = loaded_rcl_publish() if release_interpreter else None

    @property
    def releases_interpreter(self) -> bool:
        return self._rcl_publish is not None

    def publish(self, data: np.ndarray) -> None:
        """Publishes `data` (B,) uint8, contiguous; raises RuntimeError when rcl refuses it."""
        if self._rcl_publish is None:
            self.publisher.publish(data.tobytes())
            return
        data = np.ascontiguousarray(data, np.uint8)
        message = _SerializedMessage(data.ctypes.data, data.size, data.size, _Allocator())
        handle = self.publisher.handle
        with handle:  # the publisher is not destroyed while rcl uses it
            ret = self._rcl_publish(handle.pointer, ctypes.byref(message), None)
        if ret != 0:
            raise RuntimeError(
                f"rcl_publish_serialized_message failed on {self.publisher.topic_name} (rcl error {ret})"
            )
