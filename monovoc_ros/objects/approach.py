"""Where a robot should stand to reach an object (issue 26): a 2D free-space grid from the Gaussian map on
the floor plane, and an approach pose beside the object. Nothing here imports ROS.

The grid lies in the upright frame of the map's up vector (objects.upright.upright_rotation), one cell per
``cell`` metres:

* observed floor: a cell within ``floor_gap`` of a Gaussian lying within ``min_obstacle_height`` of the floor
  (a map's floor Gaussians are centimetres to decimetres apart);
* occupied: a cell holding ``min_obstacle_points`` Gaussians between ``min_obstacle_height`` and
  ``robot_height`` above the floor (what the robot would hit), then inflated by ``robot_radius``;
* free: observed floor that is not occupied or inflated. Cells never observed are unknown, not free.

The approach pose is the free cell connected to the robot's cell (when the robot's position is known)
whose distance to the object's footprint (the cells its own Gaussians cover) is closest to ``standoff``,
with a clear line of sight (no occupied cell but the object's own between the cell and the object), yaw
facing the object's nearest footprint cell. An object with no such cell (walled in, on the ceiling, in an
unobserved corner), a map without floor, or an empty map: a failure with a message, never a hang.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from monovoc_ros.objects.upright import upright_rotation

OPACITY_MIN = 0.3  # fainter Gaussians are not trusted to be surfaces
UNKNOWN, FREE, OCCUPIED, INFLATED = 0, 1, 2, 3
FOOTPRINT_CLOSING_M = 0.2  # gaps between an object's Gaussians closed to make its footprint
STANDOFF_TOLERANCE_M = 0.1  # an approach pose misses the standoff by at most this much, or it is a failure
# The largest standoff (metres) a request, the CLI or approach.standoff may give: an inf one searched the whole floor
# to answer "inf m".
MAX_STANDOFF_M = 100.0


def check_standoff(standoff: float, name: str = "standoff") -> None:
    """Raises ValueError unless 0 < standoff <= MAX_STANDOFF_M (NaN included)."""
    if not 0 < standoff <= MAX_STANDOFF_M:
        raise ValueError(f"{name} must be > 0 and <= {MAX_STANDOFF_M:g} metres, got {standoff}")


@dataclass(frozen=True)
class RobotShape:
    robot_radius: float = 0.25  # metres: the occupied cells are inflated by this
    robot_height: float = 1.2  # metres above the floor: obstacles above it are passed under
    min_obstacle_height: float = 0.1  # metres above the floor: lower Gaussians are floor (rugs, thresholds)
    cell: float = 0.05  # grid resolution, metres
    floor_gap: float = 0.15  # metres: floor cells this close to a floor Gaussian count as observed
    min_obstacle_points: int = 2  # Gaussians a cell needs between the two heights to be occupied

    def __post_init__(self) -> None:
        if not (self.cell > 0 and self.robot_radius >= 0 and self.robot_height > self.min_obstacle_height >= 0):
            raise ValueError(
                "need cell > 0, robot_radius >= 0 and robot_height > min_obstacle_height >= 0, got "
                f"cell {self.cell}, robot_radius {self.robot_radius}, robot_height {self.robot_height}, "
                f"min_obstacle_height {self.min_obstacle_height}"
            )


@dataclass
class FreeSpaceGrid:
    cells: np.ndarray  # (H, W) uint8: UNKNOWN, FREE, OCCUPIED, INFLATED
    origin: np.ndarray  # (2,) float64: upright-frame x, y of cell (0, 0)'s corner
    cell: float
    rotation: np.ndarray  # (3, 3) map -> upright frame
    floor: float  # upright-frame height of the floor
    top: np.ndarray  # (H, W) float64: height above the floor of an occupied cell's highest obstacle Gaussian

    def to_cell(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) upright-frame x, y -> (..., 2) int (row, col); may lie outside the grid."""
        ij = np.floor((np.asarray(xy, np.float64) - self.origin) / self.cell).astype(np.int64)
        return ij[..., ::-1]

    def centre(self, rc: np.ndarray) -> np.ndarray:
        """(..., 2) (row, col) -> (..., 2) upright-frame x, y of the cell centres."""
        rc = np.asarray(rc, np.float64)
        return self.origin + (rc[..., ::-1] + 0.5) * self.cell

    def to_map(self, xy: np.ndarray) -> np.ndarray:
        """Upright-frame x, y on the floor -> (3,) map-frame point."""
        return self.rotation.T @ np.array([xy[0], xy[1], self.floor])


