"""Comparing object geometries (core.object_geometry) in tests."""

from __future__ import annotations

import numpy as np

from monovoc_ros.core.object_geometry import ObjectGeometry


def assert_same_geometry(got: ObjectGeometry, want: ObjectGeometry) -> None:
    """The same objects from the same Gaussians, bit for bit."""
    np.testing.assert_array_equal(got.shape_ids, want.shape_ids)
    assert [(s.id, s.rgb, s.num_gaussians) for s in got.objects] == [
        (s.id, s.rgb, s.num_gaussians) for s in want.objects
    ]
    for a, b in zip(got.objects, want.objects, strict=True):  # the same rows in the same order: bit for bit
        np.testing.assert_array_equal(a.bbox_min, b.bbox_min)
        np.testing.assert_array_equal(a.bbox_max, b.bbox_max)
        np.testing.assert_array_equal(a.centroid, b.centroid)
