"""The fast and the incremental object geometry (core.object_geometry) held to the plain reference twin."""

from __future__ import annotations

import numpy as np
import pytest

from monovoc_ros.core.evidence.palette import UNOBSERVED_ID, VOID_ID, Palette
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.mapping import SemanticResult
from monovoc_ros.core.object_geometry import (
    ObjectGeometry,
    main_cluster_ids,
    main_cluster_ids_reference,
    object_geometry,
    object_geometry_reference,
    percentile_boxes,
    percentile_boxes_reference,
)
from tests.geometry import assert_same_geometry


def _map(means: np.ndarray, rng: np.random.Generator) -> GaussianMap:
    n = len(means)
    return GaussianMap(means, np.full((n, 3), 0.01), np.tile([1.0, 0, 0, 0], (n, 1)), rng.uniform(0.05, 1, n))


def _room(rng: np.random.Generator, n: int = 6000, objects: int = 12) -> tuple[GaussianMap, np.ndarray, np.ndarray]:
    """Objects of one to three blobs each (so clusters compete), 10% of the Gaussians mislabeled anywhere,
    some void and unobserved; confidence uniform in [0, 1]."""
    colors = rng.choice(VOID_ID, objects, replace=False).astype(np.uint32)
    blob_object = np.concatenate([np.arange(objects), rng.integers(0, objects, objects)])
    centres = rng.uniform(-4, 4, (2 * objects, 3))
    blob = rng.integers(0, blob_object.size, n)
    means = centres[blob] + rng.normal(0, rng.uniform(0.05, 0.4, blob_object.size)[blob, None], (n, 3))
    ids = colors[blob_object[blob]]
    stray = rng.random(n) < 0.1
    ids[stray] = rng.choice(colors, stray.sum())
    ids[rng.random(n) < 0.05] = VOID_ID
    ids[rng.random(n) < 0.05] = UNOBSERVED_ID
    return _map(means, rng), ids, rng.random(n).astype(np.float32)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize(
    "options", [{}, {"voxel": 0.1}, {"voxel": 0.5, "min_confidence": 0.6}, {"voxel": 0}, {"min_confidence": 0}]
)
def test_the_full_computation_equals_the_reference(seed, options):
    gaussians, ids, confidence = _room(np.random.default_rng(seed))
    for conf in (confidence, None):
        assert_same_geometry(
            object_geometry(gaussians, ids, conf, **options), object_geometry_reference(gaussians, ids, conf, **options)
        )


@pytest.mark.parametrize("min_share", [1.0, 0.3, 0.0, 2.0])
def test_main_cluster_ids_and_percentile_boxes_equal_the_reference(min_share):
    gaussians, ids, confidence = _room(np.random.default_rng(7))
    np.testing.assert_array_equal(
        main_cluster_ids(gaussians.means, ids, confidence, min_share=min_share),
        main_cluster_ids_reference(gaussians.means, ids, confidence, min_share=min_share),
    )
    got, want = percentile_boxes(gaussians, ids), percentile_boxes_reference(gaussians, ids)
    assert_same_geometry(ObjectGeometry(tuple(got), ids), ObjectGeometry(tuple(want), ids))


def _changes(rng: np.random.Generator, ids: np.ndarray, confidence: np.ndarray):
    """A sequence of (what, labels, confidence, the objects it changed), each a few changes from the one before."""
    c = np.unique(ids[ids < VOID_ID])
    ids, confidence = ids.copy(), confidence.copy()

    def step(name, *changed):
        return name, ids.copy(), confidence.copy(), {int(x) for x in changed}

    rows = rng.choice(np.flatnonzero(ids == c[4]), 40, replace=False)  # a few Gaussians change object
    ids[rows] = c[5]
    yield step("relabelled", c[4], c[5])
    near = np.flatnonzero((ids == c[6]) & (np.abs(confidence - 0.3) < 0.1))  # crossing the threshold
    confidence[near] = 0.6 - confidence[near]
    yield step("confidence crossed", c[6])
    yield step("nothing changed")
    ids[ids == c[0]] = UNOBSERVED_ID
    yield step("emptied", c[0])
    new = rng.choice(len(ids), 300, replace=False)
    old = np.unique(ids[new])
    ids[new] = 0x0A0B0C
    yield step("new object", 0x0A0B0C, *old)
    confidence[ids == c[1]] = 0.05  # the cluster filter leaves nothing: the object keeps all its Gaussians
    yield step("unconfident object", c[1])
    ids[ids == c[2]] = VOID_ID
    confidence[ids == c[3]] = 0.9
    yield step("voided", c[2], c[3])


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("options", [{}, {"voxel": 0}, {"voxel": 0.1, "min_confidence": 0.5}])
def test_updates_after_label_changes_equal_the_full_computation(seed, options):
    rng = np.random.default_rng(seed)
    gaussians, ids, confidence = _room(rng)
    geometry = object_geometry(gaussians, ids, confidence, **options)
    unsure = np.unique(ids[ids < VOID_ID])[1]
    for name, labels, conf, changed in _changes(rng, ids, confidence):
        updated = object_geometry(gaussians, labels, conf, previous=geometry, **options)
        assert_same_geometry(updated, object_geometry_reference(gaussians, labels, conf, **options))
        if name == "nothing changed":
            assert updated.objects is geometry.objects
        elif name == "unconfident object":
            lone = labels == unsure
            assert lone.any() and np.all(updated.shape_ids[lone] == unsure)
        before = {s.id: s for s in geometry.objects}
        assert all(before[s.id] is s for s in updated.objects if s.id not in changed)  # taken over
        geometry = updated


