"""onnxruntime sessions configured the same way for every backend."""

from __future__ import annotations

from pathlib import Path

import onnxruntime as ort

# The robot shares its CPU with SLAM and the ROS executors: two intra-op threads keep the embedder from
# starving them while still using the vectorised kernels well (see MODELS.md for the timings).
DEFAULT_THREADS = 2
# onnxruntime's intra-op threads spin after every run by default, waiting for the next one. Between two runs the
# caller does Python (the object index: crops, colors; a query: ranking; the segmenter: mask decoding), and on
# 2 cores the spinning threads take a core from the mapper's worker. Runs 50 ms apart, spinning against sleeping
# (benchmarks/bench_onnx_spinning.py, docs/results.md): ConSE's classifier on 3 crops 18 / 22 ms a run idle but
# 80 / 35 ms of CPU, beside a busy core 56 / 29 ms; one query text 3.6 / 4.9 ms idle but 47 / 5 ms of CPU; the
# segmenter's image 119 / 121 ms idle (285 / 230 ms of CPU), 240 / 193 ms beside a busy core.
_SPINNING = "session.intra_op.allow_spinning"


def make_session(
    path: Path, threads: int = DEFAULT_THREADS, *, prefer_cuda: bool = False, spinning: bool = False
) -> ort.InferenceSession:
    """An onnxruntime session on ``threads`` CPU threads, which sleep between runs (``spinning``: onnxruntime's
    default, for comparison); with ``prefer_cuda`` on the GPU when onnxruntime has its CUDA provider (falling
    back to the CPU)."""
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    options = ort.SessionOptions()
    options.intra_op_num_threads = int(threads)
    options.inter_op_num_threads = 1
    options.add_session_config_entry(_SPINNING, "1" if spinning else "0")
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    # Silence the per-node "initializer appears in graph inputs" style warnings on user exports.
    options.log_severity_level = 3
    providers = ["CPUExecutionProvider"]
    if prefer_cuda and "CUDAExecutionProvider" in ort.get_available_providers():
        providers.insert(0, "CUDAExecutionProvider")
    return ort.InferenceSession(str(path), sess_options=options, providers=providers)
