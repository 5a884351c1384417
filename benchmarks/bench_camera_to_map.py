"""Camera to answers on real images (issue 23): prints one JSON object.

Replica office_0's 81 RGB keyframes go through the segmenter (no ground-truth mask is read by the chain),
the per-frame masks are mapped with `mask_ids: per_frame` while the object database takes its views (as
`monovoc segment` + `monovoc map --mask-ids per-frame --objects` and the live nodes do), and everything is
scored against the reference instances of the classes the segmenter knows (the ground-truth masks serve
only as the reference; the mapping of Replica classes to COCO is REPLICA_TO_COCO):

- segmenter per frame: each reference instance's IoU with the segment matched to it in that frame
  (Hungarian per frame), averaged over the frames where it is visible (a miss counts 0);
- map, one identity: the map's objects rendered into the same frames, matched to the instances once
  over all frames (Hungarian), the same average; and the same rendering matched per frame;
- objects of those classes (the segmenter's leading name) shown in the frames, against the instances;
- retrieval top-1 / top-3 with the segmenter's labels on the office_0 queries whose expected objects
  are of those classes (soft crops, descriptions naming objects by their labels);
- ms per keyframe of the segmenter, of the mapper and of the object database, and the chain's keyframes/s.

Frames: every 3rd keyframe for all scores (the splats protocol's frames), plus the segmenter over all 81.

    python benchmarks/bench_camera_to_map.py                         # the default model and settings
    python benchmarks/bench_camera_to_map.py --variants all          # every model and setting compared
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from monovoc_ros import offline  # noqa: E402
from monovoc_ros.commands.eval_retrieval import matched_queries  # noqa: E402
from monovoc_ros.core.evaluation.datasets import open_sequence  # noqa: E402
from monovoc_ros.core.evaluation.evaluation import render_splat_labels  # noqa: E402
from monovoc_ros.core.evidence.palette import UNOBSERVED_ID, VOID_ID, labels_from_entries, pack_rgb  # noqa: E402
from monovoc_ros.core.map_store import save_snapshot  # noqa: E402
from monovoc_ros.core.mapping import MapperConfig  # noqa: E402
from monovoc_ros.embed.backend import load_backend  # noqa: E402
from monovoc_ros.objects.database import save_object_index  # noqa: E402
from monovoc_ros.objects.evaluation import RetrievalQuery, class_key, evaluate_map, load_queries  # noqa: E402
from monovoc_ros.objects.index import IndexConfig, ObjectIndex  # noqa: E402
from monovoc_ros.segment import evaluation as ev  # noqa: E402
from monovoc_ros.segment.backend import load_segmenter  # noqa: E402
from monovoc_ros.segment.options import SegmenterOptions  # noqa: E402
from monovoc_ros.segment.sequence import SegmentedSequence  # noqa: E402

REPLICA = REPO.parent / "shared" / "data" / "replica_office0"
QUERIES = REPO / "config" / "queries" / "replica_office0.json"
RELATIONAL = REPO / "tests" / "data" / "relational_queries.json"
# Replica classes of office_0 that COCO (the default models' classes) knows, and COCO's names for them.
REPLICA_TO_COCO = {
    "chair": "chair",
    "sofa": "couch",
    "table": "dining table",
    "indoor-plant": "potted plant",
    "clock": "clock",
    "tv-screen": "tv",
}
CLASS_AWARE = SegmenterOptions(score_threshold=0.25, class_agnostic=False)  # YOLO's own defaults
VARIANTS = {
    "yolov5s-seg": ("yolov5s-seg", SegmenterOptions()),  # the default: class-agnostic, 0.1
    "yolov5s-seg class-aware 0.25": ("yolov5s-seg", CLASS_AWARE),
    "yolov7-seg": ("yolov7-seg", SegmenterOptions()),
    "yolov7-seg class-aware 0.25": ("yolov7-seg", CLASS_AWARE),
}
DEFAULT_VARIANT = "yolov5s-seg"
# What the launch file's segmenter:=true sets: per-frame ids, void counted against weakly supported Gaussians,
# objects named by less than one confident detection are fragments.
MAPPER = MapperConfig(mask_ids="per_frame", min_support=0.5, min_object_score=0.5)


def run_variant(seq, model: str, options: SegmenterOptions, every: int) -> dict:
    segmenter = load_segmenter(model=model, options=options)
    view = SegmentedSequence(seq, segmenter)
    names = labels_from_entries(seq.labels())
    instances = sorted(oid for oid, name in names.items() if name in REPLICA_TO_COCO)
    known = set(REPLICA_TO_COCO.values())

    keyframes = [view.keyframe(i) for i in range(len(seq))]  # the segmenter, timed by the view
    seg_frames = {kf.index: pack_rgb(kf.mask) for kf in keyframes}
    refs_all = {i: pack_rgb(view.clean_mask(i)) for i in range(len(seq))}
    index = ObjectIndex(load_backend("conse"), IndexConfig(crop_mode="soft"))
    t_objects = []

    def observe(keyframe, mapper) -> None:  # the object database's hook, as the node's
        t0 = time.perf_counter()
        index.keyframe_listener(keyframe, mapper)
        t_objects.append(time.perf_counter() - t0)

    events = [seq.load_gaussians(), *keyframes]
    mapper, stats = offline.map_events(events, MAPPER, on_keyframe=observe)
    t_map = stats.seconds  # integration only; the hook runs after it
    t0 = time.perf_counter()
    index.refresh(mapper)
    refresh_s = time.perf_counter() - t0

    frames = list(range(0, len(seq), every))
    refs = [refs_all[i] for i in frames]
    ids = mapper.result().object_ids
    renders = []
    for i in frames:
        kf = seq.keyframe(i)
        renders.append(render_splat_labels(mapper.gaussians, ids, kf.intrinsics, kf.cam_to_world))
    kw = {"ref_void": VOID_ID}
    seg_scores = ev.per_frame([seg_frames[i] for i in frames], refs, instances, pred_void=VOID_ID, **kw)
    seg_all = ev.per_frame(list(seg_frames.values()), list(refs_all.values()), instances, pred_void=VOID_ID, **kw)
    map_once, match = ev.matched_once(renders, refs, instances, pred_void=UNOBSERVED_ID, **kw)
    map_frames = ev.per_frame(renders, refs, instances, pred_void=UNOBSERVED_ID, **kw)
    labels = mapper.object_labels()
    shown = set(np.unique(np.concatenate([r.ravel() for r in renders]))) - {UNOBSERVED_ID}
    known_objects = sorted(o for o in shown if labels.get(int(o)) in known)
    present = [i for i in instances if i in map_once]

    retrieval = score_retrieval(mapper, index, instances, names)
    relations = score_relations(mapper, index)
    seg_ms = 1e3 * np.asarray(view.seconds)
    map_ms, obj_ms = 1e3 * np.asarray(t_map), 1e3 * np.asarray(t_objects)
    chain_s = (seg_ms.sum() + map_ms.sum() + obj_ms.sum()) / 1e3 + refresh_s
    by_name = {f"{names[i]} #{i:06x}": round(100 * map_once.get(i, 0.0), 1) for i in instances}
    return {
        "segmenter_per_frame_iou": round(100 * ev.mean(seg_scores), 2),
        "segmenter_per_frame_iou_all_keyframes": round(100 * ev.mean(seg_all), 2),
        "map_iou_one_identity": round(100 * ev.mean(map_once), 2),
        "map_iou_matched_per_frame": round(100 * ev.mean(map_frames), 2),
        "map_minus_frames_points": round(100 * (ev.mean(map_once) - ev.mean(seg_scores)), 2),
        "per_instance": {
            k: {"frames": round(100 * seg_scores.get(i, 0.0), 1), "map": v}
            for (k, v), i in zip(by_name.items(), instances, strict=False)
        },
        "reference_instances": len(present),
        "objects_of_known_classes": len(known_objects),
        "objects_over_reference": round(len(known_objects) / max(1, len(present)), 2),
        "map_objects": len(shown),
        **retrieval,
        **relations,
        "segmenter_ms_median": round(float(np.median(seg_ms)), 1),
        "mapper_ms_median": round(float(np.median(map_ms)), 1),
        "objects_ms_median": round(float(np.median(obj_ms)), 1),
        "chain_keyframes_per_s": round(len(seq) / chain_s, 2),
    }


@contextlib.contextmanager
def saved_map(mapper, index) -> Iterator[str]:
    """A temporary map directory (snapshot + objects.db) of `mapper` and `index`, as `monovoc map` writes it."""
    with tempfile.TemporaryDirectory() as tmp:
        snapshot = save_snapshot(mapper, tmp)
        save_object_index(
            index, tmp, snapshot=snapshot.path.name, map_version=mapper.map_version, keyframes=mapper.n_keyframes
        )
        yield tmp


def score_relations(mapper, index) -> dict:
    """The relational office_0 queries of tests/data/relational_queries.json (issue 26) with the segmenter's
    labels: their expected reference instances renamed to the map objects matched to them; a query whose
    expected instances no map object was matched to is a miss."""
    from monovoc_ros.objects.spatial import answer

    entries = json.loads(RELATIONAL.read_text())["replica_office0"]
    queries = [RetrievalQuery(q["text"], q["expected"], "relational") for q in entries]
    with saved_map(mapper, index) as tmp:
        renamed, _ = matched_queries(tmp, str(REPLICA), queries)
    hits = []
    for q in renamed:  # expected: the map objects matched to the reference instances (unmatched keep their id)
        result = answer(index, q.text, 1)
        hits.append(bool(result.matches) and result.matches[0][0].hex in q.expected)
    return {"relational_queries": len(queries), "relational_top1": round(float(np.mean(hits)), 2)}


def score_retrieval(mapper, index, instances, names) -> dict:
    """Top-1 / top-3 on the queries whose expected objects all are reference instances of known classes."""
    queries = load_queries(str(QUERIES))
    known_hex = {f"#{i:06x}" for i in instances}
    kept = [q for q in queries if all(e in REPLICA_TO_COCO or e in known_hex for e in q.expected)]
    with saved_map(mapper, index) as tmp:
        renamed, truth = matched_queries(tmp, str(REPLICA), kept)
        # A query whose class no map object was matched to is a miss (the map lost that object).
        found = {class_key(n) for n in truth.values()}
        answerable = [q for q in renamed if all(e.startswith("#") or class_key(e) in found for e in q.expected)]
        report = evaluate_map(
            tmp,
            answerable,
            load_backend("conse"),
            modes=["soft"],
            description_weights=[0.3],
            labels=truth,
            label_nouns=[True],
            own_labels=True,
        )
    variant = report["variants"][0]["all"]
    labels = mapper.object_labels()

    def named(hex_id: str) -> str:
        return labels.get(int(hex_id.lstrip("#"), 16), "?")

    ranks = {
        q["text"]: {"rank": q["rank"], "top3": [named(h) for h in q["top3"]]}
        for q in report["variants"][0]["per_query"]
    }
    scale = len(answerable) / max(1, len(kept))
    return {
        "retrieval_queries": [q.text for q in kept],
        "retrieval_unanswerable": [q.text for q in kept if q.text not in {a.text for a in answerable}],
        "retrieval_top1": round(float(variant["top1"]) * scale, 2),
        "retrieval_top3": round(float(variant["top3"]) * scale, 2),
        "retrieval_ranks": ranks,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variants", default=DEFAULT_VARIANT, help=f"comma separated, or 'all': {', '.join(VARIANTS)}")
    parser.add_argument("--every", type=int, default=3)
    args = parser.parse_args()
    if not (REPLICA / "traj.txt").exists():
        print(f"{REPLICA} not present: nothing to measure", file=sys.stderr)
        return 1
    seq = open_sequence(str(REPLICA))
    chosen = list(VARIANTS) if args.variants == "all" else [v.strip() for v in args.variants.split(",")]
    out = {"source": str(REPLICA), "rows": []}
    for name in chosen:
        model, options = VARIANTS[name]
        row = {"variant": name, **run_variant(seq, model, options, args.every)}
        out["rows"].append(row)
        print(json.dumps(row), file=sys.stderr)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
