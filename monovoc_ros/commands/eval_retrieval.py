"""`monovoc eval-retrieval`: the paper's text-query retrieval protocol on a saved map (METHOD section 6).

    monovoc eval-retrieval config/queries/replica_office0.json --map DIR [--modes hard,soft]
        [--description off,on] [--label-nouns off] [--labels labels.json] [--out report.json]

QUERIES.json: a JSON list of {"text": ..., "expected": [palette ids "#rrggbb" or class names], "kind": ...}
(monovoc_ros.objects.evaluation). Prints a table of top-1 / top-3 per variant and writes the full report
(per-query ranks, descriptions, chance level) as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

_ON_OFF = {"on": True, "off": False}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "eval-retrieval",
        help="top-1 / top-3 accuracy of text queries on a saved map's objects",
        description="Re-crops the stored object views in each crop mode, embeds them (with and without the "
        "attribute description) and scores the queries: a query is right at k when one of its expected "
        "objects is among the first k. Class names in 'expected' need ground-truth labels (the map's, or "
        "--labels).",
    )
    p.add_argument("queries", help="QUERIES.json (see config/queries/)")
    p.add_argument("--map", required=True, metavar="DIR", help="map directory holding objects.db (or the .db file)")
    p.add_argument("--modes", default="hard,soft", help="crop modes, comma separated (default hard,soft)")
    p.add_argument("--description", default="off,on", help="attribute description off/on (default off,on)")
    p.add_argument(
        "--description-weight", type=float, default=0.3, help="share of the description when on (default 0.3)"
    )
    p.add_argument(
        "--unlabeled-noun",
        default=None,
        help="noun of descriptions without labels: 'object' or 'imagenet' (default: the map's setting)",
    )
    p.add_argument(
        "--label-nouns",
        default="off",
        help="descriptions name objects by their ground-truth labels (on) or by the best ImageNet class (off); "
        "on,off runs both (default off)",
    )
    p.add_argument(
        "--reference",
        metavar="SOURCE",
        help="a map built with per-frame mask ids: match its objects to SOURCE's reference instances "
        "(rendered overlap, every 3rd keyframe); palette ids in 'expected' and ground-truth class names "
        "then name the matched objects, and label-noun descriptions use the map's own (segment) labels",
    )
    p.add_argument("--labels", metavar="FILE", help="labels.json with ground truth class names (default: the map's)")
    p.add_argument("--backend", default=None, help="embedding backend (default: the one the map was built with)")
    p.add_argument("--model-dir", default=None, help="embedding model directory")
    p.add_argument("--out", metavar="FILE", help="write the JSON report here (default: <map>/retrieval.json)")
    p.set_defaults(func=run)


def _switches(text: str, what: str) -> list[bool]:
    try:
        return [_ON_OFF[s.strip()] for s in text.split(",") if s.strip()]
    except KeyError:
        raise ValueError(f"{what}: expected on, off or on,off; got {text!r}") from None


def matched_queries(map_dir: str, source: str, queries: list):
    """Queries and ground truth translated to a per-frame map's own object ids (core.evaluation.instance_eval):
    (queries with palette ids renamed, {map id: reference class name})."""
    import dataclasses

    from monovoc_ros import offline
    from monovoc_ros.commands.eval import sequence_frames
    from monovoc_ros.core.evaluation.evaluation import render_splat_labels
    from monovoc_ros.core.evaluation.instance_eval import match_instances
    from monovoc_ros.core.evidence.palette import format_object_id, pack_rgb, parse_object_id
    from monovoc_ros.core.map_store import load_snapshot

    mapper = load_snapshot(Path(map_dir) if Path(map_dir).is_dir() else Path(map_dir).parent)
    seq = offline.open_source(source)
    _, frames, names, _ = sequence_frames(seq, every=3)
    ids = mapper.result().object_ids
    preds = [render_splat_labels(mapper.gaussians, ids, k, pose) for k, pose, _ in frames]
    match = match_instances(preds, [pack_rgb(m) for _, _, m in frames])
    to_map = {ref: obj for obj, ref in match.mapping.items()}

    def rename(item: str) -> str:
        try:
            oid = parse_object_id(item)
        except ValueError:
            return item  # a class name
        return format_object_id(to_map.get(oid, oid))

    renamed = [dataclasses.replace(q, expected=[rename(e) for e in q.expected]) for q in queries]
    truth = {obj: names[ref] for obj, ref in match.mapping.items() if names.get(ref)}
    return renamed, truth


def run(args: argparse.Namespace) -> int:
    from monovoc_ros.core.evidence.palette import read_labels
    from monovoc_ros.embed.backend import load_backend
    from monovoc_ros.embed.model_store import ModelMissingError
    from monovoc_ros.objects.database import ObjectDatabase, ObjectDatabaseError, database_path
    from monovoc_ros.objects.evaluation import evaluate_map, format_table, load_queries

    try:
        queries = load_queries(args.queries)
        modes = [m.strip() for m in args.modes.split(",") if m.strip()]
        weights = [args.description_weight if on else 0.0 for on in _switches(args.description, "--description")]
        nouns = _switches(args.label_nouns, "--label-nouns")
        labels = read_labels(args.labels) if args.labels else None
        if args.reference:
            queries, labels = matched_queries(args.map, args.reference, queries)
        stored = ObjectDatabase(args.map, create=False).meta().get("backend") or {}
        name = args.backend or stored.get("name", "conse")
        options = {}
        if args.model_dir or (name == stored.get("name") and stored.get("model_dir")):
            options["model_dir"] = args.model_dir or stored["model_dir"]
        if name == "conse" and name == stored.get("name"):
            options.update({k: stored[k] for k in ("top_k", "fit") if k in stored})
        backend = load_backend(name, **options)
        report = evaluate_map(
            args.map,
            queries,
            backend,
            modes=modes,
            description_weights=weights,
            labels=labels,
            label_nouns=nouns,
            unlabeled_noun=args.unlabeled_noun,
            own_labels=bool(args.reference),
        )
    except (ValueError, ObjectDatabaseError, ModelMissingError, OSError) as exc:
        print(f"monovoc eval-retrieval: {exc}", file=sys.stderr)
        return 1
    out = Path(args.out) if args.out else database_path(args.map).parent / "retrieval.json"
    report["queries_file"] = str(args.queries)
    out.write_text(json.dumps(report, indent=1))
    print(format_table(report))
    print(f"report: {out}")
    return 0
