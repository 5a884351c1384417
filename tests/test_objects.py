"""Object geometry (core.object_geometry): percentile boxes, the main-cluster filter, one geometry per result."""

from __future__ import annotations

import numpy as np
import pytest

from monovoc_ros.core.evidence.palette import UNOBSERVED_ID, VOID_ID, Palette
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.mapping import SemanticResult
from monovoc_ros.core.object_geometry import main_cluster_ids, object_geometry, percentile_boxes

A, B = 0x112233, 0x445566


def _map(means: np.ndarray) -> GaussianMap:
    n = len(means)
    return GaussianMap(means, np.full((n, 3), 0.01), np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.9))


def _scene(rng: np.random.Generator) -> tuple[GaussianMap, np.ndarray, np.ndarray]:
    """Object A: a 1 x 2 x 0.5 m block plus 60 of its Gaussians mislabeled across the room (10%, too many for
    the percentile box alone); object B: a small block; one void and one unobserved Gaussian."""
    block = rng.uniform([0, 0, 0], [1, 2, 0.5], (500, 3))
    strays = rng.uniform([3, 5, 0], [6, 8, 3], (60, 3))
    small = rng.uniform([3, 0, 1], [3.5, 0.2, 1.4], (300, 3))
    means = np.vstack([block, strays, small, [[9, 9, 9]], [[8, 8, 8]]])
    ids = np.array([A] * 560 + [B] * 300 + [VOID_ID, UNOBSERVED_ID], np.uint32)
    confidence = np.full(len(ids), 0.9, np.float32)
    return _map(means), ids, confidence


def test_percentile_boxes_ignore_a_few_stray_gaussians():
    rng = np.random.default_rng(0)
    a = rng.uniform([0, 0, 0], [1, 2, 0.5], (500, 3))
    b = rng.uniform([3, 3, 1], [3.5, 3.2, 1.4], (300, 3))
    means = np.vstack([a, b, [[40.0, 40.0, 40.0]], [[9, 9, 9]], [[8, 8, 8]]])  # one mislabeled Gaussian far away
    ids = np.array([A] * 500 + [B] * 300 + [A, VOID_ID, UNOBSERVED_ID], np.uint32)
    objs = percentile_boxes(_map(means), ids)
    assert [o.id for o in objs] == [A, B]
    first = objs[0]
    assert first.rgb == (0x11, 0x22, 0x33) and first.num_gaussians == 501
    np.testing.assert_allclose(first.bbox_min, [0, 0, 0], atol=0.05)
    np.testing.assert_allclose(first.bbox_max, [1, 2, 0.5], atol=0.05)
    np.testing.assert_allclose(first.centroid, [0.5, 1.0, 0.25], atol=0.05)
    np.testing.assert_allclose(objs[1].extent, [0.5, 0.2, 0.4], atol=0.03)


def test_geometry_keeps_the_main_cluster_and_counts_every_gaussian():
    gaussians, ids, confidence = _scene(np.random.default_rng(1))
    boxes_only = {s.id: s for s in percentile_boxes(gaussians, ids)}
    assert boxes_only[A].extent.max() > 4.0  # what the objects topic used to say: the block spans the room

    geometry = object_geometry(gaussians, ids, confidence)
    assert geometry.ids.tolist() == [A, B]
    block, small = geometry.objects
    np.testing.assert_allclose(block.bbox_min, [0, 0, 0], atol=0.05)
    np.testing.assert_allclose(block.bbox_max, [1, 2, 0.5], atol=0.05)
    np.testing.assert_allclose(block.centroid, [0.5, 1.0, 0.25], atol=0.05)
    np.testing.assert_allclose(small.extent, [0.5, 0.2, 0.4], atol=0.03)
    assert (block.num_gaussians, small.num_gaussians) == (560, 300)  # strays are still the object's Gaussians
    assert np.all(geometry.shape_ids[500:560] == UNOBSERVED_ID) and np.all(geometry.shape_ids[:500] == A)
    assert geometry.shape_ids[-2] == UNOBSERVED_ID  # void shapes no object

    # voxel 0: no cluster filter, the percentile boxes of all the object's Gaussians.
    unfiltered = object_geometry(gaussians, ids, confidence, voxel=0)
    np.testing.assert_array_equal(unfiltered.objects[0].bbox_max, boxes_only[A].bbox_max)


def test_unconfident_gaussians_do_not_shape_an_object_unless_nothing_else_does():
    gaussians, ids, confidence = _scene(np.random.default_rng(2))
    confidence[:500] = 0.1  # the block itself is unsure: the strays become its main cluster
    unsure = object_geometry(gaussians, ids, confidence)
    assert unsure.objects[0].bbox_min[1] > 4.0
    confidence[:] = 0.1  # nothing confident: every Gaussian keeps its id rather than the object vanishing
    np.testing.assert_array_equal(
        main_cluster_ids(gaussians.means, ids, confidence), np.where(ids == VOID_ID, UNOBSERVED_ID, ids)
    )
    assert object_geometry(gaussians, ids, confidence).ids.tolist() == [A, B]
    assert object_geometry(gaussians, ids, None).objects[0].bbox_max[1] < 2.1  # None: no confidence filter


