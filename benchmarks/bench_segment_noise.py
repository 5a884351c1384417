"""Per-frame segments as real segmenters make them (issue 17): prints one JSON object.

For each source (Replica office_0 when present, the synthetic room), each noise generator and each noise
model, maps every keyframe with `mask_ids: per_frame` from masks that went through
`core.segments.segment_noise` (seeded per keyframe), then scores the map against the clean reference masks after
matching its objects to the reference instances (splats protocol, every 3rd keyframe): matched mIoU,
objects (those leading some evaluated pixel) against the reference instances, merges and splits; beside
it the same map with global ids.

Generators (different cutting rules and seeds): `line` (straight cuts, seed 0) and `voronoi` (irregular
parts around random seed pixels, 2-4 per segment, seed 1). Noise models at each generator: `clean`
(renumbered only), `split+fusion` (10% cut, 10% fused: the targets), `parts` (20% cut into 2-4),
`missed` (half of the small segments dropped), `jitter` (boundaries wander by 3 px), `granularity`
(a third of the keyframes coarser, a third finer, at 10% + 10%).

    python benchmarks/bench_segment_noise.py                          # everything
    python benchmarks/bench_segment_noise.py --sources synthetic --models split+fusion
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from monovoc_ros import offline  # noqa: E402
from monovoc_ros.core.evaluation.datasets import CorruptedMasks  # noqa: E402
from monovoc_ros.core.evaluation.evaluation import render_splat_labels  # noqa: E402
from monovoc_ros.core.evaluation.instance_eval import score_matched  # noqa: E402
from monovoc_ros.core.evidence.palette import pack_rgb  # noqa: E402
from monovoc_ros.core.mapping import MapperConfig, SemanticMapper  # noqa: E402
from monovoc_ros.core.segments.segment_noise import NoiseRates  # noqa: E402

REPLICA = REPO.parent / "shared" / "data" / "replica_office0"
GENERATORS = {"line": (NoiseRates(cut="line"), 0), "voronoi": (NoiseRates(cut="voronoi", pieces=4), 1)}
MODELS = {
    "clean": {},
    "split+fusion": {"split": 0.1, "merge": 0.1},
    "parts": {"split": 0.2},
    "missed": {"drop": 0.5},
    "jitter": {"jitter": 3},
    "granularity": {"split": 0.1, "merge": 0.1, "granularity": 0.33},
}


def evaluate(seq, config: MapperConfig, every: int = 3) -> dict:
    """Maps the sequence; returns matched mIoU, objects and the matching's merges / splits."""
    mapper = SemanticMapper(seq.load_gaussians(), config)
    for i in range(len(seq)):
        mapper.integrate(seq.keyframe(i))
    ids = mapper.result().object_ids
    frames = [seq.keyframe(i) for i in range(0, len(seq), every)]
    refs = [pack_rgb(seq.clean_mask(i)) for i in range(0, len(seq), every)]
    preds = [render_splat_labels(mapper.gaussians, ids, kf.intrinsics, kf.cam_to_world) for kf in frames]
    scores, match = score_matched(preds, refs)
    return {
        "miou": round(100 * float(scores["miou"]), 2),
        "objects": match.objects,
        "reference_objects": match.reference_objects,
        "merges": match.merges,
        "splits": match.splits,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sources", default="replica,synthetic")
    parser.add_argument("--generators", default=",".join(GENERATORS))
    parser.add_argument("--models", default=",".join(MODELS))
    args = parser.parse_args()
    out: dict = {"rows": []}
    for source in filter(None, args.sources.split(",")):
        if source == "replica" and not (REPLICA / "traj.txt").exists():
            print(f"skipping replica: {REPLICA} not present", file=sys.stderr)
            continue
        seq = offline.open_source(str(REPLICA) if source == "replica" else source)
        reference = evaluate(CorruptedMasks(seq, shuffled=False), MapperConfig())
        out["rows"].append({"source": source, "generator": "-", "model": "global ids", **reference})
        print(json.dumps(out["rows"][-1]), file=sys.stderr)
        for generator in args.generators.split(","):
            base, seed = GENERATORS[generator]
            for model in args.models.split(","):
                if model == "clean" and generator != "line":
                    continue  # renumbering alone has no cutting rule
                noisy = CorruptedMasks(seq, shuffled=True, rates=replace(base, **MODELS[model]), seed=seed)
                row = {"source": source, "generator": generator, "model": model}
                row.update(evaluate(noisy, MapperConfig(mask_ids="per_frame")))
                row["points_below_global_ids"] = round(reference["miou"] - row["miou"], 2)
                row["objects_over_reference"] = round(row["objects"] / row["reference_objects"], 2)
                out["rows"].append(row)
                print(json.dumps(row), file=sys.stderr)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
