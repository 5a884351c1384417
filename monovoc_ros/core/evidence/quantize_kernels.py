"""Numba kernels for palette quantization: nearest and second-nearest palette color per sample.

Each kernel takes samples (M, 3) and palette colors (K, 3) already converted to the metric's space
(float64), runs the samples in parallel and walks the K palette colors per sample, so no M x K
array is ever formed. Candidates are compared on the squared distance (the radicand of each formula,
monotone in the distance); only the two winners take a square root. Ties go to the lower palette
index, as with `np.argmin`. The formulas follow colour-science 0.4.7 term by term (`colour.delta_E`,
which `quantize.distance_matrix_reference` uses as the twin the tests hold these against).
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, inline="always")
def _finish(best_k: int, best: float, second: float) -> tuple[int, float, float]:
    return best_k, math.sqrt(max(best, 0.0)), math.sqrt(max(second, 0.0))


@numba.njit(cache=True, nogil=True, parallel=True)
def nearest_euclidean(x: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Euclidean distance (RGB, CAM16-UCS with K_L = 1, DIN99o)."""
    m, k = x.shape[0], p.shape[0]
    index = np.empty(m, np.int32)
    dist = np.empty(m, np.float32)
    second = np.empty(m, np.float32)
    for i in numba.prange(m):
        x0, x1, x2 = x[i, 0], x[i, 1], x[i, 2]
        b, s, bk = np.inf, np.inf, -1
        for j in range(k):
            d0, d1, d2 = x0 - p[j, 0], x1 - p[j, 1], x2 - p[j, 2]
            d = d0 * d0 + d1 * d1 + d2 * d2
            if d < b:
                s, b, bk = b, d, j
            elif d < s:
                s = d
        bk, b, s = _finish(bk, b, s)
        index[i], dist[i], second[i] = bk, b, s
    return index, dist, second


