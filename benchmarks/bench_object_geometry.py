"""Object geometry at robot scale (issue 25): prints one JSON object.

Labels from a real mapping (office_0's first keyframes; the synthetic room when office_0 is not here),
the map tiled to 200k / 1M / 2M Gaussians (each tile its own objects). Per size: the full computation,
the former implementation (``object_geometry_reference``) against the current one, and the update after
one keyframe (``object_geometry(previous=...)``: the next keyframe's labels in the first tile, what a
publication after a keyframe computes), each checked equal to the reference.

    python benchmarks/bench_object_geometry.py
    python benchmarks/bench_object_geometry.py --sizes 1000000 --keyframes 12
    python benchmarks/bench_object_geometry.py --sizes 1000000 --live 80   # a live node's publications
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench_map_churn import REPLICA, tiled  # noqa: E402

from monovoc_ros import offline  # noqa: E402
from monovoc_ros.core.evidence.palette import VOID_ID  # noqa: E402
from monovoc_ros.core.mapping import SemanticMapper  # noqa: E402
from monovoc_ros.core.object_geometry import ObjectGeometry, object_geometry, object_geometry_reference  # noqa: E402


def labellings(source: str, keyframes: int):
    """The map and its (object ids, confidence) after keyframes - 1 and after keyframes keyframes."""
    seq = offline.open_source(str(REPLICA) if source == "replica" else source)
    gmap = seq.load_gaussians()
    mapper = SemanticMapper(gmap)
    out = []
    for i in range(keyframes):
        mapper.integrate(seq.keyframe(i))
        if i >= keyframes - 2:
            result = mapper.result()
            out.append((result.object_ids.copy(), result.confidence.copy()))
    return gmap, out


def tiled_labels(
    ids: np.ndarray, conf: np.ndarray, objects: np.ndarray, n: int, tile: int
) -> tuple[np.ndarray, np.ndarray]:
    """The labels of a tiled map: tile t's copy of object objects[j] is object 1 + t * 4096 + j (void stays void)."""
    which = np.arange(n) // tile
    src = ids[np.arange(n) % tile]
    out = src.copy()
    real = src < VOID_ID
    out[real] = 1 + which[real] * 4096 + np.searchsorted(objects, src[real])
    return out.astype(np.uint32), conf[np.arange(n) % tile]


def same(a: ObjectGeometry, b: ObjectGeometry) -> bool:
    return np.array_equal(a.shape_ids, b.shape_ids) and all(
        (x.id, x.num_gaussians) == (y.id, y.num_gaussians)
        and all(np.array_equal(getattr(x, f), getattr(y, f)) for f in ("centroid", "bbox_min", "bbox_max"))
        for x, y in zip(a.objects, b.objects, strict=True)
    )


def best_ms(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return round(1e3 * min(times), 1), out


def row(gmap, before, after, n: int, repeats: int) -> dict:
    big, _ = tiled(gmap, n)
    tile = len(gmap)
    objects = np.union1d(before[0], after[0])
    ids0, conf0 = tiled_labels(*before, objects, n, tile)
    ids1, conf1 = tiled_labels(*after, objects, n, tile)
    ids1[tile:], conf1[tile:] = ids0[tile:], conf0[tile:]  # one keyframe: it sees the first tile only
    reference_ms, reference = best_ms(lambda: object_geometry_reference(big, ids1, conf1), max(1, repeats - 1))
    full_ms, full = best_ms(lambda: object_geometry(big, ids1, conf1), repeats)
    previous = object_geometry(big, ids0, conf0)
    update_ms, update = best_ms(lambda: object_geometry(big, ids1, conf1, previous=previous), repeats)
    changed = (ids0 != ids1) | ((conf0 >= 0.3) != (conf1 >= 0.3))
    touched = np.union1d(ids0[changed], ids1[changed])
    touched = touched[touched < VOID_ID]
    return {
        "gaussians": n,
        "objects": len(full.objects),
        "keyframe_changed_rows": int(changed.sum()),
        "keyframe_changed_objects": int(touched.size),
        "changed_objects_gaussians": int(np.isin(ids1, touched).sum()),
        "full_ms_reference": reference_ms,
        "full_ms": full_ms,
        "after_keyframe_ms": update_ms,
        "equal_to_reference": same(full, reference) and same(update, reference),
    }


def live_row(n: int, keyframes: int, every: int, update_every: int) -> dict:
    """The geometry of a live node's publications: office_0 tiled to n (bench_robot_scale.TiledSequence, keyframe k
    in tile k mod tiles, a map update without ids every `update_every` keyframes) mapped by a MappingSession, each
    `every` keyframes the result's geometry computed as a publication does (starting from the one before: most
    objects have changed by then). The last one is checked against the reference."""
    from bench_robot_scale import TiledSequence

    from monovoc_ros.core.evaluation.datasets import open_sequence
    from monovoc_ros.core.session import MappingSession

    sequence = TiledSequence(open_sequence(str(REPLICA)), n, keyframes, 10.0, update_every)
    session = MappingSession()
    session.add_map(sequence.load_gaussians())
    ms = []
    for i in range(keyframes):
        if i in sequence.updates:
            session.add_map(sequence.updates[i])
        session.add_keyframe(sequence.keyframe(i))
        session.integrate_next()
        if i % every == every - 1:
            mapper = session.mapper
            result = mapper.result()
            start = time.perf_counter()
            geometry = result.objects(mapper.gaussians)
            ms.append(1e3 * (time.perf_counter() - start))
    reference = object_geometry_reference(mapper.gaussians, result.object_ids, result.confidence)
    return {
        "gaussians": n,
        "publications": len(ms),
        "keyframes_between": every,
        "map_update_every": update_every,
        "objects": len(geometry.objects),
        "publication_ms_mean": round(float(np.mean(ms)), 1),
        "publication_ms_max": round(float(np.max(ms)), 1),
        "equal_to_reference": same(geometry, reference),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="200000,1000000,2000000")
    parser.add_argument("--keyframes", type=int, default=30, help="keyframes mapped (the last one is the update)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--live", type=int, default=0, metavar="KEYFRAMES",
        help="instead: a live node's publications over this many keyframes (office_0 tiled; see live_row)",
    )  # fmt: skip
    parser.add_argument("--publish-every", type=int, default=7, help="--live: keyframes between publications")
    parser.add_argument("--update-every", type=int, default=20, help="--live: keyframes between map updates")
    args = parser.parse_args()
    if args.live:
        if not (REPLICA / "traj.txt").exists():
            sys.exit(f"{REPLICA} not present: --live needs office_0")
        rows = [live_row(int(n), args.live, args.publish_every, args.update_every) for n in args.sizes.split(",")]
        print(json.dumps({"source": "replica", "live": rows}, indent=1))
        return
    source = "replica" if (REPLICA / "traj.txt").exists() else "synthetic"
    gmap, (before, after) = labellings(source, args.keyframes)
    out = {"source": source, "map_gaussians": len(gmap), "keyframes": args.keyframes, "rows": []}
    for n in args.sizes.split(","):
        out["rows"].append(row(gmap, before, after, int(n), args.repeats))
        print(json.dumps(out["rows"][-1]), file=sys.stderr)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
