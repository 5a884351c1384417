"""The numba kernel's building blocks, each against a plain twin: exp, depth sort, tile culling, threads."""

from __future__ import annotations

import numba
import numpy as np
from numba import njit
from test_raster import random_scene

from monovoc_ros.core.raster import accumulate
from monovoc_ros.core.raster import numba_impl as ni
from monovoc_ros.core.raster import numba_kernels as nk
from monovoc_ros.core.raster.constants import ALPHA_MIN, TILE
from monovoc_ros.core.raster.inputs import check_view
from monovoc_ros.core.raster.reference import project_map


@njit(cache=True, fastmath=nk._FASTMATH)  # as in the compositing loops it is inlined into
def _exp_all(x):
    out = np.empty_like(x)
    for i in range(x.shape[0]):
        out[i] = nk.exp_nonpositive(x[i])
    return out


def test_polynomial_exp_matches_numpy():
    x = np.concatenate([-np.linspace(0.0, 30.0, 200_001), -np.geomspace(1e-8, 1.0, 1000), [-0.0]]).astype(np.float32)
    got = _exp_all(x).astype(np.float64)
    want = np.exp(x.astype(np.float64))
    assert np.max(np.abs(got - want) / want) < 3e-7
    assert _exp_all(np.array([-40.0, -1e6], np.float32)).max() <= np.exp(-30.0) * 1.0001  # clamped, no denormals


def test_radix_depth_sort_is_a_stable_argsort():
    rng = np.random.default_rng(0)
    depth = rng.choice(np.float32([0.5, 1.0, 1.25, 3.0]), 5000) + rng.choice([0.0, 1e-3], 5000).astype(np.float32)
    depth[::7] = rng.uniform(0.2, 100.0, depth[::7].size)
    rect = np.zeros((depth.size, 4), np.int32)
    visible = rng.random(depth.size) < 0.8
    rect[visible] = (0, 1, 0, 1)
    got = nk.visible_by_depth(depth.astype(np.float32), rect)
    idx = np.flatnonzero(visible)
    np.testing.assert_array_equal(got, idx[np.argsort(depth[idx], kind="stable")])


def test_ranks_by_index_is_the_argsort_of_the_depth_order():
    rng = np.random.default_rng(1)
    for n, v in ((1000, 0), (1000, 1), (5000, 3000)):
        order = rng.choice(n, v, replace=False).astype(np.int32)
        np.testing.assert_array_equal(nk.ranks_by_index(order, n), np.argsort(order))


def test_tile_lists_are_depth_ordered_and_cull_no_reachable_tile():
    """Every tile holding a pixel with alpha >= 1/255 (float64) keeps the Gaussian; lists stay front to back."""
    for seed, kind in ((0, "mixed"), (3, "needles")):
        gmap, k, pose, _ = random_scene(seed, n=150, width=96, height=80, kind=kind)
        view = check_view(gmap, k, pose)
        b = ni.bin_view(gmap, view, None, numba.get_num_threads())
        proj = project_map(gmap, view)
        gx, gy = b.grid
        listed = set()
        for t in range(gx * gy):
            ranks = b.tile_list[b.tile_start[t] : b.tile_start[t + 1]]
            assert np.all(np.diff(ranks) > 0)  # depth order = rank order
            listed.update((int(b.order[r]), t) for r in ranks)
        # Slots: Gaussian-major and a permutation of the pairs.
        assert np.array_equal(np.sort(b.tile_slot), np.arange(len(b.tile_slot)))
        ys, xs = np.mgrid[0 : k.height, 0 : k.width]
        n_culled = 0
        for i in np.flatnonzero(proj.visible):
            x0, x1, y0, y1 = proj.rect[i]
            a, bb, c = proj.conic[i]
            dx, dy = xs - proj.mean2d[i, 0], ys - proj.mean2d[i, 1]
            alpha = gmap.opacities[i] * np.exp(-0.5 * (a * dx * dx + 2 * bb * dx * dy + c * dy * dy))
            for ty in range(y0, y1):
                for tx in range(x0, x1):
                    tile = alpha[ty * TILE : (ty + 1) * TILE, tx * TILE : (tx + 1) * TILE]
                    if (i, ty * gx + tx) in listed:
                        continue
                    n_culled += 1
                    assert tile.max() < ALPHA_MIN, f"Gaussian {i} culled from tile {(tx, ty)} it reaches"
            assert all(t // gx in range(y0, y1) and t % gx in range(x0, x1) for (j, t) in listed if j == i)
        assert n_culled > 0  # the ellipse cull did drop tiles of the radius box


def test_results_do_not_depend_on_thread_count():
    gmap, k, pose, mask = random_scene(2, n=400, width=96, height=80)
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = accumulate(gmap, mask, k, pose, background=(0.5, 0.5, 0.5))
    finally:
        numba.set_num_threads(before)
    many = accumulate(gmap, mask, k, pose, background=(0.5, 0.5, 0.5))
    np.testing.assert_array_equal(one.color_sum, many.color_sum)
    np.testing.assert_array_equal(one.weight_sum, many.weight_sum)


def test_workspace_reuse_across_map_and_image_sizes():
    """Scratch buffers outlive calls: a smaller call after a larger one must not see stale data."""
    big = random_scene(0, n=600, width=128, height=96)
    small = random_scene(1, n=50, width=40, height=30)
    first = [accumulate(g, m, k, p) for g, k, p, m in (big, small)]
    again = [accumulate(g, m, k, p) for g, k, p, m in (small, big, small)]
    for a, b in zip((first[1], first[0], first[1]), again, strict=True):
        np.testing.assert_array_equal(a.color_sum, b.color_sum)
        np.testing.assert_array_equal(a.weight_sum, b.weight_sum)
    g, k, p, m = small
    ref = accumulate(g, m, k, p, impl="reference")
    np.testing.assert_allclose(again[2].weight_sum, ref.weight_sum, atol=1e-4 * ref.weight_sum.max())
    assert ni.WORKSPACE.nbytes > 0


_BLAS_THREADS = """
import json, threadpoolctl
import numpy, cv2
import monovoc_ros.core.raster.numba_impl
import scipy.linalg
blas = [i for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]
print(json.dumps([(i["filepath"], i["num_threads"]) for i in blas]))
"""


def test_blas_runs_on_one_thread_unless_the_user_chose(tmp_path):
    """OpenBLAS's spinning threads took the cores from the kernels (numba_impl): every BLAS library, loaded
    before the rasterizer or after it, runs one thread; a user's OPENBLAS_NUM_THREADS wins."""
    import json
    import os
    import subprocess
    import sys

    def blas(**env) -> list:
        clean = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}
        out = subprocess.run([sys.executable, "-c", _BLAS_THREADS], env={**clean, **env}, capture_output=True,
                             text=True, check=True, cwd=tmp_path)  # fmt: skip
        return json.loads(out.stdout)

    ours = blas()  # pip wheels: numpy's, OpenCV's and scipy's own OpenBLAS; a distro's: one shared
    assert ours and {n for _, n in ours} == {1}, ours
    # OpenBLAS runs no more threads than there are CPUs.
    assert {n for _, n in blas(OPENBLAS_NUM_THREADS="2")} == {min(2, os.cpu_count() or 1)}
