"""The numba kernel's building blocks, each against a plain twin: exp, depth sort, tile culling, threads."""

from __future__ import annotations

import numba
import numpy as np
from numba import njit
from test_raster import random_quats, random_scene

from monovoc_ros.core.map.camera import Intrinsics, pose_from_translation_quat
from monovoc_ros.core.map.gaussians import (
    _MORTON_BITS,
    MAP_CHUNK,
    GaussianMap,
    chunk_bounds_reference,
    finite_box,
    finite_box_reference,
    group_by_chunk,
    morton_keys,
    morton_keys_reference,
    quat_norms,
    quat_norms_reference,
)
from monovoc_ros.core.map.sorting import argsort_keys
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
    identity = np.arange(depth.size, dtype=np.int32)
    got = nk.visible_by_depth(depth.astype(np.float32), rect, identity, np.ones(2, np.bool_), 4096)
    idx = np.flatnonzero(visible)
    np.testing.assert_array_equal(got, idx[np.argsort(depth[idx], kind="stable")])
    # A chunk the view culled is skipped whatever its rows hold.
    got = nk.visible_by_depth(depth.astype(np.float32), rect, identity, np.array([False, True]), 4096)
    kept = idx[idx >= 4096]
    np.testing.assert_array_equal(got, kept[np.argsort(depth[kept], kind="stable")])
    # Places of Gaussians in another order (GaussianMap.placed): ties keep the order of their map indices.
    members = rng.permutation(depth.size).astype(np.int32)
    got = nk.visible_by_depth(depth.astype(np.float32), rect, members, np.ones(2, np.bool_), 4096)
    by_map = members[idx][np.argsort(members[idx])]  # the visible Gaussians' map indices, ascending
    place_of = np.argsort(members)
    want = by_map[np.argsort(depth[place_of[by_map]], kind="stable")]
    np.testing.assert_array_equal(members[got], want)


def _chunked_scene(seed: int, chunks: int = 24):
    """Chunks of MAP_CHUNK Gaussians scattered around and behind a camera looking down +z, many just off the
    image or the near plane, some of them large enough to reach into the image from outside."""
    rng = np.random.default_rng(seed)
    k = Intrinsics(80.0, 75.0, 47.0, 41.0, 96, 80)
    means, scales = [], []
    for _ in range(chunks):
        z = rng.uniform(-2.0, 12.0)
        edge = rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 1.6) * np.array([48 / 80, 40 / 75]) * abs(z)
        center = np.array([*edge * rng.permutation([1.0, rng.uniform(-1, 1)]), z])
        spread = rng.uniform(0.01, 0.5)
        means.append(center + rng.normal(0.0, spread, (MAP_CHUNK, 3)))
        scales.append(np.exp(rng.uniform(np.log(1e-3), np.log(rng.uniform(0.01, 1.5)), (MAP_CHUNK, 3))))
    # Tiny Gaussians just left of the image, whose footprints (the 2D dilation) still touch its first tiles.
    z = np.full(MAP_CHUNK, 2.5)
    u = rng.uniform(-0.9, -0.3, MAP_CHUNK)
    means.append(np.stack([(u - k.cx) * z / k.fx, rng.uniform(-0.3, 0.3, MAP_CHUNK) * z, z], axis=1))
    scales.append(np.full((MAP_CHUNK, 3), 1e-4))
    means, scales = np.concatenate(means), np.concatenate(scales)
    n = len(means)
    gmap = GaussianMap(means, scales, random_quats(rng, n), rng.uniform(0.05, 1.0, n))
    pose = pose_from_translation_quat(np.zeros(3), np.array([1.0, *rng.normal(0, 0.001, 3)]))
    return gmap, k, pose


