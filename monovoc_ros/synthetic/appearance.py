"""RGB appearance: a base color per primitive, a procedural texture, and Lambert + ambient shading.

The same function colors image pixels (at ray hits) and Gaussians (at their surface points), so a map
and its images agree the way a well-converged 3DGS map agrees with its training views. Shading is view
independent (one point light, no shadows), as a degree-0 SH color is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monovoc_ros.synthetic.errors import SyntheticError

PATTERNS = ("plain", "noise", "grain", "checker", "stripes")
LIGHT_POSITION = np.array([0.4, -0.3, 2.45])
AMBIENT, DIFFUSE = 0.45, 0.55


@dataclass(frozen=True)
class Material:
    base: tuple[float, float, float]  # RGB in [0, 1]
    pattern: str = "noise"
    scale: float = 0.25  # metres per pattern period
    amplitude: float = 0.08  # relative brightness modulation

    def __post_init__(self) -> None:
        if self.pattern not in PATTERNS:
            raise SyntheticError(f"Material.pattern must be one of {PATTERNS}, got {self.pattern!r}")


class Appearance:
    """Textures of a list of primitives; wave directions and phases are drawn once from ``rng``."""

    def __init__(self, materials: list[Material], rng: np.random.Generator) -> None:
        self.materials = list(materials)
        dirs = rng.normal(size=(len(materials), 3, 3))
        self._dirs = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
        self._phases = rng.uniform(0, 2 * np.pi, size=(len(materials), 3))

    def albedo(self, prim: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(N, 3) RGB in [0, 1] of primitive ``prim[i]`` at ``points[i]``."""
        prim = np.asarray(prim)
        points = np.asarray(points, dtype=np.float64)
        out = np.zeros((len(prim), 3))
        for k in np.unique(prim):
            sel = prim == k
            m = self.materials[int(k)]
            x = points[sel]
            out[sel] = np.clip(np.asarray(m.base) * (1 + m.amplitude * self._pattern(int(k), x))[:, None], 0, 1)
        return out

    def _pattern(self, k: int, x: np.ndarray) -> np.ndarray:
        m, dirs, ph = self.materials[k], self._dirs[k], self._phases[k]
        w = 2 * np.pi / m.scale
        if m.pattern == "plain":
            return np.zeros(len(x))
        if m.pattern == "noise":
            octaves = [np.sin(w * (1 + j) * x @ dirs[j] + ph[j]) for j in range(3)]
            return (octaves[0] + 0.6 * octaves[1] + 0.4 * octaves[2]) / 2.0
        if m.pattern == "grain":
            return np.sin(w * x @ dirs[0] + 1.5 * np.sin(0.3 * w * x @ dirs[1] + ph[1]) + ph[0])
        if m.pattern == "checker":
            cells = np.floor(x[:, 0] / m.scale) + np.floor(x[:, 1] / m.scale) + np.floor(x[:, 2] / m.scale)
            return np.where(cells % 2 == 0, 1.0, -1.0)
        return np.sign(np.sin(w * x @ dirs[0] + ph[0]))  # stripes

    def color(self, prim: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Shaded (N, 3) RGB in [0, 1]."""
        return np.clip(self.albedo(prim, points) * shading(points, normals)[:, None], 0.0, 1.0)


def shading(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    to_light = LIGHT_POSITION - np.asarray(points, dtype=np.float64)
    to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
    return AMBIENT + DIFFUSE * np.clip(np.sum(np.asarray(normals) * to_light, axis=1), 0.0, None)
