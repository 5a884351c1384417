"""The node's watch on interpreter holds (monovoc_ros.nodes.interpreter_watch): a hold by C code that keeps the
GIL is seen, measured and counted."""

from __future__ import annotations

import ctypes
import time

from monovoc_ros.nodes.interpreter_watch import LONG_HOLD_MS, InterpreterWatch

LONG = f"interpreter_holds_over_{LONG_HOLD_MS:.0f}ms"


def _hold_interpreter(seconds: float) -> None:
    # PyDLL keeps the GIL during the call: C code that does not release it, as numpy's hashing np.unique.
    ctypes.PyDLL(None).usleep(int(seconds * 1e6))


def test_a_hold_is_measured_and_counted():
    watch = InterpreterWatch()
    watch.start()
    try:
        time.sleep(0.05)
        before = time.time()
        _hold_interpreter(0.12)
        time.sleep(0.05)
    finally:
        watch.stop()
    values = watch.diagnostics()
    assert 100.0 <= values["interpreter_hold_ms_max"] < 1000.0, values
    assert values[LONG] >= 1
    assert before + 0.1 <= values["interpreter_hold_max_at"] <= time.time()


def test_the_longest_hold_and_when_it_ended_are_kept():
    watch = InterpreterWatch()
    assert watch.diagnostics() == {"interpreter_hold_ms_max": 0.0, "interpreter_hold_max_at": 0.0, LONG: 0}
    watch.record(LONG_HOLD_MS + 1, 5.0)
    watch.record(3.0, 6.0)
    values = watch.diagnostics()
    assert values[LONG] == 1 and values["interpreter_hold_ms_max"] == LONG_HOLD_MS + 1
    assert values["interpreter_hold_max_at"] == 5.0
    watch.reset()
    assert watch.diagnostics() == {"interpreter_hold_ms_max": 0.0, "interpreter_hold_max_at": 0.0, LONG: 0}
