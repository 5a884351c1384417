"""Per-keyframe evidence time (SCD sums and votes) of the numba and torch rasterizers; prints one JSON object.

    python benchmarks/bench_scd.py                      # full run (several minutes on 2 cores)
    python benchmarks/bench_scd.py --quick              # smallest size and resolution, few repeats
    python benchmarks/bench_scd.py --scene synthetic    # another scene source (see SCENES)

A scene source is one function (n_gaussians, width, height) -> (map, intrinsics, [(cam_to_world,
mask)]); SCENES maps names to them. "replica" reads the Replica office_0 map under shared/data in
place: a random subset for sizes up to the map's 204k, jittered copies with smaller scales beyond it
(density grows as in a finer SLAM map), cameras from traj.txt, masks resized (nearest) to each
resolution. "synthetic" is monovoc_ros.synthetic's furnished room at the requested size.
Each configuration runs in a fresh subprocess so that its peak memory is its own. Timings follow a
warm-up pass; each repeat processes every benchmark keyframe once, and a keyframe's time is the
repeat's total over the number of keyframes. Other users of the CPU show in `loadavg` beside the
numbers: compare minima.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from monovoc_ros.core.map.camera import Intrinsics  # noqa: E402
from monovoc_ros.core.map.gaussians import GaussianMap  # noqa: E402

REPLICA = REPO.parent / "shared" / "data" / "replica_office0"
RESOLUTIONS = ((616, 344), (1200, 680))
SIZES = (35_000, 140_000, 560_000)


def replica_scene(n_gaussians: int, width: int, height: int, n_keyframes: int = 4, seed: int = 0):
    """(map, intrinsics, [(cam_to_world, mask)]) from Replica office_0 with about `n_gaussians` Gaussians."""
    from PIL import Image

    from monovoc_ros.core.map.ply import load_ply

    base = load_ply(REPLICA / "gaussians.ply")
    rng = np.random.default_rng(seed)
    if n_gaussians <= len(base):
        gmap = base.subset(np.sort(rng.choice(len(base), n_gaussians, replace=False)))
    else:
        copies = -(-n_gaussians // len(base))
        shrink = copies ** (-1.0 / 2.0)  # flat surfels: area per Gaussian falls as 1 / copies
        jitter = 0.5 * float(np.median(base.scales[:, :2]))
        means = np.concatenate([base.means + rng.normal(0.0, jitter, base.means.shape) for _ in range(copies)])
        keep = np.sort(rng.choice(len(means), n_gaussians, replace=False))
        gmap = GaussianMap(
            means[keep],
            np.tile(base.scales * shrink, (copies, 1))[keep],
            np.tile(base.quats, (copies, 1))[keep],
            np.tile(base.opacities, copies)[keep],
        )
    k = json.loads((REPLICA / "intrinsics.json").read_text())
    intrinsics = Intrinsics(k["fx"], k["fy"], k["cx"], k["cy"], k["width"], k["height"]).scaled_to(width, height)
    poses = np.loadtxt(REPLICA / "traj.txt").reshape(-1, 4, 4)
    views = []
    for i in np.linspace(0, len(poses) - 1, n_keyframes + 1).astype(int)[:-1]:
        mask = Image.open(REPLICA / "masks" / f"{i:06d}.png").convert("RGB").resize((width, height), Image.NEAREST)
        views.append((poses[i], np.asarray(mask)))
    return gmap, intrinsics, views


def synthetic_scene(n_gaussians: int, width: int, height: int, n_keyframes: int = 4, seed: int = 0):
    """The same from monovoc_ros.synthetic's furnished room (masks ray cast from its analytic surfaces)."""
    from monovoc_ros.synthetic import SceneConfig, generate_scene

    config = SceneConfig.at_resolution(width, height, seed=seed, n_gaussians=n_gaussians, n_keyframes=n_keyframes)
    scene = generate_scene(config)
    keyframes = [scene.keyframe(i) for i in range(len(scene))]
    return scene.load_gaussians(), keyframes[0].intrinsics, [(kf.cam_to_world, kf.mask) for kf in keyframes]


