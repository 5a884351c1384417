"""sRGB to CIELAB, written out: two conversions that differ in the fourth digit, each kept for what depends on it.

* `srgb_to_lab`: the generated palettes (`datasets.instance_palette`, `synthetic.palette`) pick colors
  farthest-first in CIELAB: a conversion that differs in the fourth digit (colour-science's, 0.02 Delta E away)
  reorders ties and changes every mask colour of the bundled data, so this one is fixed here.
* `srgb01_to_lab`: colour-science 0.4.7's `XYZ_to_Lab(sRGB_to_XYZ(rgb))` to float rounding (its constants and
  formulas; `tests/test_quantize.py` holds them equal), for palette quantization and every metric in CIELAB.
  Importing colour pulls in its plotting stack (matplotlib.pyplot): ~1 s and ~135 MB in every process that
  quantizes a mask (the live node), so only CAM16-UCS and the reference twins import it.
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


# colour-science's sRGB colourspace: the IEC 61966-2-1 matrix (4 digits) and its D65 white, xy (0.3127, 0.3290).
_COLOUR_SRGB_TO_XYZ = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
_COLOUR_D65 = np.array([0.3127 / 0.3290, 1.0, (1.0 - 0.3127 - 0.3290) / 0.3290])
# colour decodes linearly up to the encoding of 0.0031308 (0.04044994), where the standard writes 0.04045.
_COLOUR_LINEAR_UP_TO = 1.055 * 0.0031308 ** (1 / 2.4) - 0.055


def srgb01_to_lab(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) sRGB in [0, 1] -> (..., 3) float64 CIELAB (D65), as colour-science's
    `XYZ_to_Lab(sRGB_to_XYZ(rgb))` computes it (its sRGB decoding, matrix, white and CIE 1976 function)."""
    c = np.asarray(rgb, dtype=np.float64)
    lin = np.where(c <= _COLOUR_LINEAR_UP_TO, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    t = (lin @ _COLOUR_SRGB_TO_XYZ.T) / _COLOUR_D65
    # colour's spow: the sign times |t| ** (1/3) (np.cbrt differs in the last bit).
    f = np.where(t > (24 / 116) ** 3, np.sign(t) * np.abs(t) ** (1 / 3), (841 / 108) * t + 16 / 116)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], axis=-1)