def test_a_result_computes_its_geometry_once_per_map():
    gaussians, ids, confidence = _scene(np.random.default_rng(3))
    palette = Palette.from_colors(np.array([[0x11, 0x22, 0x33], [0x44, 0x55, 0x66]], np.uint8))
    result = SemanticResult(palette, ids, confidence, ids != UNOBSERVED_ID)
    first = result.objects(gaussians)
    assert result.objects(gaussians) is first  # shared by the objects topic, markers, index and objects.db
    np.testing.assert_array_equal(first.shape_ids, object_geometry(gaussians, ids, confidence).shape_ids)
    moved = _map(gaussians.means + 1.0)
    again = result.objects(moved)
    assert again is not first
    np.testing.assert_allclose(again.objects[0].centroid, first.objects[0].centroid + 1.0, atol=1e-9)


def test_empty_and_bad_input():
    gmap = _map(np.zeros((2, 3)))
    nothing = np.array([UNOBSERVED_ID, VOID_ID], np.uint32)
    assert percentile_boxes(gmap, nothing) == []
    assert object_geometry(gmap, nothing).objects == ()
    for fn in (percentile_boxes, object_geometry):
        with pytest.raises(ValueError, match="object_ids"):
            fn(gmap, np.zeros(3, np.uint32))


def test_upright_sizes_of_a_new_labelling_are_computed_again_only_where_objects_changed():
    """objects.upright: the sizes of the next labelling of the same map, in the same upright frame, equal the ones
    computed from scratch, whichever objects grew, shrank, appeared or vanished; another map or up: from scratch."""
    from monovoc_ros.objects.upright import upright_geometry

    rng = np.random.default_rng(4)
    n, ids = 20_000, np.array([0x010101 * k for k in range(1, 9)], np.uint32)
    gaussians = _map(rng.uniform(-3, 3, (n, 3)).astype(np.float32))
    confidence = rng.uniform(0, 1, n).astype(np.float32)
    labels = ids[rng.integers(0, len(ids), n)]
    labels[rng.uniform(size=n) < 0.2] = UNOBSERVED_ID
    up = np.array([0.1, -0.95, 0.2])  # a tilted SLAM world: boxes in the upright frame, not the map's

    def sizes(result):
        return result.floor, {k: (v[0].tolist(), v[1]) for k, v in sorted(result.extents.items())}

    previous = upright_geometry(gaussians, object_geometry(gaussians, labels, confidence), up, 1.0)
    for step in range(4):
        labels = labels.copy()
        grown = rng.choice(n, 300, replace=False)
        labels[grown] = ids[step]  # one object grows (and takes Gaussians of others)
        if step == 1:
            labels[labels == ids[5]] = UNOBSERVED_ID  # one vanishes
        if step == 2:
            labels[rng.choice(n, 50, replace=False)] = 0x0A0B0C  # one appears
        geometry = object_geometry(gaussians, labels, confidence)
        got = upright_geometry(gaussians, geometry, up, 1.0, previous)
        assert sizes(got) == sizes(upright_geometry(gaussians, geometry, up, 1.0)), step
        assert got._frame is previous._frame  # the upright centres computed once per map and up
        previous = got
    assert (ids[5] not in got.extents) and (0x0A0B0C in got.extents)
    same = upright_geometry(gaussians, geometry, up, 1.0, got)  # nothing changed: the same sizes, read-only
    assert sizes(same) == sizes(got) and not next(iter(same.extents.values()))[0].flags.writeable
    moved = _map(gaussians.means + np.float32(0.5))  # a map update (another map object), the same up
    on_moved = upright_geometry(moved, object_geometry(moved, labels, confidence), up, 1.0, got)
    assert on_moved._frame is not got._frame
    assert sizes(on_moved) == sizes(upright_geometry(moved, object_geometry(moved, labels, confidence), up, 1.0))
    empty = _map(np.zeros((0, 3), np.float32))
    nothing = upright_geometry(empty, object_geometry(empty, np.zeros(0, np.uint32)), up, 1.0, got)
    assert (nothing.floor, nothing.extents) == (0.0, {})
    tilted = upright_geometry(gaussians, geometry, np.array([0.0, -1.0, 0.1]), 1.0, previous)  # up re-estimated
    assert tilted._frame is not previous._frame
    assert sizes(tilted) == sizes(upright_geometry(gaussians, geometry, np.array([0.0, -1.0, 0.1]), 1.0))
    z_up = upright_geometry(gaussians, geometry, np.array([0.0, 0.0, 1.0]), 1.0, previous)  # the map's own boxes
    assert sizes(z_up)[1] == {s.id: ((s.bbox_max - s.bbox_min).tolist(), float(s.bbox_min[2] - z_up.floor))
                              for s in geometry.objects}  # fmt: skip
