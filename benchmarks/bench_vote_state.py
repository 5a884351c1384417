"""Memory and speed of the bounded vote state at robot scale; prints one JSON object.

    python benchmarks/bench_vote_state.py [--gaussians 1000000] [--objects 500] [--slots 4]

A VoteState of N Gaussians receives keyframes of votes as the kernel produces them (each keyframe
sees a random 20% of the map; each Gaussian it sees votes for 1-3 of the objects, neighbours in id
as at object boundaries). Reports bytes per Gaussian, the process's peak RSS, the time to add a
keyframe, to label the Gaussians it touched and to label the whole map, and the snapshot file size.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from monovoc_ros.core.evidence.votes import VoteState  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=1_000_000)
    parser.add_argument("--objects", type=int, default=500)
    parser.add_argument("--slots", type=int, default=4)
    parser.add_argument("--keyframes", type=int, default=20)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    n = args.gaussians
    home = rng.integers(0, args.objects, n)  # each Gaussian's object
    state = VoteState.zeros(n, args.slots)
    rss_empty = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    add_ms, touched_ms = [], []
    for stamp in range(args.keyframes):
        rows = np.sort(rng.choice(n, n // 5, replace=False))
        objects = (home[rows, None] + np.arange(3)[None, :]) % args.objects
        votes = rng.random((rows.size, 3)) * (rng.random((rows.size, 3)) < [1.0, 0.3, 0.1])
        ids = (objects * 97 + 1).astype(np.uint32)  # distinct 24-bit ids
        other = rng.random(rows.size) * 0.01
        start = time.perf_counter()
        state.add(rows, ids, votes, other, stamp)
        add_ms.append(1e3 * (time.perf_counter() - start))
        start = time.perf_counter()
        state.labels(rows)
        touched_ms.append(1e3 * (time.perf_counter() - start))
    start = time.perf_counter()
    state.labels()
    full_ms = 1e3 * (time.perf_counter() - start)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "state.npz"
        state.save(path)
        file_mb = path.stat().st_size / 2**20
    report = {
        "gaussians": n,
        "objects": args.objects,
        "slots": args.slots,
        "bytes_per_gaussian": state.evidence_nbytes / n,
        "evidence_mb": round(state.evidence_nbytes / 2**20, 1),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "peak_rss_mb_after_allocation": round(rss_empty, 1),
        "objects_in_slots": int(np.unique(state.objects[state.votes > 0]).size),
        "add_keyframe_ms_p50": round(float(np.median(add_ms[1:])), 1),
        "label_touched_ms_p50": round(float(np.median(touched_ms[1:])), 1),
        "touched_per_keyframe": n // 5,
        "label_all_ms": round(full_ms, 1),
        "snapshot_mb": round(file_mb, 1),
    }
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
