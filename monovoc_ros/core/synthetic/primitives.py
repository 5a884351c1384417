"""Analytic solids of the synthetic room: boxes (yawed about z), vertical cylinders, spheres, room faces.

World frame: metres, z up, floor at z = 0. Each primitive knows three things about itself:
- its packed row for the ray casters (``KIND_*`` code + ``PARAMS`` floats, see ``raycast``),
- its signed distance (negative inside the solid; used to cull hidden surface samples and in tests),
- how to sample its outer surface on a jittered grid of a given spacing (points, normals, tangents).

A ``RoomFace`` is one inner face of the (convex) room. The solid it bounds is everything outside the
room, so a picture touching a wall is "against a solid" there, just like a box standing on a table.
Ray casting treats it as an unbounded plane facing into the room: from any point inside a convex room
the nearest such plane hit is exactly the face the ray leaves through.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

KIND_BOX = 0
KIND_CYLINDER = 1
KIND_SPHERE = 2
KIND_PLANE = 3
N_PARAMS = 8


@dataclass(frozen=True)
class SurfaceSamples:
    points: np.ndarray  # (n, 3) on the surface
    normals: np.ndarray  # (n, 3) unit, pointing out of the solid
    tangents: np.ndarray  # (n, 3) unit, perpendicular to the normal

    @staticmethod
    def empty() -> SurfaceSamples:
        z = np.zeros((0, 3))
        return SurfaceSamples(z, z, z)

    @staticmethod
    def concat(parts: list[SurfaceSamples]) -> SurfaceSamples:
        if not parts:
            return SurfaceSamples.empty()
        return SurfaceSamples(
            *(np.concatenate([getattr(p, f) for p in parts]) for f in ("points", "normals", "tangents"))
        )


def _rect_samples(
    center: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    half_u: float,
    half_v: float,
    normal: np.ndarray,
    spacing: float,
    jitter: float,
    rng: np.random.Generator,
) -> SurfaceSamples:
    # One sample per grid cell, displaced within its cell: roughly uniform density without the clumps
    # and gaps of i.i.d. sampling, so splats of ~0.6 spacing cover the face without holes.
    nu = max(1, round(2 * half_u / spacing))
    nv = max(1, round(2 * half_v / spacing))
    iu, iv = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    n = nu * nv
    fu = (iu.ravel() + 0.5 + jitter * rng.uniform(-0.5, 0.5, n)) / nu
    fv = (iv.ravel() + 0.5 + jitter * rng.uniform(-0.5, 0.5, n)) / nv
    pts = center + np.outer((2 * fu - 1) * half_u, u) + np.outer((2 * fv - 1) * half_v, v)
    return SurfaceSamples(pts, np.tile(normal, (n, 1)), np.tile(u, (n, 1)))


def _disc_samples(
    center: np.ndarray, radius: float, normal_z: float, spacing: float, jitter: float, rng: np.random.Generator
) -> SurfaceSamples:
    n_side = max(1, round(2 * radius / spacing))
    i, j = np.meshgrid(np.arange(n_side), np.arange(n_side), indexing="ij")
    n = n_side * n_side
    x = ((i.ravel() + 0.5 + jitter * rng.uniform(-0.5, 0.5, n)) / n_side * 2 - 1) * radius
    y = ((j.ravel() + 0.5 + jitter * rng.uniform(-0.5, 0.5, n)) / n_side * 2 - 1) * radius
    keep = x * x + y * y <= radius * radius
    if not keep.any():  # a disc smaller than one cell still gets its centre
        x, y, keep = np.zeros(1), np.zeros(1), np.ones(1, bool)
    x, y = x[keep], y[keep]
    pts = np.stack([center[0] + x, center[1] + y, np.full_like(x, center[2])], axis=1)
    m = len(x)
    return SurfaceSamples(pts, np.tile([0.0, 0.0, normal_z], (m, 1)), np.tile([1.0, 0.0, 0.0], (m, 1)))


@dataclass(frozen=True)
class Box:
    """A box of half extents ``half`` centred at ``center``, rotated by ``yaw`` radians about world z."""

    center: tuple[float, float, float]
    half: tuple[float, float, float]
    yaw: float = 0.0

    kind = KIND_BOX

    def params(self) -> np.ndarray:
        c, h = self.center, self.half
        return np.array([c[0], c[1], c[2], h[0], h[1], h[2], np.cos(self.yaw), np.sin(self.yaw)])

    def _rotation(self) -> np.ndarray:
        cy, sy = np.cos(self.yaw), np.sin(self.yaw)
        return np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])

    def sdf(self, points: np.ndarray) -> np.ndarray:
        local = (np.asarray(points, float) - self.center) @ self._rotation()
        q = np.abs(local) - self.half
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
        return outside + np.minimum(q.max(axis=-1), 0.0)

    def sample(self, spacing: float, jitter: float, rng: np.random.Generator) -> SurfaceSamples:
        R, c, h = self._rotation(), np.asarray(self.center, float), np.asarray(self.half, float)
        parts = []
        for a in range(3):
            b, d = (a + 1) % 3, (a + 2) % 3
            for sign in (-1.0, 1.0):
                n = R[:, a] * sign
                parts.append(_rect_samples(c + n * h[a], R[:, b], R[:, d], h[b], h[d], n, spacing, jitter, rng))
        return SurfaceSamples.concat(parts)

    def area(self) -> float:
        hx, hy, hz = self.half
        return 8.0 * (hx * hy + hy * hz + hx * hz)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        signs = np.stack(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij"), -1).reshape(-1, 3)
        corners = np.asarray(self.center) + (signs * self.half) @ self._rotation().T
        return corners.min(axis=0), corners.max(axis=0)


@dataclass(frozen=True)
class Cylinder:
    """A closed cylinder with a vertical axis, centred (mid-height) at ``center``."""

    center: tuple[float, float, float]
    radius: float
    half_height: float

    kind = KIND_CYLINDER

    def params(self) -> np.ndarray:
        c = self.center
        return np.array([c[0], c[1], c[2], self.radius, self.half_height, 0.0, 0.0, 0.0])

    def sdf(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, float) - self.center
        d = np.stack([np.hypot(p[..., 0], p[..., 1]) - self.radius, np.abs(p[..., 2]) - self.half_height], -1)
        return np.minimum(d.max(axis=-1), 0.0) + np.linalg.norm(np.maximum(d, 0.0), axis=-1)

    def sample(self, spacing: float, jitter: float, rng: np.random.Generator) -> SurfaceSamples:
        c, r, hh = np.asarray(self.center, float), self.radius, self.half_height
        n_theta = max(3, round(2 * np.pi * r / spacing))
        n_z = max(1, round(2 * hh / spacing))
        it, iz = np.meshgrid(np.arange(n_theta), np.arange(n_z), indexing="ij")
        n = n_theta * n_z
        theta = 2 * np.pi * (it.ravel() + 0.5 + jitter * rng.uniform(-0.5, 0.5, n)) / n_theta
        z = hh * (2 * (iz.ravel() + 0.5 + jitter * rng.uniform(-0.5, 0.5, n)) / n_z - 1)
        normals = np.stack([np.cos(theta), np.sin(theta), np.zeros(n)], axis=1)
        side = SurfaceSamples(
            c + np.stack([r * normals[:, 0], r * normals[:, 1], z], axis=1),
            normals,
            np.stack([-np.sin(theta), np.cos(theta), np.zeros(n)], axis=1),
        )
        top = _disc_samples(c + (0.0, 0.0, hh), r, 1.0, spacing, jitter, rng)
        bottom = _disc_samples(c - (0.0, 0.0, hh), r, -1.0, spacing, jitter, rng)
        return SurfaceSamples.concat([side, top, bottom])

    def area(self) -> float:
        return 2 * np.pi * self.radius * (self.radius + 2 * self.half_height)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        e = np.array([self.radius, self.radius, self.half_height])
        return np.asarray(self.center) - e, np.asarray(self.center) + e


@dataclass(frozen=True)
class Sphere:
    center: tuple[float, float, float]
    radius: float

    kind = KIND_SPHERE

    def params(self) -> np.ndarray:
        c = self.center
        return np.array([c[0], c[1], c[2], self.radius, 0.0, 0.0, 0.0, 0.0])

    def sdf(self, points: np.ndarray) -> np.ndarray:
        return np.linalg.norm(np.asarray(points, float) - self.center, axis=-1) - self.radius

    def sample(self, spacing: float, jitter: float, rng: np.random.Generator) -> SurfaceSamples:
        # (z, longitude) is an equal-area parametrisation, so a jittered grid in it is uniform on the sphere.
        r = self.radius
        n_z = max(2, round(2 * r / spacing))
        n_phi = max(3, round(2 * np.pi * r / spacing))
        iz, ip = np.meshgrid(np.arange(n_z), np.arange(n_phi), indexing="ij")
        n = n_z * n_phi
        z = 2 * (iz.ravel() + 0.5 + jitter * rng.uniform(-0.5, 0.5, n)) / n_z - 1
        phi = 2 * np.pi * (ip.ravel() + 0.5 + jitter * rng.uniform(-0.5, 0.5, n)) / n_phi
        ring = np.sqrt(np.clip(1 - z * z, 0.0, 1.0))
        normals = np.stack([ring * np.cos(phi), ring * np.sin(phi), z], axis=1)
        tangents = np.stack([-np.sin(phi), np.cos(phi), np.zeros(n)], axis=1)
        return SurfaceSamples(np.asarray(self.center) + r * normals, normals, tangents)

    def area(self) -> float:
        return 4 * np.pi * self.radius**2

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.center) - self.radius, np.asarray(self.center) + self.radius


@dataclass(frozen=True)
class RoomFace:
    """An inner face of the room: rectangle ``center`` +- ``half_u`` u +- ``half_v`` v, ``normal`` into the room."""

    center: tuple[float, float, float]
    normal: tuple[float, float, float]
    u: tuple[float, float, float]
    half_u: float
    half_v: float

    kind = KIND_PLANE

    def params(self) -> np.ndarray:
        c, n = self.center, self.normal
        return np.array([c[0], c[1], c[2], n[0], n[1], n[2], 0.0, 0.0])

    def sdf(self, points: np.ndarray) -> np.ndarray:
        # Positive on the room side: the "solid" is everything beyond the face.
        return (np.asarray(points, float) - self.center) @ np.asarray(self.normal, float)

    def sample(self, spacing: float, jitter: float, rng: np.random.Generator) -> SurfaceSamples:
        n, u = np.asarray(self.normal, float), np.asarray(self.u, float)
        v = np.cross(n, u)
        return _rect_samples(np.asarray(self.center, float), u, v, self.half_u, self.half_v, n, spacing, jitter, rng)

    def area(self) -> float:
        return 4 * self.half_u * self.half_v

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        u = np.asarray(self.u, float)
        v = np.cross(np.asarray(self.normal, float), u)
        e = np.abs(u) * self.half_u + np.abs(v) * self.half_v
        return np.asarray(self.center) - e, np.asarray(self.center) + e


Primitive = Box | Cylinder | Sphere | RoomFace


def pack(primitives: list[Primitive]) -> tuple[np.ndarray, np.ndarray]:
    """(kinds (P,) int32, params (P, N_PARAMS) float64) for the ray casters."""
    kinds = np.array([p.kind for p in primitives], dtype=np.int32)
    params = np.stack([p.params() for p in primitives]).astype(np.float64) if primitives else np.zeros((0, N_PARAMS))
    return kinds, np.ascontiguousarray(params)