@numba.njit(cache=True, nogil=True, parallel=True)
def nearest_cmc(
    lab: np.ndarray, plab: np.ndarray, l: float = 2.0, c: float = 1.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CMC l:c with the sample as the reference (first) color: its weights S_L, S_C, S_H are the
    sample's, so they are computed once per sample and the palette loop is a few multiply-adds."""
    m, k = lab.shape[0], plab.shape[0]
    pc = np.empty(k)
    for j in range(k):
        pc[j] = math.hypot(plab[j, 1], plab[j, 2])
    index = np.empty(m, np.int32)
    dist = np.empty(m, np.float32)
    second = np.empty(m, np.float32)
    for i in numba.prange(m):
        L1, a1, b1 = lab[i, 0], lab[i, 1], lab[i, 2]
        C1 = math.hypot(a1, b1)
        sL = 0.511 if L1 < 16 else (0.040975 * L1) / (1 + 0.01765 * L1)
        sC = 0.0638 * C1 / (1 + 0.0131 * C1) + 0.638
        h1 = math.degrees(math.atan2(b1, a1)) % 360
        if h1 >= 164 and h1 <= 345:
            t = 0.56 + abs(0.2 * math.cos(math.radians(h1 + 168)))
        else:
            t = 0.36 + abs(0.4 * math.cos(math.radians(h1 + 35)))
        C4 = C1 * C1 * C1 * C1
        f = math.sqrt(C4 / (C4 + 1900))
        sh = sC * (f * t + 1 - f)
        wL = 1.0 / (l * sL) ** 2
        wC = 1.0 / (c * sC) ** 2
        wH = 1.0 / (sh * sh)
        b, s, bk = np.inf, np.inf, -1
        for j in range(k):
            dL = L1 - plab[j, 0]
            dC = C1 - pc[j]
            dA = a1 - plab[j, 1]
            dB = b1 - plab[j, 2]
            dH2 = dA * dA + dB * dB - dC * dC
            d = dL * dL * wL + dC * dC * wC + dH2 * wH
            if d < b:
                s, b, bk = b, d, j
            elif d < s:
                s = d
        bk, b, s = _finish(bk, b, s)
        index[i], dist[i], second[i] = bk, b, s
    return index, dist, second


@numba.njit(cache=True, nogil=True, parallel=True)
def nearest_cie94(lab: np.ndarray, plab: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CIE 1994 (graphic arts: k_L = 1, K_1 = 0.045, K_2 = 0.015), sample as the reference color."""
    m, k = lab.shape[0], plab.shape[0]
    pc = np.empty(k)
    for j in range(k):
        pc[j] = math.hypot(plab[j, 1], plab[j, 2])
    index = np.empty(m, np.int32)
    dist = np.empty(m, np.float32)
    second = np.empty(m, np.float32)
    for i in numba.prange(m):
        L1, a1, b1 = lab[i, 0], lab[i, 1], lab[i, 2]
        C1 = math.hypot(a1, b1)
        sC = 1 + 0.045 * C1
        sH = 1 + 0.015 * C1
        wC = 1.0 / (sC * sC)
        wH = 1.0 / (sH * sH)
        b, s, bk = np.inf, np.inf, -1
        for j in range(k):
            dL = L1 - plab[j, 0]
            dC = C1 - pc[j]
            dA = a1 - plab[j, 1]
            dB = b1 - plab[j, 2]
            radical = dA * dA + dB * dB - dC * dC
            d = dL * dL + dC * dC * wC + max(radical, 0.0) * wH
            if d < b:
                s, b, bk = b, d, j
            elif d < s:
                s = d
        bk, b, s = _finish(bk, b, s)
        index[i], dist[i], second[i] = bk, b, s
    return index, dist, second


@numba.njit(cache=True, nogil=True, inline="always")
def _hue_deg(b: float, a: float) -> float:
    if b == 0 and a == 0:
        return 0.0
    return math.degrees(math.atan2(b, a)) % 360


_COS30, _SIN30 = math.cos(math.radians(30.0)), math.sin(math.radians(30.0))
_COS6, _SIN6 = math.cos(math.radians(6.0)), math.sin(math.radians(6.0))
_COS63, _SIN63 = math.cos(math.radians(63.0)), math.sin(math.radians(63.0))
_POW25_7 = 25.0**7


@numba.njit(cache=True, nogil=True, inline="always")
def _ciede2000_sl(L1: float, L2: float) -> float:
    Lbar2 = ((L1 + L2) / 2 - 50) ** 2
    return 1 + (0.015 * Lbar2) / math.sqrt(20 + Lbar2)


@numba.njit(cache=True, nogil=True)
def ciede2000_squared(L1: float, a1: float, b1: float, L2: float, a2: float, b2: float) -> float:
    """The radicand of CIEDE2000 (k_L = k_C = k_H = 1), as colour's intermediate_attributes_CIE2000.

    The four cosines of the hue term T come from one cos/sin of the mean hue by multiple-angle
    identities (equal to colour's to rounding), which halves the cost per pair.
    """
    C1ab = math.hypot(a1, b1)
    C2ab = math.hypot(a2, b2)
    Cbar = (C1ab + C2ab) / 2
    Cbar2 = Cbar * Cbar
    Cbar7 = Cbar2 * Cbar2 * Cbar2 * Cbar
    G = 0.5 * (1 - math.sqrt(Cbar7 / (Cbar7 + _POW25_7)))
    ap1 = (1 + G) * a1
    ap2 = (1 + G) * a2
    Cp1 = math.hypot(ap1, b1)
    Cp2 = math.hypot(ap2, b2)
    hp1 = _hue_deg(b1, ap1)
    hp2 = _hue_deg(b2, ap2)
    dLp = L2 - L1
    dCp = Cp2 - Cp1
    dh = hp2 - hp1
    CC = Cp1 * Cp2
    if CC == 0:
        dhp = 0.0
    elif abs(dh) <= 180:
        dhp = dh
    elif dh > 180:
        dhp = dh - 360
    else:
        dhp = dh + 360
    dHp = 2 * math.sqrt(CC) * math.sin(math.radians(dhp / 2))
    Cbarp = (Cp1 + Cp2) / 2
    hsum = hp1 + hp2
    if CC == 0:
        hbar = hsum
    elif abs(hp1 - hp2) <= 180:
        hbar = hsum / 2
    elif hsum < 360:
        hbar = (hsum + 360) / 2
    else:
        hbar = (hsum - 360) / 2
    hr = math.radians(hbar)
    c1, s1 = math.cos(hr), math.sin(hr)
    c2, s2 = 2 * c1 * c1 - 1, 2 * s1 * c1
    c3, s3 = c1 * (4 * c1 * c1 - 3), s1 * (3 - 4 * s1 * s1)
    c4, s4 = 2 * c2 * c2 - 1, 2 * s2 * c2
    T = (
        1
        - 0.17 * (c1 * _COS30 + s1 * _SIN30)
        + 0.24 * c2
        + 0.32 * (c3 * _COS6 - s3 * _SIN6)
        - 0.20 * (c4 * _COS63 + s4 * _SIN63)
    )
    dtheta = 30 * math.exp(-(((hbar - 275) / 25) ** 2))
    Cbarp2 = Cbarp * Cbarp
    Cbarp7 = Cbarp2 * Cbarp2 * Cbarp2 * Cbarp
    RC = 2 * math.sqrt(Cbarp7 / (Cbarp7 + _POW25_7))
    SL = _ciede2000_sl(L1, L2)
    SC = 1 + 0.045 * Cbarp
    SH = 1 + 0.015 * Cbarp * T
    RT = -math.sin(math.radians(2 * dtheta)) * RC
    vL = dLp / SL
    vC = dCp / SC
    vH = dHp / SH
    return vL * vL + vC * vC + vH * vH + RT * vC * vH


@numba.njit(cache=True, nogil=True, parallel=True)
def nearest_ciede2000(lab: np.ndarray, plab: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CIEDE2000 (symmetric, every term depends on both colors: the full formula per pair).

    Exact search with pruning: the two palette colors nearest in plain Lab distance are scored first,
    which makes the second-best bound tight early; then any color whose lightness term alone,
    (dL / S_L)^2, reaches the second best is skipped (the chroma-hue part is >= 0 as |R_T| <= 2).
    """
    m, k = lab.shape[0], plab.shape[0]
    index = np.empty(m, np.int32)
    dist = np.empty(m, np.float32)
    second = np.empty(m, np.float32)
    for i in numba.prange(m):
        L1, a1, b1 = lab[i, 0], lab[i, 1], lab[i, 2]
        e0, e1, j0, j1 = np.inf, np.inf, -1, -1
        for j in range(k):
            d0, d1, d2 = L1 - plab[j, 0], a1 - plab[j, 1], b1 - plab[j, 2]
            e = d0 * d0 + d1 * d1 + d2 * d2
            if e < e0:
                e1, j1, e0, j0 = e0, j0, e, j
            elif e < e1:
                e1, j1 = e, j
        b, s, bk = np.inf, np.inf, -1
        for n in range(k + 2):
            if n < 2:
                j = j0 if n == 0 else j1
                if j < 0:
                    continue
            else:
                j = n - 2
                if j == j0 or j == j1:
                    continue
                dL = plab[j, 0] - L1
                sl = _ciede2000_sl(L1, plab[j, 0])
                if (dL / sl) ** 2 >= s:
                    continue
            d = ciede2000_squared(L1, a1, b1, plab[j, 0], plab[j, 1], plab[j, 2])
            if d < b or (d == b and j < bk):  # visiting out of order: ties still go to the lower index
                s, b, bk = b, d, j
            elif d < s:
                s = d
        bk, b, s = _finish(bk, b, s)
        index[i], dist[i], second[i] = bk, b, s
    return index, dist, second
