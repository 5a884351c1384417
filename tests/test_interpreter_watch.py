"""The node's watch on interpreter holds (monovoc_ros.nodes.interpreter_watch): a hold by C code that keeps the
GIL is seen, measured and counted."""

from __future__ import annotations

import ctypes
import time

import pytest

from monovoc_ros.nodes.interpreter_watch import LONG_HOLD_MS, InterpreterWatch

LONG = f"interpreter_holds_over_{LONG_HOLD_MS:.0f}ms"
# What a watch reports before any hold (gc_frozen_objects: this process's, 0 unless start-up froze them).
EMPTY = {"interpreter_hold_ms_max": 0.0, "interpreter_hold_max_at": 0.0, LONG: 0, "gc_frozen_objects": 0}


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
    assert watch.diagnostics() == EMPTY
    watch.record(LONG_HOLD_MS + 1, 5.0)
    watch.record(3.0, 6.0)
    values = watch.diagnostics()
    assert values[LONG] == 1 and values["interpreter_hold_ms_max"] == LONG_HOLD_MS + 1
    assert values["interpreter_hold_max_at"] == 5.0
    watch.reset()
    assert watch.diagnostics() == EMPTY


def _held_by_this_function(seconds: float) -> None:
    _hold_interpreter(seconds)


def test_a_traced_hold_names_its_holder(tmp_path):
    """interpreter_hold_trace_ms: a hold longer than the threshold writes every thread's stack, the holder's
    call included, while it holds; a shorter one writes nothing."""
    path = tmp_path / "logs" / "holds.txt"
    watch = InterpreterWatch(trace_after_ms=150.0, trace_path=str(path))
    watch.start()
    try:
        time.sleep(0.05)
        _hold_interpreter(0.02)
        time.sleep(0.05)
        assert path.read_text() == ""
        _held_by_this_function(0.4)
        time.sleep(0.05)
    finally:
        watch.stop()
    text = path.read_text()
    assert text.count("Timeout") == 1 and "_held_by_this_function" in text, text
    assert watch.diagnostics()["interpreter_hold_trace_file"] == str(path)
    for bad in ({"trace_after_ms": 5.0, "trace_path": str(path)}, {"trace_after_ms": 60.0}):
        with pytest.raises(ValueError, match="trace_after_ms"):
            InterpreterWatch(**bad)
    assert "interpreter_hold_trace_file" not in InterpreterWatch().diagnostics()
