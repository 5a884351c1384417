"""`monovoc ask`: a question about a saved map (offline) or the live node's `ask` service.

    monovoc ask --map DIR "how many chairs are there" [--json]
    monovoc ask "what is on the table"                  # the running node's <namespace>/ask

Exit codes: 0 answered, 1 the question was not understood or failed, 2 no node / an unreadable map.
"""

from __future__ import annotations

import argparse
import json
import sys

from monovoc_ros.commands.argument_types import add_service_options


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "ask",
        help="a question about the map: how many X, what is on Y, where is X, is there an X",
        description="Answers a question from the map's objects without an LLM (monovoc_ros/objects/questions.py). "
        "Without --map it calls the Ask service <namespace>/ask of a running semantic_mapper.",
    )
    p.add_argument("question", help="e.g. 'how many chairs are there'")
    p.add_argument("--map", metavar="DIR", help="a saved map directory (its objects.db) instead of the node")
    add_service_options(p)
    p.add_argument("--json", action="store_true", help='print {"success", "answer", "count", "objects"}')
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    answer = _offline(args) if args.map else _online(args)
    if answer is None:
        return 2
    if args.json:
        print(json.dumps(answer, indent=1))
    else:
        print(answer["answer"])
    return 0 if answer["success"] else 1


def _offline(args: argparse.Namespace) -> dict | None:
    from monovoc_ros.embed.model_store import ModelMissingError
    from monovoc_ros.objects.database import ObjectDatabaseError, load_object_index
    from monovoc_ros.objects.questions import ask
    from monovoc_ros.objects.records import QueryError

    try:
        index = load_object_index(args.map)
    except ObjectDatabaseError as exc:
        print(f"monovoc ask: {exc}", file=sys.stderr)
        return None
    try:
        answer = ask(index, args.question)
    except (QueryError, ModelMissingError) as exc:
        return {"success": False, "answer": str(exc), "count": None, "objects": []}
    objects = [{**record.to_dict(), "score": score} for record, score in answer.objects]
    return {"success": answer.success, "answer": answer.answer, "count": answer.count, "objects": objects}


def _online(args: argparse.Namespace) -> dict | None:
    import msg_adapters as ma
    from monovoc_interfaces.srv import Ask
    from monovoc_ros.ros_harness import ClientNode, HarnessError, call_service, wait_for_service

    service = args.namespace.rstrip("/") + "/ask"
    with ClientNode(name="monovoc_ask_client") as node:
        client = node.node.create_client(Ask, service)
        try:
            wait_for_service(client, args.timeout)
            response = call_service(client, Ask.Request(question=args.question), args.timeout)
        except HarnessError:
            print(
                f"monovoc ask: no answer from {service} within {args.timeout:g} s (is the node running?)",
                file=sys.stderr,
            )
            return None
    objects = [ma.semantic_object_to_dict(o) for o in response.objects]
    count = None if response.count < 0 else int(response.count)
    return {"success": bool(response.success), "answer": response.answer, "count": count, "objects": objects}
