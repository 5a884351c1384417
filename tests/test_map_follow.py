"""Registration of two map versions (core.follow.map_motion) and the per-Gaussian transfer (core.follow.map_follow)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from monovoc_ros.core.follow.map_follow import GRID_CELL_M, FollowConfig, follow_map, nearest_within
from monovoc_ros.core.follow.map_follow_kernels import PointGrid, _cell_keys, cell_order
from monovoc_ros.core.follow.map_motion import MapMotion, estimate_motion, kabsch, worst_block_plane_residual
from monovoc_ros.core.follow.map_updater import (
    MapMotionError,
    motion_refusal,
    pose_mover,
    unmoved_pose,
    update_map,
)
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.mapping import SemanticMapper
from monovoc_ros.core.session import MappingSession
from monovoc_ros.synthetic import churn
from tests.node_scene import assemble, scene_messages, small_scene


def _line_map(means, scales=None) -> GaussianMap:
    means = np.asarray(means, np.float32)
    n = len(means)
    scales = np.full((n, 3), 0.001, np.float32) if scales is None else np.asarray(scales, np.float32)
    quats = np.tile(np.float32([1, 0, 0, 0]), (n, 1))
    return GaussianMap(means, scales, quats, np.full(n, 0.9, np.float32))


def _with_ids(gmap: GaussianMap) -> GaussianMap:
    return replace(gmap, ids=np.arange(len(gmap), dtype=np.int64))


def _truth_rows(old: GaussianMap, new: GaussianMap) -> np.ndarray:
    """Per new Gaussian its old row (the churn generators keep ids when asked)."""
    index = {int(i): k for k, i in enumerate(old.ids)}
    return np.array([index.get(int(i), -1) for i in new.ids])


def test_kabsch_recovers_a_rigid_motion():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    R = churn._rot_z(30.0)
    R, t = kabsch(src, src @ R.T + [1.0, -2.0, 0.5])
    np.testing.assert_allclose(R, churn._rot_z(30.0), atol=1e-12)
    np.testing.assert_allclose(t, [1.0, -2.0, 0.5], atol=1e-12)


def test_transfer_split_children_inherit_pruned_drop_empty_space_starts_at_zero():
    old = _line_map([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], scales=[[0.05, 0.01, 0.01]] + [[0.001] * 3] * 3)
    new = _line_map(
        [
            [3.0, 0, 0],  # Gaussian 3, re-ordered first
            [0.025, 0, 0],  # Gaussian 0 split along its major axis: both children inherit it
            [-0.025, 0, 0],
            [1.004, 0, 0],  # Gaussian 1 nudged by 4 mm
            [5.0, 0, 0],  # a new Gaussian in empty space
        ],  # Gaussian 2 was pruned
        scales=[[0.001] * 3, [0.05 / 1.6, 0.01, 0.01], [0.05 / 1.6, 0.01, 0.01], [0.001] * 3, [0.001] * 3],
    )
    follow = follow_map(old, new)
    assert motion_refusal(follow, FollowConfig()) == ""
    np.testing.assert_array_equal(follow.sources, [3, 0, 0, 1, -1])
    assert follow.by_position == 4 and follow.by_id == 0


def test_ids_win_and_the_rest_follow_the_moved_position():
    scene = small_scene()
    old = _with_ids(scene.gaussians)
    moved = churn.then(churn.densify(old, keep_ids=True, seed=1), churn.loop_closure, keep_ids=True, seed=2)
    new = moved.gaussians
    follow = follow_map(old, new)
    truth = _truth_rows(old, new)
    by_id = truth >= 0
    np.testing.assert_array_equal(follow.sources[by_id], truth[by_id])
    assert follow.motion.by == "ids" and follow.by_id == int(by_id.sum())
    # New ids (the second child of each split) inherit by position, after the motion the id pairs give.
    children = np.flatnonzero(~by_id)
    assert follow.by_position >= 0.95 * len(children)
    assert follow.motion.rotation_deg == pytest.approx(2.0, abs=0.01)


@pytest.mark.parametrize("kind", ["loop", "bend"])
def test_registration_follows_rigid_and_bent_maps_without_ids(kind):
    scene = small_scene()
    old = _with_ids(scene.gaussians)
    make = churn.loop_closure if kind == "loop" else churn.drift_correction
    new_with_ids = make(old, keep_ids=True, seed=3).gaussians
    truth = _truth_rows(old, new_with_ids)
    new = replace(new_with_ids, ids=None)
    follow = follow_map(replace(old, ids=None), new)
    assert motion_refusal(follow, FollowConfig()) == "" and follow.motion.by == "registration"
    where = np.empty((len(old), 3))
    where[truth] = new.means
    err = np.linalg.norm(follow.motion.apply(old.means) - where, axis=1)
    if kind == "loop":
        assert follow.motion.rotation_deg == pytest.approx(2.0, abs=0.05)
        assert np.percentile(err, 99) < 0.003
        assert np.mean(follow.sources == truth) > 0.9
    else:
        assert np.median(err) < 0.01
    # Nothing crosses objects: the object of the source is the object of the new Gaussian.
    obj = scene.gaussian_object
    hit = follow.sources >= 0
    assert hit.mean() > (0.95 if kind == "loop" else 0.85)
    same = obj[follow.sources[hit]] == obj[truth[hit]]
    assert same.mean() > (0.995 if kind == "loop" else 0.97)


def test_absurd_motions_are_refused():
    scene = small_scene()
    old = scene.gaussians
    far = churn.loop_closure(old, degrees=0.0, translation=(25.0, 0.0, 0.0)).gaussians
    wide = FollowConfig(motion=replace_motion(start_trim=50.0))
    assert "moves part of the map" in motion_refusal(follow_map(old, far, wide), wide)
    noise = np.random.default_rng(0).uniform(-50, 50, (len(old), 3))
    unrelated = replace(old, means=noise.astype(np.float32))
    assert motion_refusal(follow_map(old, unrelated), FollowConfig()) != ""
    # beyond the first trim distance: nothing pairs up
    assert motion_refusal(follow_map(old, far), FollowConfig()) != ""


def test_a_map_whose_centres_pile_up_is_refused_without_registering_it():
    """Thousands of centres in one 10 cm cell (every Gaussian at one point): no SLAM map looks like that, and the
    registration's neighbour searches scan a cell whole per query (30k at one point took ~23 s). Refused at once as a
    registration that did not converge; a map as crowded as a real one still registers."""
    old = replace(small_scene().gaussians, ids=None)
    piled = replace(old, means=np.repeat(old.means[:1], len(old), axis=0))
    follow = follow_map(old, piled)
    assert not follow.motion.converged and follow.motion.inliers == 0.0
    assert motion_refusal(follow, FollowConfig()) == "the registration of the old map to the new one did not converge"
    moved = churn.loop_closure(old, degrees=0.5, seed=3).gaussians
    assert motion_refusal(follow_map(old, moved), FollowConfig()) == ""


def replace_motion(**changes):
    from monovoc_ros.core.follow.map_motion import MotionConfig

    return replace(MotionConfig(), **changes)


def test_nearest_within_uses_each_query_radius():
    pts = np.array([[0.0, 0, 0], [1, 0, 0]])
    q = np.array([[0.05, 0, 0], [0.05, 0, 0], [0.9, 0, 0]])
    np.testing.assert_array_equal(nearest_within(pts, q, np.array([0.1, 0.01, 0.2])), [0, -1, 1])
    np.testing.assert_array_equal(nearest_within(np.zeros((0, 3)), q, np.ones(3)), [-1, -1, -1])


def test_identity_motion_moves_nothing_and_poses_follow_a_loop_closure():
    pts = np.random.default_rng(1).normal(size=(100, 3))
    np.testing.assert_array_equal(MapMotion().apply(pts), pts)
    scene = small_scene()
    closure = churn.loop_closure(scene.gaussians, seed=4)
    motion = estimate_motion(scene.gaussians.means, closure.gaussians.means)
    pose = scene.keyframe(0).cam_to_world
    np.testing.assert_allclose(motion.move_pose(pose, scene.gaussians.means), closure.move_pose(pose), atol=2e-3)


def test_mapper_refuses_an_absurd_update_and_keeps_its_state():
    scene = small_scene()
    keyframes = assemble(scene_messages()[:3])
    mapper = SemanticMapper(scene.gaussians)
    for kf in keyframes:
        mapper.integrate(kf)
    before = mapper.state.total_weight.copy()
    far = churn.loop_closure(scene.gaussians, degrees=0.0, translation=(30.0, 0, 0)).gaussians
    with pytest.raises(MapMotionError):
        update_map(mapper, far)
    assert mapper.gaussians is scene.gaussians and np.array_equal(mapper.state.total_weight, before)
    session = MappingSession(mapper=mapper)
    assert not session.add_map(far) and session.stats.rejected["map_motion"] == 1
    # A real loop closure is applied and the labelled evidence carried over.
    assert session.add_map(churn.loop_closure(scene.gaussians).gaussians)
    assert session.stats.map_update_carried_share > 0.99


def test_kernels_equal_their_plain_twins():
    from monovoc_ros.core.follow.map_follow import nearest_within_reference
    from monovoc_ros.core.map.gaussians import covariances_reference

    rng = np.random.default_rng(7)
    pts = rng.uniform(-1, 1, (20000, 3))
    queries = np.concatenate([pts[:3000] + rng.normal(0, 0.01, (3000, 3)), rng.uniform(-1.5, 1.5, (3000, 3))])
    radius = rng.uniform(0.0, 0.12, len(queries))
    plain = nearest_within_reference(pts, queries, radius)
    far = np.array([[5.0, 5.0, 5.0]])
    for cell in (0.03, GRID_CELL_M):  # cells smaller and about as large as the radii
        fast = nearest_within(pts, queries, radius, cell=cell)
        np.testing.assert_array_equal(fast >= 0, plain >= 0)
        hit = fast >= 0
        d_fast = np.linalg.norm(pts[fast[hit]] - queries[hit], axis=1)
        d_plain = np.linalg.norm(pts[plain[hit]] - queries[hit], axis=1)
        np.testing.assert_array_equal(d_fast, d_plain)  # the same nearest (ties may name another row)
        assert hit.sum() > 2000
        # A radius many cells wide still finds the nearest point (the ring search runs farther out).
        assert (
            nearest_within(pts, far, np.array([20.0]), cell=cell)[0]
            == nearest_within_reference(pts, far, np.array([20.0]))[0]
        )

    # One grid searched again and again (the registration's targets), at the radii its ICP and field use.
    grid = PointGrid.build(pts, 0.1)
    for r in (0.5, 0.2, 0.05, 0.02):
        fast = grid.nearest(queries, np.full(len(queries), r))
        plain = nearest_within_reference(pts, queries, np.full(len(queries), r))
        np.testing.assert_array_equal(fast >= 0, plain >= 0)
        hit = fast >= 0
        d_fast = np.linalg.norm(pts[fast[hit]] - queries[hit], axis=1)
        np.testing.assert_array_equal(d_fast, np.linalg.norm(pts[plain[hit]] - queries[hit], axis=1))

    scene = small_scene()
    motion = estimate_motion(scene.gaussians.means, churn.drift_correction(scene.gaussians).gaussians.means)
    assert np.any(motion.offsets)
    np.testing.assert_allclose(motion.apply(pts), motion.apply_reference(pts), rtol=0, atol=1e-12)

    g = scene.gaussians
    plain_cov = covariances_reference(g.quats, g.scales)
    np.testing.assert_allclose(g.covariances, plain_cov, rtol=0, atol=1e-6 * np.abs(plain_cov).max())  # float32 ulps


def test_cells_numbered_on_their_box_sort_as_the_packed_keys():
    """cell_order's compact keys order the points exactly as a stable sort of `_key`'s 63-bit keys (cells x-major),
    negative coordinates, a single point and a 80 km wide box included; NaN and cells beyond the packing's reach fall
    back to the packed keys."""
    rng = np.random.default_rng(11)
    cases = [
        rng.uniform(-3.0, 4.0, (5000, 3)),
        rng.normal(0.0, 0.02, (3000, 3)) - 7.0,  # a few cells, far below zero
        np.array([[0.31, -0.2, 5.0]]),
        np.array([[0.0, 0.0, 0.0], [4e4, 0.0, 0.0], [0.0, -4e4, 4e4]]),  # keys of ~59 bits: four passes
        np.array([[0.0, 0.0, 0.0], [np.nan, 0.0, 1.0], [0.2, 0.1, 0.0]]),
        # Cells beyond the packing's +-2**20 (52 km at 5 cm): distinct cells share a packed key, the table's key.
        np.array([[0.01, 0.01, 2**20 * 0.05 + 0.01], [0.01, 0.06, -(2**20) * 0.05 + 0.01], [0.0, 0.0, 0.0]]),
    ]
    for points in cases:
        for cell in (0.05, 0.3):
            keys = _cell_keys(points, cell)
            order, sorted_keys = cell_order(points, cell)
            np.testing.assert_array_equal(order, np.argsort(keys, kind="stable"))
            same_cell = keys[order][1:] == keys[order][:-1]
            np.testing.assert_array_equal(sorted_keys[1:] == sorted_keys[:-1], same_cell)
    grid = PointGrid.build(np.zeros((0, 3)), 0.1)  # an empty grid finds nothing
    assert grid.nearest(np.zeros((2, 3)), 1.0).tolist() == [-1, -1]
    assert [len(a) for a in cell_order(np.zeros((0, 3)), 0.05)] == [0, 0]
    far = cases[-1][:2]  # two points whose cells share a packed key: both found, as with the packed keys alone
    assert PointGrid.build(far, 0.05).nearest(far, 0.01).tolist() == [0, 1]


def test_gaussians_with_non_finite_means_neither_take_nor_give_evidence():
    """The rasterizer culls a Gaussian with a NaN mean; a map update must not crash on one either."""
    scene = small_scene()
    means = np.array(scene.gaussians.means)
    means[5] = np.nan
    old = replace(scene.gaussians, means=means)
    moved = churn.loop_closure(scene.gaussians, degrees=1.0, keep_ids=True).gaussians
    new_means = np.array(moved.means)
    new_means[0] = np.nan
    closure_map = replace(moved, means=new_means)
    new = replace(closure_map, ids=None)
    follow = follow_map(old, new)
    assert motion_refusal(follow, FollowConfig()) == ""
    broken = np.flatnonzero(~np.isfinite(new.means).all(axis=1))
    assert len(broken) == 1 and follow.sources[broken[0]] == -1
    assert 5 not in set(follow.sources.tolist()) and np.mean(follow.sources >= 0) > 0.95
    with_ids = follow_map(_with_ids(old), closure_map)
    assert motion_refusal(with_ids, FollowConfig()) == "" and with_ids.motion.by == "ids"


def test_a_sampled_target_map_still_recognises_a_rigid_update():
    """Beyond target_sample new centres the targets are a sample, farther apart than the map's own centres:
    a densified, unmoved map is still explained by the rigid fit (no field), a bent one is not."""
    scene = small_scene()
    old = scene.gaussians.means
    config = replace_motion(target_sample=len(old) // 4)
    densified = churn.densify(scene.gaussians, seed=2).gaussians
    rigid = estimate_motion(old, densified.means, config)
    assert rigid.converged and not np.any(rigid.offsets) and rigid.max_displacement(old) < 0.005
    bent = estimate_motion(old, churn.drift_correction(scene.gaussians).gaussians.means, config)
    assert bent.converged and np.any(bent.offsets)


def _long_map(room: GaussianMap, copies: int) -> GaussianMap:
    """`room` repeated side by side along x (a floor of rooms), with ids."""
    width = float(np.ptp(room.means[:, 0])) + 1.0
    rows = np.arange(copies * len(room)) % len(room)
    out = replace(room, ids=None).subset(rows)
    shift = np.zeros((len(rows), 3), np.float32)
    shift[:, 0] = (np.arange(len(rows)) // len(room)) * width
    return _with_ids(replace(out, means=out.means + shift))


def test_a_sampled_target_map_sees_a_small_bend_off_the_planes():
    """With sampled targets the residual distance is mostly the sample's spacing, which hid a bend of a few mm
    over a long map (office_0 tiled to 1M, 0.1 degree: 93% of the new Gaussians took their own old Gaussian's
    evidence, 99% with the field; here 89% and 96%, and 98% for an unmoved map). The blocks' point-to-plane
    residuals see it; a densified unmoved map and a rigid loop closure stay rigid."""
    old = _long_map(small_scene().gaussians, 6)
    motion = replace_motion(target_sample=len(old) // 4)
    densified = churn.densify(old, split=0.02, prune=0.01, seed=3, keep_ids=True).gaussians
    cases = {
        "unmoved": densified,
        "loop": churn.loop_closure(densified, keep_ids=True, seed=3).gaussians,
        "bend": churn.drift_correction(
            densified, degrees=0.1, translation=(0.01, 0.01, 0.0), keep_ids=True, seed=3
        ).gaussians,
    }

    def follow(new: GaussianMap, motion_config) -> tuple[bool, float]:
        """(whether a field was fitted, share of the new Gaussians whose source is their own old Gaussian)."""
        result = follow_map(replace(old, ids=None), replace(new, ids=None), FollowConfig(motion=motion_config))
        truth = _truth_rows(old, new)
        known = truth >= 0
        return bool(np.any(result.motion.offsets)), float(np.mean(result.sources[known] == truth[known]))

    for kind in ("unmoved", "loop"):
        bent, exact = follow(cases[kind], motion)
        assert not bent and exact > 0.96, kind  # 98% when written
    bent, exact = follow(cases["bend"], motion)
    distance_only, exact_before = follow(cases["bend"], replace(motion, rigid_plane_residual=np.inf))
    assert bent and not distance_only
    assert exact > 0.94 and exact > exact_before + 0.05  # 96% and 89% when written


def test_worst_block_plane_residual_is_the_largest_block_median_off_the_planes():
    rng = np.random.default_rng(0)
    points = np.concatenate([rng.uniform(0, 3, (300, 3)), rng.uniform(0, 3, (300, 3)) + [8.0, 0, 0]])
    normals = np.tile([0.0, 0.0, 1.0], (600, 1))
    residuals = rng.normal(0, 0.004, (600, 3))
    residuals[:300, 2] = 0.001  # block one: 1 mm off its planes; block two: 3 mm
    residuals[300:, 2] = -0.003
    normals[::2] = 0.0  # pairs without a flat target do not count, wherever they are
    residuals[::2, 2] = 0.5
    assert worst_block_plane_residual(points, residuals, normals, 4.0, 100) == pytest.approx(0.003)
    assert worst_block_plane_residual(points[:300], residuals[:300], normals[:300], 4.0, 100) == pytest.approx(0.001)
    assert worst_block_plane_residual(points, residuals, normals, 4.0, 200) == 0.0  # no block holds 200 flat pairs


def test_move_poses_equals_move_pose_around_each_camera():
    """The batched pose move (one matrix product per chunk of poses) against its plain twin: a ball query
    and `move_pose` per pose; a camera with too little support around it takes the rigid rotation and the
    motion of its centre."""
    from scipy.spatial import cKDTree

    scene = small_scene()
    old = scene.gaussians
    motion = follow_map(old, churn.drift_correction(old, seed=3).gaussians).motion
    assert np.any(motion.offsets)
    support = old.means[::7].astype(np.float64)
    moved = motion.apply(support)
    rng = np.random.default_rng(1)
    poses = np.tile(np.eye(4), (150, 1, 1))
    for T in poses:
        T[:3, :3] = kabsch(rng.normal(size=(4, 3)), rng.normal(size=(4, 3)))[0]
    poses[:, :3, 3] = old.means.mean(axis=0) + rng.uniform(-4, 4, (150, 3))
    poses[-1, :3, 3] = [40.0, 0.0, 0.0]  # nothing within reach
    tree = cKDTree(support)
    expected = []
    for T in poses:
        near = tree.query_ball_point(T[:3, 3], 1.5)
        expected.append(motion.move_pose(T, support[near], moved[near]))
    np.testing.assert_allclose(motion.move_poses(poses, support, moved, 1.5), np.array(expected), atol=1e-9)
    assert len(tree.query_ball_point(poses[-1, :3, 3], 1.5)) == 0


def test_unmoved_pose_is_the_pose_a_map_update_moves_to_the_given_one():
    """A keyframe posed in a map not applied yet goes into the map in use with the pose the update will move
    back to its own (the logged poses' mover): one rigid motion exactly, a bent map to a micrometre."""
    scene = small_scene()
    old = scene.gaussians
    bent = follow_map(old, churn.drift_correction(old, seed=3).gaussians).motion
    rigid = MapMotion(
        rotation=kabsch(np.eye(3), np.eye(3) + 0.05)[0], translation=np.array([0.3, -0.1, 0.05]), by="registration"
    )
    rng = np.random.default_rng(4)
    for motion in (bent, rigid):
        mover = pose_mover(old.means, motion)
        assert mover is not None
        for _ in range(20):
            T = np.eye(4)
            T[:3, :3] = kabsch(rng.normal(size=(4, 3)), rng.normal(size=(4, 3)))[0]
            T[:3, 3] = old.means.mean(axis=0) + rng.uniform(-3, 3, 3)
            back = unmoved_pose(mover, T)
            np.testing.assert_allclose(mover(back[None])[0], T, atol=1e-6)
            assert np.linalg.norm(back[:3, 3] - T[:3, 3]) > 0.01  # it did move
    assert pose_mover(old.means, MapMotion()) is None  # an identity: poses stay


def test_surface_normals_equal_their_plain_twin():
    from monovoc_ros.core.follow.map_motion import surface_normals, surface_normals_reference

    rng = np.random.default_rng(2)
    quats = rng.normal(size=(5000, 4)) * rng.uniform(0.5, 2.0, (5000, 1))  # not unit: both normalize
    scales = rng.uniform(0.001, 0.05, (5000, 3))
    scales[:100] = 0.01  # ties: the first smallest axis, as a stable sort takes it
    scales[100:200, 1] = scales[100:200, 0]
    scales[200:210, 0] = np.nan  # NaN scales sort last: the smallest of the others, flat only if two are finite
    scales[210:220, 2] = np.nan
    scales[220:230, :2] = np.nan
    scales[230:240] = np.inf
    got, want = surface_normals(quats, scales), surface_normals_reference(quats, scales)
    np.testing.assert_allclose(got, want, atol=1e-12)
    assert np.any(got[200:220] != 0) and not np.any(got[220:240])


def test_the_fields_sums_equal_their_plain_twin_bit_for_bit():
    """One pass over the sample's points and nodes adds the same products in the same order as numpy's bincount."""
    from monovoc_ros.core.follow.map_follow_kernels import field_sums
    from monovoc_ros.core.follow.map_motion import field_sums_reference

    rng = np.random.default_rng(4)
    points, n_nodes = 4000, 60
    flat = rng.integers(0, n_nodes - 5, (points, 8))  # the last nodes support no point: zero sums
    weights = rng.random((points, 8)) * (rng.random((points, 1)) < 0.8)  # outliers weigh nothing
    A, Ar = rng.normal(size=(points, 3, 3)), rng.normal(size=(points, 3))
    got = field_sums(flat, weights, A, Ar, n_nodes)
    for fast, plain in zip(got, field_sums_reference(flat, weights, A, Ar, n_nodes), strict=True):
        np.testing.assert_array_equal(fast, plain)
    assert not got[2][-5:].any()


def test_the_labels_follow_their_rows_through_a_map_update():
    """After an update the mapper's per-Gaussian labels are gathered from the old ones by source (rows are carried
    whole), not computed again over the new map: the same as labelling the carried evidence, keyframes after it
    included."""
    scene = small_scene()
    keyframes = assemble(scene_messages()[:4])
    mapper = SemanticMapper(scene.gaussians)
    for kf in keyframes[:2]:
        mapper.integrate(kf)
    mapper.result()  # the labels kept from here on
    mapper.integrate(keyframes[2])  # rows to relabel before they are carried
    new = churn.densify(scene.gaussians, split=0.05, prune=0.05, jitter=0.002, seed=3).gaussians
    update_map(mapper, new)
    carried = mapper._labels
    assert carried is not None
    for got, want in zip(carried, mapper.state.labels(), strict=True):
        np.testing.assert_array_equal(got, want)
    assert carried[0].dtype == np.uint32 and carried[1].dtype == np.float32
    mapper.integrate(keyframes[3])
    result = mapper.result()
    ids, confidence = mapper.state.labels()
    np.testing.assert_array_equal(result.object_ids, ids)
    np.testing.assert_array_equal(result.confidence, confidence)
    assert (ids != 0xFFFFFFFF).sum() > 100
