"""The rasterizer on a real map: Replica office_0 (shared data, read in place; skipped when absent)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from monovoc_ros.core.map.camera import Intrinsics
from monovoc_ros.core.map.ply import load_ply
from monovoc_ros.core.raster import accumulate, render


@pytest.fixture(scope="module")
def office(replica_office0):
    gmap = load_ply(replica_office0 / "gaussians.ply")
    k = json.loads((replica_office0 / "intrinsics.json").read_text())
    intrinsics = Intrinsics(k["fx"], k["fy"], k["cx"], k["cy"], k["width"], k["height"])
    poses = np.loadtxt(replica_office0 / "traj.txt").reshape(-1, 4, 4)
    return gmap, intrinsics, poses, replica_office0


def load_rgb(root, i: int, mode: str = "RGB") -> np.ndarray:
    folder, ext = ("rgb", "jpg") if mode == "RGB" else ("masks", "png")
    return np.asarray(Image.open(root / folder / f"{i:06d}.{ext}").convert("RGB"))


def test_rendering_matches_the_photo_and_covers_the_view(office):
    gmap, k, poses, root = office
    out = render(gmap, gmap.colors, k, poses[0])
    photo = load_rgb(root, 0).astype(np.float32) / 255.0
    psnr = -10.0 * np.log10(np.mean((out.image - photo) ** 2))
    assert psnr > 25.0  # ~29 dB: poses, intrinsics and pixel-centre conventions all line up
    assert np.mean(out.transmittance < 0.05) > 0.95  # the map is fused from depth: the view is covered
    assert 0.5 < np.median(out.depth[out.transmittance < 0.05]) < 6.0


def test_numba_and_torch_agree_on_the_real_map(office):
    gmap, k, poses, root = office
    # A 192x128 window keeps the CPU torch path quick; the whole map is still projected and culled.
    x0, y0, w, h = 300, 150, 192, 128
    crop = Intrinsics(k.fx, k.fy, k.cx - x0, k.cy - y0, w, h)
    mask = np.ascontiguousarray(load_rgb(root, 0, "mask")[y0 : y0 + h, x0 : x0 + w])
    valid = np.any(mask != 255, axis=2)
    a = accumulate(gmap, mask, crop, poses[0], valid=valid, impl="numba")
    b = accumulate(gmap, mask, crop, poses[0], valid=valid, impl="torch")
    assert a.n_visible == b.n_visible > 5000
    np.testing.assert_allclose(a.weight_sum.sum(), b.weight_sum.sum(), rtol=1e-5)
    np.testing.assert_allclose(a.color_sum.sum(axis=0), b.color_sum.sum(axis=0), rtol=1e-5)
    # Per Gaussian, only a tiny fraction may differ (equal float32 depths may blend in either order).
    scale = a.weight_sum.max()
    differs = np.abs(a.weight_sum - b.weight_sum) > 1e-4 * scale
    differs |= np.abs(a.color_sum - b.color_sum).max(axis=1) > 1e-4 * scale
    assert differs.mean() < 1e-3


def test_deblended_colors_reproduce_the_mask(office):
    """SCD on one real keyframe: rendering the recovered per-Gaussian colors gives back its mask."""
    gmap, k, poses, root = office
    mask = load_rgb(root, 0, "mask")
    valid = np.any(mask != 255, axis=2)
    ev = accumulate(gmap, mask, k, poses[0], valid=valid)
    seen = ev.weight_sum > 1e-3
    assert seen.sum() > 0.9 * ev.n_visible
    s_hat = np.zeros((len(gmap), 3))
    s_hat[seen] = ev.color_sum[seen] / ev.weight_sum[seen, None]
    err = np.abs(render(gmap, s_hat, k, poses[0]).image - mask / 255.0).max(axis=2)
    assert np.mean(err[valid] < 0.1) > 0.9  # ~92%: the rest is overlap bias at object boundaries
