"""`monovoc query`: ask the live `/monovoc/query` service, or a saved map's objects.db, for objects.

    monovoc query "the sofa" [--top-k 3] [--min-score S] [--namespace /monovoc] [--timeout 10]
    monovoc query --map DIR "the sofa"        # offline, no ROS graph

This machine has no ros2 CLI; this is the client. Exit codes: 0 answered, 1 the query failed (empty text,
no objects yet, models missing), 2 the service is absent or did not answer in time, the map is unreadable, or an
argument is refused (argparse's line).
"""

from __future__ import annotations

import argparse
import json
import sys

from monovoc_ros.commands.argument_types import add_service_options, at_least, finite


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "query",
        help="text query for objects: the live node's service, or a saved map (--map)",
        description="Ranks the map's objects by similarity to TEXT and prints rank, id (palette color), label, "
        "score, centroid and extent (metres, map frame). Without --map it calls the TextQuery service "
        "<namespace>/query of a running semantic_mapper node (python -m monovoc_ros.nodes.semantic_mapper).",
    )
    p.add_argument("text", help="what to look for, e.g. 'the sofa'")
    p.add_argument(
        "--top-k", type=at_least(0), default=0, help="objects to return (default 0: the node's / index's default)"
    )
    p.add_argument("--min-score", type=finite, default=-1.0, help="drop objects scoring below this (default -1)")
    add_service_options(p)
    p.add_argument("--map", metavar="DIR", help="query a saved map directory's objects.db instead of the node")
    p.add_argument("--json", action="store_true", help="print the answer as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.map:
        return _offline(args)
    return _online(args)


def _print(answer: dict, as_json: bool) -> None:
    from monovoc_ros.core.segments.object_labels import ObjectLabel, display

    if as_json:
        print(json.dumps(answer, indent=1))
        return
    print(answer["message"])
    if not answer["objects"]:
        return
    print(f"{'rank':>4}  {'id':7}  {'label':20} {'score':>6}  {'centroid (m)':24} extent (m)")
    for n, o in enumerate(answer["objects"], start=1):
        c = " ".join(f"{v:7.2f}" for v in o["centroid"])
        e = " ".join(f"{v:5.2f}" for v in o["extent"])
        label = display(ObjectLabel.stored(o["label"], o.get("label_source", "")))  # a guess shows as "couch?"
        print(f"{n:>4}  {o['hex']:7}  {label[:20]:20} {o['score']:6.3f}  {c:24} {e}")
        if o.get("description"):
            print(f"{'':15}{o['description']}")


def _offline(args: argparse.Namespace) -> int:
    from monovoc_ros.embed.model_store import ModelMissingError
    from monovoc_ros.objects.database import ObjectDatabaseError, load_object_index
    from monovoc_ros.objects.records import QueryError
    from monovoc_ros.objects.spatial import answer

    try:
        index = load_object_index(args.map)
        result = answer(index, args.text, args.top_k, args.min_score)
    except ObjectDatabaseError as exc:
        print(f"monovoc query: {exc}", file=sys.stderr)
        return 2
    except (QueryError, ModelMissingError) as exc:
        print(f"monovoc query: {exc}", file=sys.stderr)
        return 1
    objects = [{**record.to_dict(), "score": score} for record, score in result.matches]
    if result.answered or args.json:
        _print({"success": result.answered, "message": result.message, "objects": objects}, args.json)
    else:
        print(f"monovoc query: {result.message}", file=sys.stderr)
    return 0 if result.answered else 1


def _online(args: argparse.Namespace) -> int:
    import msg_adapters as ma
    from monovoc_interfaces.srv import TextQuery
    from monovoc_ros.ros_harness import ClientNode, HarnessError, call_service, wait_for_service

    service = args.namespace.rstrip("/") + "/query"
    with ClientNode(name="monovoc_query_client") as node:
        client = node.node.create_client(TextQuery, service)
        try:
            wait_for_service(client, args.timeout)
        except HarnessError:
            print(
                f"monovoc query: service {service} is not available after {args.timeout:g} s (is the node running, "
                f"e.g. ros2 run monovoc_ros semantic_mapper, in this ROS_DOMAIN_ID?)",
                file=sys.stderr,
            )
            return 2
        request = TextQuery.Request(text=args.text, top_k=args.top_k, min_score=args.min_score)
        try:
            response = call_service(client, request, args.timeout)
        except HarnessError:
            print(f"monovoc query: no answer from {service} within {args.timeout:g} s", file=sys.stderr)
            return 2
    objects = [ma.semantic_object_to_dict(o) for o in response.objects]
    if response.success or args.json:
        _print({"success": bool(response.success), "message": response.message, "objects": objects}, args.json)
    else:
        print(f"monovoc query: {response.message}", file=sys.stderr)
    return 0 if response.success else 1
