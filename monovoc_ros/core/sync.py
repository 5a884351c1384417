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
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any


def lead_over_others(stamp: int, others: Iterable[int | None], max_lead_ns: int) -> int | None:
    """How far `stamp` is ahead of the newest stamp of every other topic (`others`, None = nothing yet) when
    that is more than `max_lead_ns` (> 0; 0 disables the rule), else None (StampEpochs' test)."""
    known = [t for t in others if t is not None]
    if not max_lead_ns or not known:
        return None
    lead = stamp - max(known)
    return lead if lead > max_lead_ns else None


@dataclass(frozen=True)
class Held:
    role: str
    stamp_ns: int
    item: Any


class StampEpochs:
    """The far-future rule with epochs, for the assembler and the node's reorder stage alike.

    A stamp more than `max_lead_ns` ahead of the node's clock (where there is one: ROS time, `/clock` under
    sim time) is refused at once. A stamp more than `max_lead_ns` ahead of the newest stamp of every other
    topic is either an outlier (a bad header, possibly copied onto every message of one keyframe) or the
    first message after a pause (a robot that stood still, a restarted driver or SLAM, a later bag): the
    keyframe topics all resume at once, far ahead of the stamps the pause froze. Such a message is held, not
    refused. The topics agree on a new epoch once every topic holds a message within `max_lead_ns` of it and
    one topic holds two such stamps (a stream, not one keyframe): then the held messages near it go on, in
    stamp order (counted in `epochs`, not as rejections), and held ones behind the new epoch are refused. A
    later message of the held one's own topic far behind it shows it was an outlier: it is refused then. So
    a pause of any length locks nothing out, and neither a lone outlier nor one whole keyframe stamped in
    the future blocks anything. Stamps that jump back are not an epoch: they stay out of order."""

    def __init__(
        self,
        roles: Iterable[str],
        max_lead_ns: int,
        max_held: int = 32,
        clock: Callable[[], int | None] | None = None,
    ) -> None:
        self.roles = tuple(roles)
        self.max_lead_ns = int(max_lead_ns)
        self.max_held = int(max_held)
        self.clock = clock  # now in ns, or None / 0 while unknown (sim time before the first /clock)
        self._held: dict[str, deque[Held]] = {r: deque() for r in self.roles}
        self.epochs = 0  # new epochs agreed on (streams resumed after a pause)

    @property
    def held(self) -> int:
        return sum(len(q) for q in self._held.values())

    def offer(
        self, role: str, stamp_ns: int, item: Any, newest: Mapping[str, int | None]
    ) -> tuple[list[Held], list[tuple[Held, str]]]:
        """Judges one message of one of `roles` against `newest` (per topic, the newest stamp taken). Returns
        (the messages to take now, in stamp order: this one unless it is held, and those of an agreed epoch;
        messages refused, each with why)."""
        this = Held(role, int(stamp_ns), item)
        lead_ns = self.max_lead_ns
        if not lead_ns:
            return [this], []
        now = self.clock() if self.clock is not None else None
        if now and this.stamp_ns > now + lead_ns:
            ahead = (this.stamp_ns - now) / 1e9
            return [], [
                (this, f"{role} stamp {this.stamp_ns} is {ahead:.3g} s ahead of this host's clock (time sync?)")
            ]
        own = self._held[role]
        if lead_over_others(this.stamp_ns, (t for r, t in newest.items() if r != role), lead_ns) is None:
            refused = [(h, self._ahead(h, this)) for h in own if h.stamp_ns > this.stamp_ns + lead_ns]
            if refused:
                self._held[role] = deque(h for h in own if h.stamp_ns <= this.stamp_ns + lead_ns)
            return [this], refused
        own.append(this)
        if self._agreed(this.stamp_ns):
            self.epochs += 1  # every topic resumed near this stamp: a new epoch
            go, refused = [], []
            for r, q in self._held.items():
                go += [h for h in q if abs(h.stamp_ns - this.stamp_ns) <= lead_ns]
                refused += [(h, f"{r} stamp {h.stamp_ns} held behind the new epoch") for h in q
                            if h.stamp_ns < this.stamp_ns - lead_ns]  # fmt: skip
                self._held[r] = deque(h for h in q if h.stamp_ns > this.stamp_ns + lead_ns)
            return sorted(go, key=lambda h: h.stamp_ns), refused
        if len(own) <= self.max_held:
            return [], []
        gone = own.popleft()
        return [], [(gone, f"{role} stamp {gone.stamp_ns}: {self.max_held + 1} far-future messages, none agreed on")]

    def _agreed(self, stamp_ns: int) -> bool:
        near = {
            r: {h.stamp_ns for h in q if abs(h.stamp_ns - stamp_ns) <= self.max_lead_ns} for r, q in self._held.items()
        }
        return all(near[r] for r in self.roles) and any(len(stamps) >= 2 for stamps in near.values())

    def _ahead(self, held: Held, later: Held) -> str:
        return (
            f"{held.role} stamp {held.stamp_ns} was {(held.stamp_ns - later.stamp_ns) / 1e9:.3g} s ahead of a later one"
        )

    def clear(self) -> None:
        for q in self._held.values():
            q.clear()


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
