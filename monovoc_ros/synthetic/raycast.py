"""Ray casting of packed primitives (see ``primitives.pack``): nearest hit per ray wins.

Two implementations of the same arithmetic: ``cast_rays`` (numba, one loop per ray, what rendering uses)
and ``cast_rays_reference`` (NumPy, one vectorised pass per primitive, what tests hold the kernel to).
Rays from ``camera_rays`` have a camera-frame z component of 1, so the returned ray parameter ``t`` is
the pixel's z-depth in metres.

Packed parameters per kind (``N_PARAMS`` floats):
  box:      cx cy cz hx hy hz cos(yaw) sin(yaw)
  cylinder: cx cy cz radius half_height - - -
  sphere:   cx cy cz radius - - - -
  plane:    px py pz nx ny nz - -     (n points into the room; only rays heading into the face hit)
"""

from __future__ import annotations

import numba
import numpy as np

from monovoc_ros.core.map.camera import Intrinsics
from monovoc_ros.synthetic.errors import SyntheticError
from monovoc_ros.synthetic.primitives import KIND_BOX, KIND_CYLINDER, KIND_PLANE, KIND_SPHERE

T_MIN = 1e-6  # hits nearer than this are ignored (cameras are kept outside every solid)
_PARALLEL = 1e-12  # |direction component| below which a ray counts as parallel to a slab or plane


