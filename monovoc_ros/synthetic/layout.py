"""The furnished room: which primitives make which surface, with what material and label.

World frame: metres, z up, origin on the floor at the room's centre; the room spans
x in [-3, 3], y in [-2.5, 2.5], z in [0, 2.7]. Surfaces touch the way real ones do (legs on the rug,
a box and a cup on the table, a sofa and a shelf against walls, a picture on a wall), so contact culling
and boundary handling get exercised. Unlabelled surfaces (a window, a ceiling vent) render as void.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monovoc_ros.synthetic.appearance import Material
from monovoc_ros.synthetic.primitives import Box, Cylinder, Primitive, RoomFace, Sphere

HALF_X, HALF_Y, HEIGHT = 3.0, 2.5, 2.7
ROOM_MIN = np.array([-HALF_X, -HALF_Y, 0.0])
ROOM_MAX = np.array([HALF_X, HALF_Y, HEIGHT])

# Class ids are positions in this tuple (stable across seeds, like a dataset's class list).
CLASS_NAMES = (
    "floor", "ceiling", "wall", "rug", "table", "box", "book", "cup", "chair", "sofa", "cabinet", "vase",
    "shelf", "tv", "tv stand", "picture", "poster", "door", "lamp", "bin", "ball", "plant", "window", "vent",
)  # fmt: skip


@dataclass(frozen=True)
class SurfaceSpec:
    instance_id: int
    class_name: str
    labelled: bool  # False: the segmentation has no label for it and masks show void (white)
    parts: tuple[tuple[Primitive, Material], ...]

    @property
    def class_id(self) -> int:
        return CLASS_NAMES.index(self.class_name)


def _box(x0: float, x1: float, y0: float, y1: float, z0: float, z1: float, yaw: float = 0.0) -> Box:
    return Box(((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2), ((x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2), yaw)


def _cyl(x: float, y: float, z0: float, z1: float, r: float) -> Cylinder:
    return Cylinder((x, y, (z0 + z1) / 2), r, (z1 - z0) / 2)


def room_layout() -> list[SurfaceSpec]:
    """Every surface of the room, labelled objects first in a fixed order, then the void surfaces."""
    M = Material
    wall, blue_wall = M((0.82, 0.80, 0.74), "noise", 0.9, 0.05), M((0.70, 0.76, 0.80), "noise", 0.9, 0.05)
    wood, light_wood = M((0.52, 0.34, 0.20), "grain", 0.12, 0.15), M((0.66, 0.50, 0.33), "grain", 0.10, 0.12)
    dark, chair = M((0.16, 0.16, 0.19), "noise", 0.15, 0.1), M((0.2, 0.3, 0.45), "noise", 0.12, 0.12)
    sofa = M((0.33, 0.45, 0.3), "noise", 0.2, 0.1)
    rug_top = 0.008
    surfaces: list[tuple[str, bool, list[tuple[Primitive, Material]]]] = []

    def add(name: str, *parts: tuple[Primitive, Material], labelled: bool = True) -> None:
        surfaces.append((name, labelled, list(parts)))

    add(
        "floor", (RoomFace((0, 0, 0), (0, 0, 1), (1, 0, 0), HALF_X, HALF_Y), M((0.58, 0.42, 0.28), "grain", 0.35, 0.12))
    )
    add(
        "ceiling",
        (RoomFace((0, 0, HEIGHT), (0, 0, -1), (1, 0, 0), HALF_X, HALF_Y), M((0.92, 0.92, 0.9), "noise", 1.2, 0.03)),
    )
    add("wall", (RoomFace((-HALF_X, 0, HEIGHT / 2), (1, 0, 0), (0, 1, 0), HALF_Y, HEIGHT / 2), wall))
    add("wall", (RoomFace((HALF_X, 0, HEIGHT / 2), (-1, 0, 0), (0, 1, 0), HALF_Y, HEIGHT / 2), wall))
    add("wall", (RoomFace((0, -HALF_Y, HEIGHT / 2), (0, 1, 0), (1, 0, 0), HALF_X, HEIGHT / 2), wall))
    add("wall", (RoomFace((0, HALF_Y, HEIGHT / 2), (0, -1, 0), (1, 0, 0), HALF_X, HEIGHT / 2), blue_wall))
    add("rug", (_box(-1.5, 1.5, -1.2, 1.2, 0.0, rug_top), M((0.62, 0.16, 0.14), "checker", 0.3, 0.2)))
    legs = [
        (_box(x - 0.03, x + 0.03, y - 0.03, y + 0.03, rug_top, 0.71), wood)
        for x in (-0.72, 0.72)
        for y in (-0.38, 0.38)
    ]
    add("table", (_box(-0.8, 0.8, -0.45, 0.45, 0.71, 0.75), wood), *legs)
    add("box", (Box((0.35, 0.10, 0.85), (0.15, 0.12, 0.10), 0.35), M((0.72, 0.58, 0.38), "noise", 0.1)))
    add("book", (Box((-0.30, -0.15, 0.76), (0.11, 0.075, 0.01), -0.26), M((0.70, 0.18, 0.20), "stripes", 0.05, 0.1)))
    add("cup", (_cyl(-0.50, 0.22, 0.75, 0.85, 0.04), M((0.90, 0.90, 0.95), "plain")))
    for y0, back in ((-0.85, (-1.07, -1.03)), (0.85, (1.03, 1.07))):
        seat = (_box(-0.22, 0.22, y0 - 0.22, y0 + 0.22, 0.43, 0.47), chair)
        rest = (_box(-0.22, 0.22, *back, 0.47, 0.97), chair)
        feet = [(x, y) for x in (-0.19, 0.19) for y in (y0 - 0.19, y0 + 0.19)]
        add(
            "chair", seat, rest, *[(_box(x - 0.02, x + 0.02, y - 0.02, y + 0.02, rug_top, 0.43), dark) for x, y in feet]
        )
    add("sofa", (_box(-0.5, 1.5, 1.6, 2.5, 0.0, 0.42), sofa), (_box(-0.5, 1.5, 2.3, 2.5, 0.42, 0.85), sofa),
        (_box(-0.5, -0.3, 1.6, 2.3, 0.42, 0.6), sofa), (_box(1.3, 1.5, 1.6, 2.3, 0.42, 0.6), sofa))  # fmt: skip
    add("cabinet", (_box(2.5, 3.0, -1.7, -0.7, 0.0, 0.9), M((0.80, 0.78, 0.72), "grain", 0.2, 0.06)))
    add("vase", (_cyl(2.75, -1.35, 0.9, 1.15, 0.06), M((0.15, 0.45, 0.55), "stripes", 0.04, 0.15)))
    boards = [(_box(-3.0, -2.66, -0.97, -0.03, z, z + 0.03), light_wood) for z in (0.05, 0.6, 1.15, 1.77)]
    sides = [(_box(-3.0, -2.66, y, y + 0.03, 0.0, 1.8), light_wood) for y in (-1.0, -0.03)]
    add("shelf", *sides, *boards)
    add("book", (_box(-2.95, -2.75, -0.50, -0.46, 0.63, 0.88), M((0.20, 0.30, 0.65), "stripes", 0.05)))
    add("book", (_box(-2.95, -2.77, -0.45, -0.41, 0.63, 0.86), M((0.85, 0.75, 0.20), "noise", 0.05)))
    add("tv", (_box(-0.1, 1.1, -2.5, -2.45, 1.05, 1.75), M((0.05, 0.05, 0.07), "noise", 0.3, 0.3)))
    add("tv stand", (_box(-0.2, 1.2, -2.5, -2.1, 0.0, 0.5), M((0.30, 0.22, 0.16), "grain", 0.1)))
    add("picture", (_box(2.995, 3.0, -1.6, -0.8, 1.25, 1.85), M((0.85, 0.55, 0.25), "stripes", 0.15, 0.3)))
    add("poster", (_box(0.05, 0.95, 2.495, 2.5, 1.3, 1.9), M((0.35, 0.60, 0.75), "checker", 0.1, 0.25)))
    add("door", (_box(-3.0, -2.99, 1.05, 1.95, 0.0, 2.05), M((0.60, 0.40, 0.25), "grain", 0.2, 0.1)))
    add("lamp", (_cyl(2.4, 2.0, 0.0, 0.03, 0.15), dark), (_cyl(2.4, 2.0, 0.03, 1.43, 0.015), dark),
        (_cyl(2.4, 2.0, 1.4, 1.7, 0.2), M((0.95, 0.88, 0.70), "noise", 0.1, 0.05)))  # fmt: skip
    add("bin", (_cyl(-2.5, 2.1, 0.0, 0.35, 0.15), M((0.35, 0.35, 0.38), "stripes", 0.03, 0.1)))
    add("ball", (Sphere((-1.7, -1.8, 0.12), 0.12), M((0.95, 0.45, 0.08), "stripes", 0.12, 0.2)))
    add("plant", (_cyl(-2.5, -2.0, 0.0, 0.3, 0.15), M((0.60, 0.30, 0.20), "noise", 0.1)),
        (Sphere((-2.5, -2.0, 0.52), 0.28), M((0.20, 0.50, 0.18), "noise", 0.06, 0.3)))  # fmt: skip
    add("window", (_box(-2.2, -1.0, -2.5, -2.49, 1.0, 2.0), M((0.70, 0.85, 0.95), "plain")), labelled=False)
    add("vent", (_box(-1.3, -0.7, 0.7, 1.3, 2.69, 2.7), M((0.60, 0.60, 0.62), "stripes", 0.04, 0.2)), labelled=False)
    # Instance ids with gaps, like a dataset's (not positions in any list).
    return [SurfaceSpec(2 + 3 * k, name, lab, tuple(parts)) for k, (name, lab, parts) in enumerate(surfaces)]
