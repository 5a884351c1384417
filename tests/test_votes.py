"""Vote evidence: the one-pass kernels against the float64 reference, the tile and slot rules against
their plain twins, VoteState accumulation, merging, persistence, re-indexing, and pixel labels."""

from __future__ import annotations

import numpy as np
import pytest

from monovoc_ros.core.evidence.palette import UNOBSERVED_ID, VOID_ID, Palette, pack_rgb
from monovoc_ros.core.evidence.pixel_labels import pixel_labels
from monovoc_ros.core.evidence.vote_kernels import merge_slots
from monovoc_ros.core.evidence.votes import EMPTY_SLOT, VoteState, merge_slots_reference, weakly_supported
from monovoc_ros.core.raster import accumulate_votes
from monovoc_ros.core.raster.numba_impl import tile_slots
from monovoc_ros.core.raster.reference import dense_votes, pixel_weights
from monovoc_ros.core.raster.vote_tables import OTHER_LABEL, tile_slots_reference
from tests.test_raster import SCENES, random_scene

TOL = 1e-4  # of the largest vote, float32 kernels against the float64 reference


def block_labels(k, seed: int, n_labels: int = 11, noise: float = 0.01) -> np.ndarray:
    """Blocky object labels (most tiles see 1-3 objects) with a sprinkle of noise and no-evidence pixels."""
    rng = np.random.default_rng(seed)
    labels = (np.arange(k.height)[:, None] // 20 * 3 + np.arange(k.width)[None, :] // 24) % n_labels
    noisy = rng.random(labels.shape) < noise
    return np.where(noisy, rng.integers(-1, n_labels, labels.shape), labels).astype(np.int32)


def dense_from(evidence, n: int, n_labels: int) -> tuple[np.ndarray, np.ndarray]:
    votes, other = np.zeros((n, n_labels)), np.zeros(n)
    for e in range(evidence.labels.shape[1]):
        ok = evidence.labels[:, e] >= 0
        np.add.at(votes, (evidence.rows[ok], evidence.labels[ok, e]), evidence.weights[ok, e])
    other[evidence.rows] = evidence.other
    return votes, other


@pytest.mark.parametrize("impl", ["numba", "torch"])
@pytest.mark.parametrize("seed,kind", SCENES)
@pytest.mark.parametrize("power", [1, 4])
def test_vote_kernels_match_reference(impl, seed, kind, power):
    gmap, k, pose, _ = random_scene(seed, kind=kind)
    labels = block_labels(k, seed)
    ref = dense_from(accumulate_votes(gmap, labels, k, pose, weight_power=power, impl="reference"), len(gmap), 11)
    got = dense_from(accumulate_votes(gmap, labels, k, pose, weight_power=power, impl=impl), len(gmap), 11)
    scale = max(ref[0].max(), 1e-12)
    assert np.abs(got[0] - ref[0]).max() / scale <= TOL
    assert np.abs(got[1] - ref[1]).max() / scale <= TOL
    assert ref[0].sum() > 5 * ref[1].sum() > 0  # mostly named votes, some pooled in crowded tiles


@pytest.mark.parametrize("impl", ["numba", "torch", "reference"])
def test_gaussians_beyond_max_depth_take_no_votes_and_hide_nothing(impl):
    """max_depth: the Gaussians deeper than it are culled as if they were not in the map (every implementation)."""
    gmap, k, pose, _ = random_scene(0)
    labels = block_labels(k, 0)
    w2c = np.linalg.inv(pose)
    depth = gmap.means.astype(np.float64) @ w2c[:3, :3].T[:, 2] + w2c[2, 3]
    far = float(np.median(depth))
    near = np.flatnonzero(depth <= far)
    clipped = dense_from(
        accumulate_votes(gmap, labels, k, pose, weight_power=4, max_depth=far, impl=impl), len(gmap), 11
    )
    alone = dense_from(accumulate_votes(gmap.subset(near), labels, k, pose, weight_power=4, impl=impl), len(near), 11)
    whole = dense_from(accumulate_votes(gmap, labels, k, pose, weight_power=4, impl=impl), len(gmap), 11)
    beyond = depth > far
    assert not clipped[0][beyond].any() and not clipped[1][beyond].any() and whole[0][beyond].any()
    scale = max(alone[0].max(), 1e-12)
    assert np.abs(clipped[0][near] - alone[0]).max() / scale <= TOL
    assert np.abs(clipped[1][near] - alone[1]).max() / scale <= TOL
    with pytest.raises(ValueError, match="max_depth"):
        accumulate_votes(gmap, labels, k, pose, max_depth=0.1, impl=impl)


def test_reference_votes_are_the_weights_summed_per_label():
    """Without crowded tiles, V[i, o] = sum_p w_ip^k [label_p == o] exactly (METHOD.md section 8)."""
    gmap, k, pose, _ = random_scene(0)
    labels = block_labels(k, 0, noise=0.0)
    weights, _ = pixel_weights(gmap, k, pose)
    votes, other = dense_votes(weights**2, labels, k.width, k.height, 11)
    flat = labels.reshape(-1)
    expected = np.stack([(weights**2)[flat == o].sum(axis=0) for o in range(11)], axis=1)
    np.testing.assert_allclose(votes, expected, rtol=1e-12, atol=1e-15)
    assert not other.any()


def test_tile_slots_kernel_matches_reference():
    rng = np.random.default_rng(3)
    for width, height, n_labels in ((64, 48, 3), (70, 37, 9), (33, 17, 40)):
        labels = rng.integers(-1, n_labels, (height, width)).astype(np.int32)
        labels[: height // 2] = labels[: height // 2] % 2  # calm tiles beside crowded ones
        slot_ref, table_ref = tile_slots_reference(labels, width, height)
        slot, table = tile_slots(labels, width, height)
        np.testing.assert_array_equal(slot, slot_ref)
        np.testing.assert_array_equal(table, table_ref)
    assert (table_ref[:, 3] == OTHER_LABEL).any() and (table_ref[:, 2] == -1).any()


def test_votes_are_exact_for_one_object_per_gaussian():
    """A pixel seen by one Gaussian votes its whole weight for its label."""
    gmap, k, pose, _ = random_scene(1)
    labels = np.zeros((k.height, k.width), np.int32)
    ev = accumulate_votes(gmap, labels, k, pose, weight_power=1)
    weights, _ = pixel_weights(gmap, k, pose)
    total = np.zeros(len(gmap))
    total[ev.rows] = ev.weights[:, 0]
    np.testing.assert_allclose(total, weights.sum(axis=0), rtol=1e-4, atol=1e-6)
    assert (ev.labels[:, 1:] == -1).all() and not ev.other.any()
    assert np.all(np.diff(ev.rows) > 0)  # map order: merge_slots walks the state in memory order


def test_bad_labels_raise():
    gmap, k, pose, _ = random_scene(0)
    with pytest.raises(ValueError, match="labels"):
        accumulate_votes(gmap, np.zeros((k.height, k.width), np.float32), k, pose)
    with pytest.raises(ValueError, match="intrinsics"):
        accumulate_votes(gmap, np.zeros((k.height + 1, k.width), np.int32), k, pose)
    with pytest.raises(ValueError, match="values"):
        accumulate_votes(gmap, np.full((k.height, k.width), -5, np.int32), k, pose)


def random_votes(rng, n: int, n_objects: int, seen: float = 0.7, entries: int = 3):
    rows = np.flatnonzero(rng.random(n) < seen)
    objects = rng.integers(0, n_objects, (rows.size, entries)).astype(np.uint32) * 0x010101
    votes = rng.random((rows.size, entries)) * (rng.random((rows.size, entries)) < 0.8)
    return rows, objects, votes, rng.random(rows.size) * 0.01


def test_merge_kernel_matches_reference():
    rng = np.random.default_rng(0)
    state_k, state_r = VoteState.zeros(300, 3), VoteState.zeros(300, 3)
    for _ in range(6):
        rows, objects, votes, other = random_votes(rng, 300, 7)
        merge_slots(state_k.objects, state_k.votes, state_k.other, rows, objects, votes, other)
        merge_slots_reference(state_r.objects, state_r.votes, state_r.other, rows, objects, votes, other)
    np.testing.assert_array_equal(state_k.objects, state_r.objects)
    np.testing.assert_allclose(state_k.votes, state_r.votes, rtol=1e-12)
    np.testing.assert_allclose(state_k.other, state_r.other, rtol=1e-12)
    assert (np.diff(state_k.votes, axis=1) <= 0).all() and (state_k.other > 0.02).any()


def dense_of(state: VoteState, n_objects: int) -> np.ndarray:
    out = np.zeros((len(state), n_objects))
    for s in range(state.slots):
        ok = state.objects[:, s] != EMPTY_SLOT
        np.add.at(out, (np.flatnonzero(ok), state.objects[ok, s] // 0x010101), state.votes[ok, s])
    return out


def test_state_is_exact_order_independent_and_mergeable_when_slots_suffice():
    rng = np.random.default_rng(1)
    batches = [random_votes(rng, 200, 4) for _ in range(8)]
    forward, backward = VoteState.zeros(200, 4), VoteState.zeros(200, 4)
    first, second = VoteState.zeros(200, 4), VoteState.zeros(200, 4)
    for stamp, batch in enumerate(batches):
        forward.add(*batch, stamp)
        (first if stamp % 2 else second).add(*batch, stamp)
    for stamp, batch in reversed(list(enumerate(batches))):
        backward.add(*batch, stamp)
    merged = first.merged(second)
    dense = np.zeros((200, 4))
    for rows, objects, votes, _ in batches:
        for e in range(objects.shape[1]):
            np.add.at(dense, (rows, objects[:, e] // 0x010101), votes[:, e])
    for state in (forward, backward, merged):
        np.testing.assert_allclose(dense_of(state, 4), dense, rtol=1e-12)
        np.testing.assert_allclose(state.other, forward.other, rtol=1e-12)
    ids, conf = forward.labels()
    seen = dense.max(axis=1) > 0
    np.testing.assert_array_equal(ids[seen], dense[seen].argmax(axis=1).astype(np.uint32) * 0x010101)
    assert (ids[~seen] == UNOBSERVED_ID).all() and (conf[~seen] == 0).all()
    top2 = np.sort(dense, axis=1)[:, ::-1]
    expected = (top2[:, 0] - top2[:, 1]) / (dense.sum(axis=1) + forward.other)
    np.testing.assert_allclose(conf[seen], expected[seen], rtol=1e-5)
    with pytest.raises(ValueError, match="already integrated"):
        forward.add(*batches[0], 0)
    with pytest.raises(ValueError, match="stamps are in both"):
        forward.merged(backward)


def test_bounded_slots_pool_the_lightest_objects():
    state = VoteState.zeros(1, 2)
    state.add(np.array([0]), np.array([[1, 2, 3]], np.uint32), np.array([[0.5, 3.0, 1.0]]), np.zeros(1), 1)
    assert state.objects.tolist() == [[2, 3]] and state.votes.tolist() == [[3.0, 1.0]] and state.other[0] == 0.5
    assert state.nbytes == 2 * (4 + 8) + 8 + 8 and state.evidence_nbytes == 32


def test_add_refuses_bad_votes_and_leaves_the_state_untouched():
    state = VoteState.zeros(5, 2)
    good = (np.array([0, 1]), np.array([[1, 2], [1, 0]], np.uint32), np.ones((2, 2)), np.zeros(2))
    state.add(*good, 1)
    before = {name: getattr(state, name).copy() for name in state.ARRAYS}
    bad = [
        (np.array([0, 0]), *good[1:]),  # repeated row
        (np.array([0, 9]), *good[1:]),  # out of range
        (good[0], good[1], np.full((2, 2), np.nan), good[3]),
        (good[0], good[1], -np.ones((2, 2)), good[3]),
        (good[0], np.array([[1 << 25, 2], [1, 0]], np.uint32), *good[2:]),
        (good[0], good[1][:, :1], *good[2:]),
    ]
    for args in bad:
        with pytest.raises(ValueError):
            state.add(*args, 2)
    for name, array in before.items():
        np.testing.assert_array_equal(getattr(state, name), array)
    assert state.stamps_ns.tolist() == [1]


def test_save_load_round_trip_and_foreign_files(tmp_path):
    rng = np.random.default_rng(2)
    state = VoteState.zeros(100, 3, ids=np.arange(100) * 7)
    state.add(*random_votes(rng, 100, 6), 5)
    state.save(tmp_path / "votes.npz")
    back = VoteState.load(tmp_path / "votes.npz")
    for name in (*state.ARRAYS, "ids", "stamps_ns"):
        np.testing.assert_array_equal(getattr(back, name), getattr(state, name))
    from monovoc_ros.core.evidence.state import SemanticState

    SemanticState.zeros(3).save(tmp_path / "scd.npz")
    with pytest.raises(ValueError, match="not a vote state file"):
        VoteState.load(tmp_path / "scd.npz")
    with pytest.raises(ValueError, match="not a semantic state file"):
        SemanticState.load(tmp_path / "votes.npz")


def test_empty_stores_equal_the_checked_constructors_and_check_their_ids():
    """`zeros` builds without the constructor's copies and checks; it must give what the constructor gives."""
    from monovoc_ros.core.evidence.state import SemanticState

    ids = np.arange(6, dtype=np.int32) * 3
    fast = VoteState.zeros(6, 3, ids=ids)
    checked = VoteState(np.full((6, 3), EMPTY_SLOT, np.uint32), np.zeros((6, 3)), np.zeros(6), ids)
    fast_scd, checked_scd = SemanticState.zeros(6, ids), SemanticState(np.zeros((6, 3)), np.zeros(6), ids)
    for a, b in ((fast, checked), (fast_scd, checked_scd)):
        assert type(a) is type(b)
        for name in (*a.ARRAYS, "ids", "stamps_ns"):
            got, want = getattr(a, name), getattr(b, name)
            assert got.dtype == want.dtype and got.shape == want.shape
            np.testing.assert_array_equal(got, want)
    fast.add(*random_votes(np.random.default_rng(1), 6, 4), 9)  # the arrays are its own and writable
    assert fast.stamps_ns.tolist() == [9] and (VoteState.zeros(6, 3).votes == 0).all()
    for make in (lambda bad: VoteState.zeros(3, 2, ids=bad), lambda bad: SemanticState.zeros(3, bad)):
        with pytest.raises(ValueError, match="ids must be unique"):
            make(np.array([1, 1, 2]))
        with pytest.raises(ValueError, match=r"expected shape \(3,\)"):
            make(np.arange(4))


def test_carried_over_carries_votes():
    rng = np.random.default_rng(4)
    state = VoteState.zeros(50, 2, ids=np.arange(50))
    state.add(*random_votes(rng, 50, 5, seen=1.0), 1)
    rows = np.concatenate([np.arange(50)[::-1], np.full(10, -1)])  # reversed, then 10 new Gaussians
    moved = state.carried_over(rows, np.arange(60)[::-1] - 10)
    np.testing.assert_array_equal(moved.objects[:50], state.objects[::-1])
    np.testing.assert_array_equal(moved.votes[:50], state.votes[::-1])
    assert (moved.objects[50:] == EMPTY_SLOT).all() and (moved.votes[50:] == 0).all()
    assert isinstance(moved, VoteState) and moved.stamps_ns.tolist() == [1]


def test_pixel_labels_exact_snapped_ambiguous_and_void():
    red, green, blue = (255, 0, 0), (0, 200, 0), (0, 0, 255)
    palette = Palette.from_colors(np.array([red, green, blue], np.uint8))
    mask = np.zeros((4, 5, 3), np.uint8)
    mask[:] = red
    mask[0, 0] = green
    mask[1, 1] = (250, 5, 3)  # JPEG-like: near red
    mask[2, 2] = (128, 100, 0)  # halfway red-green: ambiguous
    mask[3, 3] = (255, 255, 255)  # void
    out = pixel_labels(mask, palette)
    objects = out.objects[out.labels]
    assert objects[1, 1] == pack_rgb(np.array(red, np.uint8)) and objects[0, 0] == pack_rgb(np.array(green, np.uint8))
    assert out.labels[2, 2] == -1 and out.labels[3, 3] == -1
    assert out.snapped_pixels == 1 and out.ambiguous_pixels == 1
    everything = pixel_labels(mask, palette, min_snap_margin=0.0, include_void=True)
    assert everything.labels.min() >= 0 and everything.objects[everything.labels[3, 3]] == VOID_ID


def test_known_object_colors_take_lossy_masks():
    """A region whose color drifted (as JPEG does to flat areas) is its own object without a known
    palette, and the known object with one."""
    from monovoc_ros.core.keyframe import Keyframe
    from monovoc_ros.core.mapping import MapperConfig, SemanticMapper

    gmap, k, pose, _ = random_scene(2)
    mask = np.zeros((k.height, k.width, 3), np.uint8)
    mask[:, : k.width // 2] = (255, 0, 0)
    mask[:, k.width // 2 :] = (2, 0, 253)  # drifted blue
    keyframe = Keyframe(0, 1, pose, k, mask)
    red, blue = 0xFF0000, 0x0000FF
    plain = SemanticMapper(gmap, MapperConfig())
    plain.integrate(keyframe)
    assert set(np.unique(plain.result().object_ids)) == {red, 0x0200FD, UNOBSERVED_ID}
    known = SemanticMapper(gmap, MapperConfig(object_colors=(red, blue, 0x00FF00)))
    report = known.integrate(keyframe)
    assert set(np.unique(known.result().object_ids)) == {red, blue, UNOBSERVED_ID}
    assert report.snapped_pixels == k.height * (k.width - k.width // 2)
    with pytest.raises(ValueError, match="object_colors"):
        MapperConfig(object_colors=(VOID_ID,))


def test_relabel_kernel_matches_labels():
    rng = np.random.default_rng(7)
    state = VoteState.zeros(500, 3)
    for stamp in range(5):
        state.add(*random_votes(rng, 500, 6), stamp)
    ids, conf = state.labels()
    got_ids, got_conf = np.zeros(500, np.uint32), np.full(500, -1.0, np.float32)
    rows = np.flatnonzero(rng.random(500) < 0.5)
    state.relabel(rows, got_ids, got_conf)
    np.testing.assert_array_equal(got_ids[rows], ids[rows])
    np.testing.assert_allclose(got_conf[rows], conf[rows], rtol=1e-6)
    assert (got_conf[np.setdiff1d(np.arange(500), rows)] == -1).all()  # other rows untouched


def test_weakly_supported_against_a_loop_over_objects():
    rng = np.random.default_rng(3)
    n = 5000
    ids = rng.choice(np.array([7, 9, 0x123456, UNOBSERVED_ID], np.uint32), n, p=[0.3, 0.3, 0.01, 0.39])
    support = rng.uniform(0, 1, n) ** 2
    for min_support in (0.0, 0.3, 0.5, 1.0):
        expected = np.zeros(n, bool)
        for oid in np.unique(ids):
            if oid == UNOBSERVED_ID:
                continue
            mine = ids == oid
            expected |= mine & (support < min_support * np.median(support[mine]))
        np.testing.assert_array_equal(weakly_supported(ids, support, min_support), expected)
    assert not weakly_supported(np.full(3, UNOBSERVED_ID, np.uint32), np.zeros(3), 0.5).any()


def test_support_counts_the_pooled_votes_against_the_leader():
    state = VoteState.zeros(3, 2, None)
    rows = np.array([0, 1], np.int64)
    state.add(rows, np.array([[5, 0], [5, 6]], np.uint32), np.array([[3.0, 0.0], [2.0, 1.0]]), np.array([1.0, 0.0]), 1)
    np.testing.assert_allclose(state.support(), [0.75, 1.0, 0.0])
