"""use_sim_time: the node's timers (diagnostics, the flush of held inputs) run on the steady clock, so they
go on when /clock stops at the end of a bag (diagnostics went stale there, 45 of 55 keyframes reported)."""

from __future__ import annotations

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rosgraph_msgs.msg import Clock

import msg_adapters as ma
from monovoc_ros.ros_harness import (
    ClientNode,
    MessageCollector,
    NodeProcess,
    ros_args,
    wait_for_subscribers,
    wait_until,
)
from tests.rosutil import ros_environment

pytestmark = pytest.mark.ros


def test_diagnostics_go_on_after_the_simulated_clock_stops(tmp_path):
    env = ros_environment(tmp_path)
    args = ["-m", "monovoc_ros.nodes.mapping_node", *ros_args({"use_sim_time": True, "diagnostics_period_s": 0.2})]
    with NodeProcess.python(args, env, name="mapping_node") as node, ClientNode(env) as client:
        diagnostics = MessageCollector()
        client.node.create_subscription(DiagnosticArray, "/diagnostics", diagnostics, 10)
        clock = client.node.create_publisher(Clock, "/clock", 10)
        wait_for_subscribers(clock, 1, timeout=60.0, process=node)
        tick = Clock(clock=ma.ns_to_time(5_000_000_000))
        after_tick = lambda: sum(ma.header_stamp_ns(m) == 5_000_000_000 for m in diagnostics.messages)  # noqa: E731

        def ticked() -> bool:  # the node's /clock subscription is best effort: tick until it has the time
            if after_tick():
                return True
            clock.publish(tick)
            return False

        wait_until(ticked, 30.0, "diagnostics in simulated time", process=node, interval=0.1)
        seen = after_tick()  # from here on the clock stands still
        wait_until(lambda: after_tick() >= seen + 4, 30.0, "4 diagnostics after the clock stopped", process=node)
    assert all(ma.header_stamp_ns(m) <= 5_000_000_000 for m in diagnostics.messages)  # stamped in simulated time
