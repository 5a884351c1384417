"""How long the mapping worker's tasks hold the Python interpreter at a time, at robot scale; prints JSON.

    scripts/with_env.sh python benchmarks/bench_interpreter_holds.py                 # 1M Gaussians
    scripts/with_env.sh python benchmarks/bench_interpreter_holds.py --gaussians 2000000

While the worker runs C code that keeps the GIL (numpy's hashing `np.unique`, a numba kernel without
``nogil``), no other thread of the node runs: the executor cannot take a query, a handler cannot finish its
answer. The node's watch (nodes/interpreter_watch.py; every 5 ms in the node) wakes here every 0.5 ms beside the
tasks; per task, the most it woke late by is the longest hold (plus a scheduling slice). The node sets the
interpreter's switch interval to 1 ms (nodes/mapping_node.py), as here.

The tasks, through the session the node uses (core.session.MappingSession): the first map (office_0 tiled to the
size, with and without per-Gaussian ids), keyframes, a map update planned beside the worker and applied, the
result and its object geometry.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_map_churn import REPLICA, tiled  # noqa: E402

from monovoc_ros.core.evaluation.datasets import open_sequence  # noqa: E402
from monovoc_ros.core.session import MappingSession  # noqa: E402
from monovoc_ros.nodes.interpreter_watch import InterpreterWatch  # noqa: E402
from monovoc_ros.synthetic import churn  # noqa: E402

TICK_S = 0.0005


class HoldProbe:
    """The node's own watch (nodes/interpreter_watch.py), waking every TICK_S, read per task."""

    def __init__(self) -> None:
        self.watch = InterpreterWatch(period_s=TICK_S)

    def __enter__(self) -> HoldProbe:
        self.watch.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.watch.stop()

    def timed(self, fn) -> dict:
        """Runs fn(); its milliseconds and the longest hold (ms) while it ran."""
        self.watch.reset()
        start = time.perf_counter()
        fn()
        end = time.perf_counter()
        time.sleep(0.005)  # the wake that ends a hold at the task's end
        longest = self.watch.diagnostics()["interpreter_hold_ms_max"]
        return {"ms": round(1e3 * (end - start), 1), "longest_hold_ms": longest}


def run(gaussians, keyframes, ids: bool, probe: HoldProbe) -> dict:
    base = gaussians if ids else replace(gaussians, ids=None)
    session = MappingSession()
    out = {"first_map": probe.timed(lambda: session.add_map(base))}
    per_keyframe = []
    for kf in keyframes:
        session.add_keyframe(kf)
        per_keyframe.append(probe.timed(session.integrate_next))
    out["keyframe_longest_hold_ms"] = max(k["longest_hold_ms"] for k in per_keyframe[1:])
    new = churn.densify(session.mapper.gaussians, split=0.02, prune=0.01, seed=0, keep_ids=ids).gaussians
    plan: list = []
    out["map_update_plan"] = probe.timed(lambda: plan.append(session.plan_map(None, new)))
    out["map_update_apply"] = probe.timed(lambda: session.add_map(new, plan=plan[0]))
    result: list = []
    out["result"] = probe.timed(lambda: result.append(session.mapper.result()))
    out["object_geometry"] = probe.timed(lambda: result[0].objects(session.mapper.gaussians))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gaussians", type=int, default=1_000_000)
    parser.add_argument("--keyframes", type=int, default=6)
    args = parser.parse_args()
    if args.keyframes < 2:
        parser.error("--keyframes: at least 2 (the first is not counted: its chunks are built)")
    if not (REPLICA / "traj.txt").exists():
        print(f"{REPLICA} not present: nothing to measure", file=sys.stderr)
        return 1
    sys.setswitchinterval(0.001)  # as the node (mapping_node.run)
    seq = open_sequence(str(REPLICA))
    big, _ = tiled(seq.load_gaussians(), args.gaussians)
    keyframes = [seq.keyframe(i) for i in range(args.keyframes)]
    MappingSession().add_map(big)  # numba's kernels loaded before anything is timed
    report = {"gaussians": args.gaussians, "switch_interval_ms": 1.0}
    with HoldProbe() as probe:
        for ids in (True, False):
            report["with_ids" if ids else "without_ids"] = run(big, keyframes, ids, probe)
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
