"""onnxruntime's intra-op threads spinning between runs or sleeping, printed as JSON.

    python benchmarks/bench_onnx_spinning.py [--runs 40] [--gap-ms 50]

The object index, the query service and the segmenter call their models a few times a second with Python in
between (crops, colors, ranking, mask decoding). onnxruntime's default lets its intra-op threads spin after every
run, waiting for the next one; `make_session` makes them sleep. For ConSE's classifier (3 crops a run, as the
index's chunks), its sentence encoder (one query text) and the segmenter (YOLOv5s-seg, one 640x384 image), with
`--gap-ms` of sleep between runs: milliseconds a run (median) and CPU milliseconds of the process a run (sleeps
included: what spinning costs the other threads), idle and beside one busy process (on a 2-core machine, as the
node's: the mapper's worker on the other core). Each model runs its spinning block, then its sleeping block.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

# The benchmark runs from a checkout; make the package importable without installing it.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from monovoc_ros.embed import conse_files as cf
from monovoc_ros.embed.model_store import default_model_dir
from monovoc_ros.embed.onnx_session import make_session
from monovoc_ros.embed.sentence_encoder import load_sentence_tokenizer
from monovoc_ros.segment.model_files import DEFAULT_MODEL, resolve_model


def _runs(run: Callable[[], object], runs: int, gap_s: float) -> dict[str, float]:
    run()  # first runs allocate onnxruntime's buffers
    walls = []
    cpu0 = time.process_time()
    for _ in range(runs):
        start = time.perf_counter()
        run()
        walls.append(time.perf_counter() - start)
        time.sleep(gap_s)
    cpu = time.process_time() - cpu0
    return {"ms_per_run": round(1e3 * statistics.median(walls), 1), "cpu_ms_per_run": round(1e3 * cpu / runs, 1)}


def _models(spinning: bool) -> dict[str, Callable[[], object]]:
    model_dir = default_model_dir()
    classifier = make_session(model_dir / cf.CLASSIFIER_ONNX, spinning=spinning)
    size = cf.CLASSIFIER_INPUT_SIZE
    pixels = np.random.default_rng(0).uniform(0, 255, (3, 3, size, size)).astype(np.float32)
    sentence = make_session(model_dir / cf.SENTENCE_ONNX, spinning=spinning)
    encoding = load_sentence_tokenizer(model_dir / cf.SENTENCE_TOKENIZER).encode("the blue chair next to the sofa")
    text = {
        "input_ids": np.array([encoding.ids], np.int64),
        "attention_mask": np.array([encoding.attention_mask], np.int64),
    }
    segmenter = make_session(resolve_model(DEFAULT_MODEL), spinning=spinning)
    image = np.random.default_rng(1).uniform(0, 1, (1, 3, 384, 640)).astype(np.float32)  # a 640x360 letterboxed
    return {
        "classifier_3_crops": lambda: classifier.run(None, {"pixels": pixels}),
        "sentence_1_text": lambda: sentence.run(None, text),
        "segmenter_1_image": lambda: segmenter.run(None, {segmenter.get_inputs()[0].name: image}),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=40)
    parser.add_argument("--gap-ms", type=float, default=50.0, help="sleep between two runs (the caller's Python)")
    args = parser.parse_args(argv)
    report: dict = {"runs": args.runs, "gap_ms": args.gap_ms, "results": {}}
    sessions = {"spinning": _models(True), "sleeping": _models(False)}
    for beside in ("idle", "busy_core"):
        busy = None
        if beside == "busy_core":
            busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
        try:
            for name in sessions["spinning"]:
                for mode in ("spinning", "sleeping"):
                    key = f"{name}/{beside}/{mode}"
                    report["results"][key] = _runs(sessions[mode][name], args.runs, args.gap_ms / 1e3)
        finally:
            if busy is not None:
                busy.kill()
                busy.wait()
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
