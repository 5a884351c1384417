"""Comparing evidence stores (SCD sums or votes) in tests, whatever the semantic mode."""

from __future__ import annotations

import numpy as np

from monovoc_ros.core.evidence.state import GaussianEvidence
from monovoc_ros.core.evidence.votes import VoteState


def assert_same_evidence(
    actual: GaussianEvidence,
    expected: GaussianEvidence,
    rtol: float = 0.0,
    atol: float = 0.0,
    rows=None,
    expected_rows=None,
) -> None:
    """Every per-Gaussian array equal (floats within rtol / atol), optionally on selected rows."""
    assert type(actual) is type(expected), f"{type(actual).__name__} vs {type(expected).__name__}"
    for name in expected.ARRAYS:
        a = _canonical(actual, name)
        e = _canonical(expected, name)
        a = a if rows is None else a[rows]
        e = e if expected_rows is None else e[expected_rows]
        if e.dtype.kind == "f":
            np.testing.assert_allclose(a, e, rtol=rtol, atol=atol, err_msg=name)
        else:
            np.testing.assert_array_equal(a, e, err_msg=name)


def _canonical(state: GaussianEvidence, name: str) -> np.ndarray:
    """Vote slots sorted by object id: slots of (nearly) equal votes may come in either order."""
    array = getattr(state, name)
    if not isinstance(state, VoteState) or name not in ("objects", "votes"):
        return array
    return np.take_along_axis(array, np.argsort(state.objects, axis=1, kind="stable"), axis=1)
