"""The query and ask handlers' own time (monovoc_ros.nodes.object_query.HandlerTimes), reported in /diagnostics
to tell the node's part of a slow answer from the part spent in DDS and the executor."""

from __future__ import annotations

import threading
import time

import pytest

from monovoc_ros.nodes.object_query import SLOW_ANSWER_MS, HandlerTimes


def test_the_slowest_handler_and_the_slow_ones_are_counted():
    times = HandlerTimes()

    entered = []

    def handler(request, response):
        entered.append(time.time())
        time.sleep(request)
        return response

    timed = times.timed(handler)
    assert timed(0.0, "fast") == "fast"
    before = time.time()
    assert timed(SLOW_ANSWER_MS / 1e3 + 0.02, "slow") == "slow"
    values = times.diagnostics()
    assert values["queries.handler_ms_max"] >= SLOW_ANSWER_MS + 20
    assert values[f"queries.handler_over_{SLOW_ANSWER_MS:.0f}ms"] == 1
    # When the slow one began: after the call was made, no later than its handler ran.
    assert before - 0.001 <= values["queries.handler_slowest_at"] <= entered[-1] + 0.001  # kept to the ms


def test_a_failing_handler_is_timed_and_side_by_side_calls_are_all_counted():
    times = HandlerTimes()

    def failing(request, response):
        time.sleep(SLOW_ANSWER_MS / 1e3 + 0.01)
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError):
        times.timed(failing)(None, None)
    calls = [threading.Thread(target=times.timed(lambda q, r: time.sleep(0.06)), args=(None, None)) for _ in range(4)]
    for call in calls:
        call.start()
    for call in calls:
        call.join()
    assert times.diagnostics()[f"queries.handler_over_{SLOW_ANSWER_MS:.0f}ms"] == 5
