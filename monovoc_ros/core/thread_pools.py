"""Thread pools that sleep when idle. On 2 cores a pool's spinning threads take the core from the thread
that has work, so every pool the package drives waits passively unless the user chose otherwise:

- BLAS runs on one thread: numpy only ever hands it small matrices, and OpenBLAS's threads busy-wait for a
  while after every call (per-frame association ~41 -> ~19 ms median, bench_association: 140k Gaussians; the
  segmenter's YOLOv5s-seg keyframe ~145 -> ~100 ms: its mask decoding's one matmul had onnxruntime's next run
  wait). The limit covers the BLAS libraries loaded so far (numpy's, OpenCV's); the variable, those loaded
  later (scipy's) in this process and in the processes it starts. A user's own OPENBLAS_NUM_THREADS
  (non-empty) is left as it is.
- numba's parallel kernels run on OpenMP, whose idle threads spin after every parallel region (libgomp's
  default) while the calling thread runs the Python between two kernels: a 1M-Gaussian keyframe took
  171-191 ms of CPU for 135-157 ms of wall time beside another busy process, and 113-117 ms of CPU for
  111-115 ms with the threads sleeping. OpenMP reads OMP_WAIT_POLICY once, when its runtime starts (the first
  parallel kernel of the process), so `passive_openmp` runs when monovoc_ros.core is imported; a user's own
  OMP_WAIT_POLICY (non-empty) is left as it is.
"""

from __future__ import annotations

import os

import threadpoolctl


def single_threaded_blas() -> None:
    if not os.environ.get("OPENBLAS_NUM_THREADS"):
        os.environ["OPENBLAS_NUM_THREADS"] = "1"
        threadpoolctl.threadpool_limits(1, user_api="blas")


def passive_openmp() -> None:
    if not os.environ.get("OMP_WAIT_POLICY"):
        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
