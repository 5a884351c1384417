"""Segmentation palettes: well separated like a labelling tool's, or deliberately confusable.

Colors are uint8 sRGB. White (255, 255, 255) is reserved for void and never handed out.
"""

from __future__ import annotations

import numpy as np

from monovoc_ros.core.evidence.color import srgb_to_lab
from monovoc_ros.synthetic.errors import SyntheticError

VOID_RGB = np.array([255, 255, 255], dtype=np.uint8)
_LEVELS = np.array([0, 51, 102, 153, 204, 255])  # a 6-level grid, the look of Replica's palette
_MAX_LIGHTNESS = 90.0  # near-white candidates are left out: blends toward void would reach them


def distinct_palette(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` uint8 colors, greedily farthest apart in CIELAB (Delta E 1976), never white; order randomised."""
    grid = np.stack(np.meshgrid(_LEVELS, _LEVELS, _LEVELS, indexing="ij"), -1).reshape(-1, 3)
    lab = srgb_to_lab(grid)
    grid, lab = grid[lab[:, 0] < _MAX_LIGHTNESS], lab[lab[:, 0] < _MAX_LIGHTNESS]
    if n > len(grid):
        raise SyntheticError(f"distinct_palette: at most {len(grid)} colors, asked for {n}")
    chosen = [int(rng.integers(len(grid)))]
    dist = np.linalg.norm(lab - lab[chosen[0]], axis=1)
    for _ in range(n - 1):
        k = int(np.argmax(dist))
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(lab - lab[k], axis=1))
    out = grid[chosen].astype(np.uint8)
    return out[rng.permutation(n)]


def make_confusable(palette: np.ndarray, n_pairs: int, delta: int, rng: np.random.Generator) -> tuple[np.ndarray, list]:
    """A copy of ``palette`` where ``n_pairs`` disjoint random pairs (i, j) get colors ``delta`` apart.

    Color j becomes color i moved by up to ``delta`` units per channel (max-norm exactly ``delta``), away
    from the 0/255 bounds, so the two stay distinct but are far closer than any pair of the original.
    Returns the new palette and the list of pairs.
    """
    palette = np.asarray(palette, dtype=np.uint8)
    n = len(palette)
    if not 1 <= delta <= 60:
        raise SyntheticError(f"confusable delta must be in 1..60 RGB units, got {delta}")
    if 2 * n_pairs > n:
        raise SyntheticError(f"cannot form {n_pairs} disjoint pairs from {n} colors")
    order = rng.permutation(n)
    pairs = [(int(order[2 * k]), int(order[2 * k + 1])) for k in range(n_pairs)]
    out = palette.astype(np.int64)
    for i, j in pairs:
        base = out[i]
        for _ in range(100):
            step = rng.integers(-delta, delta + 1, 3)
            step[rng.integers(3)] = delta * (1 if rng.random() < 0.5 else -1)
            step = np.where(base + step > 255, -np.abs(step), np.where(base + step < 0, np.abs(step), step))
            cand = base + step
            others = np.delete(out, j, axis=0)
            if not np.all(cand == 255) and not np.any(np.all(others == cand, axis=1)):
                out[j] = cand
                break
        else:  # pragma: no cover - 100 draws from ~(2 delta + 1)^3 candidates
            raise RuntimeError("could not place a confusable color")
    return out.astype(np.uint8), pairs
