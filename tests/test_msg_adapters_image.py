"""sensor_msgs/Image and CompressedImage <-> NumPy."""

from __future__ import annotations

import array

import cv2
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CompressedImage, Image

from msg_adapters import (
    AdapterError,
    compressed_image_to_numpy,
    image_to_numpy,
    numpy_to_compressed_image,
    numpy_to_image,
    time_to_ns,
)

RNG = np.random.default_rng(7)
RGB = RNG.integers(0, 256, (37, 53, 3), dtype=np.uint8)
MONO8 = RNG.integers(0, 256, (37, 53), dtype=np.uint8)
MONO16 = RNG.integers(0, 65536, (37, 53), dtype=np.uint16)
DEPTH = RNG.uniform(0.1, 9.0, (37, 53)).astype(np.float32)


def _wire(msg, cls):
    return deserialize_message(serialize_message(msg), cls)


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8"])
def test_color_round_trip_through_serialization(encoding: str) -> None:
    msg = numpy_to_image(RGB, encoding, frame_id="cam", stamp=1_500_000_000_123)
    assert (msg.width, msg.height, msg.encoding, msg.header.frame_id) == (53, 37, encoding, "cam")
    back = _wire(msg, Image)
    assert time_to_ns(back.header.stamp) == 1_500_000_000_123
    out = image_to_numpy(back)
    assert out.dtype == np.uint8 and out.shape == (37, 53, 3)
    np.testing.assert_array_equal(out, RGB)


@pytest.mark.parametrize(
    ("encoding", "pixels"), [("mono8", MONO8), ("8UC1", MONO8), ("mono16", MONO16), ("16UC1", MONO16), ("32FC1", DEPTH)]
)
def test_single_channel_round_trip(encoding: str, pixels: np.ndarray) -> None:
    out = image_to_numpy(_wire(numpy_to_image(pixels, encoding), Image))
    assert out.dtype == pixels.dtype and out.shape == pixels.shape
    np.testing.assert_array_equal(out, pixels)


def test_channel_order_in_the_message_bytes() -> None:
    red = np.zeros((2, 2, 3), np.uint8)
    red[..., 0] = 200
    assert bytes(numpy_to_image(red, "bgr8").data[:3]) == b"\x00\x00\xc8"
    assert bytes(numpy_to_image(red, "rgba8").data[:4]) == b"\xc8\x00\x00\xff"
    rgba = np.dstack([red, np.full((2, 2), 7, np.uint8)])
    assert bytes(numpy_to_image(rgba, "bgra8").data[:4]) == b"\x00\x00\xc8\x07"
    # Hand-written BGR bytes come out as RGB.
    msg = Image(height=1, width=2, encoding="bgr8", step=6, data=[1, 2, 3, 4, 5, 6])
    np.testing.assert_array_equal(image_to_numpy(msg), [[[3, 2, 1], [6, 5, 4]]])


@pytest.mark.parametrize("encoding", ["rgb8", "bgra8", "mono16", "32FC1"])
def test_step_padding_is_skipped(encoding: str) -> None:
    pixels = {"rgb8": RGB, "bgra8": RGB, "mono16": MONO16, "32FC1": DEPTH}[encoding]
    tight = numpy_to_image(pixels, encoding)
    pad = 13
    rows = np.frombuffer(bytes(tight.data), np.uint8).reshape(tight.height, tight.step)
    padded = np.concatenate([rows, RNG.integers(0, 256, (tight.height, pad), dtype=np.uint8)], axis=1)
    msg = Image(height=tight.height, width=tight.width, encoding=encoding, step=tight.step + pad)
    msg.data = array.array("B", padded.reshape(-1)[:-pad].tobytes())  # the last row needs no padding
    np.testing.assert_array_equal(image_to_numpy(msg), pixels)


def test_big_endian_mono16_and_float() -> None:
    for encoding, pixels, dtype in (("mono16", MONO16, ">u2"), ("32FC1", DEPTH, ">f4")):
        msg = Image(height=37, width=53, encoding=encoding, is_bigendian=1, step=53 * 2 * (1 + (dtype[-1] == "4")))
        msg.data = array.array("B", pixels.astype(dtype).tobytes())
        out = image_to_numpy(msg)
        assert out.dtype == pixels.dtype and out.dtype.isnative
        np.testing.assert_array_equal(out, pixels)


@pytest.mark.parametrize("kind", ["bytes", "list", "ndarray", "strided"])
def test_payload_types_from_bag_decoders(kind: str) -> None:
    raw = numpy_to_image(RGB, "rgb8")
    flat = np.frombuffer(bytes(raw.data), np.uint8)
    data = {"bytes": bytes(raw.data), "list": list(raw.data), "ndarray": flat, "strided": np.repeat(flat, 2)[::2]}[kind]

    class Decoded:  # what a bag decoder hands out: plain attributes
        height, width, encoding, is_bigendian, step = raw.height, raw.width, "rgb8", 0, raw.step

    Decoded.data = data
    out = image_to_numpy(Decoded)
    np.testing.assert_array_equal(out, RGB)
    out[0, 0] = 0  # a fresh writable array, never a view of the message
    np.testing.assert_array_equal(image_to_numpy(raw), RGB)


