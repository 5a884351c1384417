"""Palette quantization: kernels held against colour-science, published values, edge cases, confidence."""

from __future__ import annotations

import subprocess
import sys

import colour
import numpy as np
import pytest

from monovoc_ros.core.evidence import quantize_kernels as kernels
from monovoc_ros.core.evidence.color import srgb01_to_lab
from monovoc_ros.core.evidence.quantize import (
    METRICS,
    Quantization,
    confidence,
    distance_matrix_reference,
    lab_to_din99o,
    quantize,
    quantize_reference,
    to_metric_space,
)


def random_palette(k: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.unique(rng.integers(0, 256, (3 * k, 3), dtype=np.uint8), axis=0)[rng.permutation(k)]


def deblended(palette: np.ndarray, n: int, seed: int = 1) -> np.ndarray:
    """Blends of two palette colors, noise, some exact palette colors, extreme colors and NaN rows."""
    rng = np.random.default_rng(seed)
    a, b = rng.integers(0, len(palette), n), rng.integers(0, len(palette), n)
    w = rng.beta(0.5, 3.0, n)[:, None]
    colors = np.clip((1 - w) * palette[a] / 255 + w * palette[b] / 255 + rng.normal(0, 0.02, (n, 3)), 0, 1)
    colors[:20] = palette[:20] / 255.0
    colors[20:28] = np.array(
        [[0, 0, 0], [1, 1, 1], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0.5, 0.5, 0.5], [0, 1, 1]]
    )
    unobserved = rng.random(n) < 0.05
    unobserved[:28] = False
    colors[unobserved] = np.nan
    return colors


@pytest.mark.parametrize("metric", METRICS)
def test_kernel_matches_colour_science(metric):
    palette = random_palette(60)
    colors = deblended(palette, 3000)
    q = quantize(colors, palette, metric)
    ref = quantize_reference(colors, palette, metric)
    observed = ~np.isnan(colors[:, 0])
    np.testing.assert_array_equal(q.index, ref.index)
    assert (q.index[~observed] == -1).all() and (q.index[observed] >= 0).all()
    np.testing.assert_allclose(q.distance[observed], ref.distance[observed], rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(q.second[observed], ref.second[observed], rtol=1e-6, atol=1e-4)
    assert np.isnan(q.distance[~observed]).all()
    # Exact palette colors snap to themselves at distance zero.
    np.testing.assert_array_equal(q.index[:20], np.arange(20))
    np.testing.assert_allclose(q.distance[:20], 0, atol=1e-6)
    assert q.index.dtype == np.int32 and q.distance.dtype == np.float32 and q.second.dtype == np.float32


def test_published_ciede2000_values():
    # Sharma, Wu & Dalal (2005) test pairs 1, 7, 17, 25.
    pairs = [
        ((50.0, 2.6772, -79.7751), (50.0, 0.0, -82.7485), 2.0425),
        ((50.0, 0.0, 0.0), (50.0, -1.0, 2.0), 2.3669),
        ((50.0, 2.5, 0.0), (73.0, 25.0, -18.0), 27.1492),
        ((60.2574, -34.0099, 36.2677), (60.4626, -34.1751, 39.4387), 1.2644),
    ]
    for a, b, expected in pairs:
        assert np.sqrt(kernels.ciede2000_squared(*a, *b)) == pytest.approx(expected, abs=5e-5)
        assert np.sqrt(kernels.ciede2000_squared(*b, *a)) == pytest.approx(expected, abs=5e-5)


def test_kernels_on_extreme_lab_values():
    # colour-science's own docstring examples, beyond the sRGB gamut.
    lab1 = np.array([[100.0, 21.57210357, 272.2281935]])
    lab2 = np.array([[100.0, 426.67945353, 72.39590835]])
    assert kernels.nearest_cmc(lab1, lab2, 2.0, 1.0)[1][0] == pytest.approx(172.704771287, rel=1e-6)
    for fn, method in ((kernels.nearest_cie94, "CIE 1994"), (kernels.nearest_ciede2000, "CIE 2000")):
        assert fn(lab1, lab2)[1][0] == pytest.approx(colour.delta_E(lab1[0], lab2[0], method=method), rel=1e-6)


def test_cmc_uses_the_deblended_color_as_reference():
    # A dark, desaturated sample vs a saturated palette color: swapping the arguments changes CMC.
    sample, target = np.array([[0.30, 0.25, 0.22]]), np.array([[200, 30, 40]], np.uint8)
    lab_s, lab_c = to_metric_space(sample, "cmc")[0], to_metric_space(target / 255.0, "cmc")[0]
    forward = colour.delta_E(lab_s, lab_c, method="CMC", l=2, c=1)
    backward = colour.delta_E(lab_c, lab_s, method="CMC", l=2, c=1)
    assert abs(forward - backward) > 1.0
    assert quantize(sample, target, "cmc").distance[0] == pytest.approx(forward, rel=1e-6)


def test_din99o_is_din99b_with_the_exact_chroma_scale():
    lab = to_metric_space(np.random.default_rng(2).random((500, 3)), "cmc")
    ours = lab_to_din99o(lab)
    din99b = colour.Lab_to_DIN99(lab, method="DIN99b")
    np.testing.assert_allclose(ours[:, 0], din99b[:, 0], rtol=1e-12)
    np.testing.assert_allclose(ours[:, 1:], din99b[:, 1:] / (23.0 * 0.0435), rtol=1e-12, atol=1e-12)


def test_conversions_are_srgb_d65():
    lab = to_metric_space(np.array([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]]), "cmc")
    np.testing.assert_allclose(lab, [[100, 0, 0], [0, 0, 0]], atol=0.01)
    np.testing.assert_allclose(to_metric_space(np.array([[1.0, 0.5, 0.0]]), "rgb"), [[255, 127.5, 0]])
    np.testing.assert_allclose(to_metric_space(np.array([[1.0, 1.0, 1.0]]), "cam16ucs")[0, 0], 100, atol=0.01)