def free_space(
    means: np.ndarray, opacities: np.ndarray, up: np.ndarray, floor: float, shape: RobotShape
) -> FreeSpaceGrid:
    """The grid of a Gaussian map: means (N, 3) float, opacities (N,) float, map frame; `floor` the height of
    the floor along `up` (objects.index.ObjectIndex.floor_height)."""
    rotation = upright_rotation(up)
    keep = np.asarray(opacities) >= OPACITY_MIN
    points = np.asarray(means, np.float64)[keep] @ rotation.T
    if len(points) == 0:
        raise ValueError("the map has no Gaussians to build free space from")
    # The grid spans the map without its far floaters (one stray Gaussian must not make it huge).
    lo, hi = np.percentile(points[:, :2], 0.1, axis=0), np.percentile(points[:, :2], 99.9, axis=0)
    points = points[np.all((points[:, :2] >= lo) & (points[:, :2] <= hi), axis=1)]
    height = points[:, 2] - floor
    origin = lo - 2 * shape.cell
    size = np.ceil((hi + 2 * shape.cell - origin) / shape.cell).astype(np.int64)
    grid = FreeSpaceGrid(
        np.zeros((size[1], size[0]), np.uint8), origin, shape.cell, rotation, floor, np.zeros((size[1], size[0]))
    )
    rc = grid.to_cell(points[:, :2])
    floor_cells = np.abs(height) < shape.min_obstacle_height
    obstacle = (height >= shape.min_obstacle_height) & (height <= shape.robot_height)
    if not floor_cells.any():
        raise ValueError(f"no floor: no Gaussians within {shape.min_obstacle_height} m of the floor height")
    seen = np.zeros(grid.cells.shape, bool)
    seen[rc[floor_cells, 0], rc[floor_cells, 1]] = True
    # A map's floor Gaussians are centimetres to decimetres apart: floor seen within floor_gap closes the holes.
    grid.cells[ndimage.binary_dilation(seen, structure=_disk(int(round(shape.floor_gap / shape.cell))))] = FREE
    counts = np.zeros(grid.cells.shape, np.int64)
    np.add.at(counts, (rc[obstacle, 0], rc[obstacle, 1]), 1)
    occupied = counts >= shape.min_obstacle_points  # a stray Gaussian is not a wall
    np.maximum.at(grid.top, (rc[obstacle, 0], rc[obstacle, 1]), height[obstacle])
    grid.top[~occupied] = 0.0
    radius = int(np.ceil(shape.robot_radius / shape.cell))
    inflated = ndimage.binary_dilation(occupied, structure=_disk(radius)) if radius else occupied
    grid.cells[inflated & (grid.cells == FREE)] = INFLATED
    grid.cells[inflated & (grid.cells == UNKNOWN)] = INFLATED
    grid.cells[occupied] = OCCUPIED
    return grid


def _disk(radius: int) -> np.ndarray:
    return np.hypot(*np.mgrid[-radius : radius + 1, -radius : radius + 1]) <= radius + 1e-9


@dataclass
class Approach:
    success: bool
    message: str
    position: np.ndarray | None = None  # (3,) map frame, on the floor
    yaw: float = 0.0  # radians about the up vector, in the upright frame (the map's own yaw when z is up)
    orientation: np.ndarray | None = None  # (4,) quaternion x, y, z, w in the map frame
    distance: float = 0.0  # metres from the object's footprint


