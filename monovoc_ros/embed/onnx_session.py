"""onnxruntime sessions configured the same way for every backend."""

from __future__ import annotations

from pathlib import Path

import onnxruntime as ort

# The robot shares its CPU with SLAM and the ROS executors: two intra-op threads keep the embedder from
# starving them while still using the vectorised kernels well (see MODELS.md for the timings).
DEFAULT_THREADS = 2


def make_session(path: Path, threads: int = DEFAULT_THREADS, *, prefer_cuda: bool = False) -> ort.InferenceSession:
    """An onnxruntime session on ``threads`` CPU threads; with ``prefer_cuda`` on the GPU when onnxruntime has
    its CUDA provider (falling back to the CPU)."""
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    options = ort.SessionOptions()
    options.intra_op_num_threads = int(threads)
    options.inter_op_num_threads = 1
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    # Silence the per-node "initializer appears in graph inputs" style warnings on user exports.
    options.log_severity_level = 3
    providers = ["CPUExecutionProvider"]
    if prefer_cuda and "CUDAExecutionProvider" in ort.get_available_providers():
        providers.insert(0, "CUDAExecutionProvider")
    return ort.InferenceSession(str(path), sess_options=options, providers=providers)
