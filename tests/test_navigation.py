"""Going to objects through the live node (issue 26): the go_to action with a real rclpy navigate_to_pose
action server standing in for Nav2 (the goal arrives with the approach pose, feedback is relayed, cancel
propagates), the same with navigation.mode goal_topic, the approach_pose service, and a clear stop when
nav2_msgs is missing."""

from __future__ import annotations

import contextlib
import threading
import time

import numpy as np
import pytest

from monovoc_ros.contract import DEFAULT_NAMESPACE
from monovoc_ros.embed import default_model_dir
from monovoc_ros.nodes import service_call
from monovoc_ros.nodes.action_client import LockedActionClient
from monovoc_ros.nodes.mapping_node import NODE_NAME
from monovoc_ros.ros_harness import (
    ClientNode,
    NodeProcess,
    call_service,
    node_endpoints,
    ros_args,
    wait_for_service,
    wait_until,
)
from tests.object_room import copy_directory, room_directory, room_id
from tests.rosutil import ros_environment

NODE = ["-m", "monovoc_ros.nodes.semantic_mapper"]

pytestmark = pytest.mark.ros


class FakeNav2:
    """navigate_to_pose served by an rclpy node of its own (multi-threaded: a goal may wait for its cancel)."""

    def __init__(self, env: dict, finish: bool) -> None:
        self.env, self.finish = env, finish  # finish: succeed each goal, else drive until canceled
        self.accept_after_s = 0.0  # how long a goal request waits for its acceptance (a busy Nav2)
        self.requested = threading.Event()  # a goal request arrived
        self.goals: list = []
        self.canceled = threading.Event()

    @contextlib.contextmanager
    def running(self):
        import rclpy
        from nav2_msgs.action import NavigateToPose
        from rclpy.action import ActionServer, CancelResponse, GoalResponse
        from rclpy.callback_groups import ReentrantCallbackGroup
        from rclpy.executors import MultiThreadedExecutor

        def execute(goal_handle):
            self.goals.append(goal_handle.request.pose)
            for remaining in (1.5, 0.5):
                feedback = NavigateToPose.Feedback()
                feedback.distance_remaining = remaining
                goal_handle.publish_feedback(feedback)
                time.sleep(0.1)
            deadline = time.monotonic() + 20.0
            while not self.finish and time.monotonic() < deadline:
                if goal_handle.is_cancel_requested:
                    self.canceled.set()
                    goal_handle.canceled()
                    return NavigateToPose.Result()
                time.sleep(0.02)
            goal_handle.succeed()
            return NavigateToPose.Result()

        def accept(_request):
            self.requested.set()
            time.sleep(self.accept_after_s)
            return GoalResponse.ACCEPT

        with ClientNode(self.env, name="fake_nav2") as holder:
            # The holder's single-threaded executor only keeps the context; the server gets its own executor.
            node = rclpy.create_node("fake_bt_navigator", context=holder.context)
            group = ReentrantCallbackGroup()
            server = ActionServer(node, NavigateToPose, "navigate_to_pose", execute, callback_group=group,
                                  goal_callback=accept, cancel_callback=lambda _g: CancelResponse.ACCEPT)  # fmt: skip
            executor = MultiThreadedExecutor(num_threads=4, context=holder.context)
            executor.add_node(node)
            thread = threading.Thread(target=executor.spin, daemon=True)
            thread.start()
            self.node = node
            try:
                yield self
            finally:
                executor.shutdown(timeout_sec=5.0)
                server.destroy()
                node.destroy_node()

    def wait_for_mapper(self, process) -> None:
        """Until this server's node sees the mapping node's navigate_to_pose client (its goal and result services):
        a server's answer to a client it has not matched yet is dropped (monovoc_ros.nodes.service_call), and the
        node sends each of its requests to Nav2 once."""
        wanted = {"/navigate_to_pose/_action/send_goal", "/navigate_to_pose/_action/get_result"}

        def seen() -> bool:
            return wanted <= set(node_endpoints(self.node, "clients", NODE_NAME, DEFAULT_NAMESPACE))

        wait_until(seen, 30.0, "the mapping node's navigate_to_pose client", process=process)


def node_params(directory, mode: str) -> dict:
    return {
        "map_directory": str(directory),
        "resume": True,
        "labels_file": str(directory / "labels.json"),
        "navigation.mode": mode,
        "navigation.nav2_wait_s": 10.0,
        "diagnostics_period_s": 5.0,
    }


