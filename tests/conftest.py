"""Fixtures shared by the whole suite."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
REPLICA_OFFICE0 = SHARED_DATA / "replica_office0"


@pytest.fixture(scope="session")
def replica_office0() -> Path:
    """The real Replica office_0 sequence (research license: read in place, never copied)."""
    if not (REPLICA_OFFICE0 / "traj.txt").exists():
        pytest.skip(f"{REPLICA_OFFICE0} is not present")
    return REPLICA_OFFICE0