def test_srgb01_to_lab_is_colour_sciences_conversion():
    """The CIELAB of quantization, written out, equals colour's XYZ_to_Lab(sRGB_to_XYZ(.)) to float rounding: on
    random colors, both sides of the sRGB decoding's and the CIE 1976 function's thresholds, black and white."""
    rng = np.random.default_rng(3)
    edges = np.array([0.0, 1.0, 0.04045, 0.04044994, 0.0404499 + 1e-9, 0.0404499 - 1e-9, 1e-4, 2e-3, 0.5])
    rgb = np.concatenate([rng.random((5000, 3)), rng.random((500, 3)) * 0.02, np.stack([edges] * 3, axis=1),
                          rng.choice(edges, (300, 3))])  # fmt: skip
    ours = srgb01_to_lab(rgb)
    theirs = colour.XYZ_to_Lab(colour.sRGB_to_XYZ(rgb))
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-10)
    np.testing.assert_array_equal(srgb01_to_lab(rgb[:5000].reshape(10, 500, 3)), ours[:5000].reshape(10, 500, 3))


def test_quantizing_does_not_import_colour():
    """The live node's path (quantize in CIELAB) runs without colour-science, whose import pulls in matplotlib."""
    code = (
        "import sys, numpy as np\n"
        "from monovoc_ros.core.evidence.quantize import quantize\n"
        "q = quantize(np.array([[0.2, 0.4, 0.6]]), np.array([[50, 100, 150], [200, 0, 0]], np.uint8), 'cmc')\n"
        "assert q.index.tolist() == [0], q.index\n"
        "print(sorted(m for m in ('colour', 'matplotlib') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_single_empty_palette_and_ties():
    colors = np.array([[0.2, 0.3, 0.4], [np.nan, np.nan, np.nan]])
    one = quantize(colors, np.array([[10, 20, 30]], np.uint8))
    assert one.index.tolist() == [0, -1] and np.isinf(one.second[0])
    assert confidence(one).tolist() == [1.0, 0.0]
    none = quantize(colors, np.zeros((0, 3), np.uint8))
    assert none.index.tolist() == [-1, -1] and np.isinf(none.distance[0]) and np.isnan(none.distance[1])
    assert confidence(none).tolist() == [0.0, 0.0]
    # Exactly halfway between two palette colors: the lower index wins, confidence is zero.
    pal = np.array([[0, 0, 0], [2, 0, 0]], np.uint8)
    mid = quantize(np.array([[1 / 255, 0.0, 0.0]]), pal, "rgb")
    assert mid.index[0] == 0 and mid.distance[0] == mid.second[0] and confidence(mid)[0] == 0.0
    assert quantize(np.array([[1 / 255, 0.0, 0.0]]), pal[::-1].copy(), "rgb").index[0] == 0
    assert len(quantize(np.zeros((0, 3)), pal).index) == 0


def test_confidence_is_a_relative_margin():
    q = Quantization(
        np.array([0, 1, 2, -1], np.int32),
        np.array([0.0, 1.0, 3.0, np.nan], np.float32),
        np.array([5.0, 3.0, 3.0, np.nan], np.float32),
    )
    np.testing.assert_allclose(confidence(q), [1.0, 0.5, 0.0, 0.0])
    palette = random_palette(30)
    conf = confidence(quantize(deblended(palette, 2000), palette))
    assert conf.dtype == np.float32 and conf.min() >= 0 and conf.max() <= 1
    assert conf[:20].min() == 1.0


def test_bad_input():
    pal = random_palette(5)
    with pytest.raises(ValueError, match="metric"):
        quantize(np.zeros((2, 3)), pal, "lab")
    with pytest.raises(ValueError, match="colors"):
        quantize(np.zeros((2, 4)), pal)
    with pytest.raises(ValueError, match="colors"):
        quantize(np.zeros((2, 3), np.uint8), pal)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        quantize(np.array([[0.5, 1.2, 0.0]]), pal)
    with pytest.raises(ValueError, match="all NaN"):
        quantize(np.array([[0.5, np.nan, 0.0]]), pal)
    with pytest.raises(ValueError, match="infinite"):
        quantize(np.array([[0.5, np.inf, 0.0]]), pal)
    with pytest.raises(ValueError, match="palette_rgb"):
        quantize(np.zeros((2, 3)), pal.astype(np.float64))
    with pytest.raises(ValueError, match="duplicate"):
        quantize(np.zeros((2, 3)), np.concatenate([pal, pal[:1]]))
    # Float rounding just outside [0, 1] is accepted and clipped.
    assert quantize(np.array([[1 + 1e-9, -1e-9, 0.5]]), pal).index[0] >= 0


def test_distance_matrix_reference_shape():
    pal = random_palette(27)
    colors = deblended(pal, 50)
    d = distance_matrix_reference(colors, pal, "cmc")
    assert d.shape == (50, 27)
    np.testing.assert_array_equal(np.isnan(d).any(axis=1), np.isnan(colors[:, 0]))
