"""Open-loop load on the text-query service: requests at a fixed rate whatever the answers, every one
counted. Shared by tests/test_query_load.py (counted, not timed) and benchmarks/bench_query.py (latency).

A closed-loop client (the next call after the last answer) never has more than one request in flight, so it
cannot show requests that are lost: at 100 queries/s while the node integrated keyframes, 30-43% of the
open-loop requests never reached the callback with the default service QoS (keep-last 10).
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from pathlib import Path
from typing import Any

from monovoc_ros.contract import DEFAULT_NAMESPACE
from monovoc_ros.nodes.qos import SERVICE_QOS

TEXTS = ("a chair", "the sofa", "a lamp", "a small box on the table", "a plant", "something red")


def query_client(node: Any, name: str = f"{DEFAULT_NAMESPACE}/query") -> Any:
    """A TextQuery client whose response queue holds as many answers as the service queues requests."""
    from monovoc_interfaces.srv import TextQuery

    return node.create_client(TextQuery, name, qos_profile=SERVICE_QOS)


def open_loop_queries(client: Any, rate_hz: float, count: int, timeout_s: float = 30.0) -> dict[str, Any]:
    """Sends `count` queries at `rate_hz` (the client's node spins in another thread) and waits up to
    `timeout_s` after the last for the answers: {sent, answered, lost, succeeded, p50_ms, p99_ms, max_ms,
    slowest}; `slowest`: the 5 slowest answered as [time.time() when sent, ms], to set beside the node's log."""
    from monovoc_interfaces.srv import TextQuery

    lock = threading.Lock()
    timed: list[tuple[float, float]] = []  # (time.time() sent, seconds) of each answered query
    succeeded = [0]
    done = threading.Semaphore(0)

    def on_done(future: Any, sent: float, sent_wall: float, n: int) -> None:
        elapsed = time.perf_counter() - sent
        with lock:
            timed.append((sent_wall, elapsed, n))
            succeeded[0] += bool(future.result() is not None and future.result().success)
        done.release()

    futures = []
    start = time.perf_counter()
    for n in range(count):
        due = start + n / rate_hz
        now = time.perf_counter()
        if due > now:
            time.sleep(due - now)
        sent, sent_wall = time.perf_counter(), time.time()
        future = client.call_async(TextQuery.Request(text=TEXTS[n % len(TEXTS)], top_k=5))
        future.add_done_callback(lambda f, sent=sent, sent_wall=sent_wall, n=n: on_done(f, sent, sent_wall, n))
        futures.append(future)
    sending_s = time.perf_counter() - start
    deadline = time.monotonic() + timeout_s
    answered = 0
    while answered < count and done.acquire(timeout=max(0.0, deadline - time.monotonic())):
        answered += 1
    with lock:
        slowest = sorted(timed, key=lambda t: -t[1])
    samples = [seconds for _, seconds, _ in reversed(slowest)]

    def pct(q: float) -> float:
        return round(1e3 * samples[min(len(samples) - 1, int(q * len(samples)))], 1) if samples else float("nan")

    return {
        "sent": count,
        "answered": len(samples),
        "lost": count - len(samples),
        "succeeded": succeeded[0],
        "achieved_hz": round(count / sending_s, 1) if sending_s > 0 else float("inf"),
        "p50_ms": pct(0.50),
        "p99_ms": pct(0.99),
        "max_ms": round(1e3 * samples[-1], 1) if samples else float("nan"),
        # [wall time sent, ms, which query (its text is TEXTS[n % len(TEXTS)]; the first of each is not cached)]
        "slowest": [[round(wall, 3), round(1e3 * seconds, 1), n] for wall, seconds, n in slowest[:5]],
    }


def main(argv: list[str] | None = None) -> int:
    """The load from a process of its own (a user's client is not in the process that replays a robot's maps:
    serializing a 50 MB map message holds that process's interpreter, which would count as the node's
    latency). Waits for the service, then for `--start-file` to exist, sends the queries and writes the
    `open_loop_queries` report as JSON to `--out`."""
    from monovoc_ros.ros_harness import ClientNode

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--rate", type=float, required=True, help="queries per second")
    parser.add_argument("--count", type=int, required=True, help="queries sent")
    parser.add_argument("--start-file", required=True, help="the load starts once this file exists")
    parser.add_argument("--out", required=True, help="JSON report")
    parser.add_argument("--service", default=f"{DEFAULT_NAMESPACE}/query")
    args = parser.parse_args(argv)
    with ClientNode(name="monovoc_query_load") as client:
        service = query_client(client.node, args.service)
        if not service.wait_for_service(timeout_sec=600.0):  # a cold node compiles its kernels first
            raise SystemExit(f"no {args.service} service within 600 s")
        start = Path(args.start_file)
        while not start.exists():
            time.sleep(0.01)
        report = open_loop_queries(service, args.rate, args.count)
    Path(args.out).write_text(json.dumps(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
