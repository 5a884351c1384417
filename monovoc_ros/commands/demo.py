"""`monovoc demo`: the bundled bag through the live nodes, then a few text queries.

    monovoc demo                                  # bags/synthetic_room.mcap, replayed as fast as possible
    monovoc demo --bag bags/replica_office0.mcap --rate 1 --query "a chair" --query "a plant"

Starts the `semantic_mapper` node with its object database and query service (python -m
monovoc_ros.nodes.semantic_mapper) as a separate process, replays the bag into it with `monovoc replay`'s
player, waits on /diagnostics until every keyframe is integrated and every object embedded, saves the map
with the save_map service, asks the query service, and scores the semantic map against the bag's masks as
`monovoc eval` does (the live cloud as discs; the saved map rendered through its Gaussians, with a figure).
Exit codes: 0 done, 1 a step failed.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
import types
from pathlib import Path
from typing import Any

from monovoc_ros.commands.argument_types import at_least, non_negative, positive
from monovoc_ros.ros_harness import (
    NAMESPACE,
    SEMANTIC_MAPPER,
    ClientNode,
    CloudMonitor,
    DiagnosticsMonitor,
    HarnessError,
    NodeProcess,
    call_service,
    keyframes_settled,
    loopback_environment,
    ros_args,
    wait_for_service,
)

DEFAULT_QUERIES = ("a sofa", "a television", "a potted plant", "the orange ball", "the small box on the table")


class DemoError(RuntimeError):
    """A step of the demo failed; the message says which and why."""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo",
        help="replay the bundled bag through the live nodes and answer a few text queries",
        description="Starts the semantic_mapper node (with the object database and the /monovoc/query "
        "service) as a separate process, replays BAG into it, waits until every keyframe is integrated and "
        "every object embedded, saves the map (save_map service), prints the answers to the queries "
        "(object, score, 3D position) and writes the semantic PLY, a rendered semantic image and a JSON summary.",
    )
    p.add_argument("--bag", default=None, help="MCAP bag to replay (default: bags/synthetic_room.mcap)")
    p.add_argument("-o", "--out", default="out/demo", help="output directory (default out/demo; its map/ is replaced)")
    speed = p.add_mutually_exclusive_group()
    speed.add_argument("--rate", type=positive, default=None, help="replay at R times the recorded rate")
    speed.add_argument("--fast", action="store_true", help="replay as fast as possible (the default)")
    p.add_argument(
        "--query", action="append", default=None, metavar="TEXT", help="a text query (repeatable; default: a few)"
    )
    p.add_argument("--top-k", type=at_least(1), default=3, help="answers per query (default 3)")
    p.add_argument(
        "--timeout", type=non_negative, default=300.0, help="seconds allowed for each waiting step (default 300)"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from monovoc_ros.bags.bundled import bundled_bag

    try:
        summary = run_demo(
            Path(args.bag) if args.bag else bundled_bag(),
            Path(args.out),
            queries=tuple(args.query or DEFAULT_QUERIES),
            rate=args.rate,
            top_k=args.top_k,
            timeout=args.timeout,
        )
    except DemoError as exc:
        print(f"monovoc demo: {exc}", file=sys.stderr)
        return 1
    print(f"\nsummary: {summary}")
    return 0


def run_demo(
    bag: Path,
    out: Path,
    *,
    queries: tuple[str, ...] = DEFAULT_QUERIES,
    rate: float | None = None,
    top_k: int = 3,
    timeout: float = 300.0,
) -> Path:
    """Runs the demo; returns the path of its JSON summary. Raises DemoError."""
    from monovoc_ros.bags import BagError, bag_info, bag_labels, topic_names

    if not bag.is_file():
        raise DemoError(f"{bag} does not exist (make it with `monovoc bag make-bundled`)")
    try:
        info = bag_info(bag)
    except BagError as exc:
        raise DemoError(str(exc)) from exc
    mask_topic = topic_names(NAMESPACE)["mask"]
    if mask_topic not in info.topics:
        raise DemoError(f"{bag} has no {mask_topic} topic (topics: {sorted(info.topics)})")
    n_keyframes = info.topics[mask_topic].count
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    map_dir = out / "map"
    shutil.rmtree(map_dir, ignore_errors=True)
    labels_file = out / "labels.json"
    labels_file.write_text(json.dumps(bag_labels(bag)))
    loopback_environment(out / "ros_log")
    params = {
        "map_directory": str(map_dir),
        "labels_file": str(labels_file),
        "save_period_s": 0.0,
        "publish_rate_hz": 2.0,
        "diagnostics_period_s": 0.5,
        "queue_size": max(32, n_keyframes),
    }
    log_path = out / "semantic_mapper.log"
    print(f"[demo] starting semantic_mapper (log: {log_path})", flush=True)
    try:
        command = ["-m", SEMANTIC_MAPPER, *ros_args(params)]
        with (
            NodeProcess.python(command, name="semantic_mapper", output_path=log_path) as mapper,
            ClientNode() as client,
        ):
            return _session(client.node, mapper, bag, out, n_keyframes, queries, rate, top_k, timeout)
    except HarnessError as exc:
        raise DemoError(str(exc)) from exc


def _session(node, mapper, bag, out, n_keyframes, queries, rate, top_k, timeout) -> Path:
    from monovoc_interfaces.srv import SaveMap, TextQuery
    from monovoc_ros.bags import replay

    diagnostics = DiagnosticsMonitor(node, "semantic mapping")
    clouds = CloudMonitor(node)
    query = node.create_client(TextQuery, f"{NAMESPACE}/query")
    save = node.create_client(SaveMap, f"{NAMESPACE}/save_map")
    for client in (query, save):
        wait_for_service(client, timeout, process=mapper)
    how = "as fast as possible" if rate is None else f"at {rate:g}x the recorded rate"
    print(f"[demo] replaying {bag} ({n_keyframes} keyframes) {how}", flush=True)
    started: list[float] = []  # when the node had subscribed to every topic and publishing began
    played = replay(
        bag,
        fast=rate is None,
        rate=rate or 1.0,
        wait_subscribers=1,
        wait_timeout=timeout,
        on_started=lambda: started.append(time.monotonic()),
    )
    if played.unacked:
        raise DemoError(f"the node did not acknowledge messages on {played.unacked}")
    start = started[0]
    replay_s = time.monotonic() - start

    diag = diagnostics.wait_for(
        lambda d: keyframes_settled(d, n_keyframes), timeout, what="every keyframe integrated", process=mapper
    )
    mapped_s = time.monotonic() - start
    if int(diag["keyframes_processed"]) != n_keyframes:
        lost = {k: v for k, v in diag.items() if k.startswith(("sync_", "rejected")) and v != "0"}
        raise DemoError(f"{diag['keyframes_processed']} of {n_keyframes} keyframes integrated: {lost}")
    diag = diagnostics.wait_for(
        lambda d: int(d["objects.indexed"]) > 0 and int(d["objects.pending"]) == 0 and int(d["queue_length"]) == 0,
        timeout,
        what="every object embedded",
        process=mapper,
    )
    indexed_s = time.monotonic() - start
    print(
        f"[demo] {diag['keyframes_processed']}/{n_keyframes} keyframes integrated in {mapped_s:.1f} s "
        f"(replay {replay_s:.1f} s, {float(diag['ms_per_keyframe_mean']):.0f} ms per keyframe), "
        f"{diag['objects']} objects, {diag['objects.indexed']} embedded after {indexed_s:.1f} s",
        flush=True,
    )
    saved = call_service(save, SaveMap.Request(), timeout, process=mapper)
    if not saved.success:
        raise DemoError(f"save_map failed: {saved.message}")

    answers = []
    for text in queries:
        answer = call_service(query, TextQuery.Request(text=text, top_k=top_k, min_score=-1.0), timeout, process=mapper)
        answers.append(_print_answer(text, answer))

    cloud = clouds.latest()
    if cloud is None:
        raise DemoError("no semantic cloud was received")
    evaluation = _render(bag, cloud, Path(saved.directory), out)
    summary = {
        "bag": str(bag),
        "keyframes_sent": n_keyframes,
        "keyframes_processed": int(diag["keyframes_processed"]),
        "keyframes_dropped": int(diag["keyframes_dropped"]),
        "ms_per_keyframe_mean": round(float(diag["ms_per_keyframe_mean"]), 1),
        "seconds_to_map": round(mapped_s, 1),
        "seconds_to_index": round(indexed_s, 1),
        "objects": int(diag["objects"]),
        "objects_embedded": int(diag["objects.indexed"]),
        "live_cloud_points": int(len(cloud.points)),
        **evaluation,
        "map_directory": saved.directory,
        "semantic_ply": str(Path(saved.directory) / "semantic.ply"),
        "object_database": str(Path(saved.directory) / "objects.db"),
        "queries": answers,
    }
    path = out / "demo.json"
    path.write_text(json.dumps(summary, indent=1))
    print(f"\n[demo] semantic PLY:       {summary['semantic_ply']}")
    print(f"[demo] object database:    {summary['object_database']}")
    print(
        f"[demo] rendered semantics: {summary['figure']} (mIoU over {summary['frames_evaluated']} keyframes: "
        f"{100 * summary['miou_splats']:.1f}% rendered through the Gaussians, {100 * summary['miou_points']:.1f}% "
        f"with the live cloud as 5 cm discs)"
    )
    print(f"[demo] offline query:      monovoc query --map {saved.directory} 'a sofa'")
    return path


def _print_answer(text: str, answer: Any) -> dict:
    from monovoc_ros.core.evidence.palette import format_object_id
    from monovoc_ros.core.segments.object_labels import ObjectLabel, display

    print(f"\nquery: {text!r} -> {answer.message}")
    found = []
    for rank, o in enumerate(answer.objects, start=1):
        c = (o.centroid.x, o.centroid.y, o.centroid.z)
        label = display(ObjectLabel.stored(o.label, o.label_source)) or "-"
        print(
            f"  {rank}. {label:12s} {format_object_id(o.id)}  score {o.score:.3f}"
            f"  at ({c[0]:6.2f}, {c[1]:6.2f}, {c[2]:6.2f}) m"
            f"  size {o.extent.x:.2f} x {o.extent.y:.2f} x {o.extent.z:.2f} m"
        )
        found.append(
            {
                "id": format_object_id(o.id),
                "label": o.label,
                "label_source": o.label_source,
                "score": round(float(o.score), 4),
                "centroid": c,
            }
        )
    return {"text": text, "success": bool(answer.success), "message": answer.message, "objects": found}


def _render(bag: Path, cloud: Any, map_dir: Path, out: Path) -> dict:
    """Scores the semantic map as `monovoc eval` does: the live cloud with the paper's points protocol, the
    saved map rendered through its Gaussians (splats); the figure shows the splats renderings."""
    import numpy as np

    from monovoc_ros.bags import bag_labels
    from monovoc_ros.commands.eval import bag_frames, score, write_figure
    from monovoc_ros.core.evidence.palette import labels_from_entries
    from monovoc_ros.core.map_store import load_snapshot

    frames = bag_frames(bag, every=3)
    points = types.SimpleNamespace(means=cloud.points)  # all that the points protocol reads of a map
    on_points, _ = score(points, cloud.object_ids, frames, "points", 0.05)
    mapper = load_snapshot(map_dir)
    on_splats, rendered = score(mapper.gaussians, mapper.result().object_ids, frames, "splats", 0.05)
    figure = out / "semantic_render.png"
    write_figure(
        figure, frames, ("splats", rendered, on_splats), labels_from_entries(bag_labels(bag)), mapper.config.metric
    )
    return {
        "frames_evaluated": len(frames),
        "miou_points": round(float(on_points["miou"]), 4),
        "mismatch_nonwhite_points": round(float(on_points["mismatch_nonwhite"]), 4),
        "miou_splats": round(float(on_splats["miou"]), 4),
        "mismatch_nonwhite_splats": round(float(on_splats["mismatch_nonwhite"]), 4),
        "figure": str(figure),
        "objects_in_cloud": int(len(np.unique(cloud.object_ids))),
    }
