"""The torch vote kernel on CUDA held against the numba kernel and timed; prints one JSON object.

    python benchmarks/gpu_check.py            # 140k, 560k and 1.12M Gaussians at 616x344 (Replica office_0 if present)

Per size: the dense per-object votes of `accumulate_votes(impl="torch", device="cuda")` against the numba
kernel (largest difference relative to the largest vote; float32 compositing on both sides, so ~1e-4 is
agreement), and the median time per keyframe of both after a warm-up. Without CUDA it says so and exits 2.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_scd import REPLICA, SCENES  # noqa: E402

from monovoc_ros.core.evidence.pixel_labels import mask_labels  # noqa: E402
from monovoc_ros.core.raster import accumulate_votes  # noqa: E402


def dense(evidence, n: int, n_labels: int) -> np.ndarray:
    out = np.zeros((n, n_labels + 1))
    for e in range(evidence.labels.shape[1]):
        ok = evidence.labels[:, e] >= 0
        np.add.at(out, (evidence.rows[ok], evidence.labels[ok, e]), evidence.weights[ok, e])
    out[evidence.rows, n_labels] = evidence.other
    return out


def timed(fn, repeats: int = 5) -> float:
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def main() -> int:
    import torch

    if not torch.cuda.is_available():
        print(json.dumps({"cuda": False, "torch": torch.__version__}))
        return 2
    scene = "replica" if (REPLICA / "gaussians.ply").exists() else "synthetic"
    report = {"cuda": True, "device": torch.cuda.get_device_name(0), "torch": torch.__version__, "scene": scene}
    runs = []
    for n in (140_000, 560_000, 1_120_000):
        gmap, k, views = SCENES[scene](n, 616, 344)
        worst, t_cuda, t_numba = 0.0, [], []
        for pose, mask in views:
            labels = mask_labels(mask)[0].labels
            n_labels = int(labels.max()) + 1

            def on_cuda(gmap=gmap, k=k, labels=labels, pose=pose):
                out = accumulate_votes(gmap, labels, k, pose, weight_power=4, impl="torch", device="cuda")
                torch.cuda.synchronize()
                return out

            def on_numba(gmap=gmap, k=k, labels=labels, pose=pose):
                return accumulate_votes(gmap, labels, k, pose, weight_power=4, impl="numba")

            ref = dense(on_numba(), len(gmap), n_labels)
            got = dense(on_cuda(), len(gmap), n_labels)
            worst = max(worst, float(np.abs(got - ref).max() / max(ref.max(), 1e-12)))
            t_cuda.append(timed(on_cuda))
            t_numba.append(timed(on_numba))
        runs.append(
            {
                "gaussians": n,
                "resolution": "616x344",
                "max_rel_difference": worst,
                "agree": worst <= 1e-3,
                "cuda_ms_per_keyframe": round(float(np.median(t_cuda)), 2),
                "numba_ms_per_keyframe": round(float(np.median(t_numba)), 2),
            }
        )
    report["runs"] = runs
    print(json.dumps(report, indent=1))
    return 0 if all(r["agree"] for r in runs) else 1


if __name__ == "__main__":
    sys.exit(main())
