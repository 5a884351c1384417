"""Segmentation corruptions of the paper's appendix ("Further Experiments"), applied to clean label images.

Labels are object indices (int, -1 = void); ``lut`` maps ``label + 1`` to a color, ``lut[0]`` being white.
Every function is deterministic given its ``rng``.
- boundary noise: pixels within ``width`` of a label boundary take a neighbour's label with probability p;
- label noise: exactly ``round(fraction * H * W)`` pixels get a random wrong palette color (never void);
- mixed boundary: boundary pixels become a blend of their color and a neighbour's (off-palette colors,
  the anti-aliased edges some segmenters produce);
- region artifacts: small blobs of a wrong label or of void (holes) and thin one-pixel lines.
"""

from __future__ import annotations

import cv2
import numpy as np

from monovoc_ros.synthetic.errors import SyntheticError


def _codes(labels: np.ndarray) -> np.ndarray:
    codes = np.asarray(labels).astype(np.int64) + 1
    if codes.min() < 0 or codes.max() > np.iinfo(np.uint16).max:
        raise SyntheticError("labels must lie in -1 .. 65534")
    return codes.astype(np.uint16)


def boundary_pixels(labels: np.ndarray, width: int) -> np.ndarray:
    """True where another label (void included) lies within ``width`` pixels (Chebyshev distance)."""
    if width < 1:
        raise SyntheticError(f"boundary width must be >= 1, got {width}")
    codes = _codes(labels)
    kernel = np.ones((2 * width + 1, 2 * width + 1), np.uint8)
    return (cv2.dilate(codes, kernel) != codes) | (cv2.erode(codes, kernel) != codes)


def neighbour_labels(labels: np.ndarray, where: np.ndarray, width: int, rng: np.random.Generator) -> np.ndarray:
    """For each pixel in ``where`` (a boolean image), the label of a random different pixel within ``width``.

    Falls back to the window's largest or smallest label when random probes all hit the pixel's own label.
    """
    labels = np.asarray(labels)
    h, w = labels.shape
    ys, xs = np.nonzero(where)
    own = labels[ys, xs]
    out = own.copy()
    found = np.zeros(len(ys), bool)
    for _ in range(8):
        py = np.clip(ys + rng.integers(-width, width + 1, len(ys)), 0, h - 1)
        px = np.clip(xs + rng.integers(-width, width + 1, len(xs)), 0, w - 1)
        probe = labels[py, px]
        take = ~found & (probe != own)
        out[take] = probe[take]
        found |= take
    if not found.all():
        codes = _codes(labels)
        kernel = np.ones((2 * width + 1, 2 * width + 1), np.uint8)
        dil = cv2.dilate(codes, kernel)[ys, xs].astype(np.int64) - 1
        ero = cv2.erode(codes, kernel)[ys, xs].astype(np.int64) - 1
        out[~found] = np.where(dil != own, dil, ero)[~found]
    return out


def boundary_noise(labels: np.ndarray, width: int, prob: float, rng: np.random.Generator) -> np.ndarray:
    """Labels where each boundary pixel took a neighbour's label with probability ``prob``."""
    swap = boundary_pixels(labels, width)
    swap &= rng.random(swap.shape) < prob
    out = np.array(labels, copy=True)
    out[swap] = neighbour_labels(labels, swap, width, rng)
    return out


def label_noise(labels: np.ndarray, fraction: float, n_objects: int, rng: np.random.Generator) -> np.ndarray:
    """Labels where exactly ``round(fraction * size)`` random pixels got a wrong object label."""
    if not 0.0 <= fraction <= 1.0:
        raise SyntheticError(f"label noise fraction must be in [0, 1], got {fraction}")
    if n_objects < 2:
        raise SyntheticError("label noise needs at least two objects")
    out = np.array(labels, copy=True).ravel()
    pick = rng.choice(out.size, round(fraction * out.size), replace=False)
    own = out[pick]
    labelled = own >= 0
    r = rng.integers(0, n_objects - labelled.astype(np.int64))
    out[pick] = r + (labelled & (r >= own))
    return out.reshape(np.shape(labels))


def mixed_boundary(
    labels: np.ndarray, lut: np.ndarray, width: int, prob: float, rng: np.random.Generator
) -> np.ndarray:
    """RGB mask whose boundary pixels are blends (weights 0.25..0.75) of their color and a neighbour's."""
    mask = lut[np.asarray(labels) + 1].copy()
    where = boundary_pixels(labels, width)
    where &= rng.random(where.shape) < prob
    other = lut[neighbour_labels(labels, where, width, rng) + 1].astype(np.float64)
    alpha = rng.uniform(0.25, 0.75, (len(other), 1))
    mask[where] = np.round(alpha * mask[where] + (1 - alpha) * other).astype(np.uint8)
    return mask


def region_artifacts(labels: np.ndarray, count: int, n_objects: int, rng: np.random.Generator) -> np.ndarray:
    """Labels with ``count`` artifacts: filled ellipses (wrong label, or void = a hole) and 1-px lines."""
    codes = _codes(labels)
    h, w = codes.shape
    size = max(1.0, w / 616.0)  # artifacts scale with the image, sized for 616 px wide keyframes
    for _ in range(count):
        value = int(rng.integers(0, n_objects + 1))  # code 0 = void
        cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
        if rng.random() < 0.7:
            axes = (max(1, round(rng.uniform(3, 10) * size)), max(1, round(rng.uniform(3, 10) * size)))
            cv2.ellipse(codes, (cx, cy), axes, float(rng.uniform(0, 180)), 0, 360, value, thickness=-1)
        else:
            length, angle = rng.uniform(20, 80) * size, rng.uniform(0, np.pi)
            end = (int(cx + length * np.cos(angle)), int(cy + length * np.sin(angle)))
            cv2.line(codes, (cx, cy), end, value, thickness=1)
    return codes.astype(np.int64) - 1
