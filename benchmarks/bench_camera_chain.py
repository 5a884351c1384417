"""The live chain a robot with only a camera runs: segmenter node + semantic_mapper on real keyframes; prints JSON.

    scripts/with_env.sh python benchmarks/bench_camera_chain.py [--keyframes-per-s 1.0] [--model yolov5s-seg]

Replica office_0 (81 RGB keyframes, 204k Gaussians) is written as a camera-only bag (`monovoc bag convert
--mask-format none`: image, camera_info, pose, the Gaussian map) and replayed over loopback at a SLAM's
keyframe rate into the two nodes, wired as `ros2 launch ... segmenter:=true` wires them (the mapper with
`mask_transport: raw`, `mask_ids: per_frame`, `use_segments: true`, `min_support` and `min_object_score`
0.5, the semantic cloud published whenever its queue is empty). Per keyframe, the latency from the image's
publication (the last of its keyframe's messages, as the replay sent it) to the first semantic cloud that
includes it (the cloud's stamp is the newest integrated keyframe): p50 / p95 / max ms; keyframes segmented,
dropped by the segmenter (newest wins), integrated and refused (all-void masks); the segmenter's mean ms.
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

from monovoc_ros.bags import iter_messages, replay, sequence_to_bag, topic_names  # noqa: E402
from monovoc_ros.core.evaluation.datasets import open_sequence  # noqa: E402
from monovoc_ros.ros_harness import (  # noqa: E402
    SEMANTIC_MAPPER,
    ClientNode,
    CloudMonitor,
    DiagnosticsMonitor,
    KeyframePublishTimes,
    NodeProcess,
    cloud_latencies_ms,
    loopback_environment,
    ros_args,
)

REPLICA = REPO.parent / "shared" / "data" / "replica_office0"
# The launch file's segmenter:=true settings of the mapper (launch/monovoc.launch.py).
MAPPER_PARAMS = {
    "mask_transport": "raw",
    "mask_ids": "per_frame",
    "use_segments": True,
    "min_support": 0.5,
    "min_object_score": 0.5,
    "publish_rate_hz": 0.0,
    "diagnostics_period_s": 0.2,
}


def run(bag: Path, work: Path, model: str, rate: float) -> dict:
    image_topic = topic_names()["image"]
    stamps = [m.log_time_ns for m in iter_messages(bag, topics=[image_topic])]
    n = len(stamps)
    with (
        NodeProcess.python(["-m", SEMANTIC_MAPPER, *ros_args({**MAPPER_PARAMS, "queue_size": n})],
                           name="semantic_mapper", output_path=work / "mapper.log") as mapper,
        NodeProcess.python(["-m", "monovoc_ros.nodes.segmenter", *ros_args({"model": model})],
                           name="segmenter", output_path=work / "segmenter.log") as segmenter,
        ClientNode() as client,
    ):  # fmt: skip
        mapping = DiagnosticsMonitor(client.node, "semantic mapping")
        segmenting = DiagnosticsMonitor(client.node, "segmenter")
        clouds = CloudMonitor(client.node)
        mapping.wait_for(lambda d: float(d.get("warm_up_ms", 0)) > 0, 300.0, what="warm-up", process=mapper)
        segmenting.wait_for(lambda d: "segmented" in d, 120.0, what="the segmenter", process=segmenter)
        published = KeyframePublishTimes()
        replay(bag, rate=rate, wait_subscribers=1, wait_timeout=60.0, on_published=published)
        seg = segmenting.wait_for(
            lambda d: int(d["segmented"]) + int(d["dropped"]) + int(d["bad_images"]) == int(d["received"]) > 0,
            120.0,
            process=segmenter,
        )
        made = int(seg["segmented"])
        done = mapping.wait_for(
            lambda d: int(d["keyframes_processed"]) + int(d["rejected.void_mask"]) >= made, 300.0, process=mapper
        )
        time.sleep(1.0)  # the last cloud
        lat = np.array(cloud_latencies_ms(published.at, clouds.arrivals))
        return {
            "keyframes_sent": n,
            "keyframes_per_s": round(rate * (n - 1) / ((stamps[-1] - stamps[0]) / 1e9), 2),
            "segmented": made,
            "segmenter_dropped": int(seg["dropped"]),
            "segmenter_ms_mean": round(float(seg["ms_mean"]), 1),
            "integrated": int(done["keyframes_processed"]),
            "refused_void_masks": int(done["rejected.void_mask"]),
            "mapper_ms_mean": round(float(done["ms_per_keyframe_mean"]), 1),
            "objects": int(done["objects"]),
            "keyframes_with_cloud": len(lat),
            "latency_ms_p50": round(float(np.percentile(lat, 50)), 1) if len(lat) else None,
            "latency_ms_p95": round(float(np.percentile(lat, 95)), 1) if len(lat) else None,
            "latency_ms_max": round(float(lat.max()), 1) if len(lat) else None,
        }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--keyframes-per-s", type=float, default=1.0, help="a SLAM's keyframe rate (default 1)")
    parser.add_argument("--model", default="yolov5s-seg")
    args = parser.parse_args()
    if not (REPLICA / "traj.txt").exists():
        print(f"{REPLICA} not present: nothing to measure", file=sys.stderr)
        return 1
    work = Path(tempfile.mkdtemp(prefix="monovoc_bench_chain_"))
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 232)))
    loopback_environment(work / "ros_log")
    sequence = open_sequence(str(REPLICA))
    bag = work / "office0_camera.mcap"
    sequence_to_bag(sequence, bag, mask_format="none")
    stamps = np.asarray(sequence.stamps_ns, np.int64)
    recorded = (len(stamps) - 1) / ((stamps[-1] - stamps[0]) / 1e9)  # keyframes per second in the bag
    report = {
        "source": str(REPLICA),
        "model": args.model,
        "cpus": os.cpu_count(),
        **run(bag, work, args.model, args.keyframes_per_s / recorded),
        "loadavg": [round(x, 2) for x in os.getloadavg()],
    }
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
