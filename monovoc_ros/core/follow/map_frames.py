"""Which map's frame a keyframe's pose is in, told by stamps (METHOD section 10).

A SLAM front-end poses each keyframe in its newest map: a keyframe's pose is in the frame of the map stamped
at or before it. The mapper does not always receive them in that order: a map of 1M Gaussians (a ~56 MB
message) reaches it ~0.5 s after its stamp, so the keyframes stamped after it come first and go into the map
in use; a segmenter's masks may come after a map stamped later than their image. With the map's stamp known
(GaussianMap.stamp_ns: its message's header):

* a map update leaves the logged poses of the keyframes stamped at or after it where they are (`in_new_frame`):
  they are in its frame already (their evidence went into the map before it as sent, and is carried with the
  rest);
* a keyframe stamped before the map in use is moved into it, before it is integrated, by the updates stamped
  after it (`MapFrames.into_map`).

Maps the live node replaced by a newer one before applying them (a SLAM sending maps faster than they are applied)
leave no update: a keyframe posed in such a map is taken as posed in the one before it (offline mapping, which
applies every map of a bag, moves it by the map it was posed in and the next).

A stamp of 0 is unknown: the order of arrival decides then, as it does without stamps (every logged pose moves
with an update, every keyframe is integrated as sent). So it does for stamps further apart than
FRAME_WINDOW_NS: clocks that do not agree (a map stamped by wall time, keyframes by simulation time) must not
keep a SLAM's logged poses from following its map.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.gaussians import GaussianMap

# A keyframe and a map stamped further apart (ns) are ordered by arrival, not by stamp (module docstring): a
# map reaches the mapper well within it (~0.5 s at 1M Gaussians, ~1 s at 2M).
FRAME_WINDOW_NS = 10 * 10**9
# Map updates remembered to move late keyframes into the map in use (one every ~2 s from a building's SLAM).
HISTORY = 8

PoseMover = Callable[[np.ndarray], np.ndarray]  # (P, 4, 4) cam_to_world in the old map -> the same in the new


def stamps_order(map_stamp_ns: int, keyframe_stamp_ns: int) -> bool:
    """Whether the stamps of a map and a keyframe tell which frame the keyframe is in (module docstring)."""
    return map_stamp_ns > 0 and keyframe_stamp_ns > 0 and abs(keyframe_stamp_ns - map_stamp_ns) <= FRAME_WINDOW_NS


def in_new_frame(map_stamp_ns: int, keyframe_stamp_ns: int) -> bool:
    """Whether a keyframe is posed in the frame of the map stamped `map_stamp_ns` (reached the mapper before that
    map or not): the stamps tell (`stamps_order`) and the keyframe's is at or after the map's."""
    return stamps_order(map_stamp_ns, keyframe_stamp_ns) and keyframe_stamp_ns >= map_stamp_ns


def posed_before(gaussians: GaussianMap, keyframe: Keyframe) -> bool:
    """Whether `keyframe` is known to be posed in a map before `gaussians`: the stamps tell and it is older."""
    return stamps_order(gaussians.stamp_ns, keyframe.stamp_ns) and keyframe.stamp_ns < gaussians.stamp_ns


def update_stamp(old: GaussianMap, new: GaussianMap) -> int:
    """The stamp a map update from `old` to `new` orders keyframes by: the new map's when it is known and newer than
    the old one's (or that one is unknown); else 0, the order of arrival (two SLAM processes, a clock reset)."""
    return new.stamp_ns if new.stamp_ns > 0 and (old.stamp_ns <= 0 or new.stamp_ns > old.stamp_ns) else 0


@dataclass(frozen=True)
class _Update:
    stamp_ns: int  # of the map it made the one in use
    mover: PoseMover | None  # poses from the map before it into it (None: they stay)


class MapFrames:
    """The newest map updates with known stamps, oldest first: what moves a late keyframe into the map in use."""

    def __init__(self) -> None:
        self._updates: list[_Update] = []
        self._base_ns = 0  # the stamp of the map before the oldest update held (0: unknown)
        # The map in use as far as this history knows; weak: an old map's arrays (~150 MB at 1M Gaussians, with
        # the rasterizer's) must not live on here.
        self._newest: weakref.ref[GaussianMap] | None = None

    def started(self, gaussians: GaussianMap) -> None:
        """A first map (or one loaded): no update before it."""
        self._updates, self._base_ns, self._newest = [], gaussians.stamp_ns, weakref.ref(gaussians)

    def updated(self, old: GaussianMap, gaussians: GaussianMap, mover: PoseMover | None) -> None:
        """A map update made `gaussians` the map in use instead of `old`; `mover` moves poses from `old` into it.
        A history of another map than `old` (a load came between), or an update that stamps cannot order
        (`update_stamp`), starts over."""
        if self._newest is None or self._newest() is not old:
            self.started(old)
        if update_stamp(old, gaussians) == 0:
            self.started(gaussians)
            return
        self._updates.append(_Update(gaussians.stamp_ns, mover))
        self._newest = weakref.ref(gaussians)
        if len(self._updates) > HISTORY:
            self._base_ns = self._updates.pop(0).stamp_ns

    def into_map(self, gaussians: GaussianMap, keyframe: Keyframe) -> Keyframe | None:
        """`keyframe` moved into `gaussians`, the map in use, when it is stamped before that map and after the
        oldest map held (module docstring); None when it is in that map's frame as sent, or nothing tells."""
        s = keyframe.stamp_ns
        if self._newest is None or self._newest() is not gaussians:  # not the map this history ends in (loaded)
            return None
        if not posed_before(gaussians, keyframe) or not 0 < self._base_ns <= s:
            return None
        movers = [u.mover for u in self._updates if u.stamp_ns > s and u.mover is not None]
        if not movers:
            return None
        pose = np.asarray(keyframe.cam_to_world, np.float64)[None]
        for mover in movers:
            pose = mover(pose)
        return replace(keyframe, cam_to_world=pose[0])
