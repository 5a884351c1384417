"""Decompression bombs against the live node (issue 9, case 5): PNG / JPEG whose headers promise huge
images are refused from their header, before decoding, and the node's peak RSS stays below twice its
steady state (a 0.9 MB PNG of 30000 x 30000 took it to 12.9 GB and stalled ingestion for 40 s)."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

import msg_adapters as ma
from monovoc_ros.nodes.keyframe_publisher import keyframe_messages
from tests.node_scene import running_mapper, scene_messages, small_scene

pytestmark = pytest.mark.ros

S = 1_000_000_000


def png_bomb(width: int, height: int, color_type: int = 0) -> bytes:
    """A valid PNG of zeros whose IHDR says width x height (~1000:1): one deflate block of rows, ended by a full
    flush so that the same bytes are valid again, repeated."""
    row = bytes(1 + width * {0: 1, 2: 3}[color_type])  # filter byte + pixels
    rows_per_block = max(1, (1 << 22) // len(row))
    blocks, rest = divmod(height, rows_per_block)
    block = row * rows_per_block
    head = zlib.compressobj(9, zlib.DEFLATED, -15)
    piece = head.compress(block) + head.flush(zlib.Z_FULL_FLUSH)
    tail = zlib.compressobj(9, zlib.DEFLATED, -15)
    end = tail.compress(row * rest) + tail.flush(zlib.Z_FINISH)
    adler = 1
    for _ in range(blocks):
        adler = zlib.adler32(block, adler)
    adler = zlib.adler32(row * rest, adler)
    idat = b"\x78\xda" + piece * blocks + end + struct.pack(">I", adler)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, color_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def jpeg_bomb(width: int, height: int) -> bytes:
    """A real 16 x 16 JPEG whose frame header (SOF0) is patched to say width x height."""
    ok, buf = cv2.imencode(".jpg", np.zeros((16, 16, 3), np.uint8))
    assert ok
    data = bytearray(buf.tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5 : sof + 9] = struct.pack(">HH", height, width)
    return bytes(data)


def _kib(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise AssertionError(f"no {key} in /proc/{pid}/status")


def test_bombs_are_refused_before_decoding(tmp_path):
    scene, messages = small_scene(), scene_messages()
    assert png_bomb(3000, 100, 2) and cv2.imdecode(np.frombuffer(png_bomb(300, 20, 2), np.uint8), -1).shape == (
        20,
        300,
        3,
    )
    h, w = scene.keyframe(0).mask.shape[:2]
    bombs = [  # (role, payload, counter): camera_info is known, so most disagree with it
        ("mask", png_bomb(30000, 30000), "size_mismatch"),  # 0.9 MB -> 900 MB
        ("mask", png_bomb(30000, 30000, 2), "size_mismatch"),  # 2.6 MB -> 2.7 GB RGB
        ("image", jpeg_bomb(30000, 30000), "size_mismatch"),
        ("mask", png_bomb(12000, 12000), "size_mismatch"),
        ("mask", png_bomb(16000, round(16000 * h / w), 2), "bad_mask"),  # the right aspect ratio, 766 MB
        ("image", png_bomb(16000, 16000, 2), "size_mismatch"),
    ]
    expected: dict[str, int] = {}
    for _, _, counter in bombs:
        expected[counter] = expected.get(counter, 0) + 1
    params = {"publish_rate_hz": 0.0, "diagnostics_period_s": 0.2}
    with running_mapper(tmp_path, params, save_map=False) as run:
        run.publisher.publish_map(scene.gaussians)
        for msgs in messages[:4]:
            run.publisher.publish_messages(msgs)
        run.diagnostics.wait_for(
            lambda v: v["keyframes_processed"] == "4" and v["queue_length"] == "0", 30.0, process=run.node
        )
        steady, peak_before = _kib(run.node.pid, "VmRSS"), _kib(run.node.pid, "VmHWM")
        last = max(ma.header_stamp_ns(m["mask"]) for m in messages[:4])
        for k, (role, payload, _) in enumerate(bombs):
            msgs = keyframe_messages(scene.keyframe(4), stamp_ns=last + (k + 1) * S // 10)
            msgs[role].data = payload
            msgs[role].format = "png" if payload.startswith(b"\x89PNG") else "jpeg"
            run.publisher.publish_messages(msgs)
        # A good keyframe after the bombs is integrated: nothing stalled.
        run.publisher.publish_messages(keyframe_messages(scene.keyframe(5), stamp_ns=last + S))
        done = run.diagnostics.wait_for(
            lambda v: (
                v["keyframes_processed"] == "5" and all(v[f"rejected.{c}"] == str(n) for c, n in expected.items())
            ),
            30.0,
            process=run.node,
        )
        peak = _kib(run.node.pid, "VmHWM")
        run.node.check_running()
    print(f"steady RSS {steady / 1024:.0f} MiB, peak before {peak_before / 1024:.0f} MiB, after {peak / 1024:.0f} MiB")
    assert peak < 2 * steady, (steady, peak)
    assert peak - peak_before < 128 * 1024, (peak_before, peak)  # the smallest bomb alone decodes to 144 MB
    assert done["keyframes_received"] == "5"
