"""``sensor_msgs/Image`` <-> NumPy.

Color encodings (rgb8, bgr8, rgba8, bgra8) always come out as (H, W, 3) uint8 **RGB** (alpha
dropped); mono8 / 8UC1 as (H, W) uint8, mono16 / 16UC1 as (H, W) uint16, 32FC1 as (H, W) float32.
Row padding (``step`` > width * pixel size) and ``is_bigendian`` are honoured. The result is always
a fresh C-contiguous array: it never aliases the message buffer.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from msg_adapters.buffers import bytes_view, to_byte_array
from msg_adapters.errors import AdapterError
from msg_adapters.stamps import make_header

# encoding -> (channels, dtype, channel order of the stored pixels; None for single-channel)
_ENCODINGS: dict[str, tuple[int, np.dtype, str | None]] = {
    "rgb8": (3, np.dtype(np.uint8), "rgb"),
    "bgr8": (3, np.dtype(np.uint8), "bgr"),
    "rgba8": (4, np.dtype(np.uint8), "rgba"),
    "bgra8": (4, np.dtype(np.uint8), "bgra"),
    "mono8": (1, np.dtype(np.uint8), None),
    "8UC1": (1, np.dtype(np.uint8), None),
    "mono16": (1, np.dtype(np.uint16), None),
    "16UC1": (1, np.dtype(np.uint16), None),
    "32FC1": (1, np.dtype(np.float32), None),
}
_TO_RGB = {"rgb": [0, 1, 2], "bgr": [2, 1, 0], "rgba": [0, 1, 2], "bgra": [2, 1, 0]}

SUPPORTED_ENCODINGS = tuple(_ENCODINGS)


def image_to_numpy(msg: Any) -> np.ndarray:
    """Pixels of a ``sensor_msgs/Image`` (see the module docstring for shapes and dtypes)."""
    encoding = str(msg.encoding)
    if encoding not in _ENCODINGS:
        raise AdapterError(f"Image: unsupported encoding {encoding!r}; supported: {', '.join(_ENCODINGS)}")
    channels, dtype, order = _ENCODINGS[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height <= 0 or width <= 0:
        raise AdapterError(f"Image: empty image {width}x{height}")
    row_bytes = width * channels * dtype.itemsize
    if step < row_bytes:
        raise AdapterError(f"Image: step {step} is smaller than width * pixel size = {row_bytes} ({encoding})")
    data = bytes_view(msg.data, "Image.data")
    # The last row needs no padding after it.
    needed = step * (height - 1) + row_bytes
    if data.size < needed:
        raise AdapterError(
            f"Image: data has {data.size} bytes, {width}x{height} {encoding} with step {step} needs {needed}"
        )
    rows = np.lib.stride_tricks.as_strided(data, shape=(height, row_bytes), strides=(step, 1), writeable=False)
    big = bool(msg.is_bigendian)
    pixels = rows.view(dtype.newbyteorder(">" if big else "<")) if dtype.itemsize > 1 else rows
    pixels = pixels.reshape(height, width, channels)
    if order is None:
        return np.ascontiguousarray(pixels[:, :, 0], dtype=dtype)
    return np.ascontiguousarray(pixels[:, :, _TO_RGB[order]])


def numpy_to_image(array: np.ndarray, encoding: str = "rgb8", *, frame_id: str = "", stamp: Any = 0):
    """A ``sensor_msgs.msg.Image`` (little endian, no padding) from an array.

    Color encodings take (H, W, 3) RGB uint8 (or (H, W, 4) RGBA; alpha 255 is added when missing);
    single-channel encodings take (H, W) arrays of their dtype.
    """
    from sensor_msgs.msg import Image

    if encoding not in _ENCODINGS:
        raise AdapterError(f"Image: unsupported encoding {encoding!r}; supported: {', '.join(_ENCODINGS)}")
    channels, dtype, order = _ENCODINGS[encoding]
    array = np.asarray(array)
    if array.dtype != dtype:
        raise AdapterError(f"Image: encoding {encoding} needs {dtype} pixels, got {array.dtype}")
    if order is None:
        if array.ndim != 2:
            raise AdapterError(f"Image: encoding {encoding} needs an (H, W) array, got shape {array.shape}")
        pixels = array.astype(dtype.newbyteorder("<"), copy=False)
    else:
        if array.ndim != 3 or array.shape[2] not in (3, 4):
            raise AdapterError(f"Image: encoding {encoding} needs an (H, W, 3) RGB array, got shape {array.shape}")
        rgb = array[:, :, :3]
        pixels = rgb[:, :, ::-1] if order.startswith("bgr") else rgb
        if channels == 4:
            alpha = array[:, :, 3:] if array.shape[2] == 4 else np.full(array.shape[:2] + (1,), 255, np.uint8)
            pixels = np.concatenate([pixels, alpha], axis=2)
    height, width = array.shape[:2]
    if height == 0 or width == 0:
        raise AdapterError(f"Image: empty image {width}x{height}")
    msg = Image(header=make_header(frame_id, stamp), height=height, width=width, encoding=encoding)
    msg.is_bigendian = 0
    msg.step = width * channels * dtype.itemsize
    msg.data = to_byte_array(pixels)
    return msg
