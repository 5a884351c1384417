"""The semantic map under SLAM map churn (issue 15): prints one JSON object.

For each source and churn: the first half of the keyframes is integrated, then the SLAM's map update
arrives (monovoc_ros.synthetic.churn, seeded; re-ordered, with or without ids; optionally followed by
the corrected keyframe poses as a `KeyframePoses` event), then the second half with the corrected poses.
Scores (splats protocol, every 3rd keyframe, poses as corrected): the first half right before the update,
right after it (the transfer alone), after the re-integration that follows (when the corrected poses, a
poor transfer or a bent map start one), and the final map, against the same events without churn. Then the
cost of a map update against one keyframe's integration at 200k / 1M / 2M Gaussians (office_0 tiled), with
the live worker's share of updates and snapshots and the object geometry after one keyframe.

    python benchmarks/bench_map_churn.py                       # everything (README tables)
    python benchmarks/bench_map_churn.py --sources synthetic --churns loop --no-scale
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from monovoc_ros import offline  # noqa: E402
from monovoc_ros.commands.eval import score  # noqa: E402
from monovoc_ros.core.follow.keyframe_log import KeyframePoses  # noqa: E402
from monovoc_ros.core.mapping import MapperConfig  # noqa: E402
from monovoc_ros.synthetic import churn  # noqa: E402

REPLICA = REPO.parent / "shared" / "data" / "replica_office0"


def _then_update(make):
    def case(g, ids):
        out = make(g, ids)
        return g, churn.unmoved, out.gaussians, out.move_pose

    return case


def _drift_corrected(g, ids):
    """Drift correction: the SLAM's map was bent (drifted) while the first half was integrated, with the
    poses drifted alike; the update brings the true map back (re-ordered) and the true poses."""
    drifted = churn.drift_correction(g, keep_ids=True)
    old = drifted.gaussians if ids else replace(drifted.gaussians, ids=None)
    return old, drifted.move_pose, churn.shuffled(g, keep_ids=ids).gaussians, churn.unmoved


# name -> (gmap, ids) -> (map before, pose before (true -> SLAM's), map after, pose after)
CHURNS = {
    "densify": _then_update(lambda g, ids: churn.densify(g, keep_ids=ids)),
    "loop": _then_update(lambda g, ids: churn.loop_closure(g, keep_ids=ids)),
    "bend": _drift_corrected,
    "densify+loop": _then_update(
        lambda g, ids: churn.then(churn.densify(g, keep_ids=ids), churn.loop_closure, keep_ids=ids)
    ),
}


def _frames(keyframes, every: int = 3):
    return [(kf.intrinsics, kf.cam_to_world, kf.mask) for kf in keyframes[::every]]


def _miou(mapper, keyframes) -> float:
    result, _ = score(mapper.gaussians, mapper.result().object_ids, _frames(keyframes), "splats", 0.05)
    return round(100 * float(result["miou"]), 2)


def run_case(gmap, keyframes, name: str, ids: bool, poses: bool) -> dict:
    half = len(keyframes) // 2
    first, second = keyframes[:half], keyframes[half:]
    if not ids:
        gmap = replace(gmap, ids=None)
    elif gmap.ids is None:
        gmap = replace(gmap, ids=np.arange(len(gmap), dtype=np.int64))
    old_map, old_pose, new_map, new_pose = CHURNS[name](gmap, ids)
    old_first = [replace(kf, cam_to_world=old_pose(kf.cam_to_world)) for kf in first]
    moved_first = [replace(kf, cam_to_world=new_pose(kf.cam_to_world)) for kf in first]
    moved_second = [replace(kf, cam_to_world=new_pose(kf.cam_to_world)) for kf in second]
    before, _ = offline.map_events([old_map, *old_first])
    start = time.perf_counter()
    events = [old_map, *old_first, new_map]
    # The transfer alone: no re-integration of the map's own accord (keyframe poses still re-integrate).
    after, stats = offline.map_events(events, MapperConfig(reintegrate_below=0.0))
    row = {
        "churn": name,
        "ids": ids,
        "keyframe_poses": poses,
        "first_half_before": _miou(before, old_first),
        "first_half_after_update": _miou(after, moved_first),
        "carried_share": round(stats.map_update_carried_share, 4),
        "update_ms": round(stats.ms_map_update_last, 1),
        "rejected": dict(stats.rejected),
    }
    if poses:
        events.append(KeyframePoses(tuple((kf.stamp_ns, kf.cam_to_world) for kf in moved_first)))
    rebuilt, stats = offline.map_events(events)
    if stats.reintegrations:
        row["first_half_after_reintegration"] = _miou(rebuilt, moved_first)
        row["reintegration_s"] = round(stats.ms_reintegration_total / 1e3, 2)
        row["reintegrated_keyframes"] = stats.keyframes_reintegrated
        row["reintegration_kf_per_s"] = round(stats.keyframes_reintegrated / (stats.ms_reintegration_total / 1e3), 1)
    final, _ = offline.map_events([*events, *moved_second])
    row["final"] = _miou(final, moved_first + moved_second)
    row["wall_s"] = round(time.perf_counter() - start, 1)
    return row


def tiled(gmap, n: int):
    """office_0 repeated side by side (x) until it holds n Gaussians: a larger map, the same keyframes."""
    reps = -(-n // len(gmap))
    width = float(np.ptp(gmap.means[:, 0])) + 1.0
    idx = np.arange(n) % len(gmap)
    shift = np.zeros((n, 3), np.float32)
    shift[:, 0] = (np.arange(n) // len(gmap)) * width
    out = gmap.subset(idx)
    return replace(out, means=out.means + shift, ids=np.arange(n, dtype=np.int64)), reps


def update_cost(gmap, keyframes, n: int, repeats: int = 3) -> dict:
    """Seconds of a map update (session.add_map: checks, registration, transfer) and of the object geometry,
    as ratios to one keyframe's integration, at n Gaussians; a live worker's share of them (the update prepared
    beside it by session.plan_map, then applied; a snapshot captured, then written beside it) and the object
    geometry of a publication after one keyframe."""
    from monovoc_ros.core.map_store import capture_snapshot, write_snapshot
    from monovoc_ros.core.session import MappingSession

    big, _ = tiled(gmap, n)
    row = {"gaussians": n}
    for ids in (True, False):
        base = big if ids else replace(big, ids=None)
        session = MappingSession()
        session.add_map(base)
        kf_s = []
        for kf in keyframes[:8]:
            session.add_keyframe(kf)
            kf_s.append(session.integrate_next().seconds)
        keyframe_s = float(np.median(kf_s[3:]))
        update_s, plan_s, apply_s = [], [], []
        for r in range(repeats):
            new = churn.densify(session.mapper.gaussians, split=0.02, prune=0.01, seed=r, keep_ids=ids).gaussians
            start = time.perf_counter()
            assert session.add_map(new)
            update_s.append(time.perf_counter() - start)
            new = churn.densify(new, split=0.02, prune=0.01, seed=10 + r, keep_ids=ids).gaussians
            start = time.perf_counter()
            plan = session.plan_map(None, new)
            planned = time.perf_counter()
            assert session.add_map(new, plan=plan)
            plan_s.append(planned - start)
            apply_s.append(time.perf_counter() - planned)
        key = "with_ids" if ids else "without_ids"
        row[f"keyframe_ms_{key}"] = round(1e3 * keyframe_s, 1)
        row[f"update_ms_{key}"] = round(1e3 * float(np.median(update_s)), 1)
        row[f"ratio_{key}"] = round(float(np.median(update_s)) / keyframe_s, 1)
        row[f"prepared_ms_{key}"] = round(1e3 * float(np.median(plan_s)), 1)
        row[f"worker_update_ms_{key}"] = round(1e3 * float(np.median(apply_s)), 1)
        row[f"worker_ratio_{key}"] = round(float(np.median(apply_s)) / keyframe_s, 1)
        result = session.mapper.result()
        start = time.perf_counter()
        result.objects(session.mapper.gaussians)
        row[f"object_geometry_ms_{key}"] = round(1e3 * (time.perf_counter() - start), 1)
        session.add_keyframe(keyframes[8])
        session.integrate_next()
        start = time.perf_counter()
        session.mapper.result().objects(session.mapper.gaussians)
        row[f"object_geometry_after_keyframe_ms_{key}"] = round(1e3 * (time.perf_counter() - start), 1)
    capture_s, write_s = [], []
    with tempfile.TemporaryDirectory() as directory:
        for _ in range(repeats):
            start = time.perf_counter()
            content = capture_snapshot(session.mapper)
            captured = time.perf_counter()
            write_snapshot(content, directory)
            capture_s.append(captured - start)
            write_s.append(time.perf_counter() - captured)
    row["snapshot_worker_ms"] = round(1e3 * float(np.median(capture_s)), 1)
    row["snapshot_written_beside_ms"] = round(1e3 * float(np.median(write_s)), 1)
    return row


def load(source: str):
    seq = offline.open_source(str(REPLICA) if source == "replica" else source)
    return seq.load_gaussians(), [seq.keyframe(i) for i in range(len(seq))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sources", default="replica,synthetic")
    parser.add_argument("--churns", default=",".join(CHURNS))
    parser.add_argument("--ids", default="no,yes")
    parser.add_argument("--poses", default="no,yes")
    parser.add_argument("--scales", default="200000,1000000,2000000", help="map update cost at these sizes ('' = none)")
    args = parser.parse_args()
    out = {"cases": [], "update_cost": []}
    if args.scales and (REPLICA / "traj.txt").exists():
        gmap, keyframes = load("replica")
        for n in args.scales.split(","):
            out["update_cost"].append(update_cost(gmap, keyframes, int(n)))
            print(json.dumps(out["update_cost"][-1]), file=sys.stderr)
    for source in filter(None, args.sources.split(",")):
        if source == "replica" and not (REPLICA / "traj.txt").exists():
            print(f"skipping replica: {REPLICA} not present", file=sys.stderr)
            continue
        gmap, keyframes = load(source)
        baseline, _ = offline.map_events([gmap, *keyframes])
        half_base, _ = offline.map_events([gmap, *keyframes[: len(keyframes) // 2]])
        base = {"source": source, "first_half": _miou(half_base, keyframes[: len(keyframes) // 2])}
        base["final"] = _miou(baseline, keyframes)
        out.setdefault("no_churn", []).append(base)
        print(json.dumps(base), file=sys.stderr)
        for name in args.churns.split(","):
            for ids in args.ids.split(","):
                for poses in args.poses.split(","):
                    row = {"source": source, **run_case(gmap, keyframes, name, ids == "yes", poses == "yes")}
                    out["cases"].append(row)
                    print(json.dumps(row), file=sys.stderr)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
