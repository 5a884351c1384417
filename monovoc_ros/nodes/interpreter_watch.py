"""How long the node's Python interpreter was held at a time: a watch thread, reported in /diagnostics.

Every thread of the node (the executor taking requests, the query handlers, the worker, the map hand-over)
needs the interpreter to run Python. C code that keeps it (numpy's hashing ``np.unique``, a numba kernel
without ``nogil``, rclpy's (de)serialization of a big message) stops all of them: a query answered in 1 ms
waits for it. The watch sleeps PERIOD_S at a time; whatever it wakes late by is the longest anyone held the
interpreter (or kept the CPU) meanwhile, as an event-loop lag monitor measures a server's loop.
benchmarks/bench_interpreter_holds.py measures the same for each mapping task alone.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from monovoc_ros.nodes.diagnostics import Longest

PERIOD_S = 0.005  # 200 wakes a second: too few to cost anything, fine enough for holds of 10 ms and more
LONG_HOLD_MS = 50.0  # holds longer than this are counted (a query's whole budget, issue 25)


class InterpreterWatch:
    def __init__(self, period_s: float = PERIOD_S) -> None:
        self.period_s = period_s
        # The time kept is when the longest hold ended (the wake that saw it).
        keys = ("interpreter_hold_ms_max", "interpreter_hold_max_at", f"interpreter_holds_over_{LONG_HOLD_MS:.0f}ms")
        self._longest = Longest(keys, LONG_HOLD_MS)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="monovoc-interpreter-watch", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(1.0)

    def _run(self) -> None:
        last = time.perf_counter()
        while not self._stop.wait(self.period_s):
            now = time.perf_counter()
            self.record(1e3 * (now - last - self.period_s), time.time())
            last = now

    def reset(self) -> None:
        """Forgets what was recorded (benchmarks/bench_interpreter_holds.py: one task at a time)."""
        self._longest.reset()

    def record(self, late_ms: float, at: float) -> None:
        """One wake, ``late_ms`` after it was due (the watch's own loop; public for the tests)."""
        self._longest.add(late_ms, at)

    def diagnostics(self) -> dict[str, Any]:
        return self._longest.values()