class Requests:
    """Requests of an action client (``send()`` makes one) as service_call.call_service sends them: again when
    unanswered, since Fast DDS may drop a fresh client's request or its answer (monovoc_ros.nodes.service_call).
    Only for requests that may run twice."""

    def __init__(self, send, name: str) -> None:
        self.send, self.srv_name = send, name

    def call_async(self, _request):
        return self.send()

    def remove_pending_request(self, _future) -> None:
        pass  # the action client forgets a request once answered; an unanswered one stays with it


def answered(send, name: str, timeout: float = 30.0, process=None):
    return call_service(Requests(send, name), None, timeout, process=process, resend_s=service_call.RESEND_S)


def send(action, goal, feedback: list, process=None):
    """Sends a GoTo goal; returns its goal handle once accepted. A goal must not run twice, so a blank one
    (which the node rejects) goes first, again until answered: then the goal's requests and answers flow."""
    from monovoc_interfaces.action import GoTo

    blank = answered(lambda: action.send_goal_async(GoTo.Goal(text=" ")), "a blank go_to goal", process=process)
    assert not blank.accepted
    future = action.send_goal_async(goal, feedback_callback=lambda msg: feedback.append(msg.feedback))
    wait_until(future.done, 30.0, "the go_to goal to be accepted", process=process)
    handle = future.result()
    assert handle.accepted
    return handle


def result_of(handle, timeout: float = 30.0):
    return answered(handle.get_result_async, "the go_to result", timeout)


def test_go_to_drives_through_nav2_relays_feedback_and_cancels(tmp_path):
    from monovoc_interfaces.action import GoTo

    directory = copy_directory(room_directory(), tmp_path / "map")
    env = ros_environment(tmp_path, extra={"MONOVOC_MODEL_DIR": str(default_model_dir())})
    sofa = room_id("sofa")
    with NodeProcess.python([*NODE, *ros_args(node_params(directory, "nav2"))], env, name="go_to_nav2") as node:
        # One Nav2 for both goals: the node's navigate_to_pose client meets a fresh server only once.
        nav2 = FakeNav2(env, finish=True)
        with nav2.running(), ClientNode(env) as client:
            action = LockedActionClient(client.node, GoTo, "/monovoc/go_to")
            wait_until(lambda: action.wait_for_server(timeout_sec=0.1), 60.0, "the go_to action", process=node)
            nav2.wait_for_mapper(node)
            feedback: list = []
            handle = send(action, GoTo.Goal(text="the sofa", standoff=0.0), feedback, node)
            done = result_of(handle)
            result = done.result
            assert result.success and result.object_id == sofa, result.message
            assert "Nav2 reached the pose" in result.message
            # Nav2 got exactly the approach pose go_to answered with, in the map frame.
            wait_until(lambda: nav2.goals, 5.0, "Nav2's goal")
            sent = nav2.goals[0]
            assert sent.header.frame_id == "map" == result.pose.header.frame_id
            np.testing.assert_allclose(
                [sent.pose.position.x, sent.pose.position.y], [result.pose.pose.position.x, result.pose.pose.position.y]
            )
            states = [f.state for f in feedback]
            assert states[0] == "planned" and "navigating" in states, states
            assert [f.distance_remaining for f in feedback if f.state == "navigating"][:2] == [1.5, 0.5]
            assert all(f.object_id == sofa for f in feedback)

            nav2.finish = False  # Nav2 now drives until canceled
            nav2.goals.clear()
            handle = send(action, GoTo.Goal(text="the table"), [], node)
            wait_until(lambda: nav2.goals, 20.0, "Nav2's goal", process=node)
            answered(handle.cancel_goal_async, "the cancel answer", 20.0, process=node)
            assert nav2.canceled.wait(20.0)  # the cancel reached Nav2
            done = result_of(handle)
            assert not done.result.success and "Nav2's goal canceled too" in done.result.message

            # Canceled while Nav2 is still deciding on the goal: Nav2's goal, once accepted, is canceled as well, and
            # the result says so as it does when the cancel comes later (the order of the two on a busy node).
            nav2.accept_after_s, nav2.goals = 1.0, []
            nav2.canceled, nav2.requested = threading.Event(), threading.Event()
            handle = send(action, GoTo.Goal(text="the table"), [], node)
            wait_until(nav2.requested.is_set, 20.0, "Nav2's goal request", process=node)
            answered(handle.cancel_goal_async, "the cancel answer", 20.0, process=node)
            done = result_of(handle)
            assert not done.result.success and "Nav2's goal canceled too" in done.result.message, done.result.message
            assert nav2.canceled.wait(20.0) and len(nav2.goals) == 1

        with ClientNode(env) as client:  # no Nav2 at all: a clear failure, not a hang
            action = LockedActionClient(client.node, GoTo, "/monovoc/go_to")
            wait_until(lambda: action.wait_for_server(timeout_sec=0.1), 30.0, "the go_to action", process=node)
            done = result_of(send(action, GoTo.Goal(text="the sofa"), [], node), timeout=60.0)
            assert not done.result.success and "navigate_to_pose is not available" in done.result.message
        node.check_running()


