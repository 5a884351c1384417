"""StampReorder: the keyframe topics reach the assembler merged by stamp, whatever their arrival order."""

from __future__ import annotations

from types import SimpleNamespace

from monovoc_ros.nodes.reorder import StampReorder

ROLES = ("image", "mask", "camera_info", "pose")


def msg(stamp: int):
    return SimpleNamespace(header=SimpleNamespace(stamp=stamp), stamp=stamp)


def test_a_burst_of_one_topic_waits_for_the_others():
    now = [0.0]
    r = StampReorder(ROLES, max_wait_s=0.5, clock=lambda: now[0])
    for s in range(1, 41):  # 40 images before anything else (more than the synchronizer buffers)
        assert r.add("image", msg(s)) == []
    out = []
    for s in range(1, 41):
        for role in ("mask", "camera_info", "pose"):
            out += r.add(role, msg(s))
    stamps = [m.stamp for _, m in out]
    assert stamps == sorted(stamps) and len(out) == 160  # every topic delivered stamp 40: nothing waits
    assert [role for role, m in out[:4]] == ["image", "mask", "camera_info", "pose"]


def test_a_keyframe_goes_as_soon_as_its_last_message_arrives():
    now = [0.0]
    r = StampReorder(ROLES, max_wait_s=0.5, clock=lambda: now[0])
    for s in (1, 2):
        assert [r.add(role, msg(s)) for role in ("pose", "camera_info", "image")] == [[], [], []] and len(r) == 3
        released = r.add("mask", msg(s))
        # The mask completes stamp s: all four go at once (no waiting for stamp s + 1 or for max_wait_s).
        assert sorted(m.stamp for _, m in released) == [s] * 4 and len(r) == 0


def test_stale_heads_are_released_in_stamp_order():
    now = [0.0]
    r = StampReorder(ROLES, max_wait_s=0.5, clock=lambda: now[0])
    r.add("mask", msg(5))
    r.add("pose", msg(3))
    assert r.due() == [] and len(r) == 2
    now[0] = 0.6  # the image and camera_info topics went quiet
    assert [(role, m.stamp) for role, m in r.due()] == [("pose", 3), ("mask", 5)]


def test_per_topic_order_is_kept_and_unstamped_messages_pass():
    r = StampReorder(("mask", "pose"), max_wait_s=10)
    r.add("mask", msg(5))
    r.add("mask", msg(2))  # out of order on its topic: stays behind 5 (the assembler rejects it)
    out = r.add("pose", msg(9))
    assert [(role, m.stamp) for role, m in out] == [("mask", 5), ("mask", 2)]
    fresh = StampReorder(("mask", "pose"), max_wait_s=10)
    assert fresh.add("pose", SimpleNamespace())[0][0] == "pose"  # no header: released at once


def test_overflow_releases_without_waiting():
    r = StampReorder(("mask", "pose"), max_wait_s=100, max_buffered=3)
    for s in range(1, 4):
        assert r.add("mask", msg(s)) == []
    assert [m.stamp for _, m in r.add("mask", msg(4))] == [1]


def test_a_topic_that_is_still_delivering_is_waited_for():
    now = [0.0]
    r = StampReorder(("image", "mask"), max_wait_s=0.5, clock=lambda: now[0])
    for s in range(1, 41):
        r.add("image", msg(s))
    # Masks lag more than max_wait_s behind the images, but keep coming: nothing is forced out.
    out = []
    for s in range(1, 41):
        now[0] += 0.1
        out += r.add("mask", msg(s))
    assert [(role, m.stamp) for role, m in out[:4]] == [("image", 1), ("mask", 1), ("image", 2), ("mask", 2)]
    assert len(out) == 80 and [m.stamp for _, m in out] == sorted(m.stamp for _, m in out) and len(r) == 0


def test_a_head_waits_for_a_silent_topic_at_most_max_wait_s():
    now = [0.0]
    r = StampReorder(("image", "mask"), max_wait_s=0.5, clock=lambda: now[0])
    r.add("image", msg(1))
    released = r.add("mask", msg(2))  # the image of stamp 2 might still come: the mask waits for it
    assert [m.stamp for _, m in released] == [1] and len(r) == 1
    now[0] += 0.4
    assert r.due() == []
    now[0] += 0.2  # the images have been silent (and the mask has waited) for max_wait_s: it goes
    assert [(role, m.stamp) for role, m in r.due()] == [("mask", 2)]
