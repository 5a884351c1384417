"""Approximate-time synchronization of several streams by stamp (message_filters is not available).

Each stream ("role") delivers items with a stamp in nanoseconds. A set is emitted when the pivot
role (the segmentation mask: it defines a keyframe) has an item and every other role has one within
`tolerance_ns` of it; the closest candidate of each role is taken. Stamps must increase per role
(callers reject the rest before pushing), which makes the matching decidable at once: a pivot item
whose partners on some role have all moved past `stamp + tolerance` can never be matched and is
dropped (counted as unmatched), as are partner items older than every pending pivot.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any


def lead_over_others(stamp: int, others: Iterable[int | None], max_lead_ns: int) -> int | None:
    """The far-future rule (ingest's stamp_future, the node's reorder stage): how far `stamp` is ahead of
    the newest stamp of every other topic (`others`, None = nothing yet) when that is more than
    `max_lead_ns` (> 0; 0 disables the rule), else None."""
    known = [t for t in others if t is not None]
    if not max_lead_ns or not known:
        return None
    lead = stamp - max(known)
    return lead if lead > max_lead_ns else None


@dataclass
class SyncStats:
    matched: int = 0
    unmatched: dict[str, int] = field(default_factory=dict)  # dropped items per role
    overflow: dict[str, int] = field(default_factory=dict)  # items pushed out of a full buffer per role


class StampSynchronizer:
    def __init__(self, roles: tuple[str, ...], pivot: str, tolerance_ns: int, max_pending: int = 32) -> None:
        if pivot not in roles:
            raise ValueError(f"pivot {pivot!r} is not one of the roles {roles}")
        if tolerance_ns < 0 or max_pending < 1:
            raise ValueError("tolerance_ns must be >= 0 and max_pending >= 1")
        self.roles = roles
        self.pivot = pivot
        self.tolerance_ns = int(tolerance_ns)
        self.max_pending = int(max_pending)
        self._queues: dict[str, deque[tuple[int, Any]]] = {r: deque() for r in roles}
        self.stats = SyncStats(unmatched=dict.fromkeys(roles, 0), overflow=dict.fromkeys(roles, 0))

    def pending(self, role: str) -> int:
        return len(self._queues[role])

    def newest(self, role: str) -> int | None:
        """Stamp of the newest item waiting on `role` (None when none waits)."""
        queue = self._queues[role]
        return queue[-1][0] if queue else None

    def discard_newer(self, role: str, stamp_ns: int) -> list[int]:
        """Removes the waiting items of `role` stamped after `stamp_ns` (outliers a later message showed to
        be in the future); returns their stamps."""
        queue = self._queues[role]
        gone = []
        while queue and queue[-1][0] > stamp_ns:
            gone.append(queue.pop()[0])
        return gone[::-1]

    def push(self, role: str, stamp_ns: int, item: Any) -> list[tuple[int, dict[str, Any]]]:
        """Adds an item; returns the sets completed by it as (pivot stamp, {role: item}), oldest first."""
        queue = self._queues[role]
        if queue and stamp_ns <= queue[-1][0]:
            raise ValueError(f"{role}: stamp {stamp_ns} does not increase (last {queue[-1][0]})")
        if len(queue) == self.max_pending:
            queue.popleft()
            self.stats.overflow[role] += 1
        queue.append((int(stamp_ns), item))
        return self._match()

    def _match(self) -> list[tuple[int, dict[str, Any]]]:
        out = []
        pivots = self._queues[self.pivot]
        while pivots:
            stamp, pivot_item = pivots[0]
            chosen: dict[str, Any] = {self.pivot: pivot_item}
            waiting = dead = False
            for role in self.roles:
                if role == self.pivot:
                    continue
                queue = self._queues[role]
                # Partners too old for this pivot are too old for every later pivot too.
                while queue and queue[0][0] < stamp - self.tolerance_ns:
                    queue.popleft()
                    self.stats.unmatched[role] += 1
                best = None
                for i, (t, _) in enumerate(queue):
                    if t > stamp + self.tolerance_ns:
                        break
                    if best is None or abs(t - stamp) < abs(queue[best][0] - stamp):
                        best = i
                if best is not None:
                    chosen[role] = best
                elif queue:  # only newer items remain: this pivot can never be matched
                    dead = True
                else:
                    waiting = True
            if dead:
                pivots.popleft()
                self.stats.unmatched[self.pivot] += 1
                continue
            if waiting:
                break
            pivots.popleft()
            result = {self.pivot: pivot_item}
            for role, index in chosen.items():
                if role == self.pivot:
                    continue
                queue = self._queues[role]
                for _ in range(index):  # skipped-over partners can no longer match a later pivot better
                    queue.popleft()
                    self.stats.unmatched[role] += 1
                result[role] = queue.popleft()[1]
            self.stats.matched += 1
            out.append((stamp, result))
        return out
