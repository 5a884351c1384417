"""Where a face meets another solid: which surface points are hidden against it, and how it bounds Gaussians.

A point of primitive k closer than ``CONTACT_EPS`` to another solid q is hidden (a leg's foot on the rug,
a sofa's back against the wall). Beyond that, for a solid standing on the face, the distance to q is the
in-plane distance to where the face disappears under it: the point is dropped while closer than its
``inset`` (the last Gaussians stop short of the contact line, as they stop short of edges), and further
out q bounds the sigma along the in-plane direction towards it by (distance - inset) / ``edge_sigmas``.
A solid straight above the face (its distance growing off the face, not along it, like the wall behind
a picture) is no edge: it neither insets nor bounds. Each point keeps the two tightest caps.

Two implementations of the same arithmetic: ``contact_limits`` (numba, one loop per point over its
primitive's neighbours) and ``contact_limits_reference`` (NumPy, one pass per neighbouring primitive,
through the primitives' own ``sdf``). Both take the packed primitives of ``primitives.pack``.
"""

from __future__ import annotations

import numba
import numpy as np

from monovoc_ros.synthetic.primitives import Primitive

CONTACT_EPS = 0.003  # metres: points this close to another solid are hidden against it
GRADIENT_STEP = 1e-5  # metres: central differences of the signed distance
ALONG_FACE = 0.3  # a neighbour bounds a face only where |in-plane part of its distance gradient| exceeds this


def neighbour_lists(primitives: list[Primitive], reach: float) -> tuple[np.ndarray, np.ndarray]:
    """CSR (start (P + 1,), index) of the other primitives whose bounds come within ``reach`` of each one's."""
    bounds = [p.bounds() for p in primitives]
    start, index = [0], []
    for k, (lo_k, hi_k) in enumerate(bounds):
        for q, (lo_q, hi_q) in enumerate(bounds):
            gap = np.linalg.norm(np.maximum(0.0, np.maximum(lo_q - hi_k, lo_k - hi_q)))
            if q != k and gap <= reach:
                index.append(q)
        start.append(len(index))
    return np.array(start, np.int64), np.array(index, np.int32)


# --------------------------------------------------------------------------------------------- numba


@numba.njit(cache=True, nogil=True)
def _sdf(kind, p, x, y, z):
    """Signed distance of (x, y, z) to packed primitive ``p`` (see ``raycast``), as its ``sdf`` method."""
    dx, dy, dz = x - p[0], y - p[1], z - p[2]
    if kind == 0:  # box, yawed about z
        c, s = p[6], p[7]
        qx = abs(c * dx + s * dy) - p[3]
        qy = abs(-s * dx + c * dy) - p[4]
        qz = abs(dz) - p[5]
        ox, oy, oz = max(qx, 0.0), max(qy, 0.0), max(qz, 0.0)
        return np.sqrt(ox * ox + oy * oy + oz * oz) + min(max(qx, max(qy, qz)), 0.0)
    if kind == 1:  # cylinder
        a = np.sqrt(dx * dx + dy * dy) - p[3]
        b = abs(dz) - p[4]
        oa, ob = max(a, 0.0), max(b, 0.0)
        return min(max(a, b), 0.0) + np.sqrt(oa * oa + ob * ob)
    if kind == 2:  # sphere
        return np.sqrt(dx * dx + dy * dy + dz * dz) - p[3]
    return dx * p[3] + dy * p[4] + dz * p[5]  # room face: positive on the room side


