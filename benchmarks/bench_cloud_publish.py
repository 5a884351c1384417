"""What sending the semantic cloud costs the node's other threads: rclpy's publish of a message against the CDR
bytes sent through rcl without the interpreter (nodes/serialized_publisher.py); prints JSON.

    scripts/with_env.sh python benchmarks/bench_cloud_publish.py                    # 600k points, as a 1M map's
    scripts/with_env.sh python benchmarks/bench_cloud_publish.py --busy 2         # both cores kept busy meanwhile

One subscriber in another process (monovoc_ros.nodes.cloud_viewer, as RViz), loopback. Per way, alternating
rounds: building the cloud from the node's arrays (`build_ms`), sending it (`send_ms`), and the longest time the
node's interpreter watch (nodes/interpreter_watch.py, waking every 0.5 ms) found the interpreter held during the
send (`send_hold_ms`): what a query waits for while the worker sends. Medians and maxima over the rounds. `--busy N`
keeps N processes spinning meanwhile, as a robot run's other processes keep the cores busy.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import msg_adapters as ma  # noqa: E402
from monovoc_ros.nodes.interpreter_watch import InterpreterWatch  # noqa: E402
from monovoc_ros.nodes.qos import latched_qos  # noqa: E402
from monovoc_ros.nodes.serialized_publisher import SerializedPublisher, loaded_rcl  # noqa: E402
from monovoc_ros.ros_harness import ClientNode, NodeProcess, wait_until  # noqa: E402

TICK_S = 0.0005
TOPIC = "bench_cloud"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=600_000, help="points of the cloud (a 1M map labels ~600k)")
    parser.add_argument("--rounds", type=int, default=20, help="sends per way")
    parser.add_argument("--busy", type=int, default=0, help="processes spinning beside the run")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    ids = rng.integers(0, 1 << 24, args.points, dtype=np.uint32)
    arrays = (rng.normal(size=(args.points, 3)).astype(np.float32), ids, ids, rng.uniform(0, 1, args.points))
    spinning = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy)]
    try:
        times = _rounds(args, arrays)
    finally:
        for p in spinning:
            p.kill()
            p.wait()
    report = {
        "points": args.points,
        "cloud_mb": round(args.points * 24 / 1e6, 1),
        "rounds": args.rounds,
        "busy_processes": args.busy,
        "releases_interpreter": loaded_rcl() is not None,
        **{
            way: {
                f"{k}_{stat}": round(float(fn(v)), 2)
                for k, v in t.items()
                for stat, fn in (("median", np.median), ("max", np.max))
            }
            for way, t in times.items()
        },
    }
    print(json.dumps(report, indent=1))


def _rounds(args: argparse.Namespace, arrays: tuple[np.ndarray, ...]) -> dict[str, dict[str, list[float]]]:
    """Per way, the build, send and hold times (ms) of each round."""
    from sensor_msgs.msg import PointCloud2

    times: dict[str, dict[str, list[float]]] = {w: {"build_ms": [], "send_ms": [], "send_hold_ms": []} for w in
                                                ("rclpy_message", "bytes_without_interpreter")}  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp, ClientNode(name="bench_cloud_publisher") as host:
        files = {k: Path(tmp) / k for k in ("ready", "stop", "out")}
        publisher = host.node.create_publisher(PointCloud2, TOPIC, latched_qos())
        sender = SerializedPublisher(publisher)
        viewer_args = ["-m", "monovoc_ros.nodes.cloud_viewer", "--topic", f"/{TOPIC}", "--ready-file",
                       str(files["ready"]), "--stop-file", str(files["stop"]), "--out", str(files["out"])]  # fmt: skip
        with NodeProcess.python(viewer_args, name="cloud_viewer", output_path=Path(tmp) / "viewer.log") as viewer:
            wait_until(files["ready"].exists, 120.0, "the viewer", process=viewer)
            wait_until(lambda: publisher.get_subscription_count() == 1, 60.0, "the subscription", process=viewer)
            watch = InterpreterWatch(period_s=TICK_S)
            watch.start()
            try:
                for i in range(2 * args.rounds):
                    way = "rclpy_message" if i % 2 == 0 else "bytes_without_interpreter"
                    start = time.perf_counter()
                    if way == "rclpy_message":
                        message = ma.semantic_cloud_from_arrays(*arrays, frame_id="map", stamp=i + 1)
                    else:
                        message = ma.serialized_semantic_cloud(*arrays, frame_id="map", stamp=i + 1)
                    built = time.perf_counter()
                    watch.reset()
                    (publisher if way == "rclpy_message" else sender).publish(message)
                    sent = time.perf_counter()
                    time.sleep(0.005)  # the wake that ends a hold at the send's end
                    times[way]["build_ms"].append(1e3 * (built - start))
                    times[way]["send_ms"].append(1e3 * (sent - built))
                    times[way]["send_hold_ms"].append(watch.diagnostics()["interpreter_hold_ms_max"])
                    time.sleep(0.1)  # the viewer takes it
            finally:
                watch.stop()
                files["stop"].touch()
            wait_until(lambda: not viewer.running(), 60.0, "the viewer to end", process=None)
    return times


if __name__ == "__main__":
    main()
