"""An rclpy node for replay and record, in its own context, torn down in the order rclpy needs.

Own context: the tools can run inside a process that has other rclpy contexts (tests, the demo).
rclpy's signal handlers are not installed: Ctrl-C arrives as ``KeyboardInterrupt`` in the main thread
and SIGTERM sets the ``stop`` event (``install_stop_signals``), so files and acknowledgements are
finished properly either way.

Replay's writers get a short Fast DDS heartbeat (monovoc_ros.fastdds_profile): Fast DDS reads the profile
once per process, when the first participant is created, so a process that replays beside another context
(ros_harness.ClientNode: tests, the demo, benchmarks) must create its first context and node under it too.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from typing import Any

from monovoc_ros.fastdds_profile import writer_heartbeat


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
            # args=[]: the command's own arguments are not ROS arguments (rcl took replay's `--remap A:=B` for
            # deprecated global remap rules, with a warning each).
            rclpy.init(args=[], context=context, signal_handler_options=SignalHandlerOptions.NO)
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