def approach_pose(
    grid: FreeSpaceGrid,
    object_points: np.ndarray,
    standoff: float,
    robot_position: np.ndarray | None = None,
    robot_height: float = RobotShape.robot_height,
) -> Approach:
    """The pose to stand at `standoff` metres from the object whose Gaussian means are `object_points`
    (M, 3), map frame; `robot_position` (3,) map frame restricts it to free space the robot can reach."""
    check_standoff(standoff)
    points = np.asarray(object_points, np.float64) @ grid.rotation.T
    if len(points) == 0:
        return Approach(False, "the object has no Gaussians")
    cells = grid.to_cell(points[:, :2])
    h, w = grid.cells.shape
    cells = cells[(cells[:, 0] >= 0) & (cells[:, 0] < h) & (cells[:, 1] >= 0) & (cells[:, 1] < w)]
    if len(cells) == 0:
        return Approach(False, "the object lies outside the mapped area")
    # Its Gaussians are centimetres apart: the footprint is the area they close (a ceiling covers the room).
    own = np.zeros(grid.cells.shape, bool)
    own[cells[:, 0], cells[:, 1]] = True
    closing = _disk(int(round(FOOTPRINT_CLOSING_M / grid.cell)))
    own = ndimage.binary_fill_holes(ndimage.binary_closing(own, structure=closing, border_value=0) | own)
    footprint = np.argwhere(own)
    bottom = float(points[:, 2].min() - grid.floor)
    if bottom > robot_height and (grid.cells[own] == FREE).mean() > 0.5:
        return Approach(
            False, f"the object is overhead ({bottom:.1f} m above the floor, over free floor): no place beside it"
        )
    free = grid.cells == FREE
    reachable = free
    if robot_position is not None:
        start = grid.to_cell((grid.rotation @ np.asarray(robot_position, np.float64))[:2])
        seed = _nearest_free(free, start, int(round(0.5 / grid.cell)))
        if seed is None:
            return Approach(False, "the robot is not on observed free floor (nothing free within 0.5 m of it)")
        reachable = _connected(free, seed)
    candidates = np.argwhere(reachable)
    if len(candidates) == 0:
        return Approach(False, "no free floor")
    # Distance from each free cell to the footprint, through a distance transform of the footprint's complement.
    mask = np.ones(grid.cells.shape, bool)
    mask[footprint[:, 0], footprint[:, 1]] = False
    distance, nearest = ndimage.distance_transform_edt(mask, return_indices=True)
    metres = distance[candidates[:, 0], candidates[:, 1]] * grid.cell
    order = np.argsort(np.abs(metres - standoff), kind="stable")
    nearest_seen = None  # the best distance with a clear view, when none is within the tolerance
    for k in order[:5000]:
        if nearest_seen is not None and abs(metres[k] - standoff) > abs(nearest_seen - standoff):
            break
        rc = candidates[k]
        target = np.array([nearest[0][tuple(rc)], nearest[1][tuple(rc)]])
        if not _line_of_sight(grid, own, rc, target, bottom):
            continue
        if abs(metres[k] - standoff) > STANDOFF_TOLERANCE_M:
            nearest_seen = float(metres[k]) if nearest_seen is None else nearest_seen
            continue
        here, there = grid.centre(rc), grid.centre(target)
        yaw = float(np.arctan2(there[1] - here[1], there[0] - here[0]))
        position = grid.to_map(here)
        return Approach(
            True,
            f"{metres[k]:.2f} m from the object (standoff {standoff:g} m)",
            position,
            yaw,
            _orientation(grid.rotation, yaw),
            float(metres[k]),
        )
    if nearest_seen is not None:
        return Approach(
            False,
            f"no reachable free floor with a clear view {standoff:g} m (+- {STANDOFF_TOLERANCE_M:g}) from the object; "
            f"the nearest such place is {nearest_seen:.2f} m from it (ask with that standoff)",
        )
    return Approach(
        False,
        "no free floor the robot can reach with a clear view of the object (walled in, behind other furniture, "
        "or beside unobserved floor)",
    )


def _nearest_free(free: np.ndarray, start: np.ndarray, reach: int) -> tuple[int, int] | None:
    r0, c0 = int(start[0]), int(start[1])
    h, w = free.shape
    best = None
    for r in range(max(0, r0 - reach), min(h, r0 + reach + 1)):
        for c in range(max(0, c0 - reach), min(w, c0 + reach + 1)):
            if free[r, c]:
                d = (r - r0) ** 2 + (c - c0) ** 2
                if best is None or d < best[0]:
                    best = (d, (r, c))
    return None if best is None else best[1]


def _connected(free: np.ndarray, seed: tuple[int, int]) -> np.ndarray:
    labels, _ = ndimage.label(free)
    return labels == labels[seed]


def _line_of_sight(grid: FreeSpaceGrid, own: np.ndarray, a: np.ndarray, b: np.ndarray, bottom: float) -> bool:
    """No occupied cell but the object's own, and none rising above the object's bottom (a table under a cup
    does not hide the cup), on the segment between cells a and b."""
    steps = int(max(abs(int(b[0]) - int(a[0])), abs(int(b[1]) - int(a[1])))) + 1
    rows = np.rint(np.linspace(a[0], b[0], steps)).astype(np.int64)
    cols = np.rint(np.linspace(a[1], b[1], steps)).astype(np.int64)
    blocked = (grid.cells[rows, cols] == OCCUPIED) & ~own[rows, cols] & (grid.top[rows, cols] > bottom + 0.05)
    return not bool(blocked.any())


