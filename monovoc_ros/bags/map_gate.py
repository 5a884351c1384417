"""A --fast replay's wait after each map message until a node reports that it took it (monovoc_ros.bags.replayer).

A SLAM poses the keyframes after a map in it. Replayed as fast as possible, the keyframes after a map overtook it on
the way into the node (it decodes a map in a process of its own: ~30 ms at 140k Gaussians, ~170 ms at 1M), and went
into the map before it with poses of the new one (36 of 40 in a bag of the synthetic room with two loop closures).
So after a map message the replay waits until a node's /diagnostics count of maps taken from the topic
(`maps_received`, nodes/diagnostics.MapperStats) has grown; the keyframes after it are then queued behind it. A
replay that finds no node reporting that count within FIND_S of its start does not wait (another consumer).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from monovoc_ros.contract import DIAGNOSTICS_TOPIC

MAPS_RECEIVED_KEY = "maps_received"  # the /diagnostics key of MapperStats.maps_received
FIND_S = 3.0  # how long a replay looks for a node reporting the count (the node's default period is 1 s)
WAIT_S = 30.0  # how long it waits for one map to be taken


class MapGate:
    """Per /diagnostics status (a node) the newest count of maps it took, from a subscription on `node`, which the
    caller spins."""

    def __init__(self, node: Any) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        self._changed = threading.Condition()
        self._taken: dict[str, int] = {}  # status name -> maps_received
        self.missed = 0  # maps no node reported taken within WAIT_S (after the first, the gate no longer waits)
        self._subscription = node.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, self._on_diagnostics, 10)

    def _on_diagnostics(self, msg: Any) -> None:
        with self._changed:
            for status in msg.status:
                for pair in status.values:
                    if pair.key == MAPS_RECEIVED_KEY and pair.value.isdigit():
                        self._taken[status.name] = int(pair.value)
            self._changed.notify_all()

    def counts(self) -> dict[str, int]:
        with self._changed:
            return dict(self._taken)

    def wait_taken(self, before: dict[str, int], stop: threading.Event, timeout: float = WAIT_S) -> None:
        """After a map was published (`before`: `counts()` just before): waits until a node's count grew past it; a
        map not reported within `timeout` is counted in `missed`, and the gate waits no more (its node is gone)."""
        taken = self._wait(lambda now: any(n > before.get(name, 0) for name, n in now.items()), timeout, stop)
        if not taken and not stop.is_set():
            self.missed += 1

    def found(self, stop: threading.Event, timeout: float = FIND_S) -> bool:
        """Whether a node reports the count within `timeout`."""
        return self._wait(bool, timeout, stop)

    def _wait(self, done: Callable[[dict[str, int]], bool], timeout: float, stop: threading.Event) -> bool:
        deadline = time.monotonic() + timeout
        with self._changed:
            while not done(self._taken):
                left = deadline - time.monotonic()
                if left <= 0 or stop.is_set():
                    return False
                self._changed.wait(min(left, 0.1))
        return True
