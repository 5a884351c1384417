"""``sensor_msgs/CompressedImage`` (PNG, JPEG) <-> NumPy, via OpenCV.

Accepted ``format`` strings: plain ``png`` / ``jpeg`` / ``jpg``, and image_transport's
``"<encoding>; png compressed <target>"`` / ``"<encoding>; jpeg compressed <target>"``. The
compressed payload is always in OpenCV's channel order (image_transport compresses color images
as bgr8), so color images are converted BGR -> RGB: results have the same shapes and dtypes as
``image_to_numpy`` ((H, W, 3) uint8 RGB, (H, W) uint8 or uint16). PNG is lossless: use it for masks.
``compressedDepth`` payloads (an extra header before the PNG) are rejected.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from msg_adapters.buffers import bytes_view, to_byte_array
from msg_adapters.errors import AdapterError
from msg_adapters.stamps import make_header


def _codec(fmt: str) -> str:
    text = fmt.lower()
    if "compresseddepth" in text.replace(" ", ""):
        raise AdapterError(f"CompressedImage: format {fmt!r} (compressedDepth) is not supported")
    tokens = text.replace(";", " ").split()
    if "png" in tokens:
        return "png"
    if "jpeg" in tokens or "jpg" in tokens:
        return "jpeg"
    raise AdapterError(f"CompressedImage: unsupported format {fmt!r}; expected png or jpeg")


def compressed_image_to_numpy(msg: Any) -> np.ndarray:
    """Decoded pixels: (H, W, 3) uint8 RGB for color, (H, W) uint8 / uint16 for gray."""
    _codec(str(msg.format))
    data = bytes_view(msg.data, "CompressedImage.data")
    if data.size == 0:
        raise AdapterError("CompressedImage: data is empty")
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

    codec = _codec(fmt)
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
