"""Palette quantization (METHOD section 4): snap each deblended color to its nearest palette color.

``s_q_i = argmin_{c in P} d(s_hat_i, c)`` for one of `METRICS`:

* ``"cmc"`` (default, best in the paper): CMC l:c = 2:1 in CIELAB.
* ``"ciede2000"``, ``"cie94"`` (graphic-arts weights): in CIELAB.
* ``"cam16ucs"``: Euclidean in CAM16-UCS J'a'b' (colour's default viewing conditions: D65, L_A = 64/pi/5
  cd/m^2, Y_b = 20, average surround).
* ``"din99o"``: Euclidean in DIN99o (DIN 6176). colour-science has DIN99 and DIN99b-d only; DIN99o is
  DIN99b with its chroma scale 23.0 written as 1/0.0435, so it is computed here (`lab_to_din99o`).
* ``"rgb"``: Euclidean in sRGB, in 8-bit units (0-255).

sRGB colors (in [0, 1], sRGB transfer function) go to CIE XYZ under D65 and then to CIELAB (D65) as
colour-science converts them (`core.evidence.color.srgb01_to_lab`, without importing colour: CAM16-UCS
does). CMC and CIE94 are asymmetric: they weight the difference by the *reference* (first) color's lightness,
chroma and hue. As written in METHOD.md and the paper, the deblended color is the reference,
``d_CMC(Lab(s_hat), Lab(c))``, so each sample is judged with tolerances of its own region of color space.
(CIEDE2000 and the Euclidean metrics are symmetric.)

Distances come from numba kernels (`core.evidence.quantize_kernels`): the samples and the palette are each
converted once, then each sample walks the K palette colors; colour's `colour.delta_E` (plain NumPy for
the Euclidean spaces) is kept as the reference twin (`distance_matrix_reference`, `quantize_reference`).

Confidence (`confidence`) is the relative margin between the nearest and the second-nearest palette
color, ``(d2 - d1) / (d2 + d1)``: 1 when the color sits on a palette color (or the palette has a single
color), 0 when it is equally far from two. It is scale-free, so it means the same for every metric.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monovoc_ros.core.evidence.color import srgb01_to_lab

METRICS = ("cmc", "ciede2000", "cie94", "cam16ucs", "din99o", "rgb")

# Deblended colors are weighted means of values in [0, 1]; allow float rounding beyond that, no more.
_RANGE_SLACK = 1e-6
# CMC lightness and chroma weights (l:c = 2:1, the acceptability setting used by the paper).
_CMC_L, _CMC_C = 2.0, 1.0


@dataclass
class Quantization:
    index: np.ndarray  # (N,) int32 index into the palette; -1 where the input color is NaN (or K == 0)
    distance: np.ndarray  # (N,) float32 distance to the nearest palette color (NaN where index is -1)
    second: np.ndarray  # (N,) float32 distance to the second nearest (inf if K == 1, NaN where index is -1)


def lab_to_din99o(lab: np.ndarray) -> np.ndarray:
    """CIELAB -> DIN99o (DIN 6176, k_E = k_CH = 1)."""
    lab = np.asarray(lab, dtype=np.float64)
    L, a, b = lab[..., 0], lab[..., 1], lab[..., 2]
    cos26, sin26 = np.cos(np.radians(26.0)), np.sin(np.radians(26.0))
    e = cos26 * a + sin26 * b
    f = 0.83 * (-sin26 * a + cos26 * b)
    G = np.hypot(e, f)
    C = np.log1p(0.075 * G) / 0.0435
    h = np.arctan2(f, e) + np.radians(26.0)
    return np.stack([303.67 * np.log1p(0.0039 * L), C * np.cos(h), C * np.sin(h)], axis=-1)


def to_metric_space(rgb: np.ndarray, metric: str, *, with_colour: bool = False) -> np.ndarray:
    """(M, 3) sRGB in [0, 1] -> (M, 3) float64 coordinates of the metric's color space. `with_colour`: CIELAB by
    colour-science itself (the reference twins) instead of its formulas written out (`srgb01_to_lab`)."""
    _check_metric(metric)
    rgb = np.asarray(rgb, dtype=np.float64).reshape(-1, 3)
    if metric == "rgb":
        return rgb * 255.0
    if rgb.shape[0] == 0:
        return np.zeros((0, 3))
    if metric == "cam16ucs" or with_colour:
        import colour  # deferred: slow to import (colour pulls in its plotting stack)

        xyz = colour.sRGB_to_XYZ(rgb)
        if metric == "cam16ucs":
            return np.asarray(colour.XYZ_to_CAM16UCS(xyz), dtype=np.float64).reshape(-1, 3)
        lab = np.asarray(colour.XYZ_to_Lab(xyz), dtype=np.float64).reshape(-1, 3)
    else:
        lab = srgb01_to_lab(rgb)
    return lab_to_din99o(lab) if metric == "din99o" else lab


def _check_metric(metric: str) -> None:
    if metric not in METRICS:
        raise ValueError(f"metric must be one of {METRICS}, got {metric!r}")


def _check_inputs(colors: np.ndarray, palette_rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated (colors clipped to [0, 1], observed rows, palette as float in [0, 1])."""
    colors = np.asarray(colors)
    if colors.ndim != 2 or colors.shape[1] != 3 or colors.dtype.kind != "f":
        raise ValueError(f"colors: expected (N, 3) float sRGB in [0, 1], got shape {colors.shape} {colors.dtype}")
    palette_rgb = np.asarray(palette_rgb)
    if palette_rgb.ndim != 2 or palette_rgb.shape[1] != 3 or palette_rgb.dtype != np.uint8:
        raise ValueError(f"palette_rgb: expected (K, 3) uint8, got shape {palette_rgb.shape} {palette_rgb.dtype}")
    if np.unique(palette_rgb, axis=0).shape[0] != palette_rgb.shape[0]:
        raise ValueError("palette_rgb has duplicate colors (each palette color is one object)")
    nan = np.isnan(colors)
    observed = ~nan.any(axis=1)
    if np.any(nan.any(axis=1) & ~nan.all(axis=1)):
        raise ValueError("colors: rows must be all NaN (unobserved) or all finite")
    values = colors[observed]
    if not np.isfinite(values).all():
        raise ValueError("colors: contains infinite values")
    if values.size and (values.min() < -_RANGE_SLACK or values.max() > 1 + _RANGE_SLACK):
        raise ValueError(f"colors: values must be in [0, 1], got [{values.min()}, {values.max()}]")
    return np.clip(values.astype(np.float64), 0.0, 1.0), observed, palette_rgb.astype(np.float64) / 255.0


