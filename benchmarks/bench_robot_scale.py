"""The live semantic_mapper at robot scale (issue 25): a building's map with SLAM map updates; prints JSON.

    scripts/with_env.sh python benchmarks/bench_robot_scale.py                       # 1M and 2M Gaussians
    scripts/with_env.sh python benchmarks/bench_robot_scale.py --sizes 1000000 --runs robot
    scripts/with_env.sh python benchmarks/bench_robot_scale.py --sizes 1000000 --runs robot --map-update-ahead-s 0
    scripts/with_env.sh python benchmarks/bench_robot_scale.py --sizes 1000000 --runs robot --fastdds-profile P.xml
    scripts/with_env.sh python benchmarks/bench_robot_scale.py --sizes 1000000 --runs robot --param query.top_k=3
    RMW_FASTRTPS_PUBLICATION_MODE=ASYNCHRONOUS scripts/with_env.sh python benchmarks/bench_robot_scale.py --runs robot
    # interleaved A/B on one bag: a setting on the odd runs only; or revision R for the even runs, HEAD for the odd
    scripts/with_env.sh python benchmarks/bench_robot_scale.py --sizes 1000000 --runs robot --repeat 6 \
        --odd-param map_update_ahead_s=0
    scripts/with_env.sh python benchmarks/bench_robot_scale.py --sizes 1000000 --runs robot --repeat 6 \
        --before-run 'git checkout -q $([ $((RUN_INDEX % 2)) = 0 ] && echo R || echo HEAD) -- monovoc_ros msg_adapters'

The scene: Replica office_0's 204k-Gaussian map tiled side by side to the size (benchmarks/bench_map_churn.py's
`tiled`, per-Gaussian ids dropped: most SLAM front-ends have none), its 81 RGB keyframes replayed in every tile
in turn (keyframe k in tile k mod tiles, the tile's own object colors), and every `--update-period-s` of
stamps a new map: 2% of the Gaussians split, 1% pruned, every mean jittered 2 mm, and a small loop closure
(a 0.1 degree bend and 1 cm; the keyframes after it posed in the bent map). Written as a bag
(`sequence_to_bag`) and replayed over loopback into `semantic_mapper` (object database, query service, periodic
snapshots into a map directory) running as its own process. Runs per size:

- ``robot``: keyframes at `--robot-rate` (2/s) with the semantic cloud published whenever the queue is empty
  (`publish_rate_hz` 0): per keyframe the latency from its publication (the last of its messages, when the
  replay sent it: `KeyframePublishTimes`) to the first semantic cloud holding it (p50 / p95 / max; and `running_`
  over the keyframes published once the first cloud was there, the time to it `first_cloud_ms`); open-loop
  text queries at 5/s meanwhile (p99, lost). The cloud's viewer (monovoc_ros.nodes.cloud_viewer) and the query
  client (monovoc_ros.nodes.query_load) are processes of their own, as RViz and a user's client are: in the
  replaying process, its serializing of 56 MB map messages counted as the node's latency;
- ``fast``: keyframes stamped at 10/s (the issue's target rate) replayed at `--fast-rate` times that rate
  (`publish_rate_hz` 1, the default): keyframes/s sustained from the first message to the last integrated, and
  keyframes dropped. (An as-fast-as-possible replay cannot hold the map updates: the map topic keeps the
  newest map only, as a SLAM's does, so DDS replaces maps published faster than ~50 MB messages travel.)
  A viewer subscribes to the semantic cloud as in the robot run, unless `--fast-without-viewer` (the node then
  builds no cloud: a robot mapping with no RViz open).

Both report the worker thread's share of the wall time by activity (diagnostics `worker_s_*`: keyframes, map
updates, re-integration, labels, object geometry, publication, snapshots, calls), the map messages' decoding
and the map updates' plans (both beside the worker), map updates applied and prepared, the node's peak RSS, and
the CPU every process of the run took (`cpu`: the node, its map reader, the replay in this process, the viewer and
the query client; core-seconds, per keyframe, and the cores kept busy): on a saturated machine the node's CPU per
keyframe, not its wall time, says what rate the cores allow.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import random
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_map_churn import REPLICA, tiled  # noqa: E402

from monovoc_ros.bags import iter_messages, replay, sequence_to_bag, topic_names  # noqa: E402
from monovoc_ros.core.evaluation.datasets import Sequence, open_sequence  # noqa: E402
from monovoc_ros.core.evidence.palette import VOID_ID, pack_rgb, unpack_rgb  # noqa: E402
from monovoc_ros.core.follow.map_ahead import DEFAULT_AHEAD_S  # noqa: E402
from monovoc_ros.core.keyframe import Keyframe  # noqa: E402
from monovoc_ros.core.map.gaussians import GaussianMap  # noqa: E402
from monovoc_ros.fastdds_profile import PROFILES_ENV, publication_mode  # noqa: E402
from monovoc_ros.ros_harness import (  # noqa: E402
    SEMANTIC_MAPPER,
    ClientNode,
    DiagnosticsMonitor,
    KeyframePublishTimes,
    NodeProcess,
    cloud_latencies_ms,
    first_cloud_at,
    loopback_environment,
    ros_args,
    wait_until,
)
from monovoc_ros.synthetic import churn  # noqa: E402

ACTIVITIES = ("keyframes", "map_updates", "reintegration", "labels", "objects", "publish", "snapshots", "calls")
TILE_COLORS = 4096  # object colors per tile: tile t's copy of color j is 1 + t * TILE_COLORS + j


class TiledSequence(Sequence):
    """office_0's keyframes replayed in every tile of the tiled map, with the map updates' pose corrections."""

    def __init__(self, base: Sequence, n_gaussians: int, count: int, rate_hz: float, update_every: int) -> None:
        base_map = base.load_gaussians()
        big, self.tiles = tiled(base_map, n_gaussians)
        self.name = f"office0_x{self.tiles}"
        self.base = base
        self.width = float(np.ptp(base_map.means[:, 0])) + 1.0
        self.intrinsics = base.intrinsics
        self.stamps_ns = (10**9 + np.arange(count) * (1e9 / rate_hz)).astype(np.int64)
        self.poses = np.stack([self._pose(k) for k in range(count)])
        self._map = dataclasses.replace(big, ids=None)
        colors = np.unique(np.concatenate([pack_rgb(base.keyframe(i).mask).ravel() for i in range(len(base))]))
        self._colors = colors[colors != VOID_ID]  # (C,) the base masks' object colors, sorted
        self.updates: dict[int, GaussianMap] = {}
        current = self._map
        for k in range(update_every, count, update_every):
            current = churn.densify(current, split=0.02, prune=0.01, jitter=0.002, seed=k).gaussians
            bent = churn.drift_correction(current, degrees=0.1, translation=(0.01, 0.01, 0.0), seed=k)
            current = bent.gaussians
            self.updates[k] = current
            for j in range(k, count):  # the keyframes after the update are posed in the bent map
                self.poses[j] = bent.move_pose(self.poses[j])

    def _pose(self, k: int) -> np.ndarray:
        pose = np.array(self.base.poses[k % len(self.base)], np.float64)
        pose[0, 3] += (k % self.tiles) * self.width
        return pose

    def load_gaussians(self) -> GaussianMap:
        return self._map

    def keyframe(self, i: int) -> Keyframe:
        kf = self.base.keyframe(i % len(self.base))
        packed = pack_rgb(kf.mask)
        slot = np.searchsorted(self._colors, packed).clip(0, len(self._colors) - 1)
        recolored = np.where(packed == VOID_ID, VOID_ID, 1 + (i % self.tiles) * TILE_COLORS + slot).astype(np.uint32)
        mask = unpack_rgb(recolored.ravel()).reshape(kf.mask.shape).astype(np.uint8)
        return dataclasses.replace(kf, index=i, stamp_ns=int(self.stamps_ns[i]), cam_to_world=self.poses[i], mask=mask)


def peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def cpu_seconds(roles: dict[str, list[int]]) -> dict[str, dict[int, float]]:
    """User + system CPU seconds so far of each role's processes (all their threads), by pid."""
    out: dict[str, dict[int, float]] = {}
    for role, pids in roles.items():
        out[role] = {}
        for pid in pids:
            with contextlib.suppress(psutil.Error):
                t = psutil.Process(pid).cpu_times()
                out[role][pid] = t.user + t.system
    return out


