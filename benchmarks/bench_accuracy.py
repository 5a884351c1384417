"""Labelling accuracy of semantic modes and settings: maps a source with each configuration and scores
the labels rendered through the Gaussians (splats protocol, every 3rd keyframe, against the clean
reference masks); prints one JSON object.

    python benchmarks/bench_accuracy.py                                  # the README's table
    python benchmarks/bench_accuracy.py --sources replica --configs vote,scd
    python benchmarks/bench_accuracy.py --sources synthetic:mixed_boundary --jpeg 90 --configs known,known_snap0.2

A source is "synthetic[:VARIANT]" or "replica" (../shared/data/replica_office0, read in place); `--jpeg Q`
sends every input mask through JPEG at quality Q first (the reference masks stay clean). A
configuration is a name in CONFIGS: MapperConfig fields.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from monovoc_ros import offline  # noqa: E402
from monovoc_ros.commands.eval import score, sequence_frames  # noqa: E402
from monovoc_ros.core.evaluation.datasets import SequenceView  # noqa: E402
from monovoc_ros.core.evidence.palette import labels_from_entries  # noqa: E402
from monovoc_ros.core.mapping import MapperConfig  # noqa: E402

REPLICA = REPO.parent / "shared" / "data" / "replica_office0"
CONFIGS = {
    "vote": {},
    "scd": {"semantic_mode": "scd"},
    "scd_k1": {"semantic_mode": "scd", "weight_power": 1},
    "vote_k1": {"weight_power": 1},
    "vote_k2": {"weight_power": 2},
    "vote_slots2": {"vote_slots": 2},
    "vote_slots8": {"vote_slots": 8},
    "snap0": {"min_snap_margin": 0.0},
    "snap0.2": {"min_snap_margin": 0.2},
    "snap0.7": {"min_snap_margin": 0.7},
    "snap1": {"min_snap_margin": 1.0},
    "vote_rgb": {"metric": "rgb"},
    "vote_include": {"void_policy": "include"},
    "known": {"object_colors": "labels"},  # the source's labels.json colors are the palette
    "known_snap0": {"object_colors": "labels", "min_snap_margin": 0.0},
    "known_snap0.2": {"object_colors": "labels", "min_snap_margin": 0.2},
}


class JpegMasks(SequenceView):
    """A sequence whose keyframe masks went through JPEG at `quality` (clean_mask stays the original)."""

    def __init__(self, sequence, quality: int) -> None:
        super().__init__(sequence)
        self._quality = quality

    def keyframe(self, i: int):
        from PIL import Image

        kf = self._seq.keyframe(i)
        buf = io.BytesIO()
        Image.fromarray(kf.mask).save(buf, format="JPEG", quality=self._quality)
        return replace(kf, mask=np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("RGB")))


def _second(item):
    return item[1]


def run(source: str, config_name: str, jpeg: int | None) -> dict:
    seq = offline.open_source(str(REPLICA) if source == "replica" else source)
    if jpeg:
        seq = JpegMasks(seq, jpeg)
    start = time.perf_counter()
    settings = dict(CONFIGS[config_name])
    if settings.get("object_colors") == "labels":
        settings["object_colors"] = tuple(labels_from_entries(seq.labels()))
    mapper, stats = offline.map_sequence(seq, MapperConfig(**settings))
    mapping_s = time.perf_counter() - start
    _, frames, _, _ = sequence_frames(seq, every=3)
    result, _ = score(mapper.gaussians, mapper.result().object_ids, frames, "splats", 0.05)
    ious = result["iou"]
    return {
        "source": source + (f"+jpeg{jpeg}" if jpeg else ""),
        "config": config_name,
        "miou": round(100 * float(result["miou"]), 2),
        "mismatch_nonwhite": round(100 * float(result["mismatch_nonwhite"]), 2),
        "objects": len(ious),
        "worst_objects": {f"{k:06x}": round(100 * float(v), 1) for k, v in sorted(ious.items(), key=_second)[:5]},
        "keyframes": stats.keyframes_processed,
        "mapping_s": round(mapping_s, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sources", default="synthetic,synthetic:boundary_noise,synthetic:mixed_boundary,replica")
    parser.add_argument("--configs", default="vote,scd")
    parser.add_argument("--jpeg", type=int, default=None, help="JPEG quality for the input masks")
    args = parser.parse_args()
    rows = []
    for source in args.sources.split(","):
        if source == "replica" and not (REPLICA / "traj.txt").exists():
            print(f"skipping replica: {REPLICA} not present", file=sys.stderr)
            continue
        for name in args.configs.split(","):
            rows.append(run(source, name, args.jpeg))
            print(json.dumps(rows[-1]), file=sys.stderr)
    print(json.dumps({"splats_every": 3, "results": rows}, indent=1))


if __name__ == "__main__":
    main()
