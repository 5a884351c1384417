"""Which map's frame a keyframe is in, told by stamps (core.follow.map_frames): keyframes that reach the mapper
before the map they are posed in (a 56 MB map message comes ~0.5 s after its stamp) or after a newer one (a slow
segmenter). The same session serves the live worker and offline mapping (tests/test_session.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from monovoc_ros.core.follow.map_frames import FRAME_WINDOW_NS, HISTORY, MapFrames, in_new_frame, posed_before
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.mapping import MapperConfig
from monovoc_ros.core.session import MappingSession
from tests.evidence import assert_same_evidence
from tests.node_scene import small_scene

S = 100 * 10**9  # keyframe i is stamped S + i * 0.1 s (past FRAME_WINDOW_NS: stamps that far before stay positive)
SHIFT = 0.05  # metres: the SLAM's loop closure moves its map (and the keyframes posed after it) this far


def keyframes(n: int) -> list[Keyframe]:
    scene = small_scene()
    return [replace(scene.keyframe(i), stamp_ns=S + scene.keyframe(i).stamp_ns) for i in range(n)]


def shifted(gaussians: GaussianMap, stamp_ns: int) -> GaussianMap:
    """The SLAM's map after a loop closure moved it SHIFT metres along z (the same ids), stamped `stamp_ns`."""
    means = gaussians.means + np.float32([0.0, 0.0, SHIFT])
    return GaussianMap(
        means, gaussians.scales, gaussians.quats, gaussians.opacities, ids=gaussians.ids, stamp_ns=stamp_ns
    )


def moved(pose: np.ndarray) -> np.ndarray:
    out = np.array(pose, np.float64)
    out[2, 3] += SHIFT
    return out


def first_map(stamp_ns: int = S - 1) -> GaussianMap:
    return replace(small_scene().gaussians, stamp_ns=stamp_ns)


def run(events) -> MappingSession:
    """A session given maps and keyframes in this order (as either loop gives them), everything integrated."""
    session = MappingSession(MapperConfig())
    for event in events:
        if isinstance(event, GaussianMap):
            assert session.add_map(event)
        else:
            session.add_keyframe(event)
        while session.keyframes_ready:
            session.integrate_next()
    return session


def logged(session: MappingSession) -> dict[int, np.ndarray]:
    return {e.stamp_ns: e.cam_to_world for e in session.mapper.keyframe_log.entries}


@pytest.mark.parametrize("map_stamp", ["stamped", "unknown", "another clock", "older than the map in use"])
def test_a_keyframe_stamped_after_a_map_update_that_reaches_the_mapper_first_keeps_its_logged_pose(map_stamp):
    """Keyframe 3 is posed in the moved map but comes before it: its logged pose is already in the new map's frame,
    and the update must not move it a second time; the older keyframes' poses move with the map. Without a
    stamp, with stamps of clocks that do not agree, or with a map stamped before the one in use (another SLAM,
    a clock reset), the order of arrival decides (every logged pose moves)."""
    kfs = keyframes(4)
    stamp = {
        "stamped": kfs[3].stamp_ns - 1,
        "unknown": 0,
        "another clock": kfs[3].stamp_ns - 2 * FRAME_WINDOW_NS,
        "older than the map in use": kfs[3].stamp_ns - 1,
    }
    # The first map: unstamped where the second is stamped far before the keyframes (only the window decides).
    first_stamp = {"another clock": 0, "older than the map in use": kfs[3].stamp_ns + 10}.get(map_stamp, S - 1)
    second = shifted(first_map(), stamp[map_stamp])
    late = replace(kfs[3], cam_to_world=moved(kfs[3].cam_to_world))  # posed in the second map
    session = run([first_map(first_stamp), *kfs[:3], late, second])
    poses = logged(session)
    for kf in kfs[:3]:
        np.testing.assert_allclose(poses[kf.stamp_ns], moved(kf.cam_to_world), atol=1e-6)
    kept = map_stamp == "stamped"
    expected = late.cam_to_world if kept else moved(late.cam_to_world)
    np.testing.assert_allclose(poses[late.stamp_ns], expected, atol=1e-6)
    assert session.stats.keyframes_before_their_map == int(kept) and session.stats.keyframes_moved_into_map == 0