def cpu_roles(node_pid: int, others: dict[str, int]) -> dict[str, list[int]]:
    """The processes whose CPU a run counts, by role: the node, its map reader, this process (the replay and the
    diagnostics client) and the viewer and query client where they run."""
    readers = []
    for child in psutil.Process(node_pid).children():
        with contextlib.suppress(psutil.Error):  # a reader restarting: gone, or a zombie
            if "monovoc_ros.nodes.map_reader" in child.cmdline():
                readers.append(child.pid)
    return {"node": [node_pid], "map_reader": readers, "replay": [os.getpid()]} | {k: [v] for k, v in others.items()}


def cpu_use(before: dict[str, dict[int, float]], after: dict[str, dict[int, float]], wall_s: float, keyframes: int):
    """The CPU a run took, by role: core-seconds, and per keyframe processed; `cores_busy`: of the machine's cores,
    how many the run kept busy on average (2 cores saturated: 2.0). A process started in between (a map reader
    restarted) counts from its start; one gone by the end is left out."""
    used = {
        role: sum(t - before.get(role, {}).get(pid, 0.0) for pid, t in pids.items()) for role, pids in after.items()
    }
    return {
        "core_s": {role: round(v, 1) for role, v in used.items()},
        "core_ms_per_keyframe": {role: round(1e3 * v / max(1, keyframes)) for role, v in used.items()},
        "cores_busy": round(sum(used.values()) / wall_s, 2),
    }