@numba.njit(cache=True, nogil=True)
def _limits_kernel(points, normals, prim, inset, start, index, kinds, params, reach, edge_sigmas, with_caps,
                   out_hidden, out_caps, out_dirs):  # fmt: skip
    h = GRADIENT_STEP
    for i in range(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        k = prim[i]
        hidden = False
        ca, cb = np.inf, np.inf
        ax = ay = az = bx = by = bz = 0.0
        for j in range(start[k], start[k + 1]):
            q = index[j]
            kind, p = kinds[q], params[q]
            d = _sdf(kind, p, x, y, z)
            if d < CONTACT_EPS:
                hidden = True
                break
            if d >= max(reach, inset[i]) or (not with_caps and d >= inset[i]):
                continue
            gx = (_sdf(kind, p, x + h, y, z) - _sdf(kind, p, x - h, y, z)) / (2 * h)
            gy = (_sdf(kind, p, x, y + h, z) - _sdf(kind, p, x, y - h, z)) / (2 * h)
            gz = (_sdf(kind, p, x, y, z + h) - _sdf(kind, p, x, y, z - h)) / (2 * h)
            g_n = gx * nx + gy * ny + gz * nz
            tx, ty, tz = gx - g_n * nx, gy - g_n * ny, gz - g_n * nz
            length = np.sqrt(tx * tx + ty * ty + tz * tz)
            if length <= ALONG_FACE:
                continue
            if d < inset[i]:
                hidden = True
                break
            if not with_caps or d >= reach:
                continue
            cap = (d - inset[i]) / edge_sigmas
            ex, ey, ez = -tx / length, -ty / length, -tz / length
            if cap < ca:
                cb, bx, by, bz = ca, ax, ay, az
                ca, ax, ay, az = cap, ex, ey, ez
            elif cap < cb:
                cb, bx, by, bz = cap, ex, ey, ez
        out_hidden[i] = hidden
        if hidden:
            ca, cb = np.inf, np.inf
            ax = ay = az = bx = by = bz = 0.0
        out_caps[i, 0], out_caps[i, 1] = ca, cb
        out_dirs[i, 0, 0], out_dirs[i, 0, 1], out_dirs[i, 0, 2] = ax, ay, az
        out_dirs[i, 1, 0], out_dirs[i, 1, 1], out_dirs[i, 1, 2] = bx, by, bz


def _check(points, normals, prim, inset):
    points = np.ascontiguousarray(points, np.float64)
    normals = np.ascontiguousarray(normals, np.float64)
    prim = np.ascontiguousarray(prim, np.int32)
    inset = np.ascontiguousarray(np.broadcast_to(inset, prim.shape), np.float64)
    return points, normals, prim, inset


def contact_limits(
    points: np.ndarray,
    normals: np.ndarray,
    prim: np.ndarray,
    inset: np.ndarray | float,
    neighbours: tuple[np.ndarray, np.ndarray],
    kinds: np.ndarray,
    params: np.ndarray,
    *,
    reach: float,
    edge_sigmas: float,
    with_caps: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(hidden (n,) bool, caps (n, 2), dirs (n, 2, 3)) of points on primitives ``prim`` with unit ``normals``.

    ``caps`` are the two tightest sigma bounds from neighbouring solids within ``reach`` (inf where none,
    and for hidden points), ``dirs`` the unit in-plane directions towards those solids.
    """
    points, normals, prim, inset = _check(points, normals, prim, inset)
    n = len(prim)
    hidden, caps, dirs = np.empty(n, bool), np.empty((n, 2)), np.empty((n, 2, 3))
    start, index = neighbours
    _limits_kernel(points, normals, prim, inset, start, index, np.ascontiguousarray(kinds, np.int32),
                   np.ascontiguousarray(params, np.float64), float(reach), float(edge_sigmas), bool(with_caps),
                   hidden, caps, dirs)  # fmt: skip
    return hidden, caps, dirs


# ------------------------------------------------------------------------------------ NumPy reference


def contact_limits_reference(
    points: np.ndarray,
    normals: np.ndarray,
    prim: np.ndarray,
    inset: np.ndarray | float,
    neighbours: tuple[np.ndarray, np.ndarray],
    primitives: list[Primitive],
    *,
    reach: float,
    edge_sigmas: float,
    with_caps: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plain twin of ``contact_limits``: one vectorised pass per neighbouring primitive, through ``sdf``."""
    points, normals, prim, inset = _check(points, normals, prim, inset)
    n = len(prim)
    start, index = neighbours
    near = np.zeros((len(primitives), len(primitives)), bool)
    for k in range(len(primitives)):
        near[k, index[start[k] : start[k + 1]]] = True
    hidden = np.zeros(n, bool)
    cap_a, cap_b = np.full(n, np.inf), np.full(n, np.inf)
    dir_a, dir_b = np.zeros((n, 3)), np.zeros((n, 3))
    for q, other in enumerate(primitives):
        sel = np.flatnonzero(near[prim, q])
        if len(sel) == 0:
            continue
        d = other.sdf(points[sel])
        hidden[sel] |= d < CONTACT_EPS
        keep = (d >= CONTACT_EPS) & (d < np.maximum(reach if with_caps else 0.0, inset[sel]))
        sel, d = sel[keep], d[keep]
        p, h = points[sel], GRADIENT_STEP
        grad = np.stack([(other.sdf(p + h * e) - other.sdf(p - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
        nrm = normals[sel]
        along = grad - np.sum(grad * nrm, axis=1, keepdims=True) * nrm
        length = np.linalg.norm(along, axis=1)
        ok = length > ALONG_FACE
        sel, d, e = sel[ok], d[ok], -along[ok] / length[ok, None]
        inside = d < inset[sel]
        hidden[sel[inside]] = True
        if not with_caps:
            continue
        keep = ~inside & (d < reach)
        sel, d, e = sel[keep], d[keep], e[keep]
        c = (d - inset[sel]) / edge_sigmas
        first = c < cap_a[sel]
        second = ~first & (c < cap_b[sel])
        i1, i2 = sel[first], sel[second]
        cap_b[i1], dir_b[i1] = cap_a[i1], dir_a[i1]
        cap_a[i1], dir_a[i1] = c[first], e[first]
        cap_b[i2], dir_b[i2] = c[second], e[second]
    caps, dirs = np.stack([cap_a, cap_b], axis=1), np.stack([dir_a, dir_b], axis=1)
    caps[hidden], dirs[hidden] = np.inf, 0.0
    return hidden, caps, dirs
