"""Live semantic_mapper throughput and latency on a bag replayed over loopback; prints one JSON object.

    scripts/with_env.sh python benchmarks/bench_mapper.py [--bag bags/synthetic_room.mcap] [--mapping-only]

The node runs as a separate process (with the object database and query service unless --mapping-only),
publishing its semantic cloud at most --publish-rate times a second (default 1, the node's default).
First, in this process, the labelling cost of a semantic-cloud update per semantic mode (``labelling``:
votes re-label the Gaussians a keyframe touched; SCD re-quantizes every observed Gaussian). Then two
runs, each on a fresh node, replaying once the node reports its kernels loaded (diagnostics ``warm_up_ms``):
- ``fast``: the bag replayed as fast as possible (reliable, nothing lost): keyframes per second sustained
  from the first message to the last keyframe integrated, mean SCD ms per keyframe, keyframes dropped;
- ``paced``: the bag at --rate times its recorded rate (10 Hz for the synthetic room): per keyframe, the latency
  from its publication (the last of its messages, as the replay sent it) to the arrival of the first semantic
  cloud that includes it (the cloud's stamp is the newest integrated keyframe), p50 / p95 / max ms.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from monovoc_ros.bags import bag_events, bag_info, iter_messages, replay, topic_names  # noqa: E402
from monovoc_ros.core.keyframe import Keyframe  # noqa: E402
from monovoc_ros.core.mapping import MapperConfig, SemanticMapper  # noqa: E402
from monovoc_ros.ros_harness import (  # noqa: E402
    MAPPING_ONLY,
    SEMANTIC_MAPPER,
    ClientNode,
    CloudMonitor,
    DiagnosticsMonitor,
    KeyframePublishTimes,
    NodeProcess,
    cloud_latencies_ms,
    keyframes_settled,
    loopback_environment,
    ros_args,
)


def _one_run(bag: Path, module: str, fast: bool, work: Path, publish_rate: float, rate: float = 1.0) -> dict:
    info = bag_info(bag)
    mask_topic = topic_names()["mask"]
    n = info.topics[mask_topic].count
    stamps = [m.log_time_ns for m in iter_messages(bag, topics=[mask_topic])]
    params = {"publish_rate_hz": publish_rate, "diagnostics_period_s": 0.2, "queue_size": max(32, n)}
    log = work / f"node-{'fast' if fast else 'rate'}.log"
    with (
        NodeProcess.python(["-m", module, *ros_args(params)], name="semantic_mapper", output_path=log) as node,
        ClientNode() as client,
    ):
        diagnostics = DiagnosticsMonitor(client.node, "semantic mapping")
        clouds = CloudMonitor(client.node)
        # As on a robot, where SLAM needs a while for its first keyframe: the node has loaded its kernels.
        warm = diagnostics.wait_for(lambda d: float(d.get("warm_up_ms", 0)) > 0, 300.0, what="warm-up", process=node)
        started: list[float] = []
        published = KeyframePublishTimes()
        replay(
            bag,
            fast=fast,
            rate=rate,
            wait_subscribers=1,
            wait_timeout=60.0,
            on_started=lambda: started.append(time.monotonic()),
            on_published=published,
        )
        done = diagnostics.wait_for(lambda d: keyframes_settled(d, n), 600.0, what="all keyframes", process=node)
        finished = time.monotonic()
        time.sleep(0.5)  # the last cloud
        out = {
            "warm_up_ms": round(float(warm["warm_up_ms"]), 1),
            "keyframes_sent": n,
            "keyframes_processed": int(done["keyframes_processed"]),
            "keyframes_dropped": int(done["keyframes_dropped"]),
            "ms_per_keyframe_mean": round(float(done["ms_per_keyframe_mean"]), 1),
        }
        if fast:
            out["seconds"] = round(finished - started[0], 2)
            out["keyframes_per_second"] = round(n / (finished - started[0]), 2)
            return out
        lat = np.array(cloud_latencies_ms(published.at, clouds.arrivals))
        if not len(lat):
            raise SystemExit(f"no cloud carried a keyframe stamp: {sorted(clouds.arrivals)[:5]} vs {stamps[:3]}")
        out.update(
            keyframes_with_cloud=len(lat),
            latency_ms_p50=round(float(np.percentile(lat, 50)), 1),
            latency_ms_p95=round(float(np.percentile(lat, 95)), 1),
            latency_ms_max=round(float(lat.max()), 1),
            latency_ms_first=[round(float(x), 1) for x in lat[:5]],  # the node's first keyframes
        )
        return out


def _labelling(bag: Path, mode: str) -> dict:
    """In this process: the labelling part of a semantic-cloud update (SemanticMapper.result after each
    keyframe, what the node does before it packs a cloud) for each keyframe of the bag."""
    events = list(bag_events(bag))
    gaussians = next(e for e in events if not isinstance(e, Keyframe) and hasattr(e, "means"))
    mapper = SemanticMapper(gaussians, MapperConfig(semantic_mode=mode))
    times = []
    for keyframe in (e for e in events if isinstance(e, Keyframe)):
        mapper.integrate(keyframe)
        start = time.perf_counter()
        mapper.result()
        times.append(1e3 * (time.perf_counter() - start))
    times = times[1:]  # the first call compiles / loads kernels
    return {
        "gaussians": len(gaussians),
        "ms_p50": round(float(np.median(times)), 2),
        "ms_max": round(float(np.max(times)), 2),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bag", default=str(REPO / "bags" / "synthetic_room.mcap"))
    parser.add_argument("--mapping-only", action="store_true", help="the node without the object database")
    parser.add_argument("--publish-rate", type=float, default=1.0, help="the node's publish_rate_hz (default 1)")
    parser.add_argument("--rate", type=float, default=0.5, help="paced run: multiple of the recorded rate (0.5)")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="monovoc_bench_mapper_"))
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 232)))
    loopback_environment(work / "ros_log")
    module = MAPPING_ONLY if args.mapping_only else SEMANTIC_MAPPER
    bag = Path(args.bag)
    report = {
        "bag": str(bag),
        "node": module,
        "cpus": os.cpu_count(),
        "publish_rate_hz": args.publish_rate,
        "labelling": {mode: _labelling(bag, mode) for mode in ("vote", "scd")},
        "fast": _one_run(bag, module, True, work, args.publish_rate),
        "paced": {"rate": args.rate, **_one_run(bag, module, False, work, args.publish_rate, args.rate)},
        "loadavg": [round(x, 2) for x in os.getloadavg()],
    }
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
