"""Analytic solids of the synthetic room: boxes (yawed about z), vertical cylinders, spheres, room faces.

World frame: metres, z up, floor at z = 0. Each primitive knows three things about itself:
- its packed row for the ray casters (``KIND_*`` code + ``PARAMS`` floats, see ``raycast``),
- its signed distance (negative inside the solid; used to cull hidden surface samples and in tests),
- its outer surface as charts (``charts``: maps from the unit square, with edges and curvature), and a
  jittered-grid sample of them at a given spacing (points, normals, tangents).

A ``RoomFace`` is one inner face of the (convex) room. The solid it bounds is everything outside the
room, so a picture touching a wall is "against a solid" there, just like a box standing on a table.
Ray casting treats it as an unbounded plane facing into the room: from any point inside a convex room
the nearest such plane hit is exactly the face the ray leaves through.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monovoc_ros.synthetic.charts import Chart, DiscChart, RectChart, SphereChart, TubeChart

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


def chart_samples(chart: Chart, spacing: float, jitter: float, rng: np.random.Generator) -> SurfaceSamples:
    """One sample per cell of the chart's base grid, displaced within its cell.

    Roughly uniform density without the clumps and gaps of i.i.d. sampling, so splats of ~0.8 spacing
    cover the face without holes. A disc smaller than one cell still gets its centre.
    """
    na, nb = chart.base_cells(spacing)
    ia, ib = np.meshgrid(np.arange(na), np.arange(nb), indexing="ij")
    n = na * nb
    a = (ia.ravel() + 0.5 + jitter * rng.uniform(-0.5, 0.5, n)) / na
    b = (ib.ravel() + 0.5 + jitter * rng.uniform(-0.5, 0.5, n)) / nb
    keep = chart.contains(a, b)
    if not keep.any():
        a, b, keep = np.full(1, 0.5), np.full(1, 0.5), np.ones(1, bool)
    p = chart.evaluate(a[keep], b[keep])
    return SurfaceSamples(p.points, p.normals, p.ta)


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

    def charts(self) -> list[Chart]:
        R, c, h = self._rotation(), np.asarray(self.center, float), np.asarray(self.half, float)
        out: list[Chart] = []
        for a in range(3):
            b, d = (a + 1) % 3, (a + 2) % 3
            for sign in (-1.0, 1.0):
                n = R[:, a] * sign
                out.append(RectChart(c + n * h[a], R[:, b], R[:, d], float(h[b]), float(h[d]), n))
        return out

    def sample(self, spacing: float, jitter: float, rng: np.random.Generator) -> SurfaceSamples:
        return _sample(self, spacing, jitter, rng)

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

    def charts(self) -> list[Chart]:
        c, r, hh = np.asarray(self.center, float), float(self.radius), float(self.half_height)
        return [TubeChart(c, r, hh), DiscChart(c + (0.0, 0.0, hh), r, 1.0), DiscChart(c - (0.0, 0.0, hh), r, -1.0)]

    def sample(self, spacing: float, jitter: float, rng: np.random.Generator) -> SurfaceSamples:
        return _sample(self, spacing, jitter, rng)

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

    def charts(self) -> list[Chart]:
        # (longitude, z) is an equal-area parametrisation, so a jittered grid in it is uniform on the sphere.
        return [SphereChart(np.asarray(self.center, float), float(self.radius))]

    def sample(self, spacing: float, jitter: float, rng: np.random.Generator) -> SurfaceSamples:
        return _sample(self, spacing, jitter, rng)

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

    def charts(self) -> list[Chart]:
        n, u = np.asarray(self.normal, float), np.asarray(self.u, float)
        return [RectChart(np.asarray(self.center, float), u, np.cross(n, u), float(self.half_u), float(self.half_v), n)]

    def sample(self, spacing: float, jitter: float, rng: np.random.Generator) -> SurfaceSamples:
        return _sample(self, spacing, jitter, rng)

    def area(self) -> float:
        return 4 * self.half_u * self.half_v

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        u = np.asarray(self.u, float)
        v = np.cross(np.asarray(self.normal, float), u)
        e = np.abs(u) * self.half_u + np.abs(v) * self.half_v
        return np.asarray(self.center) - e, np.asarray(self.center) + e


Primitive = Box | Cylinder | Sphere | RoomFace


def _sample(prim: Primitive, spacing: float, jitter: float, rng: np.random.Generator) -> SurfaceSamples:
    return SurfaceSamples.concat([chart_samples(c, spacing, jitter, rng) for c in prim.charts()])


def pack(primitives: list[Primitive]) -> tuple[np.ndarray, np.ndarray]:
    """(kinds (P,) int32, params (P, N_PARAMS) float64) for the ray casters."""
    kinds = np.array([p.kind for p in primitives], dtype=np.int32)
    params = np.stack([p.params() for p in primitives]).astype(np.float64) if primitives else np.zeros((0, N_PARAMS))
    return kinds, np.ascontiguousarray(params)