def test_a_keyframe_stamped_before_a_map_update_that_comes_after_it_is_moved_into_it():
    """Keyframe 2 is posed in the first map but its masks come after the moved map (a slow segmenter): it is moved
    into the map in use before it is integrated, and the evidence and the log end as when it came in order."""
    kfs = keyframes(4)
    second = shifted(first_map(), kfs[3].stamp_ns - 1)
    in_order = run([first_map(), *kfs[:3], second, replace(kfs[3], cam_to_world=moved(kfs[3].cam_to_world))])
    late = run([first_map(), *kfs[:2], second, kfs[2], replace(kfs[3], cam_to_world=moved(kfs[3].cam_to_world))])
    assert late.stats.keyframes_moved_into_map == 1 and in_order.stats.keyframes_moved_into_map == 0
    for stamp, pose in logged(in_order).items():
        np.testing.assert_allclose(logged(late)[stamp], pose, atol=1e-6)
    # The map moved rigidly and its Gaussians kept their ids: the same evidence, but for float32 rounding.
    assert_same_evidence(late.mapper.state, in_order.mapper.state, rtol=1e-4, atol=1e-5)


def test_a_keyframe_older_than_the_maps_held_or_from_another_clock_is_integrated_as_sent():
    kfs = keyframes(3)
    second = shifted(first_map(stamp_ns=kfs[1].stamp_ns - 1), kfs[2].stamp_ns - 1)
    # Stamped before the first map: nothing says which frame it is in.
    session = run([first_map(stamp_ns=kfs[1].stamp_ns - 1), kfs[1], second, kfs[0]])
    np.testing.assert_allclose(logged(session)[kfs[0].stamp_ns], kfs[0].cam_to_world, atol=1e-9)
    far = replace(kfs[0], stamp_ns=second.stamp_ns - 2 * FRAME_WINDOW_NS)
    assert far.stamp_ns > 0  # only the window keeps it from being moved
    session = run([first_map(stamp_ns=1), kfs[1], second, far])
    np.testing.assert_allclose(logged(session)[far.stamp_ns], far.cam_to_world, atol=1e-9)
    assert session.stats.keyframes_moved_into_map == 0


def test_map_frames_move_a_late_keyframe_through_every_update_since_its_stamp_and_forget_beyond_history():
    frames = MapFrames()
    base = first_map(stamp_ns=100)
    frames.started(base)
    maps = [replace(base, stamp_ns=100 + 10 * (k + 1)) for k in range(HISTORY + 2)]

    def step(k: int):
        return lambda poses: poses + np.float64(k + 1)  # each update adds k + 1 to every entry

    kf = Keyframe(0, 105, np.zeros((4, 4)), small_scene().keyframe(0).intrinsics, small_scene().keyframe(0).mask)
    for k, gmap in enumerate(maps[:3]):
        frames.updated(([base] + maps)[k], gmap, step(k))
    assert frames.into_map(maps[1], kf) is None  # not the map in use
    np.testing.assert_array_equal(frames.into_map(maps[2], kf).cam_to_world, np.full((4, 4), 1.0 + 2.0 + 3.0))
    np.testing.assert_array_equal(
        frames.into_map(maps[2], replace(kf, stamp_ns=125)).cam_to_world, np.full((4, 4), 3.0)
    )
    assert frames.into_map(maps[2], replace(kf, stamp_ns=130)) is None  # in its frame as sent
    for k, gmap in enumerate(maps[3:], start=3):
        frames.updated(maps[k - 1], gmap, step(k))
    assert frames.into_map(maps[-1], kf) is None  # older than the updates held
    unstamped = replace(base, stamp_ns=0)
    frames.updated(maps[-1], unstamped, None)  # an unstamped map: nothing before it can be ordered
    assert frames.into_map(unstamped, replace(kf, stamp_ns=195)) is None
    # A history of another map (a load came between) is not continued: only the update from the loaded map moves.
    frames.updated(maps[1], maps[2], step(0))
    frames.updated(replace(base, stamp_ns=500), newest := replace(base, stamp_ns=510), step(9))
    after_load = frames.into_map(newest, replace(kf, stamp_ns=505))
    np.testing.assert_array_equal(after_load.cam_to_world, np.full((4, 4), 10.0))
    assert frames.into_map(newest, replace(kf, stamp_ns=125)) is None  # older than the loaded map
    assert in_new_frame(100, 100) and not in_new_frame(0, 100) and not in_new_frame(100, 99)
    assert not in_new_frame(100, 100 + FRAME_WINDOW_NS + 1)
    assert posed_before(base, replace(kf, stamp_ns=99)) and not posed_before(replace(base, stamp_ns=0), kf)
