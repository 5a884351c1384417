"""Spatial-language query latency (issue 26): `objects.spatial.answer` on an index of 100 objects. Prints
one JSON object (questions too: `objects.questions.ask`).

The objects are 100 boxes of 20 classes scattered over a 10 x 10 m floor (some on others), labelled and
embedded with the default (conse) backend as a map with given labels would be. Timed: relational,
between and superlative queries, and plain ones for comparison; "first" is each text's first call (its
phrases embedded), "repeated" the same texts again (embeddings cached, as for a robot repeating commands).

    scripts/with_env.sh python benchmarks/bench_spatial.py [--objects 100] [--repeats 20]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from monovoc_ros.embed import load_backend  # noqa: E402
from monovoc_ros.objects.index import IndexConfig, ObjectIndex  # noqa: E402
from monovoc_ros.objects.questions import ask  # noqa: E402
from monovoc_ros.objects.records import ObjectRecord  # noqa: E402
from monovoc_ros.objects.spatial import Viewpoint, answer  # noqa: E402

CLASSES = ["chair", "table", "sofa", "cup", "book", "lamp", "plant", "bin", "box", "shelf", "cabinet", "tv",
           "vase", "door", "picture", "bed", "desk", "monitor", "keyboard", "bottle"]  # fmt: skip
QUERIES = [
    "the cup on the table", "the book on the shelf", "the chair next to the sofa", "the lamp beside the bed",
    "the bin under the desk", "the chair between the table and the sofa", "the plant left of the door",
    "the box in front of the cabinet", "the bottle behind the monitor", "the biggest table",
    "the smallest cup", "the closest chair", "the farthest lamp", "the tallest plant",
    "the nearest chair to the bed", "what is on the desk",
]  # fmt: skip
PLAIN = ["a chair", "the gray sofa", "a potted plant", "a wooden table"]
QUESTIONS = [
    "how many chairs are there", "what is on the desk", "where is the lamp", "is there a plant next to the bed",
    "how many cups are on the table", "is there a giraffe",
]  # fmt: skip


def objects(n: int, backend, rng: np.random.Generator) -> list[ObjectRecord]:
    out = []
    for k in range(n):
        label = CLASSES[k % len(CLASSES)]
        size = rng.uniform(0.1, 1.5, 3)
        lo = np.array([*rng.uniform(0, 10, 2), 0.0 if rng.random() < 0.7 else rng.uniform(0.4, 1.2)])
        hi = lo + size
        emb = backend.embed_texts([f"a {label}"])[0]
        out.append(
            ObjectRecord(
                id=k + 1, label=label, label_source="given", description=f"a {label}", color_name="gray",
                centroid=(lo + hi) / 2, bbox_min=lo, bbox_max=hi, num_gaussians=1000, num_observations=5,
                embedding=emb, image_embedding=emb, upright_extent=size, height_above_floor=float(lo[2]),
            )
        )  # fmt: skip
    return out


def timed(index, texts: list[str], view: Viewpoint, question: bool = False) -> list[float]:
    out = []
    for text in texts:
        t0 = time.perf_counter()
        if question:
            ask(index, text, view)
        else:
            answer(index, text, 5, view=view)
        out.append(time.perf_counter() - t0)
    return out


def stats(samples: list[float]) -> dict:
    ms = 1e3 * np.asarray(samples)
    p50, p99 = (round(float(np.percentile(ms, q)), 2) for q in (50, 99))
    return {"n": len(ms), "p50_ms": p50, "p99_ms": p99}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    backend = load_backend("conse")
    index = ObjectIndex(backend, IndexConfig(up_axis="+z"))
    index.restore(objects(args.objects, backend, np.random.default_rng(0)), [], floor=0.0, up=[0.0, 0.0, 1.0])
    pose = np.eye(4)
    pose[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # an optical camera looking along +y, level
    pose[:3, 3] = [5.0, -1.0, 1.2]
    view = Viewpoint(pose)
    first = timed(index, QUERIES, view)
    repeated = timed(index, QUERIES * args.repeats, view)
    plain = timed(index, PLAIN * args.repeats, view)
    questions_first = timed(index, QUESTIONS, view, question=True)
    questions = timed(index, QUESTIONS * args.repeats, view, question=True)
    print(
        json.dumps(
            {
                "objects": len(index),
                "relational_first": stats(first),
                "relational_repeated": stats(repeated),
                "plain_repeated": stats(plain),
                "ask_first": stats(questions_first),
                "ask_repeated": stats(questions),
                "target_p99_ms": 20.0,
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
