"""The paper's retrieval protocol on a saved map: top-1 / top-3 accuracy of text queries (METHOD 6).

QUERIES.json is a JSON list of queries::

    [
      {"text": "a sofa", "expected": ["sofa"], "kind": "class"},
      {"text": "the orange ball", "expected": ["#cc3300"], "kind": "attribute"}
    ]

``expected`` lists the objects that count as a correct answer, each either a palette color id
(``#rrggbb``, ``0xrrggbb``) or a class name, meaning every object with that ground-truth class name
(matched case-insensitively, "-"/"_"/" " alike) -- class names need ground-truth labels (the map's
stored labels or a labels.json). ``kind`` (optional, default "query") groups the queries in the report.
A query whose expected objects are all missing from the map (too small, never seen) counts as a miss
and is listed under ``unanswerable``.

The stored views are re-cropped in every crop mode asked for, so hard and soft masks are compared on
exactly the same views; each variant combines the image embedding with the attribute description or not
(``description_weight``). With ``label_nouns`` the descriptions use the ground-truth class names (what a
labelled segmenter provides); without, ``unlabeled_noun`` ("object": attributes only, or "imagenet": the
best ImageNet class of the object's image embedding).
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from monovoc_ros.core.evidence.palette import format_object_id, parse_object_id
from monovoc_ros.core.segments.object_labels import GUESS
from monovoc_ros.embed.retrieval import chance_topk
from monovoc_ros.objects.database import ObjectDatabase
from monovoc_ros.objects.index import CROP_MODES, IndexConfig, ObjectIndex
from monovoc_ros.objects.labels import noun
from monovoc_ros.objects.spatial import answer

KS = (1, 3)


@dataclass
class RetrievalQuery:
    text: str
    expected: list[str]
    kind: str = "query"


def load_queries(source: str | os.PathLike | Sequence[Mapping]) -> list[RetrievalQuery]:
    """Queries from a QUERIES.json path or an already-parsed list; raises ValueError naming the entry."""
    where = "queries"
    if isinstance(source, str | os.PathLike):
        where = str(source)
        try:
            source = json.loads(Path(source).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"{where}: unreadable queries file ({exc})") from None
    if not isinstance(source, list) or not source:
        raise ValueError(f"{where}: expected a non-empty JSON list of {{text, expected}} entries")
    out = []
    for n, entry in enumerate(source):
        if not isinstance(entry, Mapping):
            raise ValueError(f"{where}: entry {n} is not an object")
        text, expected = entry.get("text"), entry.get("expected")
        if not isinstance(text, str) or not text.strip():
            raise ValueError(f"{where}: entry {n} needs a non-empty 'text'")
        if isinstance(expected, str | int):
            expected = [expected]
        if not isinstance(expected, list) or not expected:
            raise ValueError(f"{where}: entry {n} ({text!r}) needs 'expected': a list of ids or class names")
        out.append(RetrievalQuery(text.strip(), [str(e) for e in expected], str(entry.get("kind", "query"))))
    return out


def class_key(name: str) -> str:
    return noun(name).lower()


def resolve_expected(query: RetrievalQuery, labels: Mapping[int, str]) -> set[int]:
    """Object ids a query accepts; class names resolve through ``labels`` (id -> class name)."""
    by_class: dict[str, set[int]] = {}
    for oid, name in labels.items():
        by_class.setdefault(class_key(name), set()).add(int(oid))
    ids: set[int] = set()
    for item in query.expected:
        try:
            ids.add(parse_object_id(item))
            continue
        except ValueError:
            pass
        key = class_key(item)
        if key not in by_class:
            known = ", ".join(sorted(by_class)) or "none: give labels"
            raise ValueError(f"query {query.text!r}: unknown class name {item!r} (known: {known})")
        ids |= by_class[key]
    return ids


def score_rankings(ranked_ids: Sequence[Sequence[int]], expected: Sequence[set[int]]) -> dict:
    """top-k accuracy and MRR; a query with no expected object among the ranked ones is a miss."""
    first = []
    for row, want in zip(ranked_ids, expected, strict=True):
        hits = [i for i, oid in enumerate(row) if oid in want]
        first.append(hits[0] if hits else np.inf)
    first = np.asarray(first, dtype=np.float64)
    out = {f"top{k}": round(float(np.mean(first < k)), 4) for k in KS}
    out["mrr"] = round(float(np.mean(np.where(np.isfinite(first), 1.0 / (first + 1), 0.0))), 4)
    out["n_queries"] = len(first)
    return out


def evaluate_index(index: ObjectIndex, queries: Sequence[RetrievalQuery], labels: Mapping[int, str]) -> dict:
    """Scores one index on the queries, overall and per kind, ranked as `/monovoc/query` and `monovoc query` rank
    them (objects.spatial.answer: the index's ranking, spatial language read; no robot viewpoint)."""
    ids, _ = index.embedding_matrix()
    if not ids:
        raise ValueError("the index has no embedded objects to rank")
    ranked = [[r.id for r, _ in answer(index, q.text, len(ids))] for q in queries]
    expected = [resolve_expected(q, labels) for q in queries]
    listed = set(ids)
    result = {"all": score_rankings(ranked, expected)}
    for kind in sorted({q.kind for q in queries}):
        pick = [i for i, q in enumerate(queries) if q.kind == kind]
        result[kind] = score_rankings([ranked[i] for i in pick], [expected[i] for i in pick])
    result["unanswerable"] = [q.text for q, e in zip(queries, expected, strict=True) if not e & listed]
    result["per_query"] = [
        {
            "text": q.text,
            "kind": q.kind,
            "expected": sorted(format_object_id(i) for i in e),
            "top3": [format_object_id(i) for i in row[:3]],
            "rank": next((n + 1 for n, oid in enumerate(row) if oid in e), None),
        }
        for q, e, row in zip(queries, expected, ranked, strict=True)
    ]
    result["chance"] = _chance(len(ids), [len(e & listed) for e in expected])
    return result


def _chance(n_objects: int, n_expected: Iterable[int]) -> dict:
    per_query = [[chance_topk(n_objects, e, k) if e else 0.0 for k in KS] for e in n_expected]
    return {f"top{k}": round(float(np.mean([q[i] for q in per_query])), 4) for i, k in enumerate(KS)}


def evaluate_map(
    location: str | os.PathLike,
    queries: Sequence[RetrievalQuery],
    backend,
    *,
    modes: Sequence[str] = CROP_MODES,
    description_weights: Sequence[float] = (0.0, 0.3),
    labels: Mapping[int, str] | None = None,
    label_nouns: Sequence[bool] = (False,),
    unlabeled_noun: str | None = None,
    noun_labels: Mapping[int, str] | None = None,
    own_labels: bool = False,
) -> dict:
    """Every (mode, description weight, label nouns) variant of a saved map's objects, re-embedded from
    its stored views. ``labels``: ground truth for class-name expectations (default: the map's);
    ``noun_labels``: the names the label-noun descriptions use (default: the ground truth, as given labels);
    ``own_labels``: the map's own stored labels instead (a segmenter's, with their source and confidence), to
    score what the map itself knows."""
    db = ObjectDatabase(location, create=False)
    meta = db.meta()
    base = IndexConfig.from_dict(meta.get("config") or {})
    truth = dict(labels) if labels is not None else dict(base.labels or {})
    named = dict(noun_labels) if noun_labels is not None else truth
    records, views = db.records(), db.views()
    if not records:
        raise ValueError(f"{db.path}: the map has no objects")
    for mode in modes:
        if mode not in CROP_MODES:
            raise ValueError(f"unknown crop mode {mode!r}; choose from {CROP_MODES}")
    # A variant without label nouns must not name objects either by the labels the map was saved with
    # (labels.json or a segmenter's, restored with their source): the model's guesses are re-derived on refresh.
    unlabelled = [dataclasses.replace(r, label="", label_source=GUESS) for r in records]
    variants = []
    for mode in modes:
        for weight in description_weights:
            for nouns in label_nouns:
                if weight == 0 and nouns and False in label_nouns:
                    continue  # without a description the nouns do not matter
                config = dataclasses.replace(
                    base,
                    crop_mode=mode,
                    description_weight=float(weight),
                    labels=named if nouns and not own_labels else None,
                )
                if unlabeled_noun is not None:
                    config.unlabeled_noun = unlabeled_noun
                index = ObjectIndex(backend, config)
                # Shared view objects: each mode's crops are embedded once for all its variants.
                index.restore(
                    records if nouns else unlabelled,
                    views,
                    observations=db.observations(),
                    floor=float(meta.get("floor") or 0.0),
                    up=meta.get("up"),
                    embeddings_valid=False,
                )
                index.refresh()
                scores = evaluate_index(index, queries, truth)
                scores.update(
                    mode=mode,
                    description_weight=float(weight),
                    label_nouns=bool(nouns),
                    unlabeled_noun=config.unlabeled_noun,
                    descriptions={r.hex: r.description for r in index.records()},
                )
                variants.append(scores)
    return {
        "map": str(db.path),
        "n_objects": len(records),
        "n_queries": len(queries),
        "backend": meta.get("backend"),
        "variants": variants,
    }


def format_table(report: Mapping) -> str:
    """A short text table: one row per variant, top-1 / top-3 per query kind."""
    kinds = sorted({k for v in report["variants"] for k in v if isinstance(v.get(k), dict) and "top1" in v[k]})
    kinds = ["all"] + [k for k in kinds if k not in ("all", "chance")]
    header = f"{'mode':5} {'desc':5} {'nouns':8}" + "".join(f" {k + ' t1/t3':>18}" for k in kinds)
    lines = [header, "-" * len(header)]
    for v in report["variants"]:
        cells = "".join(f" {v[k]['top1']:>8.2f} / {v[k]['top3']:<7.2f}" for k in kinds)
        desc = f"{v['description_weight']:.2f}" if v["description_weight"] else "off"
        nouns = "labels" if v["label_nouns"] else v["unlabeled_noun"] if v["description_weight"] else "-"
        lines.append(f"{v['mode']:5} {desc:5} {nouns:8}{cells}")
    chance = report["variants"][0]["chance"]
    lines.append(f"chance (random ranking): top1 {chance['top1']:.2f}, top3 {chance['top3']:.2f}")
    missing = report["variants"][0]["unanswerable"]
    if missing:
        lines.append(f"unanswerable (expected objects not in the map): {missing}")
    return "\n".join(lines)
