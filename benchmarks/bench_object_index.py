"""The object index's refresh after each keyframe at robot scale, printed as JSON.

    python benchmarks/bench_object_index.py [--gaussians 1000000] [--keyframes 40]

office_0's map tiled to `--gaussians` (benchmarks/bench_robot_scale.py's TiledSequence, its keyframes replayed in
every tile) is mapped keyframe by keyframe in process; after each one the index observes the keyframe and
refreshes as the live node's indexing thread does (ConSE, at most LIVE_OBJECTS_PER_REFRESH objects embedded per
call), without map updates (every refresh after the first one of the map: the incremental path). Reports the
milliseconds of a refresh (mean, median, max), the process CPU milliseconds per refresh, and what the refreshes
did (views and descriptions embedded, objects listed). A refresh's time includes the result's object geometry,
which the live node's publication computes first (shared). The live node runs this beside its worker on the
same two cores: every millisecond here is taken from keyframes, map updates and queries.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_robot_scale import REPLICA, TiledSequence

from monovoc_ros.core.evaluation.datasets import open_sequence
from monovoc_ros.core.mapping import SemanticMapper
from monovoc_ros.objects.index import LIVE_OBJECTS_PER_REFRESH, IndexConfig, ObjectIndex, lazy_backend


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=1_000_000)
    parser.add_argument("--keyframes", type=int, default=40)
    args = parser.parse_args(argv)
    if args.keyframes < 1:
        parser.error("--keyframes must be at least 1")
    if not (REPLICA / "traj.txt").exists():
        print(f"{REPLICA} not present: nothing to measure", file=sys.stderr)
        return 1
    sequence = TiledSequence(open_sequence(str(REPLICA)), args.gaussians, args.keyframes, 2.0, args.keyframes + 1)
    mapper = SemanticMapper(sequence.load_gaussians())
    index = ObjectIndex(lazy_backend("conse"), IndexConfig())
    _ = index.backend  # the models loaded before the first refresh, as the node does
    walls, views, texts = [], 0, 0
    cpu = 0.0
    for i in range(args.keyframes):
        keyframe = sequence.keyframe(i)
        mapper.integrate(keyframe)
        start, cpu0 = time.perf_counter(), time.process_time()
        index.keyframe_listener(keyframe, mapper)
        report = index.refresh(mapper, max_objects=LIVE_OBJECTS_PER_REFRESH)
        walls.append(time.perf_counter() - start)
        cpu += time.process_time() - cpu0
        views += report.embedded_views
        texts += report.embedded_descriptions
    out = {
        "gaussians": args.gaussians,
        "keyframes": args.keyframes,
        "refresh_ms_mean": round(1e3 * statistics.mean(walls), 1),
        "refresh_ms_median": round(1e3 * statistics.median(walls), 1),
        "refresh_ms_max": round(1e3 * max(walls), 1),
        "refresh_cpu_ms_mean": round(1e3 * cpu / args.keyframes, 1),
        "views_embedded": views,
        "descriptions_embedded": texts,
        "objects_listed": report.listed,
    }
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
