"""SemanticState: accumulation, order independence, merging, persistence and map re-indexing."""

from __future__ import annotations

import zipfile
from dataclasses import dataclass

import numpy as np
import pytest

from monovoc_ros.core.evidence.state import SemanticState


@dataclass
class FakeEvidence:
    color_sum: np.ndarray
    weight_sum: np.ndarray
    n_visible: int = 0


def random_evidence(rng: np.random.Generator, n: int, seen: float = 0.6) -> FakeEvidence:
    """Evidence as SCD produces it: color_sum = sum w y with y in [0, 1], zero where unseen."""
    weight = rng.random(n) * 3 * (rng.random(n) < seen)
    color = weight[:, None] * rng.random((n, 3))
    return FakeEvidence(color, weight, int((weight > 0).sum()))


def sequence(n: int = 500, k: int = 12, seed: int = 0) -> list[tuple[int, FakeEvidence]]:
    rng = np.random.default_rng(seed)
    return [(1_000_000_000 + 33_000_000 * i, random_evidence(rng, n)) for i in range(k)]


def integrate(items, n: int, ids=None) -> SemanticState:
    state = SemanticState.zeros(n, ids)
    for stamp, ev in items:
        state.add(ev, stamp)
    return state


def test_add_accumulates_and_colors_are_weighted_means():
    state = SemanticState.zeros(3)
    state.add(FakeEvidence(np.array([[0.5, 0.0, 0.0], [0.0, 0.0, 0.0], [0.2, 0.4, 0.6]]), np.array([1.0, 0, 2])), 10)
    state.add(FakeEvidence(np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), np.array([1.0, 0, 0])), 20)
    assert state.observed.tolist() == [True, False, True]
    colors = state.colors()
    np.testing.assert_allclose(colors[0], [0.25, 0.5, 0.0])
    assert np.isnan(colors[1]).all()
    np.testing.assert_allclose(colors[2], [0.1, 0.2, 0.3])
    assert state.stamps_ns.tolist() == [10, 20]
    assert state.has_stamp(20) and not state.has_stamp(30)
    assert state.nbytes == 3 * 3 * 8 + 3 * 8 + 2 * 8


def test_exact_recovery_of_a_single_color():
    # One Gaussian seen with weights w_p of pixels all of color s: s_hat == s whatever the weights.
    rng = np.random.default_rng(1)
    s = np.array([0.3, 0.7, 0.1])
    state = SemanticState.zeros(1)
    for k in range(5):
        w = rng.random(40)
        state.add(FakeEvidence((w.sum() * s)[None], np.array([w.sum()])), k)
    np.testing.assert_allclose(state.colors()[0], s, rtol=1e-14)


def test_rejected_evidence_leaves_the_state_untouched():
    state = integrate(sequence(n=20, k=2), 20)
    before = (state.color_sum.copy(), state.weight_sum.copy(), state.stamps_ns.copy())
    good = random_evidence(np.random.default_rng(5), 20)
    bad_cases = [
        (FakeEvidence(np.zeros((19, 3)), np.zeros(19)), 99, "color_sum"),
        (FakeEvidence(np.zeros((20, 3)), np.zeros(21)), 99, "weight_sum"),
        (FakeEvidence(np.full((20, 3), np.nan), np.ones(20)), 99, "NaN"),
        (FakeEvidence(np.zeros((20, 3)), -np.ones(20)), 99, "negative"),
        (good, int(state.stamps_ns[0]), "already integrated"),
    ]
    for ev, stamp, message in bad_cases:
        with pytest.raises(ValueError, match=message):
            state.add(ev, stamp)
    np.testing.assert_array_equal(state.color_sum, before[0])
    np.testing.assert_array_equal(state.weight_sum, before[1])
    np.testing.assert_array_equal(state.stamps_ns, before[2])