def test_an_update_takes_over_only_the_same_map_and_settings():
    rng = np.random.default_rng(11)
    gaussians, ids, confidence = _room(rng)
    geometry = object_geometry(gaussians, ids, confidence)
    moved = _map(gaussians.means + 0.3, rng)  # a map update: a new map object, everything again
    assert_same_geometry(
        object_geometry(moved, ids, confidence, previous=geometry), object_geometry_reference(moved, ids, confidence)
    )
    coarse = object_geometry(gaussians, ids, confidence, voxel=0.5, previous=geometry)
    assert_same_geometry(coarse, object_geometry_reference(gaussians, ids, confidence, voxel=0.5))
    assert_same_geometry(
        object_geometry(gaussians, ids, None, previous=geometry), object_geometry_reference(gaussians, ids, None)
    )
    ids2 = ids.copy()
    ids2[:50] = ids[60]
    again = object_geometry(gaussians, ids2, confidence, previous=geometry)
    ids2[:] = UNOBSERVED_ID  # the caller's array may change afterwards: the geometry holds its own labels
    assert_same_geometry(
        object_geometry(gaussians, ids, confidence, previous=again),
        object_geometry_reference(gaussians, ids, confidence),
    )


def test_too_large_a_map_is_refused_as_before():
    rng = np.random.default_rng(5)
    gaussians, ids, confidence = _room(rng, n=2000)
    means = gaussians.means.copy()
    means[0] = [3000.0, 0, 0]  # 12000 voxels of 0.25 m from the rest
    far = _map(means, rng)
    confidence[0] = 0.1  # not confident: not among the keys, which fit
    geometry = object_geometry(far, ids, confidence)
    assert_same_geometry(geometry, object_geometry_reference(far, ids, confidence))
    ids[0], confidence[0] = ids[1] if ids[1] < VOID_ID else 0x0A0B0C, 0.9  # now it is
    for compute in (
        lambda: object_geometry(far, ids, confidence, previous=geometry),
        lambda: object_geometry(far, ids, confidence),
        lambda: object_geometry_reference(far, ids, confidence),
    ):
        with pytest.raises(ValueError, match="map too large"):
            compute()


def test_a_result_starts_from_the_geometry_of_the_one_it_follows():
    rng = np.random.default_rng(13)
    gaussians, ids, confidence = _room(rng)
    palette = Palette.from_colors(np.array([[1, 2, 3]], np.uint8))
    labellings = [(labels, conf) for _, labels, conf, _ in _changes(rng, ids, confidence)]
    first = SemanticResult(palette, ids, confidence, ids != UNOBSERVED_ID)
    first.objects(gaussians)
    previous = first
    for k, (labels, conf) in enumerate(labellings):
        result = SemanticResult(palette, labels, conf, labels != UNOBSERVED_ID)
        result.follows(previous)
        assert result._before is not None and result._before._objects is not None  # never one never computed
        if k % 2 == 0:  # every other result is never asked for its objects
            assert_same_geometry(result.objects(gaussians), object_geometry_reference(gaussians, labels, conf))
            assert result._before is None  # the previous result is let go
        previous = result


