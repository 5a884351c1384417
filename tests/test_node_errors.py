"""Background failures of the mapping node are logged with their traceback and counted, never taken for bad
input (issue 24): a worker task nobody waits for, and a keyframe assembler that raises on a message."""

from __future__ import annotations

import concurrent.futures

import pytest
import rclpy

from monovoc_ros.nodes.mapping_node import MappingNode
from monovoc_ros.nodes.worker import WorkerStopped
from tests.rosutil import random_domain_id

pytestmark = pytest.mark.ros


@pytest.fixture()
def node(tmp_path, monkeypatch):
    monkeypatch.setenv("ROS_LOG_DIR", str(tmp_path))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=random_domain_id())
    mapper = MappingNode(context=context, namespace="/errors_test")
    yield mapper
    mapper.stop()
    mapper.destroy_node()
    rclpy.try_shutdown(context=context)


def failed(exc: BaseException) -> concurrent.futures.Future:
    future: concurrent.futures.Future = concurrent.futures.Future()
    future.set_exception(exc)
    return future


def test_a_failed_background_task_is_counted_and_a_discarded_one_is_not(node, capfd):
    node._report_failure(failed(RuntimeError("boom")))
    assert "worker task failed: RuntimeError: boom" in capfd.readouterr().err
    node._report_failure(failed(WorkerStopped("republish_objects: the node is shutting down")))
    done: concurrent.futures.Future = concurrent.futures.Future()
    done.set_result(3)
    node._report_failure(done)
    assert node.stats.snapshot()["worker_errors"] == 1


class Exploding:
    """A pose message whose pose raises what no adapter expects (a stand-in for a bug in our own code)."""

    def __init__(self):
        from std_msgs.msg import Header

        self.header = Header()
        self.header.stamp.sec = 5

    @property
    def pose(self):
        raise RuntimeError("a bug")


def test_a_message_the_assembler_raises_on_is_an_ingest_error_not_bad_input(node, capfd):
    node._push([("pose", Exploding())])
    stats = node.stats.snapshot()
    assert stats["ingest_errors"] == 1 and sum(stats["rejected"].values()) == 0
    logged = capfd.readouterr().err
    assert "the keyframe assembler failed (RuntimeError: a bug)" in logged and "Traceback" in logged
