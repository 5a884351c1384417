"""Faces of the analytic solids as maps from the unit square: what the adaptive map sampler refines.

A chart sends parameters (a, b) in [0, 1]^2 to surface points, with the outward normal, unit tangents
along increasing a and b, and the metric (metres per unit of a and of b), so a cell of the parameter
square has a known size on the surface in any tangent direction. It also knows its own edges (distance
from a point to the nearest edge of its face, the in-plane direction towards it, and the edge's radius of
curvature within the face) and the face's curvature radii: both limit how large a Gaussian may be there
before its footprint leaves the face or its flat disc stands off the curved surface.

Kinds: rectangles (box faces, room faces), cylinder sides (periodic in a), cylinder caps (equal-area
polar coordinates, the rim at b = 1) and spheres (equal-area (longitude, z) coordinates, no edges).
``half_width`` is the smallest distance from the face's middle to an edge (inf without edges);
``curved`` says whether the face bends (a tube or sphere).

Every chart kind evaluates many charts of its kind at once from packed parameters (``params`` rows
gathered per point), so a whole atlas costs one vectorised call per kind; the instance methods are the
same functions on one chart's row.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ChartPoints:
    points: np.ndarray  # (n, 3)
    normals: np.ndarray  # (n, 3) unit, out of the solid
    ta: np.ndarray  # (n, 3) unit tangent along increasing a
    tb: np.ndarray  # (n, 3) unit tangent along increasing b
    ga: np.ndarray  # (n,) metres per unit of a
    gb: np.ndarray  # (n,) metres per unit of b


@dataclass(frozen=True)
class Limits:
    """What bounds a Gaussian's size at each point: own-face edges and curvature, each with its direction."""

    edge_distance: list[np.ndarray]  # (n,) in-plane distance (m) to an edge of the face
    edge_direction: list[np.ndarray]  # (n, 3) unit tangent pointing at that edge
    edge_radius: list[np.ndarray]  # (n,) radius (m) of the edge's curve within the face (inf: straight); a
    # face bounded by a convex curve (a disc's rim) is left by a straight line along the edge
    curvature_radius: list[np.ndarray]  # (n,) radius (m) of the surface's curvature along ...
    curvature_direction: list[np.ndarray]  # (n, 3) ... this unit tangent


