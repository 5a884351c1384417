"""One BLAS thread: numpy only ever hands BLAS small matrices here, and OpenBLAS's threads busy-wait for a
while after every call and take the cores from the threads that do the work (numba kernels, onnxruntime).

Measured: per-frame association fell from ~41 to ~19 ms median (bench_association: 140k Gaussians, 2 cores)
with its 50-90 ms outliers gone; the segmenter's YOLOv5s-seg keyframe from ~145 to ~100 ms (its mask
decoding's one matmul had onnxruntime's next run wait). The limit covers the BLAS libraries loaded so far
(numpy's, OpenCV's); the variable, those loaded later (scipy's) in this process and in the processes it
starts. Only a user's own OPENBLAS_NUM_THREADS (non-empty) is left as it is.
"""

from __future__ import annotations

import os

import threadpoolctl


def single_threaded_blas() -> None:
    if not os.environ.get("OPENBLAS_NUM_THREADS"):
        os.environ["OPENBLAS_NUM_THREADS"] = "1"
        threadpoolctl.threadpool_limits(1, user_api="blas")