def test_the_box_kernel_takes_numpys_percentiles_bit_for_bit():
    from monovoc_ros.core.object_geometry_kernels import percentile_boxes as kernel

    rng = np.random.default_rng(7)
    sizes = [1, 2, 3, 7, 99, 100, 101, 257, 1000]
    means = rng.normal(0, 3, (sum(sizes), 3)).astype(np.float32)
    means[:50] = np.round(means[:50])  # ties
    opacities = rng.uniform(0, 1, len(means)).astype(np.float32)
    opacities[:3] = 0  # the first objects' weights sum to zero: plain means
    bounds = np.concatenate([[0], np.cumsum(sizes)])
    low, high, centroid = (np.empty((len(sizes), 3)) for _ in range(3))
    kernel(means.astype(np.float64), opacities.astype(np.float64), bounds, 0.01, 0.99, low, high, centroid)
    for k in range(len(sizes)):
        pts = means[bounds[k] : bounds[k + 1]].astype(np.float64)
        lo, hi = np.percentile(pts, [1.0, 99.0], axis=0)
        np.testing.assert_array_equal(low[k], lo)
        np.testing.assert_array_equal(high[k], hi)
    np.testing.assert_array_equal(centroid[0], means[0])  # zero weight: the plain mean, in row order
    np.testing.assert_array_equal(centroid[1], (means[1].astype(np.float64) + means[2]) / 2)


def test_the_box_kernel_selects_numpys_quantiles_on_ties_and_constant_axes():
    """The kernel finds the two order statistics a percentile reads by selection, not a sort: any quantile,
    objects of one value per axis, many ties. An axis with NaN (which no map from the topic has) is sorted, NaN
    last, and its percentiles read the values there (numpy's would be NaN: a box that could not be published)."""
    from monovoc_ros.core.object_geometry_kernels import percentile_boxes as kernel

    rng = np.random.default_rng(3)
    for trial in range(120):
        sizes = rng.integers(1, 400, rng.integers(1, 12)).tolist()
        means = rng.normal(0, 3, (sum(sizes), 3)).astype(np.float32)
        if trial % 2:
            means = np.round(means)  # ties
        if trial % 5 == 0:
            means[:, 1] = 1.0  # one value
        q = sorted(rng.uniform(0, 1, 2)) if trial % 3 == 0 else [0.01, 0.99]
        bounds = np.concatenate([[0], np.cumsum(sizes)])
        low, high, centroid = (np.empty((len(sizes), 3)) for _ in range(3))
        opacities = np.ones(len(means), np.float32)
        kernel(means.astype(np.float64), opacities.astype(np.float64), bounds, q[0], q[1], low, high, centroid)
        for k in range(len(sizes)):
            lo, hi = np.quantile(means[bounds[k] : bounds[k + 1]].astype(np.float64), q, axis=0)
            np.testing.assert_array_equal(low[k], lo, err_msg=f"trial {trial}, object {k}")
            np.testing.assert_array_equal(high[k], hi, err_msg=f"trial {trial}, object {k}")
    means = rng.normal(0, 1, (50, 3)).astype(np.float32)
    means[7, 2] = np.nan
    low, high, centroid = (np.empty((1, 3)) for _ in range(3))
    kernel(means.astype(np.float64), np.ones(50), np.array([0, 50]), 0.01, 0.99, low, high, centroid)
    ordered = np.sort(means[:, 2].astype(np.float64))  # NaN last: the 1st percentile reads two finite values
    np.testing.assert_array_equal(low[0, 2], ordered[0] + (ordered[1] - ordered[0]) * 0.49)
    np.testing.assert_array_equal(low[0, :2], np.quantile(means[:, :2].astype(np.float64), 0.01, axis=0))


def test_the_maps_voxel_order_and_each_labellings_own_keys_give_the_same_geometry():
    """Main clusters of many Gaussians come from the map's voxel order (made once, kept by later labellings), of
    few from their own keys' sort, of a map with a centre that is not finite always from their own: all equal
    to the reference."""
    rng = np.random.default_rng(17)
    gaussians, ids, confidence = _room(rng, n=8000, objects=40)
    geometry = object_geometry(gaussians, ids, confidence)
    voxels = geometry._labelling.voxels
    assert voxels is not None and voxels._made  # made by the full computation (most of the map)
    assert_same_geometry(geometry, object_geometry_reference(gaussians, ids, confidence))
    objects, counts = np.unique(ids[ids < VOID_ID], return_counts=True)
    small = objects[np.argmin(counts)]
    labels = ids.copy()
    labels[rng.choice(np.flatnonzero(ids == small), 5, replace=False)] = UNOBSERVED_ID  # one small object
    updated = object_geometry(gaussians, labels, confidence, previous=geometry)
    assert updated._labelling.voxels is voxels
    assert 8 * np.count_nonzero(ids == small) < len(labels)  # its own keys
    assert_same_geometry(updated, object_geometry_reference(gaussians, labels, confidence))
    labels[labels < VOID_ID] = np.roll(labels[labels < VOID_ID], 7)  # most objects change: the map's order
    assert_same_geometry(
        object_geometry(gaussians, labels, confidence, previous=updated),
        object_geometry_reference(gaussians, labels, confidence),
    )
    only_small = np.where(ids == small, ids, UNOBSERVED_ID)  # a first labelling of few Gaussians: no voxel order
    first = object_geometry(gaussians, only_small, confidence)
    assert not first._labelling.voxels._made
    later = object_geometry(gaussians, ids, confidence, previous=first)  # most of the map: made here
    assert later._labelling.voxels is first._labelling.voxels and later._labelling.voxels._made
    assert_same_geometry(later, object_geometry_reference(gaussians, ids, confidence))
    means = gaussians.means.copy()
    means[3] = np.nan
    broken = _map(means, rng)
    ids[3] = UNOBSERVED_ID
    geometry = object_geometry(broken, ids, confidence)
    assert geometry._labelling.voxels.sorted(broken.means) is None
    assert_same_geometry(geometry, object_geometry_reference(broken, ids, confidence))