def test_chunk_cull_keeps_every_chunk_a_visible_gaussian_is_in():
    """`live_chunks` drops a chunk only when the reference projection keeps none of its Gaussians, and the
    numba path then sees exactly the reference's visible Gaussians in depth order, whatever the map's order
    (chunks are made by place: a shuffled map, as densification leaves a SLAM's, culls as well)."""
    for shuffled in (False, True):
        culled = 0
        for seed in range(4):
            gmap, k, pose = _chunked_scene(seed)
            if shuffled:
                gmap = gmap.subset(np.random.default_rng(seed).permutation(len(gmap)))
            for far in (np.inf, 6.0):
                view = check_view(gmap, k, pose, far)
                live = ni.live_chunks(gmap, view)
                visible = project_map(gmap, view).visible
                holds = np.bincount(np.argsort(gmap.chunk_members)[visible] // MAP_CHUNK, minlength=len(live)) > 0
                assert not np.any(holds & ~live), (seed, far, np.flatnonzero(holds & ~live))
                culled += int(np.count_nonzero(~live))
                b = ni.bin_view(gmap, view, None, numba.get_num_threads())
                np.testing.assert_array_equal(np.sort(b.order), np.flatnonzero(visible))
        assert culled >= 30, shuffled  # of 200 chunks: the cull does its job on chunks far off the view


def test_chunk_bounds_equal_their_plain_twin():
    gmap, _, _ = _chunked_scene(5, chunks=3)
    part = gmap.subset(np.random.default_rng(5).permutation(len(gmap))[: 2 * MAP_CHUNK + 100])  # a last chunk of 100
    members = part.chunk_members
    # A permutation, ascending inside each chunk, each chunk's Gaussians of one place (the scene's clusters).
    np.testing.assert_array_equal(np.sort(members), np.arange(len(part)))
    chunks = [members[c : c + MAP_CHUNK] for c in range(0, len(part), MAP_CHUNK)]
    assert all(np.all(np.diff(c) > 0) for c in chunks)
    placed = part.placed
    np.testing.assert_array_equal(placed.members, members)
    np.testing.assert_array_equal(placed.means, part.means[members])
    np.testing.assert_array_equal(placed.covariances, part.covariances[members])
    np.testing.assert_array_equal(placed.opacities, part.opacities[members])
    want = chunk_bounds_reference(part.means, part.scales, members, MAP_CHUNK)
    for got, w in zip(part.chunk_bounds, want, strict=True):
        np.testing.assert_array_equal(got, w)
    lower, upper, reach = part.chunk_bounds
    assert lower.shape == upper.shape == (3, 3) and reach.shape == (3,)
    np.testing.assert_array_equal(lower[2], part.means[chunks[2]].min(axis=0))
    # The Z-order keys and the grouping against their plain twins (NaN and out-of-box means included).
    rng = np.random.default_rng(8)
    means = rng.uniform(-3.0, 7.0, (20000, 3)).astype(np.float32)
    means[::997] = np.nan
    low, scale = np.full(3, -2.0), np.full(3, ((1 << _MORTON_BITS) - 1) / 8.0)  # a box smaller than the points: clamped
    np.testing.assert_array_equal(morton_keys(means, low, scale), morton_keys_reference(means, low, scale))
    means[5] = (np.inf, 0.0, 0.0)
    means[9] = (-0.0, 1.0, -np.inf)
    # The finite means' box (NaN and inf rows left out): whole, fewer rows than work items, one NaN row, none.
    for rows in (slice(None), slice(1, 40), slice(0, 1), slice(0, 0)):
        want = finite_box_reference(means[rows])
        for got, w in zip(finite_box(means[rows]), want, strict=True):
            np.testing.assert_array_equal(got, w)
    assert finite_box(means[1:40])[0][0] > -3.0 and finite_box(means[:1])[0][0] == np.inf
    # How many rows are finite: all but the NaN rows and rows 5 and 9.
    assert finite_box(means)[2] == 20000 - len(range(0, 20000, 997)) - 2 and finite_box(means[1:40])[2] == 37
    order = rng.permutation(20000)
    grouped = group_by_chunk(order, 4096)
    for c in range(0, 20000, 4096):
        np.testing.assert_array_equal(grouped[c : c + 4096], np.sort(order[c : c + 4096]))
    # By place, not by the map's order: 8 chunks of a uniform cube are (about) its 8 octants.
    cube = np.random.default_rng(6).uniform(0.0, 1.0, (8 * MAP_CHUNK, 3))
    cube_map = GaussianMap(cube, np.full_like(cube, 0.01), random_quats(np.random.default_rng(6), len(cube)),
                           np.full(len(cube), 0.5))  # fmt: skip
    for c in range(0, len(cube), MAP_CHUNK):  # the octants hold MAP_CHUNK points give or take a few dozen
        points = cube[cube_map.chunk_members[c : c + MAP_CHUNK]]
        octant = (points >= 0.5) @ np.array([1, 2, 4])
        assert np.bincount(octant, minlength=8).max() >= 0.93 * MAP_CHUNK
    bad = GaussianMap(np.where(np.arange(len(part))[:, None] == 5, np.nan, part.means), part.scales, part.quats,
                      part.opacities)  # fmt: skip
    assert 5 in bad.chunk_members[-100:]  # a non-finite mean goes last, into the last chunk
    assert np.isnan(bad.chunk_bounds[0][-1]).all() and not np.isnan(bad.chunk_bounds[0][:-1]).any()
    want = chunk_bounds_reference(bad.means, bad.scales, bad.chunk_members, MAP_CHUNK)
    for got, w in zip(bad.chunk_bounds, want, strict=True):
        np.testing.assert_array_equal(got, w)
    view = check_view(part, Intrinsics(80.0, 75.0, 47.0, 41.0, 96, 80), np.eye(4))
    assert ni.live_chunks(bad, view)[-1]  # a chunk with a non-finite mean is never dropped
    # An infinite scale or mean makes its chunk's bounds NaN, as in the twin; the placed rows stay the gathered ones.
    scales = part.scales.copy()
    scales[members[3]] = (np.inf, 0.01, 0.01)
    means = part.means.copy()
    means[members[MAP_CHUNK + 7]] = (1.0, np.inf, 0.0)
    odd = GaussianMap(means, scales, part.quats, part.opacities)
    placed_at = odd.chunk_members
    assert members[MAP_CHUNK + 7] in placed_at[2 * MAP_CHUNK :]  # the infinite mean went to the last chunk
    assert np.isnan(odd.chunk_bounds[2]).sum() == 2 and np.isnan(odd.chunk_bounds[2][-1])
    for got, w in zip(odd.chunk_bounds, chunk_bounds_reference(means, scales, placed_at, MAP_CHUNK), strict=True):
        np.testing.assert_array_equal(got, w)
    np.testing.assert_array_equal(odd.placed.means, means[placed_at])
    np.testing.assert_array_equal(odd.placed.covariances, odd.covariances[placed_at])


def test_quat_norms_equal_numpys_bit_for_bit():
    """A map's quaternions are renormalized only where their numpy norm is off unit: the kernel's norms are
    numpy's to the bit, over magnitudes where the squares lose precision, underflow or overflow."""
    rng = np.random.default_rng(3)
    for scale in (1.0, 1e-20, 3e-38, 1e19):
        quats = (rng.standard_normal((5000, 4)) * scale).astype(np.float32)
        quats[5, 2], quats[9, 1], quats[11] = np.nan, np.inf, 0.0
        with np.errstate(over="ignore", under="ignore", invalid="ignore"):
            quats[::7] /= np.linalg.norm(quats[::7], axis=-1, keepdims=True).clip(1e-30)
            want = quat_norms_reference(quats)
        np.testing.assert_array_equal(quat_norms(quats), want)
    assert quat_norms(np.zeros((0, 4), np.float32)).shape == (0,)
    # The map keeps unit quaternions as given and normalizes the others with those norms.
    quats = rng.standard_normal((300, 4)).astype(np.float32)
    quats[::2] /= np.linalg.norm(quats[::2], axis=-1, keepdims=True)
    given = quats.copy()
    scales = np.full((300, 3), 0.1, np.float32)
    gmap = GaussianMap(np.zeros((300, 3), np.float32), scales, quats, np.full(300, 0.5, np.float32))
    norms = np.linalg.norm(given, axis=-1)
    off = np.abs(norms - 1.0) > 1e-6
    np.testing.assert_array_equal(gmap.quats[~off], given[~off])
    np.testing.assert_array_equal(gmap.quats[off], given[off] / norms[off, None])
    assert off.sum() >= 140


def test_argsort_keys_equals_numpys_stable_argsort():
    rng = np.random.default_rng(3)
    cases = [
        rng.integers(0, 2**62, 5000),  # every digit differs
        (1 << 41) * 7 + rng.integers(0, 300, 5000),  # high digits shared (skipped), many ties
        np.full(100, 12345),  # one key
        rng.integers(0, 2**20, 1),
        np.zeros(0, np.int64),
    ]
    for keys in cases:
        keys = np.asarray(keys, np.int64)
        np.testing.assert_array_equal(argsort_keys(keys), np.argsort(keys, kind="stable"))


def test_ranks_by_index_is_the_argsort_of_the_depth_order():
    rng = np.random.default_rng(1)
    for n, v in ((1000, 0), (1000, 1), (5000, 3000)):
        order = rng.choice(n, v, replace=False).astype(np.int32)
        np.testing.assert_array_equal(nk.ranks_by_index(order, n), np.argsort(order))


def test_voted_ranks_are_the_gaussians_with_a_positive_slot():
    """Its NumPy twin: a Gaussian is voted when any channel of any of its pair slots is above 0 (NaN, 0 and negative
    rounding are not); Gaussians without pairs are not."""
    rng = np.random.default_rng(2)
    for n, pairs in ((1, 0), (3, 0), (7, 30), (20_000, 60_000)):
        cuts = np.sort(rng.integers(0, pairs + 1, max(0, n - 1)))
        gauss_start = np.concatenate([[0], cuts, [pairs]]).astype(np.int64)
        acc = rng.choice(np.array([0.0, 0.0, 0.0, -1e-9, np.nan, 0.25], np.float32), (pairs, 4))
        positive = (acc > 0).any(axis=1)
        want = np.flatnonzero([positive[a:b].any() for a, b in zip(gauss_start[:-1], gauss_start[1:], strict=True)])
        np.testing.assert_array_equal(nk.voted_ranks(acc, gauss_start, 2), want)


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


_OPENMP_WAIT_POLICY = """
import ctypes, numba, numpy
from monovoc_ros.core.map.gaussians import gather_rows
gather_rows(numpy.ones((64, 3)), numpy.arange(64))  # a parallel kernel: the OpenMP runtime starts here
assert numba.threading_layer() == "omp", numba.threading_layer()
gomp = sorted({line.split()[-1] for line in open("/proc/self/maps") if "libgomp" in line})
ctypes.CDLL(gomp[0]).omp_display_env(1)  # the runtime's own settings (verbose: its spin count), on stderr
"""


def test_openmp_threads_sleep_when_idle_unless_the_user_chose(tmp_path):
    """libgomp's idle threads spin after every parallel region, taking the core from the node's other threads:
    the OpenMP runtime numba's kernels run on waits passively, unless the user set OMP_WAIT_POLICY."""
    import os
    import subprocess
    import sys

    def spin_count(**env) -> int:
        """How long libgomp's idle threads spin before they sleep (the wait policy's effect)."""
        clean = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
        out = subprocess.run([sys.executable, "-c", _OPENMP_WAIT_POLICY], env={**clean, **env}, capture_output=True,
                             text=True, check=True, cwd=tmp_path)  # fmt: skip
        (line,) = [ln for ln in out.stderr.splitlines() if ln.strip().startswith("GOMP_SPINCOUNT")]
        return int(line.split("=")[1].strip().strip("'"))

    assert spin_count() == 0
    assert spin_count(OMP_WAIT_POLICY="ACTIVE") > 10**6