def test_order_independence():
    items = sequence()
    forward = integrate(items, 500)
    shuffled = integrate([items[i] for i in np.random.default_rng(2).permutation(len(items))], 500)
    np.testing.assert_allclose(shuffled.color_sum, forward.color_sum, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(shuffled.weight_sum, forward.weight_sum, rtol=1e-13, atol=1e-15)
    np.testing.assert_array_equal(forward.observed, shuffled.observed)
    assert sorted(shuffled.stamps_ns) == sorted(forward.stamps_ns)


def test_two_halves_merged_equal_the_whole():
    items = sequence()
    whole = integrate(items, 500)
    first, second = integrate(items[::2], 500), integrate(items[1::2], 500)
    merged = first.merged(second)
    np.testing.assert_allclose(merged.color_sum, whole.color_sum, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(merged.weight_sum, whole.weight_sum, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(merged.colors(), whole.colors(), rtol=1e-12)
    assert sorted(merged.stamps_ns) == sorted(whole.stamps_ns)
    # Merging is a new state: the inputs keep their own evidence.
    assert len(first.stamps_ns) == 6 and len(second.stamps_ns) == 6


def test_merge_aligns_by_ids_and_refuses_what_does_not_fit():
    items = sequence(n=50, k=4)
    ids = np.arange(100, 150)
    a = integrate(items[:2], 50, ids)
    b = integrate(items[2:], 50, ids)
    # The other robot holds the same Gaussians in another order.
    perm = np.random.default_rng(3).permutation(50)
    b_perm = SemanticState(b.color_sum[perm], b.weight_sum[perm], ids[perm], b.stamps_ns)
    merged = a.merged(b_perm)
    np.testing.assert_array_equal(merged.ids, ids)
    np.testing.assert_allclose(merged.color_sum, integrate(items, 50, ids).color_sum, rtol=1e-13, atol=1e-15)

    with pytest.raises(ValueError, match="in both states"):
        a.merged(a)
    other_ids = SemanticState(b.color_sum, b.weight_sum, ids + 1, b.stamps_ns)
    with pytest.raises(ValueError, match="different Gaussian ids"):
        a.merged(other_ids)
    with pytest.raises(ValueError, match="50 and 49"):
        a.merged(SemanticState.zeros(49))


def test_constructor_checks():
    with pytest.raises(ValueError, match="color_sum"):
        SemanticState(np.zeros((4, 2)), np.zeros(4))
    with pytest.raises(ValueError, match="weight_sum"):
        SemanticState(np.zeros((4, 3)), np.zeros(5))
    with pytest.raises(ValueError, match="unique"):
        SemanticState.zeros(3, ids=np.array([1, 1, 2]))
    with pytest.raises(ValueError, match="duplicate"):
        SemanticState(np.zeros((1, 3)), np.zeros(1), None, np.array([5, 5]))
    with pytest.raises(ValueError, match="n must be"):
        SemanticState.zeros(-1)


@pytest.mark.parametrize("with_ids", [False, True])
def test_save_load_is_bit_exact_and_atomic(tmp_path, with_ids):
    ids = np.random.default_rng(4).permutation(10_000)[:300] if with_ids else None
    state = integrate(sequence(n=300, k=3), 300, ids)
    path = tmp_path / "state.npz"
    path.write_bytes(b"an older file that must be replaced")
    state.save(path)
    loaded = SemanticState.load(path)
    assert loaded.color_sum.tobytes() == state.color_sum.tobytes()
    assert loaded.weight_sum.tobytes() == state.weight_sum.tobytes()
    np.testing.assert_array_equal(loaded.stamps_ns, state.stamps_ns)
    if with_ids:
        np.testing.assert_array_equal(loaded.ids, ids)
        assert loaded.ids.dtype == np.int64
    else:
        assert loaded.ids is None
    assert [p.name for p in tmp_path.iterdir()] == ["state.npz"]  # no temp file left behind

    empty = SemanticState.zeros(0)
    empty.save(tmp_path / "empty.npz")
    assert len(SemanticState.load(tmp_path / "empty.npz")) == 0


def test_load_rejects_corrupt_and_foreign_files(tmp_path):
    state = integrate(sequence(n=100, k=2), 100)
    good = tmp_path / "good.npz"
    state.save(good)
    data = good.read_bytes()

    (tmp_path / "truncated.npz").write_bytes(data[: len(data) // 2])
    (tmp_path / "garbage.npz").write_bytes(b"\x00not a zip at all" * 10)
    flipped = bytearray(data)
    flipped[len(data) // 3] ^= 0xFF  # inside color_sum: the zip CRC catches it
    (tmp_path / "flipped.npz").write_bytes(bytes(flipped))
    np.savez(tmp_path / "foreign.npz", color_sum=np.zeros((2, 3)))
    np.save(tmp_path / "array.npy", np.zeros(3))
    np.savez(tmp_path / "future.npz", format=np.array("monovoc_semantic_state"), format_version=np.array(99))
    for name in ("truncated.npz", "garbage.npz", "flipped.npz", "foreign.npz", "array.npy", "future.npz"):
        with pytest.raises(ValueError, match=name):
            SemanticState.load(tmp_path / name)
    with pytest.raises(FileNotFoundError):
        SemanticState.load(tmp_path / "missing.npz")
    assert zipfile.is_zipfile(good)


def test_carried_over_takes_the_chosen_rows():
    state = SemanticState.zeros(4, np.array([10, 11, 12, 13]))
    state.add(FakeEvidence(np.arange(12.0).reshape(4, 3), np.array([1.0, 2.0, 3.0, 4.0])), 7)
    # New Gaussian 0 takes old row 3, 1 starts over, 2 and 3 both take row 1 (split children); 0, 2 pruned.
    new = state.carried_over(np.array([3, -1, 1, 1]), np.array([13, 20, 11, 21]))
    np.testing.assert_array_equal(new.ids, [13, 20, 11, 21])
    np.testing.assert_array_equal(new.weight_sum, [4.0, 0.0, 2.0, 2.0])
    np.testing.assert_array_equal(new.color_sum, [[9, 10, 11], [0, 0, 0], [3, 4, 5], [3, 4, 5]])
    np.testing.assert_array_equal(new.stamps_ns, [7])
    assert len(state.carried_over(np.zeros(0, np.int64), None)) == 0


def test_all_distinct_agrees_with_numpy_unique():
    """The ids check every evidence store and map runs (a sort; np.unique hashes, 13x slower at 1M and holding
    the interpreter): the same answer as np.unique on random and edge cases."""
    from monovoc_ros.core.map.gaussians import all_distinct

    rng = np.random.default_rng(3)
    for n in (0, 1, 2, 7, 1000):
        for high in (3, 10 * n + 10, 2**62):
            values = rng.integers(0, high, n, dtype=np.int64)
            assert all_distinct(values) == (np.unique(values).size == n), (n, high)
    assert all_distinct(np.array([2**63 - 1, -(2**63)], np.int64))
    assert not all_distinct(np.array([5, 1, 5], np.uint32))
    assert all_distinct(rng.permutation(1_000_000))
    with pytest.raises(ValueError, match="unique"):
        SemanticState.zeros(4, ids=np.array([9, 1, 2, 9]))