def test_the_box_kernel_takes_large_objects_tails_beyond_sampled_pivots_bit_for_bit():
    """Objects of 2048+ Gaussians: the quantiles from the values beyond two pivots of a sample, numpy's to the bit
    at any quantile, with ties, one value, a sample that misleads (every sampled value far below the others: the
    whole column is selected instead) and NaN (sorted, as for small objects)."""
    from monovoc_ros.core.object_geometry_kernels import percentile_boxes as kernel

    rng = np.random.default_rng(29)
    for trial in range(24):
        sizes = rng.integers(2048, 9000, rng.integers(1, 4)).tolist()
        sizes[0] = 8001 if trial % 4 == 3 else (2048 if trial % 4 == 1 else sizes[0])  # 2048: the smallest sampled
        means = rng.normal(0, 3, (sum(sizes), 3)).astype(np.float64)
        if trial % 2:
            means = np.round(means * 4) / 4  # ties
        if trial % 5 == 0:
            means[:, 1] = 1.0  # one value
        if trial % 6 == 2:  # infinities among the tails' values, signed zeros in the middle
            means[rng.choice(len(means), 3, replace=False), 2] = [np.inf, -np.inf, np.inf]
            means[rng.choice(len(means), 40, replace=False), 0] = np.resize([0.0, -0.0], 40)
        if trial % 4 == 3:  # the sample half -100, half 100: 64 values beyond each pivot, not the 1st percentile's 80
            step = sizes[0] // 128
            means[: 128 * step : step, 0] = np.resize([-100.0, 100.0], 128)
        q = sorted(rng.uniform(0, 1, 2)) if trial % 3 == 0 else [0.01, 0.99]
        if trial == 6:
            q = [0.0, 1.0]
        bounds = np.concatenate([[0], np.cumsum(sizes)])
        low, high, centroid = (np.empty((len(sizes), 3)) for _ in range(3))
        kernel(means, np.ones(len(means)), bounds, q[0], q[1], low, high, centroid)
        for k in range(len(sizes)):
            lo, hi = np.quantile(means[bounds[k] : bounds[k + 1]], q, axis=0)
            np.testing.assert_array_equal(low[k], lo, err_msg=f"trial {trial}, object {k}")
            np.testing.assert_array_equal(high[k], hi, err_msg=f"trial {trial}, object {k}")
    means = rng.normal(0, 1, (5000, 3))
    means[1234, 0] = np.nan
    low, high, centroid = (np.empty((1, 3)) for _ in range(3))
    kernel(means, np.ones(5000), np.array([0, 5000]), 0.01, 0.99, low, high, centroid)
    ordered = np.sort(means[:, 0])  # NaN last
    virtual = 4999 * 0.99
    below = int(virtual)
    want = ordered[below] + (ordered[below + 1] - ordered[below]) * (virtual - below)
    np.testing.assert_array_equal(high[0, 0], want)
    np.testing.assert_array_equal(low[0, 1:], np.quantile(means[:, 1:], 0.01, axis=0))


def test_a_labelled_gaussian_with_a_non_finite_centre_is_an_error_not_a_crash():
    """The rasterizer culls such a Gaussian, so the mapper never labels it; labels that do (a caller's own) raise
    instead of indexing the union-find out of bounds."""
    rng = np.random.default_rng(23)
    gaussians, ids, confidence = _room(rng, n=2000)
    means = gaussians.means.copy()
    means[5] = np.nan
    broken = _map(means, rng)
    ids[5], confidence[5] = ids[ids < VOID_ID][0], 0.9
    with pytest.raises(ValueError, match="non-finite centre"):
        object_geometry(broken, ids, confidence)
    with pytest.raises(ValueError, match="non-finite centre"):
        main_cluster_ids(broken.means, ids, confidence)
