"""Numba kernel for `evaluation.render_point_labels`: depth-sorted disc splatting, nearest point wins.

The plain twin is `evaluation.render_point_labels_reference` (painter's algorithm, far to near).
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def splat_discs(
    u: np.ndarray,
    v: np.ndarray,
    radius: np.ndarray,
    labels: np.ndarray,
    order: np.ndarray,
    height: int,
    width: int,
    background: np.uint32,
) -> np.ndarray:
    """Draws points front to back (`order`: nearest first); a pixel keeps the first label it gets.

    A point covers the pixel centres within `radius` of (u, v), and always the pixel its centre
    falls in (pixel centres sit at integer coordinates, so that pixel is floor(u + 0.5)).
    """
    image = np.full((height, width), background, np.uint32)
    written = np.zeros((height, width), np.bool_)
    for n in range(order.shape[0]):
        i = order[n]
        cu, cv, r = u[i], v[i], radius[i]
        label = labels[i]
        x0 = max(int(math.ceil(cu - r)), 0)
        x1 = min(int(math.floor(cu + r)), width - 1)
        y0 = max(int(math.ceil(cv - r)), 0)
        y1 = min(int(math.floor(cv + r)), height - 1)
        r2 = r * r
        for y in range(y0, y1 + 1):
            dy2 = (y - cv) * (y - cv)
            for x in range(x0, x1 + 1):
                if not written[y, x] and (x - cu) * (x - cu) + dy2 <= r2:
                    image[y, x] = label
                    written[y, x] = True
        px = int(math.floor(cu + 0.5))
        py = int(math.floor(cv + 0.5))
        if 0 <= px < width and 0 <= py < height and not written[py, px]:
            image[py, px] = label
            written[py, px] = True
    return image
