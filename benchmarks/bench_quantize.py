"""Palette quantization speed: numba kernels vs colour-science, N deblended colors x K palette colors.

    python benchmarks/bench_quantize.py [--n 140000] [--k 100] [--reference-n N] [--metrics cmc ...]

Prints one JSON object: per metric the color conversion time (N samples, done once), the kernel time
(after compilation, best of --repeat), the colour-science reference time (`colour.delta_E` per palette
color, on --reference-n samples and scaled to N when fewer) and the share of samples with the same
nearest palette color.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numba
import numpy as np

# The benchmark runs from a checkout; make the package importable without installing it.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from monovoc_ros.core.evidence.quantize import (
    METRICS,
    distance_matrix_reference,
    quantize,
    to_metric_space,
)


def synthetic(n: int, k: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """K distinct palette colors and N deblended colors: blends of two palette colors (weights skewed
    toward one, as overlap bias makes them), a little noise, 10% unobserved."""
    rng = np.random.default_rng(seed)
    palette = np.unique(rng.integers(0, 256, (4 * k, 3), dtype=np.uint8), axis=0)[:k]
    palette = palette[rng.permutation(len(palette))]
    a, b = rng.integers(0, k, n), rng.integers(0, k, n)
    w = rng.beta(0.5, 4.0, n)[:, None]
    colors = (1 - w) * palette[a] / 255.0 + w * palette[b] / 255.0 + rng.normal(0, 0.01, (n, 3))
    colors = np.clip(colors, 0, 1)
    colors[rng.random(n) < 0.1] = np.nan
    return colors, palette


def best_of(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=140_000)
    parser.add_argument("--k", type=int, default=100)
    parser.add_argument("--reference-n", type=int, default=None, help="samples for colour-science (default: all)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--metrics", nargs="+", default=list(METRICS), choices=METRICS)
    args = parser.parse_args()

    colors, palette = synthetic(args.n, args.k)
    observed = ~np.isnan(colors[:, 0])
    ref_n = min(args.reference_n or args.n, args.n)
    result = {
        "n": args.n,
        "k": int(len(palette)),
        "observed": int(observed.sum()),
        "numba_threads": numba.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "machine": platform.processor() or platform.machine(),
        "metrics": {},
    }
    for metric in args.metrics:
        quantize(colors[:64], palette, metric)  # compile (or load the cache) outside the timing
        convert = best_of(lambda metric=metric: to_metric_space(colors[observed], metric), args.repeat)
        total = best_of(lambda metric=metric: quantize(colors, palette, metric), args.repeat)
        q = quantize(colors, palette, metric)
        start = time.perf_counter()
        dist = distance_matrix_reference(colors[:ref_n], palette, metric)
        reference = (time.perf_counter() - start) * args.n / ref_n
        seen = observed[:ref_n]
        same = float(np.mean(np.argmin(dist[seen], axis=1) == q.index[:ref_n][seen]))
        result["metrics"][metric] = {
            "convert_s": round(convert, 4),
            "quantize_s": round(total, 4),
            "kernel_s": round(max(total - convert, 0.0), 4),
            "colour_science_s": round(reference, 3),
            "colour_science_measured_on": ref_n,
            "speedup": round(reference / total, 1),
            "same_argmin": same,
        }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