def test_image_rejects_bad_input() -> None:
    good = numpy_to_image(RGB, "rgb8")

    def variant(**fields) -> Image:
        msg = Image(height=good.height, width=good.width, encoding=good.encoding, step=good.step, data=good.data)
        for k, v in fields.items():
            setattr(msg, k, v)
        return msg

    with pytest.raises(AdapterError, match="unsupported encoding 'yuv422'"):
        image_to_numpy(variant(encoding="yuv422"))
    with pytest.raises(AdapterError, match="step 100 is smaller than width"):
        image_to_numpy(variant(step=100))
    with pytest.raises(AdapterError, match="data has 5880 bytes"):
        image_to_numpy(variant(data=array.array("B", bytes(good.data)[:-3])))
    with pytest.raises(AdapterError, match="empty image"):
        image_to_numpy(variant(height=0))
    with pytest.raises(AdapterError, match="needs uint8 pixels, got uint16"):
        numpy_to_image(MONO16, "mono8")
    with pytest.raises(AdapterError, match=r"needs an \(H, W, 3\) RGB array"):
        numpy_to_image(MONO8, "rgb8")
    with pytest.raises(AdapterError, match="unsupported encoding"):
        numpy_to_image(RGB, "yuv422")
    with pytest.raises(ValueError):  # AdapterError is a ValueError
        image_to_numpy(variant(step=1))


@pytest.mark.parametrize(("pixels", "fmt"), [(RGB, "png"), (MONO8, "png"), (MONO16, "png"), (MONO8, "jpeg")])
def test_compressed_round_trip(pixels: np.ndarray, fmt: str) -> None:
    msg = _wire(numpy_to_compressed_image(pixels, fmt, frame_id="cam", stamp=5), CompressedImage)
    assert fmt in msg.format and msg.header.frame_id == "cam"
    out = compressed_image_to_numpy(msg)
    assert out.dtype == pixels.dtype and out.shape == pixels.shape
    if fmt == "png":
        np.testing.assert_array_equal(out, pixels)  # lossless: masks survive exactly
    else:
        assert np.abs(out.astype(int) - pixels).mean() < 20


def test_compressed_color_matches_image_transport_conventions() -> None:
    smooth = np.zeros((32, 48, 3), np.uint8)
    smooth[:, :24] = (220, 30, 10)  # red left half, in RGB
    for fmt in ("png", "jpeg"):
        msg = numpy_to_compressed_image(smooth, fmt)
        assert msg.format == f"rgb8; {fmt} compressed bgr8"
        # The payload is BGR, as image_transport and cv2.imdecode expect.
        bgr = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_COLOR)
        assert abs(int(bgr[5, 5, 2]) - 220) <= 3 and abs(int(bgr[5, 5, 0]) - 10) <= 3
        rgb = compressed_image_to_numpy(msg)
        assert abs(int(rgb[5, 5, 0]) - 220) <= 3 and abs(int(rgb[5, 5, 2]) - 10) <= 3
    assert numpy_to_compressed_image(MONO8, "png").format == "mono8; png compressed "
    # Formats written by other publishers.
    ok, buf = cv2.imencode(".png", cv2.cvtColor(RGB, cv2.COLOR_RGB2BGR))
    for fmt in ("png", "PNG", "bgr8; png compressed bgr8", "rgb8; png compressed bgr8"):
        msg = CompressedImage(format=fmt, data=array.array("B", buf.tobytes()))
        np.testing.assert_array_equal(compressed_image_to_numpy(msg), RGB)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.dstack([RGB, MONO8]), cv2.COLOR_RGBA2BGRA))
    np.testing.assert_array_equal(compressed_image_to_numpy(CompressedImage(format="png", data=buf.tobytes())), RGB)


def test_compressed_rejects_bad_input() -> None:
    png = numpy_to_compressed_image(RGB, "png")
    with pytest.raises(AdapterError, match="unsupported format 'tiff'"):
        compressed_image_to_numpy(CompressedImage(format="tiff", data=png.data))
    with pytest.raises(AdapterError, match="compressedDepth"):
        compressed_image_to_numpy(CompressedImage(format="16UC1; compressedDepth png", data=png.data))
    with pytest.raises(AdapterError, match="not a PNG"):
        compressed_image_to_numpy(CompressedImage(format="png", data=b"not a png at all"))
    with pytest.raises(AdapterError, match="cannot decode"):  # a valid header, then nothing
        compressed_image_to_numpy(CompressedImage(format="png", data=bytes(png.data)[:40]))
    with pytest.raises(AdapterError, match="data is empty"):
        compressed_image_to_numpy(CompressedImage(format="jpeg"))
    with pytest.raises(AdapterError, match="cannot encode uint16"):
        numpy_to_compressed_image(MONO16, "jpeg")
    with pytest.raises(AdapterError, match="cannot encode float32"):
        numpy_to_compressed_image(DEPTH, "png")
    with pytest.raises(AdapterError, match="unsupported format"):
        numpy_to_compressed_image(RGB, "webp")
