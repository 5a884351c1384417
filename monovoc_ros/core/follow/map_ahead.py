"""Keyframes ahead of a map update: one rule for the live worker and offline mapping (docs/map_updates.md).

A map update's plan (registration and the evidence's sources) takes ~0.3-0.7 s at 1M Gaussians; the keyframes
stamped after the map are posed in it, so in line they would wait for it. Instead, once the registration has the
map's motion, the keyframes stamped less than the window (`ahead_s`, seconds of stamps) after the map go into the
map in use, each with the pose the update will move back to its own (`map_updater.unmoved_pose`; those stamped
before the map are posed in the map in use already and go as sent), and the update is applied, carrying their
evidence with the rest and moving their logged poses to where they were sent:

* before the first keyframe stamped at or after the window's end;
* before any other input (a map, corrected poses, a service call) and at the end of the input;
* live, also once the worker has had no input for the window's length and the plan is ready (a robot that
  stopped still gets its map).

What goes ahead is decided by stamps and the order of the input, never by how fast the plan was made, so offline
mapping of a bag ends with the same map as the live node that received it. Where they can still differ: a pause in
the input longer than the window right after a map (live applies the update during it); a map arriving while a
re-integration still runs live (offline finishes each before the next input; live applies that map in line); a
map prepared against one the node then refused (live applies it in line); a stop (live applies the update before
the keyframes still queued); maps the node coalesced and its service calls (only live).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from monovoc_ros.core.follow.map_frames import FRAME_WINDOW_NS, PoseMover, posed_before, stamps_order
from monovoc_ros.core.follow.map_updater import unmoved_pose
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.gaussians import GaussianMap

# Seconds of stamps after a map update whose keyframes go into the map in use (MappingSession's `ahead_s`, the
# node's map_update_ahead_s, `monovoc map --map-update-ahead-s`; 0: in line). At 1M Gaussians a map reaches the node
# 0.5-0.9 s after its stamp and its plan takes ~0.7 s more there: with 2 s, keyframes stop queueing behind it. In
# four interleaved pairs of the robot-scale bench, once the object index yielded to the worker, 2 s lowered latency
# p95 by 22-42% and query p99 in three, for 1-3% of the fast run's keyframes/s (docs/results.md, twentieth session).
DEFAULT_AHEAD_S = 2.0
# The longest window: stamps further apart are taken as clocks that do not agree (map_frames.FRAME_WINDOW_NS).
MAX_AHEAD_S = FRAME_WINDOW_NS / 1e9


@dataclass
class MapAhead:
    """A map update (to `gaussians`) whose later keyframes go into the map in use until it is applied."""

    gaussians: GaussianMap  # the new map
    mover: PoseMover | None  # how the update moves poses (None: they stay)
    until_ns: int  # keyframes stamped at or after this apply the update first
    taken_back: set[int] = field(default_factory=set)  # stamps of the keyframes whose poses were taken back

    def applies_before(self, keyframe: Keyframe | None) -> bool:
        """Whether the update is applied before the next input: `keyframe`, or None for any other input (a map,
        corrected poses, a service call). Before a keyframe stamped at or after the window's end, or with a stamp
        that does not order against the map's (a clock that does not agree)."""
        if keyframe is None:
            return True
        return keyframe.stamp_ns >= self.until_ns or not stamps_order(self.gaussians.stamp_ns, keyframe.stamp_ns)

    def posed(self, keyframe: Keyframe) -> Keyframe:
        """`keyframe` as it goes into the map in use: its pose taken back by the update's motion (recorded), unless
        it is stamped before the map (posed in the map in use already) or the update moves no pose."""
        if self.mover is None or posed_before(self.gaussians, keyframe):
            return keyframe
        self.taken_back.add(keyframe.stamp_ns)
        return replace(keyframe, cam_to_world=unmoved_pose(self.mover, keyframe.cam_to_world))