def worker_shares(values: dict[str, str], wall_s: float) -> dict:
    shares = {a: round(float(values[f"worker_s_{a}"]) / wall_s, 3) for a in ACTIVITIES}
    shares["total"] = round(sum(shares.values()), 3)
    shares["map_decoding_beside_the_worker"] = round(float(values["map_decode_s"]) / wall_s, 3)
    shares["map_update_plans_beside_the_worker"] = round(float(values["map_prepare_s"]) / wall_s, 3)
    # Of the worker's map updates: waiting for the motion or the plan prepared beside it.
    shares["map_update_waits"] = round(float(values.get("map_update_wait_s", 0)) / wall_s, 3)
    # The motions the map reader process registered for the plans (another process: not the node's cores' share).
    shares["map_motions_in_the_map_reader"] = round(float(values.get("map_reader_motion_s", 0)) / wall_s, 3)
    return shares


def run(
    bag: Path, work: Path, kind: str, keyframes: int, maps: int, rate: float, node_params: dict,
    query_rate_hz: float = 5.0, viewer: bool = True,
) -> dict:  # fmt: skip
    """One run of the node on `bag` (`keyframes` keyframes, `maps` map messages, the first included);
    `node_params`: the node's parameters the command line chose (map_update_ahead_s, map_reader_process,
    interpreter_hold_trace_ms);
    `viewer`: whether the fast run subscribes to the semantic cloud."""
    mask_topic = topic_names()["mask"]
    stamps = [m.log_time_ns for m in iter_messages(bag, topics=[mask_topic])]
    params = {
        "publish_rate_hz": 0.0 if kind == "robot" else 1.0,
        "diagnostics_period_s": 0.2,
        "queue_size": keyframes + 8,
        "map_directory": str(work / f"map_{kind}"),
        "map_update_max_shrink": 1.0,
        **node_params,
    }
    # Named after the bag (size and run): the sizes share the work folder.
    start_file, queries_file = work / f"{bag.stem}_queries.start", work / f"{bag.stem}_queries.json"
    viewer_files = {k: work / f"{bag.stem}_viewer.{k}" for k in ("ready", "stop", "json")}
    for stale in (start_file, queries_file, *viewer_files.values()):
        stale.unlink(missing_ok=True)
    duration = (stamps[-1] - stamps[0]) / 1e9
    with contextlib.ExitStack() as stack:
        mapper_args = ["-m", SEMANTIC_MAPPER, *ros_args(params)]
        node = stack.enter_context(
            NodeProcess.python(mapper_args, name="semantic_mapper", output_path=work / f"mapper_{kind}.log")
        )
        client = stack.enter_context(ClientNode())
        querying = None
        if kind == "robot":  # open-loop queries from a process of their own, as a user's client
            load_args = ["-m", "monovoc_ros.nodes.query_load", "--rate", str(query_rate_hz),
                         "--count", str(max(1, int(duration * query_rate_hz))), "--start-file", str(start_file),
                         "--out", str(queries_file)]  # fmt: skip
            querying = stack.enter_context(
                NodeProcess.python(load_args, name="query_load", output_path=work / f"query_load_{kind}.log")
            )
        diagnostics = DiagnosticsMonitor(client.node, "semantic mapping")
        # A viewer of the semantic cloud (the node builds it only while something subscribes) from a process of
        # its own, as RViz (monovoc_ros.nodes.cloud_viewer): the robot run's latency needs it; the fast run has
        # one unless --fast-without-viewer.
        cloud_viewer = None
        if kind == "robot" or viewer:
            viewer_args = ["-m", "monovoc_ros.nodes.cloud_viewer", "--ready-file", str(viewer_files["ready"]),
                           "--stop-file", str(viewer_files["stop"]), "--out", str(viewer_files["json"])]  # fmt: skip
            cloud_viewer = stack.enter_context(
                NodeProcess.python(viewer_args, name="cloud_viewer", output_path=work / f"cloud_viewer_{kind}.log")
            )
            wait_until(viewer_files["ready"].exists, 300.0, "the cloud viewer", process=cloud_viewer)
        diagnostics.wait_for(lambda d: float(d.get("warm_up_ms", 0)) > 0, 300.0, what="warm-up", process=node)
        started: list[float] = []
        others = {"viewer": cloud_viewer.pid} if cloud_viewer is not None else {}
        others |= {"query_load": querying.pid} if querying is not None else {}
        cpu_before: dict[str, dict[int, float]] = {}

        def on_started() -> None:
            started.append(time.monotonic())
            cpu_before.update(cpu_seconds(cpu_roles(node.pid, others)))
            start_file.touch()

        published = KeyframePublishTimes()
        replay(
            bag, rate=rate, wait_subscribers=1, wait_timeout=120.0, ack_timeout=300.0, on_started=on_started,
            on_published=published,
        )  # fmt: skip
        done = diagnostics.wait_for(
            lambda d: int(d["keyframes_processed"]) + int(d["keyframes_dropped"]) >= keyframes
            and d["queue_length"] == "0",
            900.0, what="all keyframes", process=node,
        )  # fmt: skip
        finished = time.monotonic()
        # Read now: the map reader's count is lost once the node stops it.
        cpu_after = cpu_seconds(cpu_roles(node.pid, others))
        queries: dict = {}
        if querying is not None:
            wait_until(lambda: not querying.running(), 120.0, "the query load to end", process=None)
            if querying.returncode != 0 or not queries_file.exists():
                raise RuntimeError(f"the query load failed\n{querying.describe()}")
            queries = json.loads(queries_file.read_text())
        time.sleep(1.0)  # the last cloud
        arrivals: dict[int, float] = {}
        if cloud_viewer is not None:
            viewer_files["stop"].touch()
            wait_until(lambda: not cloud_viewer.running(), 60.0, "the cloud viewer to end", process=None)
            if cloud_viewer.returncode != 0 or not viewer_files["json"].exists():
                raise RuntimeError(f"the cloud viewer failed\n{cloud_viewer.describe()}")
            arrivals = {int(k): v for k, v in json.loads(viewer_files["json"].read_text())["arrivals"].items()}
        values = diagnostics.values()
        wall = finished - started[0]
        out = {
            "run": kind,
            "keyframes_sent": keyframes,
            "keyframes_processed": int(done["keyframes_processed"]),
            "keyframes_dropped": int(done["keyframes_dropped"]),
            "maps_sent": maps,
            "maps_received": int(values["maps_received"]),
            "map_updates_applied": int(values["map_updates"]),
            "map_updates_prepared": int(values["map_updates_prepared"]),
            "map_motions_given": int(values.get("map_motions_given", 0)),  # registered in the map reader process
            "map_updates_ahead": int(values["map_updates_ahead"]),
            "reintegrations": int(values["reintegrations"]),
            "maps_coalesced": int(values["maps_coalesced"]),
            "gaussians_at_end": int(values["gaussians"]),
            "objects": int(values["objects"]),
            # The object index when the last keyframe was integrated: objects queryable, and waiting to be embedded.
            "objects_indexed": int(done.get("objects.indexed", -1)),
            "objects_pending": int(done.get("objects.pending", -1)),
            "keyframes_per_s_sent": round(rate * (len(stamps) - 1) / ((stamps[-1] - stamps[0]) / 1e9), 2),
            "wall_s": round(wall, 1),
            "keyframes_per_s": round(int(done["keyframes_processed"]) / wall, 2),
            "integration_ms_mean": round(float(values["ms_per_keyframe_mean"]), 1),
            "map_update_ms_last": round(float(values["ms_map_update_last"]), 1),
            "map_decode_ms_mean": round(1e3 * float(values["map_decode_s"]) / max(1, int(values["maps_decoded"])), 1),
            "snapshots": int(values["snapshots_saved"]),
            "cloud_viewer": cloud_viewer is not None,
            "clouds_skipped": int(values.get("clouds_skipped", 0)),
            "worker_share": worker_shares(values, wall),
            # Every process of the run on the machine's cores, from the first message to the last keyframe integrated.
            "cpu": cpu_use(cpu_before, cpu_after, wall, int(done["keyframes_processed"])),
            # What one publication took the worker: the labels, the object geometry, the messages.
            "publications": int(values["publishes"]),
            "publication_ms_mean": {
                a: round(1e3 * float(values[f"worker_s_{a}"]) / max(1, int(values["publishes"])), 1)
                for a in ("labels", "objects", "publish")
            },
            # The longest time any thread of the node held the interpreter (nodes/interpreter_watch.py), and when; with
            # --hold-trace-ms, the file of the holders' stacks.
            **{
                k: v if k.endswith("_file") else float(v) for k, v in values.items() if k.startswith("interpreter_hold")
            },
            "node_peak_rss_mb": round(peak_rss_mb(node.pid)),
            "map_reader_peak_rss_mb": [
                round(peak_rss_mb(c.pid))
                for c in psutil.Process(node.pid).children()
                if "monovoc_ros.nodes.map_reader" in c.cmdline()
            ],
        }
        if kind == "robot":
            lat = np.array(cloud_latencies_ms(published.at, arrivals))
            # Running: the keyframes published once the first cloud was there (the node had its first map); those
            # before it waited for the first 1M map's ~56 MB message: startup, counted in first_cloud_ms.
            first = first_cloud_at(published.at, arrivals)
            running = np.array(
                cloud_latencies_ms(published.at, arrivals, after=first if first is not None else math.inf)
            )
            out.update(
                keyframes_with_cloud=len(lat),
                latency_ms_p50=round(float(np.percentile(lat, 50)), 1) if len(lat) else None,
                latency_ms_p95=round(float(np.percentile(lat, 95)), 1) if len(lat) else None,
                latency_ms_max=round(float(lat.max()), 1) if len(lat) else None,
                first_cloud_ms=round(1e3 * (first - min(published.at.values())), 1) if first is not None else None,
                keyframes_running=len(running),
                running_latency_ms_p50=round(float(np.percentile(running, 50)), 1) if len(running) else None,
                running_latency_ms_p95=round(float(np.percentile(running, 95)), 1) if len(running) else None,
                latency_ms_by_keyframe=[round(float(x)) for x in lat],
                queries={
                    **{k: queries.get(k) for k in ("sent", "answered", "lost", "p50_ms", "p99_ms", "max_ms")},
                    "slowest": queries.get("slowest"),
                    # The node's own part (its handlers' time): the rest of a slow answer was DDS and the executor.
                    **{
                        f"node_{k.split('.', 1)[1]}": float(v)
                        for k, v in values.items()
                        if k.startswith("queries.handler_")
                    },
                },
            )
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="1000000,2000000")
    parser.add_argument("--runs", default="robot,fast")
    parser.add_argument("--robot-rate", type=float, default=2.0, help="keyframes/s of the robot run")
    parser.add_argument("--robot-keyframes", type=int, default=40)
    parser.add_argument("--fast-keyframes", type=int, default=120, help="stamped at 10/s")
    parser.add_argument("--fast-rate", type=float, default=1.0, help="replay rate of the fast run (1: 10 keyframes/s)")
    parser.add_argument("--update-period-s", type=float, default=2.0)
    parser.add_argument(
        "--map-update-ahead-s", type=float, default=DEFAULT_AHEAD_S, help="the node's map_update_ahead_s (0: in line)"
    )
    parser.add_argument("--map-in-node", action="store_true", help="map_reader_process false: the node takes the map")
    parser.add_argument("--fast-without-viewer", action="store_true", help="nothing subscribes to the fast run's cloud")
    parser.add_argument(
        "--fastdds-profile", type=Path, help="a Fast DDS XML profile for every process (node, replay, clients)"
    )
    parser.add_argument(
        "--hold-trace-ms", type=float, default=0.0,
        help="the node's interpreter_hold_trace_ms: stacks of holds longer than this, in the node's ROS log directory",
    )  # fmt: skip
    parser.add_argument("--repeat", type=int, default=1, help="runs of the node on each bag (built once)")
    parser.add_argument(
        "--before-run", metavar="CMD",
        help="a shell command run before each run (RUN_INDEX in its environment): e.g. a checkout, for A/B runs",
    )  # fmt: skip
    parser.add_argument(
        "--odd-param", action="append", default=[], metavar="NAME=VALUE",
        help="a node parameter for the odd runs of --repeat only (interleaved A/B of a setting)",
    )  # fmt: skip
    parser.add_argument(
        "--param", action="append", default=[], metavar="NAME=VALUE",
        help="another node parameter (repeatable), typed as on a ROS command line: objects.description_weight=0.0",
    )  # fmt: skip
    args = parser.parse_args()
    extra = dict(p.split("=", 1) for p in args.param if "=" in p)
    odd = dict(p.split("=", 1) for p in args.odd_param if "=" in p)
    if len(extra) != len(args.param) or len(odd) != len(args.odd_param):
        parser.error("--param, --odd-param: expected NAME=VALUE")
    if args.fastdds_profile is not None:
        if not args.fastdds_profile.is_file():
            parser.error(f"--fastdds-profile: no file {args.fastdds_profile}")
        # Set before the first participant of this process (Fast DDS reads it once); the node and clients inherit it.
        # The replay's and the node's 50 ms writer heartbeat (monovoc_ros/fastdds_profile.py) then applies only if
        # the profile sets it.
        os.environ[PROFILES_ENV] = str(args.fastdds_profile.resolve())
    node_params = {
        "map_update_ahead_s": args.map_update_ahead_s,
        "map_reader_process": not args.map_in_node,
        "interpreter_hold_trace_ms": args.hold_trace_ms,
        **extra,
    }
    if not (REPLICA / "traj.txt").exists():
        print(f"{REPLICA} not present: nothing to measure", file=sys.stderr)
        return 1
    work = Path(tempfile.mkdtemp(prefix="monovoc_bench_scale_"))
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 232)))
    loopback_environment(work / "ros_log")
    base = open_sequence(str(REPLICA))
    profile = os.environ.get(PROFILES_ENV)
    # Every process inherits the caller's RMW_FASTRTPS_PUBLICATION_MODE.
    report = {"source": str(REPLICA), "cpus": os.cpu_count(), "update_period_s": args.update_period_s,
              "fastdds_profile": profile, "publication_mode": publication_mode(), **node_params,
              "rows": []}  # fmt: skip
    for n in (int(s) for s in args.sizes.split(",")):
        for kind in args.runs.split(","):
            rate, count = (args.robot_rate, args.robot_keyframes) if kind == "robot" else (10.0, args.fast_keyframes)
            t0 = time.perf_counter()
            seq = TiledSequence(base, n, count, rate, max(1, round(args.update_period_s * rate)))
            bag = work / f"scale_{n}_{kind}.mcap"
            sequence_to_bag(seq, bag, map_updates=seq.updates)
            built = time.perf_counter() - t0
            row = {
                "gaussians": n,
                "tiles": seq.tiles,
                "bag_mb": round(bag.stat().st_size / 1e6),
                "bag_build_s": round(built),
            }
            replay_rate = 1.0 if kind == "robot" else args.fast_rate
            for repeat in range(args.repeat):
                if args.before_run:  # e.g. another version of the code checked out, for interleaved A/B runs
                    env = {**os.environ, "RUN_INDEX": str(repeat)}
                    subprocess.run(args.before_run, shell=True, check=True, env=env)
                params = {**node_params, **odd} if repeat % 2 else node_params
                measured = dict(row, repeat=repeat, params={k: params.get(k, "default") for k in odd} if odd else None)
                measured.update(
                    run(bag, work, kind, count, 1 + len(seq.updates), replay_rate, params,
                        viewer=not args.fast_without_viewer)
                )  # fmt: skip
                # The node's snapshots (~1 GB at 1M): a run left them behind and repeated runs filled the disk. The
                # logs (mapper_*.log, query_load_*.log, cloud_viewer_*.log) stay in the work folder.
                shutil.rmtree(work / f"map_{kind}", ignore_errors=True)
                report["rows"].append(measured)
                print(json.dumps(measured), file=sys.stderr)
            seq.updates.clear()
            bag.unlink()
    report["loadavg"] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
