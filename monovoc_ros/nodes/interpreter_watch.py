"""How long the node's Python interpreter was held at a time: a watch thread, reported in /diagnostics.

Every thread of the node (the executor taking requests, the query handlers, the worker, the map hand-over)
needs the interpreter to run Python. C code that keeps it (numpy's hashing ``np.unique``, a numba kernel
without ``nogil``, rclpy's (de)serialization of a big message) stops all of them: a query answered in 1 ms
waits for it. The watch sleeps PERIOD_S at a time; whatever it wakes late by is the longest anyone held the
interpreter (or kept the CPU) meanwhile, as an event-loop lag monitor measures a server's loop.
benchmarks/bench_interpreter_holds.py measures the same for each mapping task alone.

Who held it (`trace_after_ms`, the node's ``interpreter_hold_trace_ms``): at every wake the watch re-arms
faulthandler's watchdog, a C thread that needs no interpreter; when a hold outlasts it, the watchdog writes every
thread's Python stack to `trace_path` while the holder is still in its call. That is how the 0.12-0.3 s holds of
1M robot runs were found: the node's /diagnostics ``publish()`` waiting inside Fast DDS (rclpy keeps the
interpreter while it publishes). faulthandler has one watchdog per process: while tracing, nothing else in the
process may use ``dump_traceback_later``.

One holder the node removes at start (`freeze_startup_objects`): the garbage collector's full collections, which
walked every object start-up built.
"""

from __future__ import annotations

import faulthandler
import gc
import threading
import time
from pathlib import Path
from typing import Any

from monovoc_ros.nodes.diagnostics import Longest

PERIOD_S = 0.005  # 200 wakes a second: too few to cost anything, fine enough for holds of 10 ms and more
LONG_HOLD_MS = 50.0  # holds longer than this are counted (a query's whole budget, issue 25)
# Shortest hold traced (ms): a wake is due every PERIOD_S and the scheduler may run it a slice late.
MIN_HOLD_TRACE_MS = 20.0

# How many objects `freeze_startup_objects` froze, counted once: gc.get_freeze_count() walks the frozen list, ~18 ms
# holding the interpreter in a 1M robot run's node (its objects spread over 2 GB), at every /diagnostics message.
_frozen_objects = 0


def freeze_startup_objects() -> None:
    """Moves every object alive now out of the cyclic garbage collector (`gc.freeze`), after collecting what is
    garbage already; called once start-up has built what lives as long as the node (rclpy, numba's kernels and
    their types, the components): ~155k objects, which every full collection walked again, ~55-65 ms holding
    the interpreter in 1M robot runs (the longest hold of each of three), triggered in whichever thread
    allocated (a query's handler, the worker building markers). Later full collections walk what came after."""
    global _frozen_objects
    gc.collect()
    gc.freeze()
    _frozen_objects = gc.get_freeze_count()


class InterpreterWatch:
    def __init__(self, period_s: float = PERIOD_S, trace_after_ms: float = 0.0, trace_path: str | None = None) -> None:
        """`trace_after_ms` > 0: holds longer than that write every thread's stack to `trace_path` (appended)."""
        if trace_after_ms and (trace_after_ms < MIN_HOLD_TRACE_MS or not trace_path):
            raise ValueError(f"trace_after_ms: 0, or >= {MIN_HOLD_TRACE_MS:g} with a trace_path")
        self.period_s = period_s
        self.trace_path = trace_path if trace_after_ms else None
        self._trace_after_s = trace_after_ms / 1e3
        # The time kept is when the longest hold ended (the wake that saw it).
        keys = ("interpreter_hold_ms_max", "interpreter_hold_max_at", f"interpreter_holds_over_{LONG_HOLD_MS:.0f}ms")
        self._longest = Longest(keys, LONG_HOLD_MS)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="monovoc-interpreter-watch", daemon=True)
        # Opened here: a trace file that cannot be written fails the node's start (OSError), as the user asked for it.
        self._trace = None
        if self.trace_path is not None:
            Path(self.trace_path).parent.mkdir(parents=True, exist_ok=True)
            self._trace = open(self.trace_path, "a")  # closed when the watch ends

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(1.0)

    def _run(self) -> None:
        trace = self._trace
        try:
            last = time.perf_counter()
            while not self._stop.wait(self.period_s):
                if trace is not None:  # replaces the watchdog armed at the last wake
                    faulthandler.dump_traceback_later(self._trace_after_s, file=trace)
                now = time.perf_counter()
                self.record(1e3 * (now - last - self.period_s), time.time())
                last = now
        finally:
            if trace is not None:
                faulthandler.cancel_dump_traceback_later()
                trace.close()

    def reset(self) -> None:
        """Forgets what was recorded (benchmarks/bench_interpreter_holds.py: one task at a time)."""
        self._longest.reset()

    def record(self, late_ms: float, at: float) -> None:
        """One wake, ``late_ms`` after it was due (the watch's own loop; public for the tests)."""
        self._longest.add(late_ms, at)

    def diagnostics(self) -> dict[str, Any]:
        values = self._longest.values()
        values["gc_frozen_objects"] = _frozen_objects
        if self.trace_path is not None:
            values["interpreter_hold_trace_file"] = self.trace_path
        return values
