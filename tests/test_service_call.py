"""The resend rule of monovoc_ros.nodes.service_call, against a client whose server loses chosen answers."""

from __future__ import annotations

import time

import pytest
from rclpy.task import Future

from monovoc_ros.nodes.service_call import call_service


class LossyClient:
    """Answers request n (0-based) with "answer n" unless n is in ``lost``, the way a server whose response
    writer had not matched the client drops an answer; keeps the pending futures like rclpy's Client."""

    def __init__(self, lost: set[int]):
        self.lost = lost
        self.sent: list[float] = []
        self.pending: list[Future] = []

    def call_async(self, request: str) -> Future:
        future = Future()
        n = len(self.sent)
        self.sent.append(time.monotonic())
        self.pending.append(future)
        if n not in self.lost:
            future.set_result(f"{request}: answer {n}")
        return future

    def remove_pending_request(self, future: Future) -> None:
        self.pending.remove(future)


def test_a_lost_first_answer_is_recovered_by_sending_again():
    client = LossyClient(lost={0})
    assert call_service(client, "q", 5.0, time.sleep, resend_s=0.05) == "q: answer 1"
    assert len(client.sent) == 2
    assert client.sent[1] - client.sent[0] >= 0.05
    assert all(f.done() for f in client.pending)  # the lost request is no longer pending


def test_resends_back_off_and_stop_at_the_deadline():
    client = LossyClient(lost=set(range(100)))
    start = time.monotonic()
    assert call_service(client, "q", 0.5, time.sleep, resend_s=0.05) is None
    assert 0.5 <= time.monotonic() - start < 1.5
    gaps = [b - a for a, b in zip(client.sent, client.sent[1:], strict=False)]
    assert len(client.sent) == 4  # at 0, 0.05, 0.15, 0.35 s; the next would be at 0.75
    assert gaps == sorted(gaps)
    assert client.pending == []


def test_requests_that_must_run_once_are_never_resent():
    client = LossyClient(lost={0})
    assert call_service(client, "save", 0.3, time.sleep, resend_s=None) is None
    assert len(client.sent) == 1


def test_poll_failures_reach_the_caller():
    client = LossyClient(lost={0})

    def poll() -> None:
        raise RuntimeError("the node exited")

    with pytest.raises(RuntimeError, match="the node exited"):
        call_service(client, "q", 5.0, time.sleep, poll=poll)
    assert client.pending == []


def test_only_cheap_read_only_requests_are_resent_by_default():
    from monovoc_interfaces.srv import Reset, SaveMap, TextQuery
    from monovoc_ros.nodes.service_call import RESEND_S, default_resend

    assert default_resend(TextQuery.Request(text="a chair")) == RESEND_S
    assert default_resend(SaveMap.Request()) is None and default_resend(Reset.Request()) is None
    with pytest.raises(ValueError, match="resend_s"):
        call_service(LossyClient(lost=set()), "q", 1.0, time.sleep, resend_s=0.0)