SCENES = {"replica": replica_scene, "synthetic": synthetic_scene}


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_config(scene: str, impl: str, n: int, width: int, height: int, repeats: int, mode: str = "scd") -> dict:
    """One configuration in this process: warm-up, then `repeats` passes over the keyframes.

    mode "scd" times core.raster.accumulate (color sums); "vote" times core.raster.accumulate_votes on
    the masks' pixel labels (made once per keyframe beforehand, as SemanticMapper does: `labels_ms`)."""
    from monovoc_ros.core.evidence.pixel_labels import mask_labels
    from monovoc_ros.core.raster import accumulate, accumulate_votes

    gmap, intrinsics, views = SCENES[scene](n, width, height)
    _ = gmap.covariances  # once per map, not per keyframe
    rss_before = _peak_rss_mb()
    if mode == "vote":
        mask_labels(views[0][1])  # kernels load on first use
    t0 = time.perf_counter()
    if mode == "vote":
        inputs = [mask_labels(mask)[0].labels for _, mask in views]
    else:
        inputs = [np.any(mask != 255, axis=2) for _, mask in views]
    labels_ms = 1e3 * (time.perf_counter() - t0) / len(views)

    def one(pose, mask, extra):
        if mode == "vote":
            return accumulate_votes(gmap, extra, intrinsics, pose, weight_power=4, impl=impl).n_visible
        return accumulate(gmap, mask, intrinsics, pose, valid=extra, weight_power=4, impl=impl).n_visible

    visible = []
    t0 = time.perf_counter()
    for (pose, mask), extra in zip(views, inputs, strict=True):
        visible.append(one(pose, mask, extra))
    warmup = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for (pose, mask), extra in zip(views, inputs, strict=True):
            one(pose, mask, extra)
        times.append((time.perf_counter() - t0) / len(views))
    return {
        "scene": scene,
        "mode": mode,
        "labels_ms": round(labels_ms, 2) if mode == "vote" else None,
        "impl": impl,
        "gaussians": len(gmap),
        "resolution": f"{width}x{height}",
        "keyframes": len(views),
        "repeats": repeats,
        "ms_per_keyframe_median": round(1e3 * float(np.median(times)), 2),
        "ms_per_keyframe_min": round(1e3 * float(np.min(times)), 2),
        "warmup_s": round(warmup, 3),
        "visible_mean": int(np.mean(visible)),
        "peak_rss_mb": round(_peak_rss_mb(), 1),
        "peak_rss_mb_before_calls": round(rss_before, 1),
        "threads": _threads(impl),
        "loadavg": [round(x, 2) for x in os.getloadavg()],
    }


def _threads(impl: str) -> int:
    if impl == "torch":
        import torch

        return torch.get_num_threads()
    import numba

    return numba.get_num_threads()


_COMPILE_SNIPPET = """
import json, sys, time
t0 = time.perf_counter()
import numpy as np
from monovoc_ros.core.map.camera import Intrinsics
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.raster import accumulate, render
t1 = time.perf_counter()
rng = np.random.default_rng(0)
g = GaussianMap(rng.uniform(-1, 1, (50, 3)) + [0, 0, 3], np.full((50, 3), 0.05), rng.normal(size=(50, 4)),
                np.full(50, 0.5))
k = Intrinsics(40.0, 40.0, 31.5, 23.5, 64, 48)
mask = np.zeros((48, 64, 3), np.uint8)
accumulate(g, mask, k, np.eye(4), valid=np.ones((48, 64), bool))
accumulate(g, mask.astype(np.float32), k, np.eye(4), background=(1, 1, 1))
render(g, np.zeros((50, 3)), k, np.eye(4))
t2 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "first_calls_s": t2 - t1}))
"""


def compile_times() -> dict:
    """First-call time of the numba pipeline from an empty cache (cold) and from a filled one (warm)."""
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, PYTHONPATH=str(REPO))
        for name in ("cold_cache", "warm_cache"):
            res = subprocess.run(
                [sys.executable, "-c", _COMPILE_SNIPPET], env=env, capture_output=True, text=True, check=True
            )
            out[name] = {k: round(v, 3) for k, v in json.loads(res.stdout.strip().splitlines()[-1]).items()}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smallest size and resolution, few repeats")
    parser.add_argument("--scene", choices=sorted(SCENES), default=None, help="default: replica if present")
    parser.add_argument("--impl", choices=("numba", "torch"), action="append", help="default: both")
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--mode", choices=("scd", "vote"), action="append", help="evidence kind; default: both")
    parser.add_argument("--config", help=argparse.SUPPRESS)  # scene,impl,n,width,height,repeats: in-process
    args = parser.parse_args()
    if args.config:
        scene, impl, n, w, h, reps, mode = args.config.split(",")
        print(json.dumps(run_config(scene, impl, int(n), int(w), int(h), int(reps), mode)))
        return
    scene = args.scene or ("replica" if (REPLICA / "gaussians.ply").exists() else "synthetic")
    sizes = SIZES[:1] if args.quick else SIZES
    resolutions = RESOLUTIONS[:1] if args.quick else RESOLUTIONS
    report = {"scene": scene, "cpu_count": os.cpu_count(), "compile": compile_times(), "runs": []}
    for impl, mode in ((i, m) for i in args.impl or ("numba", "torch") for m in args.mode or ("scd", "vote")):
        for w, h in resolutions:
            for n in sizes:
                # The torch path exists for GPUs; on a CPU its large configurations get one repeat.
                reps = args.repeats or (2 if args.quick else (7 if impl == "numba" else (3 if n <= 140_000 else 1)))
                cmd = [sys.executable, __file__, "--config", f"{scene},{impl},{n},{w},{h},{reps},{mode}"]
                res = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(REPO)))
                if res.returncode != 0:
                    tail = res.stderr.strip().splitlines()[-1:]
                    failed = {"impl": impl, "mode": mode, "gaussians": n, "resolution": f"{w}x{h}", "error": tail}
                    report["runs"].append(failed)
                    continue
                report["runs"].append(json.loads(res.stdout.strip().splitlines()[-1]))
    report["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