def camera_rays(cam_to_world: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """World origin (3,) and directions (H*W, 3), row-major over pixels, scaled so that camera z = 1."""
    k = intrinsics
    u, v = np.meshgrid(np.arange(k.width, dtype=np.float64), np.arange(k.height, dtype=np.float64))
    cam = np.stack([(u.ravel() - k.cx) / k.fx, (v.ravel() - k.cy) / k.fy, np.ones(u.size)], axis=1)
    T = np.asarray(cam_to_world, dtype=np.float64)
    return T[:3, 3].copy(), np.ascontiguousarray(cam @ T[:3, :3].T)


# --------------------------------------------------------------------------------------------- numba


@numba.njit(cache=True, nogil=True)
def _box(ox, oy, oz, dx, dy, dz, p):
    c, s = p[6], p[7]
    rx, ry, rz = ox - p[0], oy - p[1], oz - p[2]
    lo = (c * rx + s * ry, -s * rx + c * ry, rz)
    ld = (c * dx + s * dy, -s * dx + c * dy, dz)
    h = (p[3], p[4], p[5])
    tnear, tfar, axis = -np.inf, np.inf, -1
    for a in range(3):
        if abs(ld[a]) < _PARALLEL:
            if abs(lo[a]) > h[a]:
                return np.inf, 0.0, 0.0, 0.0
            continue
        t1 = (-h[a] - lo[a]) / ld[a]
        t2 = (h[a] - lo[a]) / ld[a]
        if t1 > t2:
            t1, t2 = t2, t1
        if t1 > tnear:
            tnear, axis = t1, a
        if t2 < tfar:
            tfar = t2
    if axis < 0 or tnear > tfar or tnear <= T_MIN:
        return np.inf, 0.0, 0.0, 0.0
    sign = -1.0 if ld[axis] > 0 else 1.0
    if axis == 0:
        return tnear, sign * c, sign * s, 0.0
    if axis == 1:
        return tnear, -sign * s, sign * c, 0.0
    return tnear, 0.0, 0.0, sign


@numba.njit(cache=True, nogil=True)
def _cylinder(ox, oy, oz, dx, dy, dz, p):
    rx, ry, rz = ox - p[0], oy - p[1], oz - p[2]
    r, hh = p[3], p[4]
    best, nx, ny, nz = np.inf, 0.0, 0.0, 0.0
    a = dx * dx + dy * dy
    if a > _PARALLEL * _PARALLEL:
        b = rx * dx + ry * dy
        cc = rx * rx + ry * ry - r * r
        disc = b * b - a * cc
        if disc >= 0.0:
            t = (-b - np.sqrt(disc)) / a
            if t > T_MIN and abs(rz + t * dz) <= hh:
                best, nx, ny = t, (rx + t * dx) / r, (ry + t * dy) / r
    if abs(dz) > _PARALLEL and abs(rz) > hh:
        zc = hh if rz > 0 else -hh
        t = (zc - rz) / dz
        if t > T_MIN and t < best:
            x, y = rx + t * dx, ry + t * dy
            if x * x + y * y <= r * r:
                best, nx, ny, nz = t, 0.0, 0.0, (1.0 if rz > 0 else -1.0)
    return best, nx, ny, nz


@numba.njit(cache=True, nogil=True)
def _sphere(ox, oy, oz, dx, dy, dz, p):
    rx, ry, rz = ox - p[0], oy - p[1], oz - p[2]
    r = p[3]
    a = dx * dx + dy * dy + dz * dz
    b = rx * dx + ry * dy + rz * dz
    cc = rx * rx + ry * ry + rz * rz - r * r
    disc = b * b - a * cc
    if disc < 0.0:
        return np.inf, 0.0, 0.0, 0.0
    t = (-b - np.sqrt(disc)) / a
    if t <= T_MIN:
        return np.inf, 0.0, 0.0, 0.0
    return t, (rx + t * dx) / r, (ry + t * dy) / r, (rz + t * dz) / r


@numba.njit(cache=True, nogil=True)
def _plane(ox, oy, oz, dx, dy, dz, p):
    denom = dx * p[3] + dy * p[4] + dz * p[5]
    if denom > -_PARALLEL:
        return np.inf, 0.0, 0.0, 0.0
    t = ((p[0] - ox) * p[3] + (p[1] - oy) * p[4] + (p[2] - oz) * p[5]) / denom
    if t <= T_MIN:
        return np.inf, 0.0, 0.0, 0.0
    return t, p[3], p[4], p[5]


@numba.njit(cache=True, nogil=True, inline="always")
def _outside_sphere(ox, oy, oz, dx, dy, dz, a, sphere, limit):
    """Whether the ray misses the bounding sphere (x, y, z, r), or enters it only beyond parameter `limit`:
    the primitive inside can then not be hit before `limit`. An infinite radius bounds everything."""
    rad = sphere[3]
    if rad == np.inf:
        return False
    rx, ry, rz = ox - sphere[0], oy - sphere[1], oz - sphere[2]
    b = rx * dx + ry * dy + rz * dz
    disc = b * b - a * (rx * rx + ry * ry + rz * rz - rad * rad)
    if disc < 0.0:
        return True
    sq = np.sqrt(disc)
    return -b + sq <= 0.0 or (-b - sq) / a > limit * (1.0 + 1e-9) + 1e-9


@numba.njit(cache=True, nogil=True)
def _cast_kernel(origin, dirs, kinds, params, spheres, out_t, out_prim, out_n):
    ox, oy, oz = origin[0], origin[1], origin[2]
    for i in range(dirs.shape[0]):
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        a = dx * dx + dy * dy + dz * dz
        best, best_k, bnx, bny, bnz = np.inf, -1, 0.0, 0.0, 0.0
        for k in range(kinds.shape[0]):
            # Skip a primitive whose bounding sphere the ray misses, or enters beyond the current best hit:
            # it cannot win, so results equal the reference's exactly.
            if _outside_sphere(ox, oy, oz, dx, dy, dz, a, spheres[k], best):
                continue
            kind = kinds[k]
            if kind == 0:
                t, nx, ny, nz = _box(ox, oy, oz, dx, dy, dz, params[k])
            elif kind == 1:
                t, nx, ny, nz = _cylinder(ox, oy, oz, dx, dy, dz, params[k])
            elif kind == 2:
                t, nx, ny, nz = _sphere(ox, oy, oz, dx, dy, dz, params[k])
            else:
                t, nx, ny, nz = _plane(ox, oy, oz, dx, dy, dz, params[k])
            if t < best:
                best, best_k, bnx, bny, bnz = t, k, nx, ny, nz
        out_t[i] = best
        out_prim[i] = best_k
        out_n[i, 0], out_n[i, 1], out_n[i, 2] = bnx, bny, bnz


def _check(origin, dirs, kinds, params):
    origin = np.ascontiguousarray(origin, dtype=np.float64).reshape(3)
    dirs = np.ascontiguousarray(dirs, dtype=np.float64)
    if dirs.ndim != 2 or dirs.shape[1] != 3:
        raise SyntheticError(f"ray directions: expected (N, 3), got {dirs.shape}")
    kinds = np.ascontiguousarray(kinds, dtype=np.int32)
    params = np.ascontiguousarray(params, dtype=np.float64)
    if params.ndim != 2 or params.shape[0] != kinds.shape[0]:
        raise SyntheticError(f"primitive params {params.shape} do not match {kinds.shape[0]} kinds")
    if np.any((kinds < KIND_BOX) | (kinds > KIND_PLANE)):
        raise SyntheticError(f"unknown primitive kind in {np.unique(kinds).tolist()}")
    return origin, dirs, kinds, params


def bounding_spheres(kinds: np.ndarray, params: np.ndarray) -> np.ndarray:
    """(P, 4) centre and radius enclosing each packed primitive (slightly inflated; inf for planes)."""
    out = np.zeros((len(kinds), 4))
    out[:, :3] = params[:, :3]
    for k, (kind, p) in enumerate(zip(kinds, params, strict=True)):
        if kind == KIND_BOX:
            r = np.linalg.norm(p[3:6])
        elif kind == KIND_CYLINDER:
            r = np.hypot(p[3], p[4])
        elif kind == KIND_SPHERE:
            r = p[3]
        else:
            r = np.inf
        out[k, 3] = r * (1 + 1e-6) + 1e-6
    return out


def cast_rays(
    origin, dirs, kinds, params, spheres: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t (N,) float64, inf on a miss; primitive index (N,) int32, -1 on a miss; outward normals (N, 3)).

    ``spheres`` (from ``bounding_spheres``) may be passed to save recomputing them per call.
    """
    origin, dirs, kinds, params = _check(origin, dirs, kinds, params)
    spheres = bounding_spheres(kinds, params) if spheres is None else np.ascontiguousarray(spheres, np.float64)
    n = dirs.shape[0]
    out_t, out_prim, out_n = np.empty(n), np.empty(n, np.int32), np.empty((n, 3))
    _cast_kernel(origin, dirs, kinds, params, spheres, out_t, out_prim, out_n)
    return out_t, out_prim, out_n


# ------------------------------------------------------------------------------------ NumPy reference


def _box_ref(o, d, p):
    c, s = p[6], p[7]
    rx, ry, rz = o[0] - p[0], o[1] - p[1], o[2] - p[2]
    lo = (c * rx + s * ry, -s * rx + c * ry, rz)
    ld = (c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2])
    n = d.shape[0]
    tnear, tfar, axis = np.full(n, -np.inf), np.full(n, np.inf), np.full(n, -1)
    miss = np.zeros(n, bool)
    for a in range(3):
        h = p[3 + a]
        par = np.abs(ld[a]) < _PARALLEL
        if abs(lo[a]) > h:
            miss |= par
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-h - lo[a]) / ld[a]
            t2 = (h - lo[a]) / ld[a]
        t1, t2 = np.minimum(t1, t2), np.maximum(t1, t2)
        upd = ~par & (t1 > tnear)
        tnear, axis = np.where(upd, t1, tnear), np.where(upd, a, axis)
        tfar = np.where(~par & (t2 < tfar), t2, tfar)
    hit = ~miss & (axis >= 0) & (tnear <= tfar) & (tnear > T_MIN)
    lda = np.choose(np.clip(axis, 0, 2), ld)
    sign = np.where(lda > 0, -1.0, 1.0)
    normals = np.zeros((n, 3))
    normals[axis == 0] = np.stack([c * sign, s * sign, 0 * sign], 1)[axis == 0]
    normals[axis == 1] = np.stack([-s * sign, c * sign, 0 * sign], 1)[axis == 1]
    normals[axis == 2, 2] = sign[axis == 2]
    return np.where(hit, tnear, np.inf), normals


def _cylinder_ref(o, d, p):
    rx, ry, rz = o[0] - p[0], o[1] - p[1], o[2] - p[2]
    r, hh = p[3], p[4]
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    n = d.shape[0]
    a = dx * dx + dy * dy
    b = rx * dx + ry * dy
    disc = b * b - a * (rx * rx + ry * ry - r * r)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (-b - np.sqrt(disc)) / a
    side = (a > _PARALLEL * _PARALLEL) & (disc >= 0) & (t > T_MIN) & (np.abs(rz + t * dz) <= hh)
    best = np.where(side, t, np.inf)
    normals = np.zeros((n, 3))
    normals[side, 0] = ((rx + t * dx) / r)[side]
    normals[side, 1] = ((ry + t * dy) / r)[side]
    if abs(rz) > hh:
        zc = hh if rz > 0 else -hh
        with np.errstate(divide="ignore", invalid="ignore"):
            tc = (zc - rz) / dz
        x, y = rx + tc * dx, ry + tc * dy
        cap = (np.abs(dz) > _PARALLEL) & (tc > T_MIN) & (tc < best) & (x * x + y * y <= r * r)
        best = np.where(cap, tc, best)
        normals[cap] = (0.0, 0.0, 1.0 if rz > 0 else -1.0)
    return best, normals


def _sphere_ref(o, d, p):
    rx, ry, rz = o[0] - p[0], o[1] - p[1], o[2] - p[2]
    r = p[3]
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    a = dx * dx + dy * dy + dz * dz
    b = rx * dx + ry * dy + rz * dz
    disc = b * b - a * (rx * rx + ry * ry + rz * rz - r * r)
    with np.errstate(invalid="ignore"):
        t = (-b - np.sqrt(disc)) / a
    hit = (disc >= 0) & (t > T_MIN)
    normals = np.stack([(rx + t * dx) / r, (ry + t * dy) / r, (rz + t * dz) / r], axis=1)
    return np.where(hit, t, np.inf), np.where(hit[:, None], normals, 0.0)


def _plane_ref(o, d, p):
    denom = d[:, 0] * p[3] + d[:, 1] * p[4] + d[:, 2] * p[5]
    num = (p[0] - o[0]) * p[3] + (p[1] - o[1]) * p[4] + (p[2] - o[2]) * p[5]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num / denom
    hit = (denom <= -_PARALLEL) & (t > T_MIN)
    normals = np.tile(p[3:6], (d.shape[0], 1))
    return np.where(hit, t, np.inf), np.where(hit[:, None], normals, 0.0)


_REFERENCE = {KIND_BOX: _box_ref, KIND_CYLINDER: _cylinder_ref, KIND_SPHERE: _sphere_ref, KIND_PLANE: _plane_ref}


def cast_rays_reference(origin, dirs, kinds, params) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plain NumPy twin of ``cast_rays`` (same arithmetic, primitive by primitive)."""
    origin, dirs, kinds, params = _check(origin, dirs, kinds, params)
    n = dirs.shape[0]
    best, prim, normals = np.full(n, np.inf), np.full(n, -1, np.int32), np.zeros((n, 3))
    for k in range(kinds.shape[0]):
        t, nrm = _REFERENCE[int(kinds[k])](origin, dirs, params[k])
        closer = t < best
        best[closer], prim[closer], normals[closer] = t[closer], k, nrm[closer]
    return best, prim, normals
