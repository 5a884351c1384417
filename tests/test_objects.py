"""Object geometry summaries."""

from __future__ import annotations

import numpy as np
import pytest

from monovoc_ros.core.gaussians import GaussianMap
from monovoc_ros.core.objects import summarize_objects
from monovoc_ros.core.palette import UNOBSERVED_ID, VOID_ID


def test_summaries_are_robust_boxes_per_object():
    rng = np.random.default_rng(0)
    a = rng.uniform([0, 0, 0], [1, 2, 0.5], (500, 3))
    b = rng.uniform([3, 3, 1], [3.5, 3.2, 1.4], (300, 3))
    stray = np.array([[40.0, 40.0, 40.0]])  # one mislabeled Gaussian far away
    means = np.vstack([a, b, stray, [[9, 9, 9]], [[8, 8, 8]]])
    ids = np.array([0x112233] * 500 + [0x445566] * 300 + [0x112233, VOID_ID, UNOBSERVED_ID], np.uint32)
    n = len(means)
    gmap = GaussianMap(means, np.full((n, 3), 0.01), np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.9))
    objs = summarize_objects(gmap, ids)
    assert [o.id for o in objs] == [0x112233, 0x445566]
    first = objs[0]
    assert first.rgb == (0x11, 0x22, 0x33) and first.num_gaussians == 501
    np.testing.assert_allclose(first.bbox_min, [0, 0, 0], atol=0.05)
    np.testing.assert_allclose(first.bbox_max, [1, 2, 0.5], atol=0.05)  # the stray point is ignored
    np.testing.assert_allclose(first.centroid, [0.5, 1.0, 0.25], atol=0.05)
    np.testing.assert_allclose(objs[1].extent, [0.5, 0.2, 0.4], atol=0.03)


def test_empty_and_bad_input():
    gmap = GaussianMap(np.zeros((2, 3)), np.full((2, 3), 0.01), np.tile([1.0, 0, 0, 0], (2, 1)), np.full(2, 0.5))
    assert summarize_objects(gmap, np.array([UNOBSERVED_ID, VOID_ID], np.uint32)) == []
    with pytest.raises(ValueError, match="object_ids"):
        summarize_objects(gmap, np.zeros(3, np.uint32))
