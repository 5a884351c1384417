"""``sensor_msgs/CompressedImage`` (PNG, JPEG) <-> NumPy, via OpenCV.

Accepted ``format`` strings: plain ``png`` / ``jpeg`` / ``jpg``, and image_transport's
``"<encoding>; png compressed <target>"`` / ``"<encoding>; jpeg compressed <target>"``. The
compressed payload is always in OpenCV's channel order (image_transport compresses color images
as bgr8), so color images are converted BGR -> RGB: results have the same shapes and dtypes as
``image_to_numpy`` ((H, W, 3) uint8 RGB, (H, W) uint8 or uint16). PNG is lossless: use it for masks.
``compressedDepth`` payloads (an extra header before the PNG) are rejected.

Decompression bombs: the pixel dimensions are read from the PNG / JPEG header first
(``compressed_image_header``), and ``compressed_image_to_numpy(msg, max_pixels=...)`` refuses an image
larger than ``max_pixels`` (always: more than MAX_SIDE pixels per side) before anything is decoded. A
0.9 MB PNG that decodes to 30000 x 30000 took the node to 12.9 GB before this check.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from msg_adapters.buffers import bytes_view, to_byte_array
from msg_adapters.camera_info import MAX_IMAGE_SIDE as MAX_SIDE  # one plausibility bound for cameras and images
from msg_adapters.errors import AdapterError
from msg_adapters.stamps import make_header

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}  # color type -> decoded channels (palette -> RGB)
# JPEG start-of-frame markers (SOF0..SOF15 without DHT C4, JPG C8, DAC CC)
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


@dataclass(frozen=True)
class ImageHeader:
    codec: str  # "png" | "jpeg"
    width: int
    height: int
    channels: int
    bit_depth: int


def compressed_image_header(data: bytes | np.ndarray, codec: str) -> ImageHeader:
    """Dimensions, channels and bit depth from a PNG (IHDR) or JPEG (SOF) header, without decoding."""
    head = bytes(memoryview(data)[: 1 << 16]) if codec == "jpeg" else bytes(memoryview(data)[:33])
    if codec == "png":
        if len(head) < 33 or head[:8] != _PNG_MAGIC or head[12:16] != b"IHDR":
            raise AdapterError("CompressedImage: not a PNG (no PNG signature and IHDR header)")
        width, height = struct.unpack(">II", head[16:24])
        depth, color = head[24], head[25]
        if color not in _PNG_CHANNELS:
            raise AdapterError(f"CompressedImage: PNG color type {color} is invalid")
        return ImageHeader("png", width, height, _PNG_CHANNELS[color], 8 if color == 3 else depth)
    if head[:2] != b"\xff\xd8":
        raise AdapterError("CompressedImage: not a JPEG (no SOI marker)")
    pos = 2
    while pos + 4 <= len(head):
        if head[pos] != 0xFF:
            raise AdapterError(f"CompressedImage: malformed JPEG marker at byte {pos}")
        marker = head[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
            pos += 2
            continue
        (length,) = struct.unpack(">H", head[pos + 2 : pos + 4])
        if marker in _JPEG_SOF:
            if pos + 10 > len(head):
                break
            depth = head[pos + 4]
            height, width = struct.unpack(">HH", head[pos + 5 : pos + 9])
            return ImageHeader("jpeg", width, height, head[pos + 9], depth)
        if marker == 0xDA or length < 2:  # scan data before any frame header
            break
        pos += 2 + length
    raise AdapterError("CompressedImage: JPEG without a frame header (SOF) in its first 64 kB")


def format_codec(fmt: str) -> str:
    """'png' or 'jpeg' for a CompressedImage format string (AdapterError otherwise)."""
    text = fmt.lower()
    if "compresseddepth" in text.replace(" ", ""):
        raise AdapterError(f"CompressedImage: format {fmt!r} (compressedDepth) is not supported")
    tokens = text.replace(";", " ").split()
    if "png" in tokens:
        return "png"
    if "jpeg" in tokens or "jpg" in tokens:
        return "jpeg"
    raise AdapterError(f"CompressedImage: unsupported format {fmt!r}; expected png or jpeg")


def compressed_image_to_numpy(msg: Any, max_pixels: int | None = None) -> np.ndarray:
    """Decoded pixels: (H, W, 3) uint8 RGB for color, (H, W) uint8 / uint16 for gray.

    The header's size is checked first: more than MAX_SIDE per side, or more than ``max_pixels``
    pixels, raises AdapterError before decoding.
    """
    codec = format_codec(str(msg.format))
    data = bytes_view(msg.data, "CompressedImage.data")
    if data.size == 0:
        raise AdapterError("CompressedImage: data is empty")
    header = compressed_image_header(data, codec)
    if not (0 < header.width <= MAX_SIDE and 0 < header.height <= MAX_SIDE):
        raise AdapterError(
            f"CompressedImage: {codec} header says {header.width}x{header.height}, beyond {MAX_SIDE} pixels per side "
            "(not decoded)"
        )
    if max_pixels is not None and header.width * header.height > max_pixels:
        raise AdapterError(
            f"CompressedImage: {codec} header says {header.width}x{header.height}, more than the {max_pixels} "
            "pixels allowed here (not decoded)"
        )
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise AdapterError(f"CompressedImage: OpenCV cannot decode {data.size} bytes as {msg.format!r}")
    if image.ndim == 2:
        return image
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    if image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    raise AdapterError(f"CompressedImage: decoded image has unsupported shape {image.shape}")


def numpy_to_compressed_image(
    array: np.ndarray,
    fmt: str = "png",
    *,
    frame_id: str = "",
    stamp: Any = 0,
    jpeg_quality: int = 95,
    png_level: int = 3,
):
    """A ``sensor_msgs.msg.CompressedImage`` with an image_transport-style ``format`` string.

    ``array``: (H, W, 3) uint8 RGB, (H, W) uint8, or (H, W) uint16 (PNG only).
    """
    from sensor_msgs.msg import CompressedImage

    codec = format_codec(fmt)
    array = np.asarray(array)
    if array.ndim == 3 and array.shape[2] == 3 and array.dtype == np.uint8:
        encoding, target, pixels = "rgb8", "bgr8", cv2.cvtColor(np.ascontiguousarray(array), cv2.COLOR_RGB2BGR)
    elif array.ndim == 2 and array.dtype == np.uint8:
        encoding, target, pixels = "mono8", "", array
    elif array.ndim == 2 and array.dtype == np.uint16 and codec == "png":
        encoding, target, pixels = "mono16", "", array
    else:
        raise AdapterError(
            f"CompressedImage: cannot encode {array.dtype} array of shape {array.shape} as {codec} "
            "(expected (H, W, 3) uint8 RGB, (H, W) uint8, or (H, W) uint16 for png)"
        )
    if array.shape[0] == 0 or array.shape[1] == 0:
        raise AdapterError(f"CompressedImage: empty image of shape {array.shape}")
    if codec == "png":
        ok, buf = cv2.imencode(".png", pixels, [cv2.IMWRITE_PNG_COMPRESSION, int(png_level)])
    else:
        ok, buf = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:
        raise AdapterError(f"CompressedImage: OpenCV failed to encode {codec}")
    msg = CompressedImage(header=make_header(frame_id, stamp), format=f"{encoding}; {codec} compressed {target}")
    msg.data = to_byte_array(buf)
    return msg
