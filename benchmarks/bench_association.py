"""Cost of per-frame mask association per keyframe (core.segments.association); prints one JSON object.

    python benchmarks/bench_association.py                       # synthetic room: 140k Gaussians, 616x344
    python benchmarks/bench_association.py --source ../shared/data/replica_office0
    python benchmarks/bench_association.py --association-scale 1   # overlaps at full resolution
    python benchmarks/bench_association.py --mask-noise shuffled,merge=0.1,split=0.1   # a noisy segmenter

Maps the first --warmup keyframes of the source with every mask renumbered (`--mask-noise`, default
`shuffled`; fused and cut segments make the association render the runner-up objects too) and
`mask_ids: per_frame`, then times the association of the next --keyframes keyframes: the mask's
segments, the map's labels rendered into the view (one pass), the matching, and the total (median
ms, and the minimum; the target is <= 40 ms at 140k Gaussians, 616x344). The integration that follows
(the ordinary vote path, one rasterization pass of the same view) is timed beside it: on a shared
machine, compare the two, and `loadavg`.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from monovoc_ros import offline  # noqa: E402
from monovoc_ros.core.evaluation.datasets import CorruptedMasks  # noqa: E402
from monovoc_ros.core.mapping import MapperConfig, SemanticMapper  # noqa: E402
from monovoc_ros.core.segments.segment_noise import parse_mask_noise  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", default="synthetic")
    parser.add_argument("--warmup", type=int, default=8)
    parser.add_argument("--keyframes", type=int, default=8)
    parser.add_argument("--association-scale", type=int, default=MapperConfig.association_scale)
    parser.add_argument("--mask-noise", default="shuffled", help="as `monovoc map --mask-noise`")
    args = parser.parse_args()
    shuffled, rates = parse_mask_noise(args.mask_noise)
    seq = CorruptedMasks(offline.open_source(args.source), shuffled=shuffled, rates=rates)
    gaussians = seq.load_gaussians()
    mapper = SemanticMapper(gaussians, MapperConfig(mask_ids="per_frame", association_scale=args.association_scale))
    n = min(len(seq), args.warmup + args.keyframes)
    total, segment, render, match, integrate, segments = [], [], [], [], [], []
    for i in range(n):
        report = mapper.integrate(seq.keyframe(i))
        a = report.association
        if i >= args.warmup:
            total.append(1e3 * a.seconds)
            segment.append(1e3 * a.segment_seconds)
            render.append(1e3 * a.render_seconds)
            match.append(1e3 * (a.seconds - a.segment_seconds - a.render_seconds))
            integrate.append(1e3 * (report.seconds - a.seconds))
            segments.append(len(a.segment_objects))
    kf = seq.keyframe(0)
    med = statistics.median
    print(
        json.dumps(
            {
                "source": args.source,
                "gaussians": len(gaussians),
                "resolution": f"{kf.intrinsics.width}x{kf.intrinsics.height}",
                "association_scale": args.association_scale,
                "mask_noise": args.mask_noise,
                "keyframes_timed": len(total),
                "segments_per_keyframe": med(segments),
                "objects": len(mapper.associator.issued),
                "association_ms": round(med(total), 1),
                "association_min_ms": round(min(total), 1),
                "segments_ms": round(med(segment), 1),
                "render_ms": round(med(render), 1),
                "match_ms": round(med(match), 1),
                "integration_ms": round(med(integrate), 1),
                "integration_min_ms": round(min(integrate), 1),
                "loadavg": [round(x, 2) for x in os.getloadavg()],
                "target_ms": 40,
            },
            indent=1,
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
