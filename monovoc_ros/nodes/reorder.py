"""Feeds the keyframe topics to the KeyframeAssembler in header-stamp order, whatever order they arrive in.

Each topic is delivered in order, but the topics are not in step with each other: during a burst (a bag
replayed with --fast, a backlog after a network hiccup) the executor can hand over dozens of messages of
one topic before the first of another. The assembler's synchronizer buffers only `sync_max_pending`
decoded messages per topic, so such a skew lost keyframes (measured: 64 of 96 in a burst of 96).

`StampReorder` keeps the raw messages (compressed, cheap) per topic and releases the oldest head once
every other topic has a message waiting or has already delivered that stamp (each topic is in order, so
nothing older can come from it), so the synchronizer sees the streams merged by stamp and a keyframe goes
on as soon as its last message arrives. A message
is released anyway once it has waited `max_wait_s` and every topic it waits for has been silent for
`max_wait_s` (a topic that stopped, or that will never send this stamp), or when a topic holds
`max_buffered` messages, so nothing waits forever. A topic that is still delivering is only behind: at
start-up, while the node loaded its models, the masks of a --fast replay ran more than 0.5 s behind the
images, and a wait counted from the image's arrival alone lost 23 of 60 keyframes; on two busy cores one
topic's callbacks also stalled for more than 0.5 s while another's ran (a backlog lost up to half its
keyframes), hence the 3 s default. Per-topic order is
never changed: out-of-order and duplicate stamps still reach the assembler as sent, and are rejected there.
The one exception are far-future stamps (more than `max_lead_s` ahead of every other topic): they are held
aside (core.sync.StampEpochs, as in the assembler; at most `max_held` per topic) until every topic agrees on
their epoch (the streams resumed after a pause: they are queued then) or a later message of their own topic
shows them outliers (passed on at once, the assembler rejects them: stamp_future), so one outlier neither
holds its topic's later messages back nor releases the other topics early. A far-future message that comes
before any other topic has sent anything cannot be judged yet: it is queued, and goes out as an outlier
when a later message of its topic shows it one.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

from monovoc_ros.core.sync import StampEpochs
from msg_adapters import header_stamp_ns


class StampReorder:
    def __init__(
        self,
        roles: Sequence[str],
        max_wait_s: float = 3.0,
        max_buffered: int = 1000,
        max_held: int = 32,
        clock: Callable[[], float] = time.monotonic,
        max_lead_s: float = 30.0,
        clock_ns: Callable[[], int | None] | None = None,
    ) -> None:
        self.roles = tuple(roles)
        self.max_lead_ns = int(round(max_lead_s * 1e9))
        self.max_wait_s = max_wait_s
        self.max_buffered = max_buffered
        self._clock = clock
        # role -> (stamp or None, arrival time, message); the role's rank breaks ties at equal stamps
        self._queues: dict[str, deque[tuple[int | None, float, Any]]] = {r: deque() for r in self.roles}
        self._rank = {r: i for i, r in enumerate(self.roles)}
        self._last_arrival = dict.fromkeys(self.roles, -float("inf"))
        self._passed: dict[str, int | None] = dict.fromkeys(self.roles)  # newest stamp each topic delivered
        self.epochs = StampEpochs(
            self.roles, self.max_lead_ns, max_held, clock_ns
        )  # far-future stamps: outliers or a pause
        self.released_early = 0  # messages let go without their partners (waited too long, or overflow)

    def __len__(self) -> int:
        return sum(len(q) for q in self._queues.values())

    def add(self, role: str, msg: Any) -> list[tuple[str, Any]]:
        """Adds one message; returns the (role, message) pairs now due, in the order to push them."""
        try:
            stamp: int | None = header_stamp_ns(msg)
        except ValueError:
            stamp = None  # no readable stamp: released at once, the assembler rejects it
        now = self._clock()
        if stamp is None:
            return self._queue(role, None, now, msg)
        go, refused = self.epochs.offer(role, stamp, msg, self._passed)
        out = [(h.role, h.item) for h, _ in refused]  # to the assembler, whose own StampEpochs refuses them
        for held in go:
            out += self._queue(held.role, held.stamp_ns, now, held.item)
        return out

    def _queue(self, role: str, stamp: int | None, now: float, msg: Any) -> list[tuple[str, Any]]:
        outliers: list[tuple[str, Any]] = []
        queue = self._queues[role]
        if (
            stamp is not None
            and self.max_lead_ns
            and any(s is not None and s > stamp + self.max_lead_ns for s, _, _ in queue)
        ):
            # Queued far-future messages of this topic (sent before any other topic): out now, so they do not
            # hold this one back.
            outliers = [(role, m) for s, _, m in queue if s is not None and s > stamp + self.max_lead_ns]
            kept = [e for e in queue if not (e[0] is not None and e[0] > stamp + self.max_lead_ns)]
            queue.clear()
            queue.extend(kept)
            self._passed[role] = max((e[0] for e in kept if e[0] is not None), default=None)
        queue.append((stamp, now, msg))
        self._last_arrival[role] = now
        if stamp is not None:
            passed = self._passed[role]
            self._passed[role] = stamp if passed is None else max(passed, stamp)
        return [*outliers, *self.due()]

    def due(self) -> list[tuple[str, Any]]:
        """Messages that may go now: the oldest head once every other topic has a head or has delivered its
        stamp already (nothing older can come: each topic is in order); stale or overflowing heads."""
        out = []
        while True:
            heads = {r: q[0] for r, q in self._queues.items() if q}
            if not heads:
                return out
            role = min(heads, key=lambda r: (heads[r][0] if heads[r][0] is not None else -1, self._rank[r]))
            oldest = heads[role][0]
            missing = [r for r in self.roles if r not in heads]
            if oldest is not None and all(self._passed[r] is not None and self._passed[r] >= oldest for r in missing):
                out.append((role, self._queues[role].popleft()[2]))
                continue
            now = self._clock()
            # Waiting ends max_wait_s after the later of the head's arrival and the last message of the
            # topics it waits for.
            heard = max((self._last_arrival[r] for r in self.roles if r not in heads), default=-float("inf"))
            forced = [r for r, (stamp, arrived, _) in heads.items()
                      if stamp is None or now - max(arrived, heard) >= self.max_wait_s
                      or len(self._queues[r]) > self.max_buffered]  # fmt: skip
            if not forced:
                return out
            # Even when a head is forced out, the oldest of all heads goes first: stamp order is kept.
            out.append((role, self._queues[role].popleft()[2]))
            self.released_early += 1

    def clear(self) -> None:
        for q in self._queues.values():
            q.clear()
        self._last_arrival = dict.fromkeys(self.roles, -float("inf"))
        self._passed = dict.fromkeys(self.roles)
        self.epochs.clear()
