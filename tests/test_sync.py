"""The approximate-time stamp synchronizer."""

from __future__ import annotations

import pytest

from monovoc_ros.core.sync import Held, StampEpochs, StampSynchronizer, lead_over_others

MS = 1_000_000


def make() -> StampSynchronizer:
    return StampSynchronizer(("image", "mask", "pose"), "mask", tolerance_ns=10 * MS, max_pending=4)


def test_matches_within_tolerance_in_any_arrival_order():
    sync = make()
    assert sync.push("pose", 100 * MS + 3 * MS, "p1") == []
    assert sync.push("mask", 100 * MS, "m1") == []
    out = sync.push("image", 100 * MS - 2 * MS, "i1")
    assert out == [(100 * MS, {"mask": "m1", "pose": "p1", "image": "i1"})]
    assert sync.stats.matched == 1
    assert all(sync.pending(r) == 0 for r in sync.roles)


def test_picks_closest_partner_and_drops_skipped_ones():
    sync = make()
    sync.push("image", 95 * MS, "far")
    sync.push("image", 101 * MS, "near")
    sync.push("pose", 100 * MS, "p")
    out = sync.push("mask", 100 * MS, "m")
    assert out[0][1]["image"] == "near"
    assert sync.stats.unmatched["image"] == 1


def test_pivot_that_can_never_match_is_dropped_and_counted():
    sync = make()
    sync.push("mask", 100 * MS, "m_old")
    sync.push("pose", 100 * MS, "p_old")
    # The image stream has moved past 100 ms + tolerance: m_old can never get an image.
    sync.push("image", 150 * MS, "i_new")
    assert sync.stats.unmatched["mask"] == 1
    sync.push("pose", 151 * MS, "p_new")
    out = sync.push("mask", 149 * MS, "m_new")
    assert out == [(149 * MS, {"mask": "m_new", "pose": "p_new", "image": "i_new"})]
    assert sync.stats.unmatched["pose"] == 1  # p_old: too old for the next mask


def test_several_sets_complete_at_once_oldest_first():
    sync = make()
    for k in range(3):
        sync.push("mask", (100 + 50 * k) * MS, f"m{k}")
        sync.push("pose", (100 + 50 * k) * MS, f"p{k}")
    out = []
    for k in range(3):
        out += sync.push("image", (100 + 50 * k) * MS, f"i{k}")
    assert [s for s, _ in out] == [100 * MS, 150 * MS, 200 * MS]
    assert [parts["image"] for _, parts in out] == ["i0", "i1", "i2"]


def test_bounded_buffers_drop_oldest_and_count():
    sync = make()
    for k in range(6):
        sync.push("mask", (100 + k) * MS * 100, k)
    assert sync.pending("mask") == 4
    assert sync.stats.overflow["mask"] == 2


def test_rejects_non_increasing_stamps_and_bad_configuration():
    sync = make()
    sync.push("mask", 100 * MS, "a")
    with pytest.raises(ValueError, match="does not increase"):
        sync.push("mask", 100 * MS, "b")
    with pytest.raises(ValueError):
        StampSynchronizer(("a",), "b", 0)
    with pytest.raises(ValueError):
        StampSynchronizer(("a",), "a", -1)


def test_far_future_rule():
    """One rule for ingest (stamp_future) and the node's reorder stage: ahead of every other topic's newest."""
    s = 1_000_000_000
    assert lead_over_others(100 * s, [50 * s, None, 60 * s], 30 * s) == 40 * s
    assert lead_over_others(90 * s, [50 * s, 60 * s], 30 * s) is None  # exactly the allowed lead
    assert lead_over_others(100 * s, [None, None], 30 * s) is None  # nothing to compare with yet
    assert lead_over_others(100 * s, [1], 0) is None  # 0 disables the rule


def test_stamp_epochs_hold_confirm_and_refuse():
    s = 1_000_000_000
    epochs = StampEpochs(("a", "b"), 30 * s, max_held=2)
    newest = {"a": 10 * s, "b": 10 * s}
    assert epochs.offer("a", 11 * s, "a11", newest) == ([Held("a", 11 * s, "a11")], [])  # in step: taken
    assert epochs.offer("a", 500 * s, "a500", newest) == ([], [])  # far ahead of b: held
    assert epochs.offer("b", 510 * s, "b510", newest) == ([], [])  # within 30 s of it, but one message each
    go, refused = epochs.offer("b", 511 * s, "b511", newest)  # a stream: a new epoch
    assert [h.item for h in go] == ["a500", "b510", "b511"] and refused == [] and epochs.epochs == 1
    assert epochs.held == 0
    for t in (900, 901, 902):  # never confirmed: the oldest beyond max_held is refused
        go, refused = epochs.offer("a", t * s, f"a{t}", newest)
    assert go == [] and [h.item for h, _ in refused] == ["a900"] and "none agreed on" in refused[0][1]
    go, refused = epochs.offer("a", 12 * s, "a12", newest)  # its own topic goes on: the held ones were outliers
    assert [h.item for h in go] == ["a12"] and [h.item for h, _ in refused] == ["a901", "a902"]
    assert "ahead of a later one" in refused[0][1] and epochs.held == 0
    assert StampEpochs(("a", "b"), 0).offer("a", 10**18, "x", newest) == ([Held("a", 10**18, "x")], [])  # 0: off
    three = StampEpochs(("a", "b", "c"), 30 * s)
    newest = {"a": 10 * s, "b": 10 * s, "c": 10 * s}
    for role, t in (("a", 500), ("b", 501), ("c", 502)):  # one message each: could be one bad keyframe
        assert three.offer(role, t * s, role, newest) == ([], [])
    go, _ = three.offer("a", 503 * s, "a2", newest)  # every topic, and a stream: an epoch
    assert [h.item for h in go] == ["a", "b", "c", "a2"] and three.epochs == 1