def _empty(n: int) -> Quantization:
    return Quantization(np.full(n, -1, np.int32), np.full(n, np.nan, np.float32), np.full(n, np.nan, np.float32))


def quantize(colors: np.ndarray, palette_rgb: np.ndarray, metric: str = "cmc") -> Quantization:
    """Nearest palette color of each deblended sRGB color (NaN rows = unobserved -> index -1).

    An empty palette gives index -1 and infinite distances for every observed color.
    """
    from monovoc_ros.core.evidence import quantize_kernels as kernels  # deferred: numba compiles/loads on first use

    _check_metric(metric)
    values, observed, palette = _check_inputs(colors, palette_rgb)
    out = _empty(len(observed))
    if palette.shape[0] == 0:
        out.distance[observed] = np.inf
        out.second[observed] = np.inf
        return out
    x = np.ascontiguousarray(to_metric_space(values, metric))
    p = np.ascontiguousarray(to_metric_space(palette, metric))
    if metric == "cmc":
        index, dist, second = kernels.nearest_cmc(x, p, _CMC_L, _CMC_C)
    elif metric == "cie94":
        index, dist, second = kernels.nearest_cie94(x, p)
    elif metric == "ciede2000":
        index, dist, second = kernels.nearest_ciede2000(x, p)
    else:
        index, dist, second = kernels.nearest_euclidean(x, p)
    out.index[observed], out.distance[observed], out.second[observed] = index, dist, second
    return out


def distance_matrix_reference(colors: np.ndarray, palette_rgb: np.ndarray, metric: str = "cmc") -> np.ndarray:
    """(N, K) float64 distances with colour-science's `colour.delta_E` (plain NumPy for Euclidean
    spaces): the reference twin of the kernels. NaN rows stay NaN. Memory is N x K: for tests."""
    import colour  # deferred: slow to import (colour pulls in its plotting stack)

    _check_metric(metric)
    values, observed, palette = _check_inputs(colors, palette_rgb)
    out = np.full((len(observed), palette.shape[0]), np.nan)
    x, p = to_metric_space(values, metric, with_colour=True), to_metric_space(palette, metric, with_colour=True)
    method = {"cmc": "CMC", "cie94": "CIE 1994", "ciede2000": "CIE 2000", "cam16ucs": "CAM16-UCS"}.get(metric)
    rows = np.empty((x.shape[0], p.shape[0]))
    for j in range(p.shape[0]):
        if method == "CMC":
            rows[:, j] = colour.delta_E(x, p[j], method=method, l=_CMC_L, c=_CMC_C)
        elif method is not None:
            rows[:, j] = colour.delta_E(x, p[j], method=method)
        else:
            rows[:, j] = np.linalg.norm(x - p[j], axis=1)
    out[observed] = rows
    return out


def quantize_reference(colors: np.ndarray, palette_rgb: np.ndarray, metric: str = "cmc") -> Quantization:
    """`quantize` computed from `distance_matrix_reference` with np.argmin / np.partition."""
    dist = distance_matrix_reference(colors, palette_rgb, metric)
    n, k = dist.shape
    out = _empty(n)
    observed = ~np.isnan(dist).any(axis=1) if k else ~np.isnan(np.asarray(colors)).any(axis=1)
    if k == 0:
        out.distance[observed] = out.second[observed] = np.inf
        return out
    d = dist[observed]
    out.index[observed] = np.argmin(d, axis=1)
    out.distance[observed] = d.min(axis=1)
    out.second[observed] = np.partition(d, 1, axis=1)[:, 1] if k > 1 else np.inf
    return out


def confidence(q: Quantization) -> np.ndarray:
    """(N,) float32 in [0, 1]: (second - distance) / (second + distance); 1 with a single palette
    color, 0 where unobserved (index -1)."""
    d = q.distance.astype(np.float64)
    s = q.second.astype(np.float64)
    out = np.zeros(len(q.index), np.float32)
    known = q.index >= 0
    single = known & np.isinf(s)
    both = known & ~single
    total = s[both] + d[both]
    out[both] = np.where(total > 0, (s[both] - d[both]) / np.where(total > 0, total, 1.0), 0.0)
    out[single] = 1.0
    return np.clip(out, 0.0, 1.0)
