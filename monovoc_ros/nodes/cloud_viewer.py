"""A viewer of the semantic cloud from a process of its own, as RViz is: records when each cloud arrived, for
the latency of benchmarks/bench_robot_scale.py.

It used to be a subscription of the benchmark's own process, the one that replays the bag: while that process
serialized a 56 MB map message (rclpy holds the interpreter) its viewer took no cloud, which a robot's viewer,
not in its SLAM's process, does not suffer (the query client left that process for the same reason,
monovoc_ros.nodes.query_load).

Arrival times are ``time.monotonic()`` (CLOCK_MONOTONIC: one clock for every process of the machine), so the
caller sets them beside its own publication times (ros_harness.cloud_latencies_ms).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

POLL_S = 0.01


def main(argv: list[str] | None = None) -> int:
    """Subscribes to the semantic cloud; once the node publishes it, writes `--ready-file`; writes
    {"arrivals": {stamp ns: monotonic s}} as JSON to `--out` whenever a new stamp arrived (replaced whole), and
    exits once `--stop-file` exists."""
    from monovoc_ros.ros_harness import ClientNode, CloudMonitor

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--topic", help="the semantic cloud's topic (default: the node's, ros_harness.CloudMonitor)")
    parser.add_argument("--ready-file", required=True, help="written once the cloud's publisher is seen")
    parser.add_argument("--stop-file", required=True, help="the viewer ends once this file exists")
    parser.add_argument("--out", required=True, help="JSON: when each cloud stamp first arrived")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds to wait for the publisher")
    args = parser.parse_args(argv)
    with ClientNode(name="monovoc_cloud_viewer") as client:
        clouds = CloudMonitor(client.node, *([args.topic] if args.topic else []))
        topic = clouds.subscription.topic_name
        deadline = time.monotonic() + args.timeout
        while client.node.count_publishers(topic) == 0:  # a cold node compiles its kernels first
            if time.monotonic() > deadline:
                raise SystemExit(f"no publisher of {topic} within {args.timeout:.0f} s")
            time.sleep(POLL_S)
        Path(args.ready_file).touch()
        stop, out, written = Path(args.stop_file), Path(args.out), -1
        while True:
            stopping = stop.exists()
            arrivals = clouds.arrivals_now()
            if len(arrivals) != written:  # a caller can wait for a stamp in the file before it stops the viewer
                partial = out.with_name(out.name + ".part")
                partial.write_text(json.dumps({"arrivals": {str(k): v for k, v in arrivals.items()}}))
                partial.replace(out)
                written = len(arrivals)
            if stopping:
                break
            time.sleep(POLL_S)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
