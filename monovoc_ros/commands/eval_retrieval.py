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


def run(args: argparse.Namespace) -> int:
    from monovoc_ros.embed.backend import load_backend
    from monovoc_ros.embed.model_store import ModelMissingError
    from monovoc_ros.objects.database import ObjectDatabase, ObjectDatabaseError, database_path
    from monovoc_ros.objects.evaluation import evaluate_map, format_table, load_queries
    from monovoc_ros.objects.labels import load_labels

    try:
        queries = load_queries(args.queries)
        modes = [m.strip() for m in args.modes.split(",") if m.strip()]
        weights = [args.description_weight if on else 0.0 for on in _switches(args.description, "--description")]
        nouns = _switches(args.label_nouns, "--label-nouns")
        labels = load_labels(args.labels) if args.labels else None
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
