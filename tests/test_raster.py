"""The SCD rasterizer: fast implementations against the float64 reference, METHOD.md's oracles, input errors."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from monovoc_ros.core.map.camera import Intrinsics, pose_from_translation_quat
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.raster import IMPLEMENTATIONS, Evidence, Rendering, accumulate, render
from monovoc_ros.core.raster.reference import pixel_weights

FAST = ("numba", "torch")
TOL = 1e-4  # of the largest value, as float32 kernels against the float64 reference


def random_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def random_scene(seed: int, n: int = 300, width: int = 64, height: int = 48, kind: str = "mixed"):
    """A small random scene: Gaussians of all sizes and shapes, some behind the camera or before the
    near plane, some off-screen, many overlapping; a random camera pose and a random mask."""
    rng = np.random.default_rng(seed)
    k = Intrinsics(
        rng.uniform(40, 70), rng.uniform(40, 70), width / 2 + rng.uniform(-4, 4), height / 2 + rng.uniform(-4, 4),
        width, height,
    )  # fmt: skip
    z = rng.uniform(-1.0, 6.0, n)
    half_w, half_h = width / (2 * k.fx), height / (2 * k.fy)
    x = rng.uniform(-1.4, 1.4, n) * half_w * np.abs(z) + rng.normal(0, 0.05, n)
    y = rng.uniform(-1.4, 1.4, n) * half_h * np.abs(z) + rng.normal(0, 0.05, n)
    cam = np.stack([x, y, z], axis=1)
    if kind == "needles":
        scales = np.stack([rng.uniform(0.1, 0.6, n), np.full(n, 0.005), rng.uniform(0.001, 0.01, n)], axis=1)
    else:
        scales = np.exp(rng.uniform(np.log(0.003), np.log(0.5), (n, 3)))
        flat = rng.random(n) < 0.3  # surfels, as SLAM maps are full of
        scales[flat, 2] = 1e-4
    opacities = np.concatenate([rng.uniform(0.001, 1.0, n - n // 10), np.full(n // 10, 0.999)])
    cam_to_world = pose_from_translation_quat(rng.normal(0, 0.3, 3), np.array([1.0, *rng.normal(0, 0.1, 3)]))
    means = cam @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]
    gmap = GaussianMap(means, scales, random_quats(rng, n), rng.permutation(opacities))
    mask = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    return gmap, k, cam_to_world, mask


def assert_close(actual: np.ndarray, expected: np.ndarray, what: str, tol: float = TOL) -> None:
    scale = max(float(np.abs(expected).max()), 1e-12)
    err = float(np.abs(np.asarray(actual, np.float64) - expected).max()) / scale
    assert err <= tol, f"{what}: max error {err:.2e} of the largest value {scale:.3g}"


SCENES = [(0, "mixed"), (1, "mixed"), (2, "mixed"), (3, "needles")]


@pytest.mark.parametrize("impl", FAST)
@pytest.mark.parametrize("seed,kind", SCENES)
def test_accumulate_matches_reference(impl, seed, kind):
    gmap, k, pose, mask = random_scene(seed, kind=kind)
    ref = accumulate(gmap, mask, k, pose, impl="reference")
    out = accumulate(gmap, mask, k, pose, impl=impl)
    assert isinstance(out, Evidence)
    assert out.color_sum.shape == (len(gmap), 3) and out.color_sum.dtype == np.float64
    assert out.weight_sum.shape == (len(gmap),) and out.weight_sum.dtype == np.float64
    assert 0 < ref.n_visible < len(gmap)  # the scene really has culled Gaussians
    assert out.n_visible == ref.n_visible
    assert_close(out.weight_sum, ref.weight_sum, "weight_sum")
    assert_close(out.color_sum, ref.color_sum, "color_sum")


@pytest.mark.parametrize("impl", FAST)
@pytest.mark.parametrize("seed,kind", SCENES[::3])
def test_accumulate_with_valid_and_background_matches_reference(impl, seed, kind):
    gmap, k, pose, mask = random_scene(seed, kind=kind)
    rng = np.random.default_rng(seed + 100)
    valid = rng.random(mask.shape[:2]) < 0.7
    mask_f = mask.astype(np.float32) / 255.0
    bg = (0.3, 0.6, 0.9)
    ref = accumulate(gmap, mask_f, k, pose, valid=valid, background=bg, impl="reference")
    out = accumulate(gmap, mask_f, k, pose, valid=valid, background=bg, impl=impl)
    assert_close(out.weight_sum, ref.weight_sum, "weight_sum")
    assert_close(out.color_sum, ref.color_sum, "color_sum")
    # The background term really changes the answer, and invalid pixels really are left out.
    plain = accumulate(gmap, mask_f, k, pose, impl="reference")
    assert np.abs(plain.color_sum - ref.color_sum).max() > 0.1 * np.abs(ref.color_sum).max()
    assert np.all(ref.weight_sum <= plain.weight_sum + 1e-12)
    assert ref.weight_sum.sum() < 0.9 * plain.weight_sum.sum()


@pytest.mark.parametrize("impl", FAST)
@pytest.mark.parametrize("power", [2, 3, 4])
def test_weight_powers_match_reference(impl, power):
    gmap, k, pose, mask = random_scene(3, kind=SCENES[0][1])
    valid = np.random.default_rng(7).random(mask.shape[:2]) < 0.8
    ref = accumulate(gmap, mask, k, pose, valid=valid, weight_power=power, impl="reference")
    out = accumulate(gmap, mask, k, pose, valid=valid, weight_power=power, impl=impl)
    assert_close(out.weight_sum, ref.weight_sum, "weight_sum")
    assert_close(out.color_sum, ref.color_sum, "color_sum")
    # w^k <= w: larger powers only shrink the sums, and the per-pixel weights stay consistent.
    plain = accumulate(gmap, mask, k, pose, valid=valid, impl="reference")
    assert np.all(ref.weight_sum <= plain.weight_sum + 1e-12) and ref.weight_sum.sum() < plain.weight_sum.sum()


@pytest.mark.parametrize("power", [0, 5, 1.5, True])
def test_bad_weight_power_raises_value_error(power):
    gmap, k, pose, mask = random_scene(0, kind=SCENES[0][1])
    with pytest.raises(ValueError, match="weight_power"):
        accumulate(gmap, mask, k, pose, weight_power=power)


@pytest.mark.parametrize("impl", FAST)
@pytest.mark.parametrize("seed,kind", SCENES[::3])
def test_render_matches_reference(impl, seed, kind):
    gmap, k, pose, _ = random_scene(seed, kind=kind)
    colors = np.random.default_rng(seed).random((len(gmap), 3))
    ref = render(gmap, colors, k, pose, background=(0.2, 0.5, 1.0), impl="reference")
    out = render(gmap, colors, k, pose, background=(0.2, 0.5, 1.0), impl=impl)
    assert isinstance(out, Rendering)
    assert out.image.shape == (k.height, k.width, 3) and out.image.dtype == np.float32
    assert out.transmittance.shape == out.depth.shape == (k.height, k.width)
    assert 0.02 < ref.transmittance.mean() < 0.98  # partly covered, partly background
    err = np.maximum(np.abs(out.image - ref.image).max(axis=2), np.abs(out.transmittance - ref.transmittance))
    depth_err = np.abs(out.depth - ref.depth) / ref.depth.max()
    if kind == "needles":
        # float32 evaluation of 100:1 footprints is off by ~1e-4 relative in alpha, enough to flip the
        # alpha >= 1/255 test at a rare pixel (a jump of ~T/255): the CUDA rasterizers do the same.
        assert np.mean(err > TOL) < 2e-3 and err.max() < 1.5 / 255
        assert np.mean(depth_err > TOL) < 2e-3
    else:
        assert err.max() <= TOL and depth_err.max() <= TOL


def test_reference_partition_of_unity():
    for seed, kind in SCENES:
        gmap, k, pose, _ = random_scene(seed, kind=kind)
        weights, T = pixel_weights(gmap, k, pose)
        assert weights.shape == (k.height * k.width, len(gmap)) and T.shape == (k.height * k.width,)
        assert weights.min() >= 0.0 and weights.max() <= 1.0 and T.min() >= 0.0 and T.max() <= 1.0
        np.testing.assert_allclose(weights.sum(axis=1) + T, 1.0, atol=1e-12)
        assert (weights > 0).sum(axis=1).max() >= 3  # overlapping Gaussians


@pytest.mark.parametrize("impl", FAST)
def test_partition_of_unity(impl):
    gmap, k, pose, _ = random_scene(1)
    out = render(gmap, np.ones((len(gmap), 3)), k, pose, impl=impl)
    assert out.transmittance.min() >= 0.0 and out.transmittance.max() <= 1.0
    np.testing.assert_allclose(out.image[:, :, 0] + out.transmittance, 1.0, atol=2e-6)


def one_hot_scene(seed: int, width: int = 64, height: int = 48):
    """One small Gaussian per 16x16 tile, centred in it, so each pixel is covered by at most one."""
    rng = np.random.default_rng(seed)
    k = Intrinsics(50.0, 50.0, 31.5, 23.5, width, height)
    gx, gy = width // 16, height // 16
    tx, ty = np.meshgrid(np.arange(gx), np.arange(gy))
    u, v = tx.ravel() * 16 + 7.5, ty.ravel() * 16 + 7.5
    z = rng.uniform(1.0, 4.0, u.size)
    means = np.stack([(u - k.cx) * z / k.fx, (v - k.cy) * z / k.fy, z], axis=1)
    # Footprint radius ceil(3 sqrt(lambda_max)) stays below 8 px: the Gaussian reaches only its own tile.
    scales = np.stack([0.02 * z, 0.03 * z, 0.01 * z], axis=1) * rng.uniform(0.5, 1.0, (u.size, 1))
    gmap = GaussianMap(means, scales, random_quats(rng, u.size), rng.uniform(0.3, 1.0, u.size))
    return gmap, k, np.eye(4)


@pytest.mark.parametrize("impl", IMPLEMENTATIONS)
def test_exact_recovery_when_each_pixel_sees_one_gaussian(impl):
    gmap, k, pose = one_hot_scene(0)
    weights, _ = pixel_weights(gmap, k, pose)
    assert (weights > 0).sum(axis=1).max() == 1  # one-hot by construction
    owner = np.where(weights.max(axis=1) > 0, weights.argmax(axis=1), -1)
    rng = np.random.default_rng(1)
    s = rng.integers(0, 256, (len(gmap), 3)).astype(np.uint8)
    mask = rng.integers(0, 256, (k.height * k.width, 3)).astype(np.uint8)  # uncovered pixels: noise
    mask[owner >= 0] = s[owner[owner >= 0]]
    ev = accumulate(gmap, mask.reshape(k.height, k.width, 3), k, pose, impl=impl)
    assert np.all(ev.weight_sum > 0)
    s_hat = ev.color_sum / ev.weight_sum[:, None]
    np.testing.assert_allclose(s_hat, s / 255.0, atol=1e-6)


@pytest.mark.parametrize("impl", IMPLEMENTATIONS)
def test_overlap_bias_identity(impl):
    """Masks rendered from the same Gaussians: s_hat_i = sum_j G_ij s_j / W_i exactly (METHOD.md 3)."""
    gmap, k, pose, _ = random_scene(2, n=120)
    rng = np.random.default_rng(3)
    s = rng.random((len(gmap), 3))
    b = np.array([0.9, 0.1, 0.4])
    weights, T = pixel_weights(gmap, k, pose)
    mask = (weights @ s + T[:, None] * b).reshape(k.height, k.width, 3).astype(np.float32)
    ev = accumulate(gmap, mask, k, pose, background=b, impl=impl)
    W = weights.sum(axis=0)
    G = weights.T @ weights
    seen = W > 1e-2
    assert seen.sum() > 40 and np.count_nonzero(G[np.ix_(seen, seen)] - np.diag(np.diag(G[np.ix_(seen, seen)]))) > 0
    expected = (G @ s)[seen] / W[seen, None]
    s_hat = ev.color_sum[seen] / ev.weight_sum[seen, None]
    np.testing.assert_allclose(s_hat, expected, atol=1e-4)
    assert np.abs(expected - s[seen]).max() > 0.1  # overlap really biases the estimate


def culling_scene():
    k = Intrinsics(50.0, 50.0, 31.5, 23.5, 64, 48)
    means = [
        [0.0, 0.0, 2.0],  # visible
        [0.0, 0.0, 0.15],  # in front of the camera but before the near plane: culled, never occludes
        [0.0, 0.0, -2.0],  # behind the camera
        [40.0, 0.0, 2.0],  # far off-screen to the right
        [0.0, -30.0, 3.0],  # far off-screen above
        [np.nan, 0.0, 2.0],  # broken input must not poison the others
    ]
    scales = [[0.2, 0.2, 0.2], [0.5, 0.5, 0.5], [1.0, 1.0, 1.0], [0.1, 0.1, 0.1], [0.1, 0.1, 0.1], [0.1, 0.1, 0.1]]
    return GaussianMap(np.array(means), np.array(scales), np.tile([1.0, 0, 0, 0], (6, 1)), np.full(6, 0.9)), k


@pytest.mark.parametrize("impl", IMPLEMENTATIONS)
def test_culled_gaussians_get_zero_weight(impl):
    gmap, k = culling_scene()
    mask = np.full((48, 64, 3), 200, np.uint8)
    ev = accumulate(gmap, mask, k, np.eye(4), impl=impl)
    assert ev.n_visible == 1
    assert ev.weight_sum[0] > 1.0 and np.all(ev.weight_sum[1:] == 0) and np.all(ev.color_sum[1:] == 0)
    alone = accumulate(gmap.subset(np.array([0])), mask, k, np.eye(4), impl=impl)
    np.testing.assert_allclose(ev.weight_sum[0], alone.weight_sum[0], rtol=1e-6)


@pytest.mark.parametrize("impl", IMPLEMENTATIONS)
def test_empty_view_and_empty_map(impl):
    gmap, k = culling_scene()
    behind = gmap.subset(np.array([1, 2, 3, 4, 5]))
    mask = np.zeros((48, 64, 3), np.uint8)
    ev = accumulate(behind, mask, k, np.eye(4), impl=impl)
    assert ev.n_visible == 0 and np.all(ev.weight_sum == 0) and np.all(ev.color_sum == 0)
    empty = gmap.subset(np.zeros(0, dtype=np.int64))
    ev = accumulate(empty, mask, k, np.eye(4), impl=impl)
    assert ev.n_visible == 0 and ev.color_sum.shape == (0, 3) and ev.weight_sum.shape == (0,)
    for g in (behind, empty):
        out = render(g, np.ones((len(g), 3)), k, np.eye(4), background=(0.1, 0.2, 0.3), impl=impl)
        assert np.all(out.transmittance == 1) and np.all(out.depth == 0)
        np.testing.assert_allclose(out.image, np.broadcast_to([0.1, 0.2, 0.3], (48, 64, 3)), atol=1e-7)


@pytest.mark.parametrize("impl", FAST)
def test_uint8_and_float_masks_agree(impl):
    gmap, k, pose, mask = random_scene(0)
    a = accumulate(gmap, mask, k, pose, impl=impl)
    b = accumulate(gmap, mask.astype(np.float64) / 255.0, k, pose, impl=impl)
    np.testing.assert_allclose(a.color_sum, b.color_sum, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(a.weight_sum, b.weight_sum)


@pytest.mark.parametrize("impl", IMPLEMENTATIONS)
def test_bad_input_raises_value_error(impl):
    gmap, k, pose, mask = random_scene(0, n=20)
    with pytest.raises(ValueError, match="32x24.*64x48"):
        accumulate(gmap, mask[:24, :32], k, pose, impl=impl)
    with pytest.raises(ValueError, match="dtype"):
        accumulate(gmap, mask.astype(np.int32), k, pose, impl=impl)
    with pytest.raises(ValueError, match="dtype"):
        accumulate(gmap, mask > 100, k, pose, impl=impl)
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        accumulate(gmap, mask[:, :, 0], k, pose, impl=impl)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        accumulate(gmap, mask.astype(np.float32), k, pose, impl=impl)
    bad_pose = pose.copy()
    bad_pose[0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        accumulate(gmap, mask, k, bad_pose, impl=impl)
    with pytest.raises(ValueError, match="orthonormal"):
        accumulate(gmap, mask, k, np.diag([2.0, 1.0, 1.0, 1.0]), impl=impl)
    with pytest.raises(ValueError, match="valid"):
        accumulate(gmap, mask, k, pose, valid=np.ones((48, 63), bool), impl=impl)
    with pytest.raises(ValueError, match="valid"):
        accumulate(gmap, mask, k, pose, valid=np.ones((48, 64), np.uint8), impl=impl)
    with pytest.raises(ValueError, match="background"):
        accumulate(gmap, mask, k, pose, background=(1.0, 0.0), impl=impl)
    with pytest.raises(ValueError, match="colors"):
        render(gmap, np.ones((len(gmap) + 1, 3)), k, pose, impl=impl)


def test_bad_implementation_or_device_raises_value_error():
    gmap, k, pose, mask = random_scene(0, n=20)
    with pytest.raises(ValueError, match="impl must be one of"):
        accumulate(gmap, mask, k, pose, impl="cuda")
    with pytest.raises(ValueError, match="device"):
        accumulate(gmap, mask, k, pose, impl="numba", device="cpu")
    with pytest.raises(ValueError, match="device"):
        accumulate(gmap, mask, k, pose, impl="torch", device="not-a-device")


def test_torch_explicit_cpu_device():
    gmap, k, pose, mask = random_scene(1)
    a = accumulate(gmap, mask, k, pose, impl="torch", device="cpu")
    b = accumulate(gmap, mask, k, pose, impl="torch")
    np.testing.assert_array_equal(a.color_sum, b.color_sum)


def test_numba_is_deterministic_and_thread_safe():
    scenes = [random_scene(seed, n=400, width=96, height=80) for seed in (0, 3)]
    expected = [accumulate(g, m, k, p) for g, k, p, m in scenes]
    results: dict[int, Evidence] = {}
    errors: list[BaseException] = []

    def work(i: int) -> None:
        try:
            g, k, p, m = scenes[i % 2]
            for _ in range(5):
                results[i] = accumulate(g, m, k, p)
        except BaseException as exc:  # surfaced below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    for i, ev in results.items():
        np.testing.assert_array_equal(ev.color_sum, expected[i % 2].color_sum)
        np.testing.assert_array_equal(ev.weight_sum, expected[i % 2].weight_sum)