def test_go_to_publishes_on_the_goal_topic_and_approach_pose_answers(tmp_path):
    from geometry_msgs.msg import PoseStamped

    from monovoc_interfaces.action import GoTo
    from monovoc_interfaces.srv import ApproachPose
    from monovoc_ros.ros_harness import MessageCollector

    directory = copy_directory(room_directory(), tmp_path / "map")
    env = ros_environment(tmp_path, extra={"MONOVOC_MODEL_DIR": str(default_model_dir())})
    params = node_params(directory, "goal_topic")
    with NodeProcess.python([*NODE, *ros_args(params)], env, name="go_to_topic") as node, ClientNode(env) as client:
        poses = MessageCollector()
        client.node.create_subscription(PoseStamped, "/goal_pose", poses, 10)
        service = client.node.create_client(ApproachPose, "/monovoc/approach_pose")
        wait_for_service(service, 60.0, process=node)
        planned = call_service(service, ApproachPose.Request(text="the chair right of the table"), 20.0, process=node)
        assert planned.success and planned.object.id == room_id("chair", 1), planned.message
        ceiling = call_service(service, ApproachPose.Request(text="the ceiling"), 20.0, process=node)
        assert not ceiling.success and "overhead" in ceiling.message
        for standoff in (-1.0, float("nan"), float("inf"), 100.5):  # a caller's mistake, refused (0 is the default)
            bad = call_service(service, ApproachPose.Request(text="the sofa", standoff=standoff), 20.0, process=node)
            assert not bad.success and "standoff must be 0-100 metres" in bad.message, bad.message

        action = LockedActionClient(client.node, GoTo, "/monovoc/go_to")
        wait_until(lambda: action.wait_for_server(timeout_sec=0.1), 30.0, "the go_to action", process=node)
        wait_until(lambda: client.node.count_publishers("/goal_pose") >= 1, 20.0, "the goal publisher", process=node)
        done = result_of(send(action, GoTo.Goal(text="the sofa", standoff=0.8), [], node))
        assert done.result.success and "published on /goal_pose" in done.result.message
        wait_until(lambda: poses.messages, 10.0, "the goal pose", process=node)
        got = poses.messages[-1].pose.position
        want = done.result.pose.pose.position
        assert (got.x, got.y, got.z) == (want.x, want.y, want.z)
        node.check_running()


def test_navigation_mode_nav2_without_nav2_msgs_stops_with_one_line(tmp_path):
    shadow = tmp_path / "shadow" / "nav2_msgs"
    shadow.mkdir(parents=True)
    (shadow / "__init__.py").write_text("raise ImportError('nav2_msgs is not installed here')\n")
    env = ros_environment(tmp_path, extra={"MONOVOC_MODEL_DIR": str(default_model_dir())})
    env["PYTHONPATH"] = f"{tmp_path / 'shadow'}:{env['PYTHONPATH']}"
    with NodeProcess.python([*NODE, *ros_args({"navigation.mode": "nav2"})], env, name="no_nav2") as node:
        wait_until(lambda: not node.running(), 60.0, "the node to stop")
        assert node.returncode == 1
    lines = [line for line in node.output().splitlines() if "nav2_msgs" in line]
    assert len(lines) == 1 and "navigation.mode nav2 needs nav2_msgs" in lines[0], node.output()[-2000:]
    assert "Traceback" not in node.output()
