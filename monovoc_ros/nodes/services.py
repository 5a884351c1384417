"""One guard around every service callback: whatever goes wrong, the client gets an answer.

An exception that escapes a service callback is re-raised by the rclpy executor and ends the node (a
corrupt snapshot passed to load_map did exactly that). `guarded(srv_type, name, handler, ...)` wraps a
handler so that ANY exception becomes a fresh response with `success: false` and a message naming the
service and the problem; the handler's contract is to change state only once everything it needs has
been read and checked, so a failure leaves the state as it was.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable
from typing import Any

Handler = Callable[[Any, Any], Any]


def guarded(
    srv_type: type,
    name: str,
    handler: Handler,
    *,
    log: Callable[[str], Any] | None = None,
    on_error: Callable[[], None] | None = None,
    text_field: str = "message",
) -> Handler:
    """`handler(request, response)` that never raises; failures answer success=false with the reason in
    `text_field` (`answer` for Ask), counted through `on_error`, logged through `log`."""

    def call(request: Any, response: Any) -> Any:
        try:
            return handler(request, response)
        except Exception as exc:  # the one guard: no exception may reach the executor
            if on_error is not None:
                on_error()
            if log is not None:
                log(f"service {name} failed: {type(exc).__name__}: {exc}\n{traceback.format_exc(limit=4)}")
            fresh = srv_type.Response()
            fresh.success = False
            setattr(fresh, text_field, f"{name} failed: {type(exc).__name__}: {exc}")
            return fresh

    return call
