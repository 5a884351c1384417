"""Publishing a message already serialized (CDR bytes) without holding the interpreter.

Why: rclpy's `Publisher.publish` keeps the interpreter lock through `rcl_publish` (converting the message, serializing
it, handing it to the middleware), as does `publish` of bytes (`publish_raw`, which first copies them into a
string). At 1M Gaussians the semantic cloud is ~14 MB: 5-7 ms of publish on an idle machine, 60-230 ms when the
thread is preempted on two saturated cores, during which no query is answered (docs/results.md, issue 25).

So the bytes go to `rcl_publish_serialized_message`, called through ctypes, which lets go of the interpreter for the
call; the symbol is looked up through rclpy's own extension module, so it is the librcl its bindings link. The
publisher stays rclpy's (its QoS, events, subscription count); only the call that sends differs. Where the lookup
fails (a build without the symbols visible) the bytes go through rclpy's `publish`.
"""

from __future__ import annotations

import ctypes
import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

RCUTILS_ERROR_MESSAGE_MAX_LENGTH = 1024  # rcutils/error_handling.h


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


class _ErrorString(ctypes.Structure):
    """rcutils_error_string_t."""

    _fields_ = [("str", ctypes.c_char * RCUTILS_ERROR_MESSAGE_MAX_LENGTH)]


@dataclass(frozen=True)
class _Rcl:
    """The functions of rclpy's librcl (and its rcutils) this module calls."""

    publish_serialized: Any
    error_string: Any
    reset_error: Any


@functools.cache
def loaded_rcl() -> _Rcl | None:
    """rcl's functions as rclpy's bindings link them, or None where they cannot be looked up."""
    import rclpy.impl.implementation_singleton  # noqa: F401  (loads the bindings: their module is then importable)
    from rclpy import _rclpy_pybind11

    try:
        # A lookup in the extension's handle searches it and the libraries it depends on: rclpy's librcl.
        library = ctypes.CDLL(_rclpy_pybind11.__file__)
        rcl = _Rcl(
            library.rcl_publish_serialized_message, library.rcutils_get_error_string, library.rcutils_reset_error
        )
    except (OSError, AttributeError):
        return None
    rcl.publish_serialized.argtypes = [ctypes.c_void_p, ctypes.POINTER(_SerializedMessage), ctypes.c_void_p]
    rcl.publish_serialized.restype = ctypes.c_int
    rcl.error_string.argtypes = []
    rcl.error_string.restype = _ErrorString
    rcl.reset_error.argtypes = []
    rcl.reset_error.restype = None
    return rcl


class SerializedPublisher:
    """Sends CDR bytes (with their encapsulation header, as `rclpy.serialization.serialize_message` makes them) on
    an rclpy publisher of the matching type."""

    def __init__(self, publisher: Any, *, release_interpreter: bool = True) -> None:
        """`release_interpreter` False: always rclpy's `publish` (the reference the tests hold the other against)."""
        self.publisher = publisher
        self._rcl = loaded_rcl() if release_interpreter else None

    @property
    def releases_interpreter(self) -> bool:
        return self._rcl is not None

    def publish(self, data: np.ndarray) -> None:
        """Publishes `data` (B,) uint8, contiguous. Raises ValueError for other arrays, rclpy's InvalidHandle for a
        destroyed publisher, RuntimeError with rcl's reason when rcl refuses the message."""
        if not (isinstance(data, np.ndarray) and data.dtype == np.uint8 and data.ndim == 1 and data.flags.c_contiguous):
            raise ValueError(f"serialized message: expected a contiguous (B,) uint8 array, got {type(data).__name__}")
        if self._rcl is None:
            self.publisher.publish(data.tobytes())
            return
        message = _SerializedMessage(data.ctypes.data, data.size, data.size, _Allocator())
        handle = self.publisher.handle
        with handle:  # the publisher is not destroyed while rcl uses it
            ret = self._rcl.publish_serialized(handle.pointer, ctypes.byref(message), None)
            if ret != 0:
                # rcl's error state is per thread: read it and clear it, as rclpy does, or the next error on this
                # thread is reported as overwriting it.
                reason = self._rcl.error_string().str.decode(errors="replace")
                self._rcl.reset_error()
                raise RuntimeError(f"Failed to publish on {self.publisher.topic_name}: {reason}")