def _orientation(rotation: np.ndarray, yaw: float) -> np.ndarray:
    """Quaternion (x, y, z, w), map frame, of a body whose x axis faces `yaw` in the upright frame and z is up."""
    from scipy.spatial.transform import Rotation

    facing = rotation.T @ np.array([np.cos(yaw), np.sin(yaw), 0.0])
    up = rotation.T @ np.array([0.0, 0.0, 1.0])
    return Rotation.from_matrix(np.column_stack([facing, np.cross(up, facing), up])).as_quat()


def plot(
    grid: FreeSpaceGrid,
    path: str,
    objects: list[tuple[str, np.ndarray]] = (),
    poses: list[tuple[str, Approach]] = (),
    robot_position: np.ndarray | None = None,
) -> None:
    """A PNG of the grid (free white, occupied black, inflated gray, unknown blue-gray), each object's
    footprint outline and name (`objects`: (name, (M, 3) map-frame Gaussian means)), the approach poses as
    arrows and the robot as a dot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = np.array([[0.80, 0.84, 0.90], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [0.62, 0.62, 0.62]])
    h, w = grid.cells.shape
    extent = (grid.origin[0], grid.origin[0] + w * grid.cell, grid.origin[1], grid.origin[1] + h * grid.cell)
    fig, ax = plt.subplots(figsize=(8, 8 * h / max(w, 1) + 0.5))
    ax.imshow(colors[grid.cells], origin="lower", extent=extent, interpolation="nearest")
    for name, points in objects:
        xy = (np.asarray(points, np.float64) @ grid.rotation.T)[:, :2]
        if len(xy) == 0:
            continue
        lo, hi = np.percentile(xy, 2, axis=0), np.percentile(xy, 98, axis=0)
        ax.add_patch(plt.Rectangle(lo, *(hi - lo), fill=False, edgecolor="tab:orange", linewidth=1))
        ax.text(*((lo + hi) / 2), name, fontsize=6, ha="center", va="center", color="tab:red")
    for name, pose in poses:
        if not pose.success:
            continue
        xy = (grid.rotation @ pose.position)[:2]
        ax.arrow(*xy, 0.25 * np.cos(pose.yaw), 0.25 * np.sin(pose.yaw), width=0.03, color="tab:green")
        ax.text(xy[0], xy[1] - 0.12, name, fontsize=6, ha="center", color="tab:green")
    if robot_position is not None:
        xy = (grid.rotation @ np.asarray(robot_position, np.float64))[:2]
        ax.plot(*xy, "o", color="tab:blue")
    ax.set_xlabel("x (m, upright frame)")
    ax.set_ylabel("y (m)")
    ax.set_title("free space: white free, gray inflated, black occupied, blue-gray unknown")
    fig.savefig(path, dpi=150, bbox_inches="tight")
    plt.close(fig)


@dataclass
class Goal:
    """An approach pose for a text: the object the text named (its record and score), and the pose."""

    approach: Approach
    record: object | None = None  # objects.records.ObjectRecord
    score: float = 0.0

    def to_dict(self, frame_id: str) -> dict:
        """The JSON of `monovoc approach --json` and of the node's answers."""
        a = self.approach
        pose = None
        if a.success:
            pose = {
                "position": [float(v) for v in a.position],
                "yaw": float(a.yaw),
                "orientation": [float(v) for v in a.orientation],
                "frame_id": frame_id,
            }
        obj = None if self.record is None else {**self.record.to_dict(), "score": float(self.score)}
        return {"success": a.success, "message": a.message, "pose": pose, "object": obj}


def goal_for_text(
    index,
    text: str,
    grid: FreeSpaceGrid,
    means: np.ndarray,
    object_ids: np.ndarray,
    standoff: float,
    robot_position: np.ndarray | None,
    robot_height: float,
) -> Goal:
    """The object `text` names (objects.spatial.answer: relations read) and the pose to approach it: means
    (N, 3) and object_ids (N,) of the Gaussian map, map frame. Raises QueryError for a text that cannot be
    asked (empty, no models)."""
    from monovoc_ros.objects.spatial import answer

    result = answer(index, text, 1)
    if not result.matches:
        return Goal(Approach(False, f"no object to go to: {result.message}"))
    record, score = result.matches[0]
    points = np.asarray(means)[np.asarray(object_ids) == record.id]
    approach = approach_pose(grid, points, standoff, robot_position, robot_height)
    name = record.label or record.hex
    approach.message = f"{name} {record.hex}: {approach.message}"
    return Goal(approach, record, score)
