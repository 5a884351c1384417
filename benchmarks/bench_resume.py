"""Resuming a long session (issue 24): a snapshot whose keyframe log holds N keyframes, loaded as the node's
`resume: true` loads it. Prints one JSON object.

The log's entries are what a day of mapping leaves: 616x344 masks of a few segments (zstd, ~4 KB each, as
the live log stores them), poses along a path, one camera, segment names. The default 256 MiB log holds
~62k of them.

    python benchmarks/bench_resume.py                 # 60k keyframes
    python benchmarks/bench_resume.py --keyframes 4000
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from monovoc_ros.core.follow.keyframe_log import KeyframeLog, LoggedKeyframe, encode_mask  # noqa: E402
from monovoc_ros.core.map.camera import Intrinsics  # noqa: E402
from monovoc_ros.core.map_store import load_snapshot, save_snapshot  # noqa: E402
from monovoc_ros.core.mapping import SemanticMapper  # noqa: E402
from monovoc_ros.core.segments.segment_labels import SegmentLabel  # noqa: E402
from monovoc_ros.core.warm_up import warm_up_scene  # noqa: E402

CAMERA = Intrinsics(600.0, 600.0, 307.5, 171.5, 616, 344)


def masks(count: int, rng: np.random.Generator) -> list[bytes]:
    """`count` distinct masks of a few rectangles on white (a segmenter's output on a room)."""
    out = []
    for _ in range(count):
        mask = np.full((CAMERA.height, CAMERA.width, 3), 255, np.uint8)
        for _ in range(int(rng.integers(3, 9))):
            y, x = int(rng.integers(0, 300)), int(rng.integers(0, 560))
            mask[y : y + int(rng.integers(20, 120)), x : x + int(rng.integers(20, 200))] = rng.integers(0, 255, 3)
        out.append(encode_mask(mask))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--keyframes", type=int, default=60_000)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    gaussians, _ = warm_up_scene()
    mapper = SemanticMapper(gaussians)
    log = KeyframeLog()
    blobs = masks(64, rng)
    segments = (SegmentLabel(0xC81E1E, "chair", 0.8), SegmentLabel(0x1E1EC8, "table", 0.6))
    for k in range(args.keyframes):
        pose = np.eye(4)
        pose[:3, 3] = (0.01 * k, np.sin(k / 100), 0.0)
        log.append(LoggedKeyframe(k, (k + 1) * 200_000_000, pose, CAMERA, blobs[k % len(blobs)], segments))
    mapper.keyframe_log = log
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        info = save_snapshot(mapper, tmp, export_cloud=False)
        save_s = time.perf_counter() - t0
        log_bytes = (info.path / "keyframe_log.npz").stat().st_size
        t0 = time.perf_counter()
        resumed = load_snapshot(tmp)
        load_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        KeyframeLog.load(info.path / "keyframe_log.npz")
        log_s = time.perf_counter() - t0
    assert len(resumed.keyframe_log) == args.keyframes
    print(
        json.dumps(
            {
                "keyframes": args.keyframes,
                "keyframe_log_mb": round(log_bytes / 2**20, 1),
                "save_s": round(save_s, 2),
                "resume_s": round(load_s, 2),
                "keyframe_log_load_s": round(log_s, 2),
                "target_resume_s": 10.0,
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
