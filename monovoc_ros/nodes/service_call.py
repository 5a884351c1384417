"""One service call that survives a lost first answer.

Fast DDS (rmw_fastrtps, Jazzy) drops a response when the server has not matched the client's response
reader within the writer's max_blocking_time (100 ms): the server logs "failed to send response (timeout):
client will not receive response" and the caller waits forever. A fresh client's first call on a loaded
machine hits it (CI once saw a warm-up query time out after 30 s), and `service_is_ready()` only reports the
client's half of the match. So an idempotent request is sent again when no answer came within `resend_s`
(doubling each time); the first answer wins and the other requests are dropped from the client. Only
cheap read-only requests are resent by default (`RESENT_REQUESTS`): a slow load_map or reset that ran
twice would hold executor threads, or wipe what came after it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

RESEND_S = 2.0
# Request classes (rclpy's "<Service>_Request") that may run any number of times: read-only (ApproachPose draws
# its arrow again) and cheap (a resent ApproachPose that came while the first builds the free-space grid of a
# new map waits for that grid, holding an executor thread meanwhile; resends come at 2, 6, 14 s).
RESENT_REQUESTS = frozenset(
    {"TextQuery_Request", "Ask_Request", "ApproachPose_Request", "GetParameters_Request", "DescribeParameters_Request"}
)


def default_resend(request: Any) -> float | None:
    """RESEND_S for the requests of RESENT_REQUESTS, else None (sent once)."""
    return RESEND_S if type(request).__name__ in RESENT_REQUESTS else None


def call_service(
    client: Any,
    request: Any,
    timeout_s: float,
    wait: Callable[[float], None],
    *,
    resend_s: float | None = RESEND_S,
    poll: Callable[[], None] | None = None,
) -> Any | None:
    """The response, or None after ``timeout_s``. ``wait(seconds)`` lets the client's node spin (spin_once,
    or sleep when an executor spins it in another thread); ``poll`` runs between waits and may raise (a
    watched process that died). ``resend_s`` None sends once: for requests that must not run twice."""
    if resend_s is not None and not resend_s > 0:
        raise ValueError(f"resend_s must be > 0 or None, got {resend_s!r}")
    start = time.monotonic()
    deadline = start + timeout_s
    futures = [client.call_async(request)]
    next_send = None if resend_s is None else start + resend_s
    gap = resend_s
    try:
        while True:
            for future in futures:
                if future.done():
                    return future.result()
            if poll is not None:
                poll()
            now = time.monotonic()
            if now >= deadline:
                return None
            if next_send is not None and now >= next_send:
                futures.append(client.call_async(request))
                gap *= 2.0
                next_send = now + gap
            wait(min(0.01, deadline - now))
    finally:
        for future in futures:
            if not future.done():
                client.remove_pending_request(future)
