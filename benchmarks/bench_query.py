"""Object index and text-query timings, and semantic memory per scene, printed as JSON.

    scripts/with_env.sh python benchmarks/bench_query.py [--gaussians 140000] [--keyframes 60] [--no-ros]

On a synthetic room (default: the full 140k-Gaussian, 60-keyframe scene at 616x344):
- ``build``: ms per keyframe to offer object views (the node's keyframe hook), and the first full refresh
  (summaries + embedding every object's views);
- ``offline``: query latency on the index alone (text embedding + cosine ranking), p50 / p99 ms;
- ``memory``: semantic bytes of this scene (per-Gaussian object index + records + embeddings) and of the
  reference scene of 140k Gaussians and 100 objects, against MonoVoc's 14 MB, with the vote state
  (mapping state) and the view cache reported separately;
- ``service`` (unless --no-ros): round-trip latency through the live node's ``/monovoc/query`` at 100
  queries/s, p50 / p99 ms, on a map resumed from the first half of the keyframes (idle), and on the same
  map while the other half is published into the node at 10 Hz (it integrates them and re-embeds the
  objects that get better views);
- ``open_loop_while_mapping`` (unless --no-ros): 100 queries/s sent whatever the answers (open loop,
  monovoc_ros.nodes.query_load) while keyframes arrive at 3/s: sent / answered / lost, p50 / p99 ms.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import random
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

# The benchmark runs from a checkout; make the package importable without installing it.
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from monovoc_ros.ros_harness import FOREIGN_ROS_VARIABLES  # noqa: E402

QUERIES = [
    "a sofa",
    "the red book on the table",
    "a lamp",
    "something to sit on",
    "the small box on the table",
    "a potted plant",
    "the orange ball",
    "a television",
    "where can I put my cup",
    "a tall bookshelf with books",
]


def _percentiles(samples_s: list[float]) -> dict:
    ms = np.asarray(samples_s) * 1e3
    return {
        "n": len(ms),
        "p50_ms": round(float(np.percentile(ms, 50)), 2),
        "p99_ms": round(float(np.percentile(ms, 99)), 2),
        "max_ms": round(float(ms.max()), 2),
    }


def build(args):
    from monovoc_ros.core.evidence.palette import labels_from_entries
    from monovoc_ros.core.map_store import save_snapshot
    from monovoc_ros.core.mapping import SemanticMapper
    from monovoc_ros.embed import load_backend
    from monovoc_ros.objects.database import save_object_index
    from monovoc_ros.objects.index import IndexConfig, ObjectIndex
    from monovoc_ros.synthetic import SceneConfig, generate_scene

    scene = generate_scene(SceneConfig(n_gaussians=args.gaussians, n_keyframes=args.keyframes))
    backend = load_backend("conse")
    mapper = SemanticMapper(scene.gaussians)
    index = ObjectIndex(backend, IndexConfig(labels=labels_from_entries(scene.labels())))
    observe = []
    half = len(scene) // 2
    directory = Path(tempfile.mkdtemp(prefix="bench-query-"))
    for i in range(len(scene)):
        keyframe = scene.keyframe(i)
        mapper.integrate(keyframe)
        start = time.perf_counter()
        index.keyframe_listener(keyframe, mapper)
        observe.append(time.perf_counter() - start)
        if i == half - 1:
            # The map the service benchmark resumes from: the node then integrates the other half.
            refresh = index.refresh(mapper)
            info = save_snapshot(mapper, directory, export_cloud=False)
            saved = save_object_index(index, directory, snapshot=info.path.name, keyframes=mapper.n_keyframes)
    index.refresh(mapper)
    again = index.refresh(mapper)
    (directory / "labels.json").write_text(json.dumps(scene.labels()))
    result = {
        "scene": {"gaussians": len(scene.gaussians), "keyframes": len(scene), "objects": len(index)},
        "observe_ms_per_keyframe": _percentiles(observe),
        "first_refresh_half_the_keyframes": {
            "seconds": round(refresh.seconds, 3),
            "views_embedded": refresh.embedded_views,
            "objects": refresh.embedded_objects,
        },
        "unchanged_refresh_ms": round(1e3 * again.seconds, 2),
        "save_objects_db": {"seconds": round(saved.seconds, 3), "bytes": (directory / "objects.db").stat().st_size},
    }
    return scene, mapper, index, directory, result


def offline(index, repeats: int) -> dict:
    index.query("warm up")
    samples = []
    for n in range(repeats):
        start = time.perf_counter()
        index.query(QUERIES[n % len(QUERIES)], top_k=5)
        samples.append(time.perf_counter() - start)
    return _percentiles(samples)


def memory(index, mapper) -> dict:
    from monovoc_ros.objects.memory import measure_memory, semantic_memory

    return {
        "this_scene": measure_memory(index, mapper).to_dict(),
        "reference_140k_gaussians_100_objects": semantic_memory(140_000, 100, index.backend.dim).to_dict(),
    }


def _ros_env(tmp: Path) -> dict:
    from monovoc_ros.embed import default_model_dir

    env = dict(os.environ)
    for key in FOREIGN_ROS_VARIABLES:
        env.pop(key, None)
    venv = REPO / ".venv"
    env.update(
        ROS_DOMAIN_ID=str(random.SystemRandom().randint(1, 232)),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_LOG_DIR=str(tmp / "ros_log"),
        MONOVOC_MODEL_DIR=str(default_model_dir()),
        AMENT_PREFIX_PATH=str(venv),
        PYTHONPATH=str(REPO),
        PYTHONUNBUFFERED="1",
    )
    return env


class _Client:
    """An rclpy node on the benchmark's domain, spun in a background thread."""

    def __init__(self, env: dict) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOG_DIR", "AMENT_PREFIX_PATH"):
            os.environ[key] = env[key]
        self.context = rclpy.Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("bench_query_client", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=5.0)
        self.thread.join(5.0)
        self.node.destroy_node()
        self.context.try_shutdown()


