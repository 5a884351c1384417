"""Bag throughput: reading, offline keyframes, and replay into a live subscriber process on loopback.

    scripts/with_env.sh python benchmarks/bench_replay.py [--bag bags/synthetic_room.mcap] [--timed]

Prints one JSON object:
- ``read``: iterating every raw message (``iter_messages``), seconds and MB/s of CDR;
- ``bag_events``: decoding + KeyframeAssembler for every keyframe (no ROS graph), ms per keyframe;
- ``replay_fast``: ``replay(fast=True)`` in this process into ``monovoc record`` in another process
  (reliable, waits for acknowledgements): seconds from the first publish to the last acknowledgement,
  messages/s and MB/s, and whether the recording holds every message;
- with ``--timed``: ``replay(rate=1)``: wall seconds against the bag's duration, and the worst lateness
  behind the recorded schedule.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# The benchmark runs from a checkout; make the package importable without installing it.
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from monovoc_ros.bags import bag_events, bag_info, iter_messages  # noqa: E402
from monovoc_ros.bags.bundled import SYNTHETIC_BAG, bundled_bag  # noqa: E402
from monovoc_ros.core.keyframe import Keyframe  # noqa: E402


def bench_read(bag: Path) -> dict:
    start = time.perf_counter()
    n = size = 0
    for message in iter_messages(bag):
        n += 1
        size += len(message.data)
    seconds = time.perf_counter() - start
    return {
        "messages": n,
        "mb": round(size / 1e6, 2),
        "seconds": round(seconds, 3),
        "mb_per_s": round(size / 1e6 / seconds),
    }


def bench_events(bag: Path) -> dict:
    start = time.perf_counter()
    keyframes = sum(isinstance(e, Keyframe) for e in bag_events(bag))
    seconds = time.perf_counter() - start
    return {
        "keyframes": keyframes,
        "seconds": round(seconds, 3),
        "ms_per_keyframe": round(1e3 * seconds / keyframes, 2),
    }


def bench_replay(bag: Path, tmp: Path, *, fast: bool) -> dict:
    from monovoc_ros.bags import replay

    info = bag_info(bag)
    out = tmp / ("fast.mcap" if fast else "timed.mcap")
    command = [sys.executable, "-m", "monovoc_ros.cli", "record", "-o", str(out), *info.topics]
    command += ["--count", str(info.message_count), "--log-time", "header"]
    log = open(tmp / "record.out", "wb")
    recorder = subprocess.Popen(command, cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while b"recording" not in (tmp / "record.out").read_bytes():
            if time.monotonic() > deadline or recorder.poll() is not None:
                raise RuntimeError((tmp / "record.out").read_text())
            time.sleep(0.05)
        summary = replay(bag, fast=fast, wait_subscribers=1, wait_timeout=60.0)
        recorder.wait(60)
    finally:
        if recorder.poll() is None:
            recorder.kill()
        log.close()
    size = sum(len(m.data) for m in iter_messages(bag))
    result = {
        "messages": sum(summary.messages.values()),
        "seconds": round(summary.seconds, 3),
        "recorded_all": bag_info(out).message_count == info.message_count,
    }
    if fast:
        result["messages_per_s"] = round(result["messages"] / summary.seconds)
        result["mb_per_s"] = round(size / 1e6 / summary.seconds, 1)
    else:
        result["bag_duration_s"] = round(info.duration_s, 3)
        result["max_late_ms"] = round(summary.max_late_ms, 2)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bag", type=Path, default=bundled_bag(SYNTHETIC_BAG))
    parser.add_argument("--timed", action="store_true", help="also replay at the recorded rate")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        # Own domain and log folder, loopback only (the replay here and the recorder child share them).
        os.environ.update(
            ROS_DOMAIN_ID=str(random.SystemRandom().randint(1, 232)),
            ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
            ROS_LOG_DIR=str(Path(tmp) / "ros_log"),
            PYTHONPATH=str(REPO) + (os.pathsep + os.environ["PYTHONPATH"] if os.environ.get("PYTHONPATH") else ""),
        )
        info = bag_info(args.bag)
        result = {
            "bag": str(args.bag),
            "size_mb": round(info.size_bytes / 1e6, 2),
            "topics": {t.name: t.count for t in info.topics.values()},
            "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
            "read": bench_read(args.bag),
            "bag_events": bench_events(args.bag),
            "replay_fast": bench_replay(args.bag, Path(tmp), fast=True),
        }
        if args.timed:
            result["replay_rate_1"] = bench_replay(args.bag, Path(tmp), fast=False)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