def _ring(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit radial and tangential (counter-clockwise) horizontal vectors at angles ``theta``."""
    c, s, z = np.cos(theta), np.sin(theta), np.zeros(len(theta))
    return np.stack([c, s, z], axis=1), np.stack([-s, c, z], axis=1)


class _Chart:
    """Instance methods: the packed (many-chart) functions of the chart's kind on its own parameter row."""

    def _rows(self, n: int) -> np.ndarray:
        return np.broadcast_to(self.params(), (n, len(self.params())))

    def evaluate(self, a: np.ndarray, b: np.ndarray) -> ChartPoints:
        return type(self).evaluate_packed(self._rows(len(a)), a, b)

    def limits(self, a: np.ndarray, b: np.ndarray) -> Limits:
        return type(self).limits_packed(self._rows(len(a)), a, b)

    def contains(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.ones(len(a), bool)


@dataclass(frozen=True)
class RectChart(_Chart):
    center: np.ndarray
    u: np.ndarray  # unit axis along a
    v: np.ndarray  # unit axis along b
    half_u: float
    half_v: float
    normal: np.ndarray

    curved = False

    def params(self) -> np.ndarray:  # center 0:3, u 3:6, v 6:9, normal 9:12, half_u 12, half_v 13
        return np.concatenate([self.center, self.u, self.v, self.normal, [self.half_u, self.half_v]])

    def half_width(self) -> float:
        return min(self.half_u, self.half_v)

    def base_cells(self, spacing: float) -> tuple[int, int]:
        return max(1, round(2 * self.half_u / spacing)), max(1, round(2 * self.half_v / spacing))

    @staticmethod
    def evaluate_packed(P: np.ndarray, a: np.ndarray, b: np.ndarray) -> ChartPoints:
        hu, hv = P[:, 12], P[:, 13]
        pts = P[:, 0:3] + ((2 * a - 1) * hu)[:, None] * P[:, 3:6] + ((2 * b - 1) * hv)[:, None] * P[:, 6:9]
        return ChartPoints(pts, P[:, 9:12], P[:, 3:6], P[:, 6:9], 2 * hu, 2 * hv)

    @staticmethod
    def limits_packed(P: np.ndarray, a: np.ndarray, b: np.ndarray) -> Limits:
        su, sv = 2 * a - 1, 2 * b - 1
        straight = np.full(len(a), np.inf)
        return Limits(
            [P[:, 12] * (1 - np.abs(su)), P[:, 13] * (1 - np.abs(sv))],
            [np.where(su >= 0, 1.0, -1.0)[:, None] * P[:, 3:6], np.where(sv >= 0, 1.0, -1.0)[:, None] * P[:, 6:9]],
            [straight, straight],
            [],
            [],
        )


@dataclass(frozen=True)
class TubeChart(_Chart):
    """The side of a vertical cylinder: a = angle / 2 pi (periodic, no edge), b = height."""

    center: np.ndarray
    radius: float
    half_height: float

    curved = True

    def params(self) -> np.ndarray:  # center 0:3, radius 3, half_height 4
        return np.concatenate([self.center, [self.radius, self.half_height]])

    def half_width(self) -> float:
        return self.half_height

    def base_cells(self, spacing: float) -> tuple[int, int]:
        return max(3, round(2 * np.pi * self.radius / spacing)), max(1, round(2 * self.half_height / spacing))

    @staticmethod
    def evaluate_packed(P: np.ndarray, a: np.ndarray, b: np.ndarray) -> ChartPoints:
        r, hh = P[:, 3], P[:, 4]
        radial, around = _ring(2 * np.pi * a)
        pts = P[:, 0:3] + r[:, None] * radial
        pts[:, 2] += hh * (2 * b - 1)
        up = np.zeros_like(pts)
        up[:, 2] = 1.0
        return ChartPoints(pts, radial, around, up, 2 * np.pi * r, 2 * hh)

    @staticmethod
    def limits_packed(P: np.ndarray, a: np.ndarray, b: np.ndarray) -> Limits:
        sz = 2 * b - 1
        _, around = _ring(2 * np.pi * a)
        up = np.zeros((len(a), 3))
        up[:, 2] = np.where(sz >= 0, 1.0, -1.0)
        # The rims are circles, but ones that follow the tube: straight in the unrolled face.
        return Limits([P[:, 4] * (1 - np.abs(sz))], [up], [np.full(len(a), np.inf)], [P[:, 3].copy()], [around])


@dataclass(frozen=True)
class DiscChart(_Chart):
    """A horizontal disc (cylinder cap), ``normal_z`` +1 (top) or -1 (bottom), in equal-area polar coordinates.

    a = angle / 2 pi (periodic), b = (rho / radius)^2: the rim is the edge b = 1, so cells split across it
    stay narrow rings instead of the staircase a square grid would need.
    """

    center: np.ndarray
    radius: float
    normal_z: float

    curved = False

    def params(self) -> np.ndarray:  # center 0:3, radius 3, normal_z 4
        return np.concatenate([self.center, [self.radius, self.normal_z]])

    def half_width(self) -> float:
        return self.radius

    def base_cells(self, spacing: float) -> tuple[int, int]:
        # Rings of about one spacing at the rim (thicker inwards), cells of about one spacing along it.
        return max(3, round(2 * np.pi * self.radius / spacing)), max(1, round(self.radius / (2 * spacing)))

    @staticmethod
    def evaluate_packed(P: np.ndarray, a: np.ndarray, b: np.ndarray) -> ChartPoints:
        r = P[:, 3]
        radial, around = _ring(2 * np.pi * a)
        rho = r * np.sqrt(np.clip(b, 0.0, 1.0))
        normals = np.zeros((len(a), 3))
        normals[:, 2] = P[:, 4]
        gb = r / (2 * np.sqrt(np.maximum(b, 1e-12)))  # d rho / d b
        return ChartPoints(P[:, 0:3] + rho[:, None] * radial, normals, around, radial, 2 * np.pi * rho, gb)

    @staticmethod
    def limits_packed(P: np.ndarray, a: np.ndarray, b: np.ndarray) -> Limits:
        radial, _ = _ring(2 * np.pi * a)
        r = P[:, 3]
        return Limits([r * (1 - np.sqrt(np.clip(b, 0.0, 1.0)))], [radial], [r.copy()], [], [])


@dataclass(frozen=True)
class SphereChart(_Chart):
    """A sphere in equal-area coordinates: a = longitude / 2 pi (periodic), b = (z + 1) / 2 on the unit sphere."""

    center: np.ndarray
    radius: float

    curved = True

    def params(self) -> np.ndarray:  # center 0:3, radius 3
        return np.concatenate([self.center, [self.radius]])

    def half_width(self) -> float:
        return np.inf

    def base_cells(self, spacing: float) -> tuple[int, int]:
        return max(3, round(2 * np.pi * self.radius / spacing)), max(2, round(2 * self.radius / spacing))

    @staticmethod
    def evaluate_packed(P: np.ndarray, a: np.ndarray, b: np.ndarray) -> ChartPoints:
        r = P[:, 3]
        radial, around = _ring(2 * np.pi * a)
        z = 2 * b - 1
        ring = np.sqrt(np.clip(1 - z * z, 0.0, 1.0))
        normals = ring[:, None] * radial
        normals[:, 2] = z
        tb = -z[:, None] * radial  # d(normal)/dz, normalised
        tb[:, 2] = ring
        gb = 2 * r / np.maximum(ring, 1e-6)
        return ChartPoints(P[:, 0:3] + r[:, None] * normals, normals, around, tb, 2 * np.pi * r * ring, gb)

    @staticmethod
    def limits_packed(P: np.ndarray, a: np.ndarray, b: np.ndarray) -> Limits:
        p = SphereChart.evaluate_packed(P, a, b)
        r = P[:, 3].copy()
        return Limits([], [], [], [r, r], [p.ta, p.tb])


Chart = RectChart | TubeChart | DiscChart | SphereChart
CHART_KINDS: tuple[type, ...] = (RectChart, TubeChart, DiscChart, SphereChart)
