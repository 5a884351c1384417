"""An output built only while something subscribes to it, and sent to a subscriber that appears later.

At robot scale the big outputs (the semantic cloud: 24 MB at 1M Gaussians; a query's highlight) cost the node
~16-110 ms each to build and serialize, for nobody when no viewer runs. `SubscribedOutput.wanted` tells the
publishing thread whether to build one, and keeps what it left out; the publisher's matched event (executor
thread) hands that to `on_subscriber`, so a late subscriber still gets the newest output, as the transient-local
QoS promises. The lock orders the publishing thread's check of the subscriber count against the matched event:
a subscriber that appears meanwhile is never missed.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from rclpy.event_handler import PublisherEventCallbacks

from monovoc_ros.nodes.qos import output_events


class SubscribedOutput:
    def __init__(self, on_subscriber: Callable[[Any], None] | None = None) -> None:
        """`on_subscriber(left_out)`: called on the executor's thread when a subscriber appears and an output was
        left out (`left_out` is what `wanted` was given then)."""
        self.publisher: Any = None  # the publisher created with `events()`, set by its owner
        self.skipped = 0  # outputs left out (counted in /diagnostics)
        self._on_subscriber = on_subscriber
        self._lock = threading.Lock()
        self._left_out: Any = None

    def events(self) -> PublisherEventCallbacks:
        """The publisher's event callbacks (`qos.output_events` with this output's matched event)."""
        return output_events(matched=self._matched)

    def wanted(self, what: Any = True) -> bool:
        """Whether anything subscribes (publishing thread); if not, `what` (not None) is kept for the next subscriber
        and the output counted as skipped."""
        with self._lock:
            if self.publisher.get_subscription_count() > 0:
                self._left_out = None
                return True
            self._left_out = what
            self.skipped += 1
            return False

    def _matched(self, status: Any) -> None:
        if status.current_count_change <= 0:
            return
        with self._lock:
            left_out, self._left_out = self._left_out, None
        if left_out is not None and self._on_subscriber is not None:
            self._on_subscriber(left_out)
