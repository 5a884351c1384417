"""Approach poses (issue 26): the free-space grid of a Gaussian map and the pose to stand at beside an object,
on the synthetic room and Replica office_0, the failures, and the offline `monovoc approach`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from monovoc_ros.cli import main as cli_main
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.objects import approach as ap
from tests.object_room import room, room_directory, room_map

STANDOFF = 0.6


def check_every_object(mapper, index, robot) -> tuple[int, list[str]]:
    """Approach poses for every object: each pose on free floor (outside the inflated obstacles), in line of
    sight of the object and within 10 cm of the standoff; returns (poses, failures)."""
    g, ids = mapper.gaussians, mapper.result().object_ids
    grid = ap.free_space(g.means, g.opacities, index.up_vector(), index.floor_height(), ap.RobotShape())
    poses, failures = 0, []
    for r in index.records():
        points = g.means[ids == r.id]
        a = ap.approach_pose(grid, points, STANDOFF, robot)
        if not a.success:
            assert a.message and a.position is None
            failures.append(r.label)
            continue
        poses += 1
        xy = (grid.rotation @ a.position)[:2]
        rc = grid.to_cell(xy)
        assert grid.cells[tuple(rc)] == ap.FREE, r.label
        assert abs(a.distance - STANDOFF) <= ap.STANDOFF_TOLERANCE_M + 1e-9, (r.label, a.distance)
        up = grid.rotation.T @ [0, 0, 1.0]
        assert abs(float((a.position - grid.to_map(xy)) @ up)) < 1e-9  # on the floor
        target = (points @ grid.rotation.T)[:, :2]
        facing = np.array([np.cos(a.yaw), np.sin(a.yaw)])
        nearest = target[np.argmin(np.linalg.norm(target - xy, axis=1))]
        assert (nearest - xy) @ facing > 0, r.label  # it faces the object
        assert np.isclose(np.linalg.norm(a.orientation), 1.0)
    return poses, failures


def test_approach_poses_on_the_synthetic_room():
    mapper, index = room_map()
    robot = room().keyframe(len(room()) - 1).cam_to_world[:3, 3]
    poses, failures = check_every_object(mapper, index, robot)
    assert "ceiling" in failures  # overhead: no place beside it
    assert poses >= 22, failures
    for name in ("sofa", "table", "chair", "cup", "tv", "plant", "lamp", "bin"):
        assert name not in failures, name


def test_approach_poses_on_replica_office0(replica_office0):
    from tests.test_spatial_queries import office_index

    index, view, mapper = office_index()
    poses, failures = check_every_object(mapper, index, view.cam_to_world[:3, 3])
    assert poses >= 28, failures
    for name in ("sofa", "table", "chair", "tv-screen", "indoor-plant", "bin"):
        assert name not in failures, name


def wall_box(lo, hi, n, rng):
    return rng.uniform(lo, hi, (n, 3))


def test_a_walled_in_object_an_empty_map_and_no_floor_fail_clearly():
    rng = np.random.default_rng(0)
    floor = np.column_stack([rng.uniform(0, 4, 20000), rng.uniform(0, 4, 20000), np.zeros(20000)])
    # A box at the centre, inside four walls 0.3 m around it, taller than the robot; the robot outside them.
    box = wall_box([1.9, 1.9, 0.2], [2.1, 2.1, 0.6], 400, rng)
    walls = np.concatenate([
        wall_box([1.5, 1.5, 0.1], [2.5, 1.55, 2.0], 2000, rng), wall_box([1.5, 2.45, 0.1], [2.5, 2.5, 2.0], 2000, rng),
        wall_box([1.5, 1.5, 0.1], [1.55, 2.5, 2.0], 2000, rng), wall_box([2.45, 1.5, 0.1], [2.5, 2.5, 2.0], 2000, rng),
    ])  # fmt: skip
    means = np.concatenate([floor, box, walls])
    grid = ap.free_space(means, np.ones(len(means)), np.array([0, 0, 1.0]), 0.0, ap.RobotShape())
    walled = ap.approach_pose(grid, box, STANDOFF, robot_position=np.array([0.5, 0.5, 1.0]))
    assert not walled.success and "no free floor the robot can reach" in walled.message
    reachable = ap.approach_pose(grid, walls[:2000], STANDOFF, robot_position=np.array([0.5, 0.5, 1.0]))
    assert reachable.success  # the enclosure itself is approachable from outside
    with pytest.raises(ValueError, match="no Gaussians"):
        ap.free_space(np.zeros((0, 3)), np.zeros(0), np.array([0, 0, 1.0]), 0.0, ap.RobotShape())
    with pytest.raises(ValueError, match="no floor"):
        ap.free_space(walls, np.ones(len(walls)), np.array([0, 0, 1.0]), 0.0, ap.RobotShape())
    with pytest.raises(ValueError, match="robot_height > min_obstacle_height"):
        ap.RobotShape(robot_height=0.05)


def test_offline_monovoc_approach_json_and_plot(capsys, tmp_path):
    plot = tmp_path / "grid.png"
    args = ["approach", "--map", str(room_directory()), "the sofa", "--json", "--plot", str(plot)]
    assert cli_main(args) == 0
    answer = json.loads(capsys.readouterr().out)
    assert answer["success"] and answer["object"]["label"] == "sofa" and answer["pose"]["frame_id"] == "map"
    assert len(answer["pose"]["position"]) == 3 and isinstance(answer["pose"]["yaw"], float)
    # The room's up is estimated (close to +z, not exactly): the yaw is the map's, the one its orientation has.
    x, y, z, w = answer["pose"]["orientation"]
    turn = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)) - answer["pose"]["yaw"]
    assert abs(np.angle(np.exp(1j * turn))) < 1e-3
    assert plot.stat().st_size > 10_000 and plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert cli_main(["approach", "--map", str(room_directory()), "the ceiling"]) == 1
    assert "overhead" in capsys.readouterr().err
    assert cli_main(["approach", "--map", str(room_directory()), "the sofa", "--standoff", "0"]) == 1
    capsys.readouterr()
    assert cli_main(["approach", "--map", str(room_directory()), "the sofa", "--standoff", "inf"]) == 1
    assert "--standoff must be > 0 and <= 100 metres, got inf" in capsys.readouterr().err
    assert cli_main(["approach", "--map", str(tmp_path), "the sofa"]) == 2
    # A plot into a folder that does not exist is refused before the work, in one line.
    capsys.readouterr()
    nowhere = str(tmp_path / "no" / "p.png")
    assert cli_main(["approach", "--map", str(room_directory()), "the sofa", "--plot", nowhere]) == 1
    assert "--plot" in capsys.readouterr().err and not (tmp_path / "no").exists()
    # A folder given as the plot: refused before the work (matplotlib would have written folder.png beside it).
    (tmp_path / "plots").mkdir()
    assert cli_main(["approach", "--map", str(room_directory()), "the sofa", "--plot", str(tmp_path / "plots")]) == 1
    assert "a directory; give the image's name" in capsys.readouterr().err
    assert not (tmp_path / "plots.png").exists() and not any((tmp_path / "plots").iterdir())
    # An image format matplotlib does not write: said in one line after the answer, which is still printed.
    odd = ["approach", "--map", str(room_directory()), "the sofa", "--json", "--plot", str(tmp_path / "g.xyz")]
    assert cli_main(odd) == 1
    out = capsys.readouterr()
    assert json.loads(out.out)["success"] and out.err.startswith("monovoc approach: --plot")


def test_the_upright_frame_of_a_map_whose_up_is_near_z_is_the_map_s_own():
    from monovoc_ros.objects.upright import upright_rotation

    for up in ((1e-5, 2e-6, 1.0), (2e-6, 1e-5, 1.0), (0.0, 0.0, 1.0)):
        np.testing.assert_allclose(upright_rotation(np.array(up)), np.eye(3), atol=1e-4)
    for up in ((0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.3, -0.2, 0.9), (0.0, 0.0, -1.0)):
        rotation = upright_rotation(np.array(up))
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0) and rotation[2] @ up == pytest.approx(np.linalg.norm(up))


def test_the_gaussian_map_type_builds_a_grid():
    """A GaussianMap's arrays are what the node passes (float32 means, activated opacities)."""
    g = room_map()[0].gaussians
    assert isinstance(g, GaussianMap)
    grid = ap.free_space(g.means, g.opacities, np.array([0, 0, 1.0]), 0.0, ap.RobotShape())
    assert (grid.cells == ap.FREE).sum() > 3000 and (grid.cells == ap.OCCUPIED).sum() > 500
