"""sRGB to CIELAB, written out so that palettes built from it are the same on every machine.

The generated palettes (`datasets.instance_palette`, `synthetic.palette`) pick colors farthest-first in
CIELAB: a conversion that differs in the fourth digit (colour-science's, 0.02 Delta E away) reorders ties and
changes every mask colour of the bundled data, so this one is fixed here.
"""

from __future__ import annotations

import numpy as np

_SRGB_TO_XYZ = np.array(
    [[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750], [0.0193339, 0.1191920, 0.9503041]]
)
_D65_WHITE = np.array([0.95047, 1.0, 1.08883])


def srgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """CIELAB (D65) of sRGB colors given as uint8 or floats in [0, 255]; (..., 3) -> (..., 3) float64."""
    c = np.asarray(rgb, dtype=np.float64) / 255.0
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    xyz = lin @ _SRGB_TO_XYZ.T / _D65_WHITE
    f = np.where(xyz > (6 / 29) ** 3, np.cbrt(xyz), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], axis=-1)