def _call(client, request, timeout: float = 10.0):
    response = client.call(request, timeout_sec=timeout)  # the executor spins in another thread
    if response is None:
        raise TimeoutError("no answer from /monovoc/query")
    return response


def _paced_queries(client, seconds: float, rate_hz: float) -> dict:
    """Queries at ``rate_hz`` for ``seconds``; latency per call (a late call starts at once)."""
    from monovoc_interfaces.srv import TextQuery

    samples, failures = [], 0
    period = 1.0 / rate_hz
    start = time.perf_counter()
    n = 0
    while time.perf_counter() - start < seconds:
        due = start + n * period
        now = time.perf_counter()
        if due > now:
            time.sleep(due - now)
        t0 = time.perf_counter()
        response = _call(client, TextQuery.Request(text=QUERIES[n % len(QUERIES)], top_k=5))
        samples.append(time.perf_counter() - t0)
        failures += not response.success
        n += 1
    out = _percentiles(samples)
    out.update(achieved_hz=round(n / (time.perf_counter() - start), 1), failures=failures)
    return out


def _feed(publisher, messages: list, period: float = 0.1) -> None:
    for msgs in messages:  # 10 Hz, like a SLAM front-end's keyframes at most (3 Hz for the open loop)
        publisher.publish_messages(msgs)
        time.sleep(period)


def service(scene, directory: Path, seconds: float) -> dict:
    from monovoc_interfaces.srv import TextQuery
    from monovoc_ros.nodes.keyframe_publisher import KeyframePublisher, keyframe_messages
    from monovoc_ros.nodes.query_load import open_loop_queries, query_client

    tmp = Path(tempfile.mkdtemp(prefix="bench-query-ros-"))
    env = _ros_env(tmp)
    (tmp / "ros_log").mkdir()
    out = {}
    for phase in ("idle", "mapping", "open_loop_while_mapping"):
        # Both phases resume the map of the first half of the keyframes (a copy: nodes save into it).
        copy = tmp / f"map-{phase}"
        shutil.copytree(directory, copy)
        params = ["-p", f"map_directory:={copy}", "-p", "resume:=true", "-p", "save_period_s:=0.0"]
        params += ["-p", f"labels_file:={directory / 'labels.json'}"]
        log = open(tmp / f"{phase}.out", "w")
        proc = subprocess.Popen(
            [sys.executable, "-m", "monovoc_ros.nodes.semantic_mapper", "--ros-args", *params],
            env=env,
            cwd=REPO,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        client = _Client(env)
        try:
            cli = query_client(client.node)
            if not cli.wait_for_service(timeout_sec=60.0):
                raise RuntimeError(f"node did not come up; see {tmp / (phase + '.out')}")
            feeder = None
            if phase != "idle":
                publisher = KeyframePublisher(client.node)
                deadline = time.monotonic() + 30
                while any(p.get_subscription_count() == 0 for p in publisher.all_publishers()):
                    if time.monotonic() > deadline:
                        raise RuntimeError("node did not subscribe")
                    time.sleep(0.05)
                messages = [keyframe_messages(scene.keyframe(i)) for i in range(len(scene) // 2, len(scene))]

                period = 0.1 if phase == "mapping" else 1 / 3
                feeder = threading.Thread(target=_feed, args=(publisher, messages, period), daemon=True)
                feeder.start()
                seconds_here = min(seconds, period * len(messages))
            else:
                seconds_here = seconds
            _call(cli, TextQuery.Request(text="warm up"), 30.0)
            if phase == "open_loop_while_mapping":
                out[phase] = open_loop_queries(cli, 100.0, int(100 * seconds_here), timeout_s=30.0)
            else:
                out[phase] = _paced_queries(cli, seconds_here, 100.0)
            if feeder is not None:
                feeder.join()
        finally:
            client.close()
            proc.send_signal(2)
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
            log.close()
    shutil.rmtree(tmp, ignore_errors=True)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=140_000)
    parser.add_argument("--keyframes", type=int, default=60)
    parser.add_argument("--repeats", type=int, default=300, help="offline queries timed")
    parser.add_argument("--seconds", type=float, default=5.0, help="seconds of service queries per phase")
    parser.add_argument("--no-ros", action="store_true", help="skip the live-node service measurements")
    args = parser.parse_args(argv)

    scene, mapper, index, directory, result = build(args)
    try:
        result["offline"] = offline(index, args.repeats)
        result["memory"] = memory(index, mapper)
        if not args.no_ros:
            result["service_100hz"] = service(scene, directory, args.seconds)
    finally:
        shutil.rmtree(directory, ignore_errors=True)
    result["machine"] = {"cpus": os.cpu_count(), "python": platform.python_version()}
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
