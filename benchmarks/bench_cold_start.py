"""A fresh install's first start (issue 24): numba's cache empty (a new NUMBA_CACHE_DIR), the semantic_mapper
started, then the first keyframe of the synthetic room published as soon as the node subscribes. Prints one
JSON object: seconds from start to subscription (the kernels compiled in a child, then loaded), the node's
own compile and load times, and the seconds from the first keyframe's publication to its integration.

    python benchmarks/bench_cold_start.py            # cold cache
    python benchmarks/bench_cold_start.py --warm     # the install's own (warm) cache, for comparison
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from monovoc_ros.nodes.keyframe_publisher import KeyframePublisher  # noqa: E402
from monovoc_ros.ros_harness import ClientNode, DiagnosticsMonitor, NodeProcess, ros_args  # noqa: E402
from tests.node_scene import NODE, scene_messages, small_scene  # noqa: E402
from tests.rosutil import ros_environment  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--warm", action="store_true", help="keep numba's cache (a second start)")
    args = parser.parse_args()
    scene, messages = small_scene(), scene_messages()
    with tempfile.TemporaryDirectory() as tmp:
        extra = {} if args.warm else {"NUMBA_CACHE_DIR": str(Path(tmp) / "numba_cache")}
        env = ros_environment(Path(tmp), extra=extra)
        params = {"publish_rate_hz": 0.0, "diagnostics_period_s": 0.05}
        with ClientNode(env) as client:
            publisher = KeyframePublisher(client.node)
            diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
            publisher.publish_map(scene.gaussians)  # latched: the node gets it when it subscribes
            started = time.monotonic()
            with NodeProcess.python([*NODE, *ros_args(params)], env, name="semantic_mapper") as node:
                mask = publisher.publishers["mask"]
                while mask.get_subscription_count() == 0 or any(
                    p.get_subscription_count() == 0 for p in publisher.all_publishers()
                ):
                    node.check_running()
                    time.sleep(0.01)
                subscribed = time.monotonic() - started
                diagnostics.wait_for(lambda v: v["has_map"] == "true", 30.0, process=node)
                sent = time.monotonic()
                publisher.publish_messages(messages[0])
                done = diagnostics.wait_for(lambda v: v["keyframes_processed"] == "1", 60.0, process=node)
                first = time.monotonic() - sent
                node.stop()
    print(
        json.dumps(
            {
                "cache": "warm" if args.warm else "cold",
                "start_to_subscribed_s": round(subscribed, 2),
                "kernel_compile_s": round(float(done["kernel_compile_ms"]) / 1e3, 2),
                "kernel_load_s": round(float(done["warm_up_ms"]) / 1e3, 2),
                "first_keyframe_published_to_integrated_s": round(first, 3),
                "first_keyframe_ms_in_worker": float(done["ms_per_keyframe_last"]),
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
