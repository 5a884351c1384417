"""An rclpy node for replay and record, in its own context, torn down in the order rclpy needs.

Own context: the tools can run inside a process that has other rclpy contexts (tests, the demo).
rclpy's signal handlers are not installed: Ctrl-C arrives as ``KeyboardInterrupt`` in the main thread
and SIGTERM sets the ``stop`` event (``install_stop_signals``), so files and acknowledgements are
finished properly either way.

Replay's writers get a Fast DDS heartbeat period of WRITER_HEARTBEAT_MS instead of 3 s (when no Fast
DDS profile is configured): a reliable reader acknowledges only on a heartbeat, so with the default the
final ``wait_for_all_acked`` of a fast replay idled up to 3 s (measured 2.9 s of a 3.3 s replay of the
bundled bag; 0.5 s with the profile). Fast DDS reads the profile once per process, when the first
participant is created, so a process that replays beside another context (ros_harness.ClientNode:
tests, the demo, benchmarks) must create its first context and node under `writer_heartbeat` too.
"""

from __future__ import annotations

import contextlib
import os
import signal
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

WRITER_HEARTBEAT_MS = 50  # acknowledgements within ~50 ms instead of Fast DDS's 3 s
_PROFILES_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"
_WRITER_PROFILE = """<?xml version="1.0" encoding="UTF-8"?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <data_writer profile_name="monovoc_replay_writer" is_default_profile="true">
    <times><heartbeatPeriod><sec>0</sec><nanosec>{ns}</nanosec></heartbeatPeriod></times>
  </data_writer>
</profiles>
"""


@contextlib.contextmanager
def writer_heartbeat(period_ms: int | None) -> Iterator[None]:
    # Fast DDS reads the default profiles file when it creates the process's first participant (with
    # the first node of the first context); a user's own profile, another middleware or an earlier
    # context in the process win.
    rmw = os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    if period_ms is None or os.environ.get(_PROFILES_ENV) or rmw != "rmw_fastrtps_cpp":
        yield
        return
    fd, name = tempfile.mkstemp(prefix="monovoc_replay_", suffix=".xml")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(_WRITER_PROFILE.format(ns=int(period_ms) * 1_000_000))
        os.environ[_PROFILES_ENV] = name
        yield
    finally:
        os.environ.pop(_PROFILES_ENV, None)
        Path(name).unlink(missing_ok=True)


@contextlib.contextmanager
def ros_node(name: str, node: Any = None, *, writer_heartbeat_ms: int | None = None) -> Iterator[Any]:
    """Yields ``node`` when given (its owner keeps it); else a new node in a new context, destroyed on exit.

    ``writer_heartbeat_ms``: the Fast DDS heartbeat period of the writers (see above). The profile is
    process-wide: it takes effect only if this node creates the process's first participant, and then
    every later writer of the process has it too.
    """
    if node is not None:
        yield node
        return
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    context = rclpy.Context()
    own = None
    try:
        # The participant (and with it the profile) comes with the context's first node, not with init.
        with writer_heartbeat(writer_heartbeat_ms):
            rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
            own = rclpy.create_node(name, context=context, start_parameter_services=False)
        yield own
    finally:
        if own is not None:
            own.destroy_node()
        context.try_shutdown()


@contextlib.contextmanager
def spinning(node: Any) -> Iterator[Any]:
    """Spins ``node`` in a background thread; stops the executor and joins the thread before leaving."""
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    stop = threading.Event()

    def spin() -> None:
        # spin_once in a loop, not spin(): shutting an executor down while another thread waits in it lets
        # rclpy destroy the wait set under that thread (AttributeError: 'NoneType' object has no attribute
        # 'handle'); the loop ends first and the executor is shut down after the join.
        with contextlib.suppress(ExternalShutdownException):
            while not stop.is_set() and node.context.ok():
                executor.spin_once(timeout_sec=0.05)

    thread = threading.Thread(target=spin, name=f"{node.get_name()}-spin", daemon=True)
    thread.start()
    try:
        yield executor
    finally:
        stop.set()
        thread.join(5.0)
        executor.shutdown(timeout_sec=5.0)


def install_stop_signals(stop: threading.Event) -> None:
    """SIGTERM (and SIGHUP) set ``stop``; call from the main thread of a command."""
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, lambda *_: stop.set())
