"""Going to objects: the ``go_to`` action and the ``approach_pose`` service, a component beside the mapping
node (monovoc_ros.nodes.component) that reads the object component's index.

A request's text picks an object (objects.spatial.answer: relations read) and objects.approach computes where
to stand beside it from the Gaussian map's free space (the grid is rebuilt when the map changes). Then, by
``navigation.mode``:

* ``nav2``: the pose goes to Nav2's ``navigate_to_pose`` (nav2_msgs/action/NavigateToPose); its feedback is
  relayed (``distance_remaining``), its result ends the goal, and canceling go_to cancels Nav2's goal.
  nav2_msgs is imported only in this mode: without it the node stops at start with one line;
* ``goal_topic``: the pose is published on ``navigation.goal_topic`` (PoseStamped; RViz's Nav2 Goal tool and
  Nav2's bt_navigator use /goal_pose) and the goal succeeds;
* ``none``: the goal succeeds with the pose.

Poses are in the map frame of the gaussians topic (``frame_id``, or ``navigation.goal_frame``); there is no tf
here to transform them. Every answer also publishes an arrow on ``approach/marker`` for RViz.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msg_adapters as ma
from monovoc_ros.nodes.component import MappingHost
from monovoc_ros.nodes.outputs import semantic_objects
from monovoc_ros.nodes.qos import SERVICE_QOS, latched_qos, output_events
from monovoc_ros.nodes.services import guarded
from monovoc_ros.objects import approach as ap
from monovoc_ros.objects.records import QueryError

POLL_S = 0.05


class NavigationUnavailable(ValueError):
    """navigation.mode nav2 without nav2_msgs installed (raised at start: one line)."""


@dataclass(frozen=True)
class NavigationSettings:
    mode: str  # nodes.object_query_params.NAVIGATION_MODES
    goal_topic: str
    nav2_action: str
    nav2_wait_s: float
    goal_frame: str  # "" = the host's frame_id
    standoff: float
    shape: ap.RobotShape

    @classmethod
    def from_values(cls, values: dict[str, Any]) -> NavigationSettings:
        return cls(
            mode=str(values["navigation.mode"]),
            goal_topic=str(values["navigation.goal_topic"]),
            nav2_action=str(values["navigation.nav2_action"]),
            nav2_wait_s=float(values["navigation.nav2_wait_s"]),
            goal_frame=str(values["navigation.goal_frame"]),
            standoff=float(values["approach.standoff"]),
            shape=ap.RobotShape(
                robot_radius=float(values["approach.robot_radius"]),
                robot_height=float(values["approach.robot_height"]),
                min_obstacle_height=float(values["approach.min_obstacle_height"]),
                cell=float(values["approach.cell"]),
            ),
        )


class NavigationComponent:
    """See the module docstring."""

    def __init__(
        self,
        host: MappingHost,
        settings: NavigationSettings,
        index: Callable[[], Any],
        labelled_map: Callable[[], tuple[Any, Any]],
    ) -> None:
        """``index()``: the object component's ObjectIndex; ``labelled_map()``: its newest (Gaussian map,
        per-Gaussian object ids)."""
        from geometry_msgs.msg import PoseStamped
        from visualization_msgs.msg import MarkerArray

        from monovoc_interfaces.action import GoTo
        from monovoc_interfaces.srv import ApproachPose

        self.host, self.settings, self._index, self._labelled_map = host, settings, index, labelled_map
        self.log = host.logger
        self.frame_id = settings.goal_frame or host.frame_id
        self._navigate = None
        if settings.mode == "nav2":
            try:
                from nav2_msgs.action import NavigateToPose
            except ImportError as exc:
                raise NavigationUnavailable(
                    f"navigation.mode nav2 needs nav2_msgs (apt install ros-jazzy-nav2-msgs): {exc}"
                ) from None
            self._navigate_type = NavigateToPose
            self._navigate = host.create_action_client(NavigateToPose, settings.nav2_action)
        self._goal_publisher = (
            host.create_publisher(PoseStamped, settings.goal_topic, 10) if settings.mode == "goal_topic" else None
        )
        self.marker = host.create_publisher(
            MarkerArray, "approach/marker", latched_qos(), event_callbacks=output_events()
        )
        self._grid_lock = threading.Lock()
        self._grid: tuple[Any, ap.FreeSpaceGrid] | None = None  # (the Gaussian map it was built from, grid)
        self.goals = {"succeeded": 0, "failed": 0, "canceled": 0, "rejected": 0}
        # One goal at a time: its execute callback waits on Nav2 in an executor thread, and the robot has one body.
        self._active = threading.Lock()
        self._stopping = threading.Event()
        self.action = host.create_action_server(GoTo, "go_to", self._execute, self._on_goal, self._on_cancel)
        handler = guarded(ApproachPose, "approach_pose", self._on_approach, log=self.log.error)
        self.service = host.create_service(ApproachPose, "approach_pose", handler, SERVICE_QOS)
        host.add_diagnostics_source(lambda: {f"go_to.{k}": v for k, v in self.goals.items()})

    def start(self) -> None:
        pass

    def stop(self) -> None:
        self._stopping.set()  # a goal waiting on Nav2 ends (Nav2's goal canceled) instead of waiting forever
        # Wait (bounded) for a goal in progress to end; the lock stays held: no goal starts any more.
        self._active.acquire(timeout=self.settings.nav2_wait_s + 1.0)
        self.action.destroy()

    # ------------------------------------------------------------------ the approach pose

    def plan(self, text: str, standoff: float) -> ap.Goal:
        """The object `text` names and the approach pose (never raises for a bad map: a failed Goal)."""
        standoff = float(standoff)
        if not 0 <= standoff <= ap.MAX_STANDOFF_M:  # NaN, negative, inf: a caller's mistake, not "the default" (0 is)
            reason = f"standoff must be 0-{ap.MAX_STANDOFF_M:g} metres (0: approach.standoff), got {standoff}"
            return ap.Goal(ap.Approach(False, reason))
        index = self._index()
        gaussians, object_ids = self._labelled_map()
        if gaussians is None or object_ids is None or len(object_ids) != len(gaussians):
            return ap.Goal(ap.Approach(False, "no map with objects yet (or it is being updated): try again"))
        standoff = standoff if standoff > 0 else self.settings.standoff
        try:
            grid = self._grid_of(index, gaussians)
        except ValueError as exc:
            return ap.Goal(ap.Approach(False, f"no free space: {exc}"))
        robot = None if index.viewpoint is None else index.viewpoint[:3, 3]
        return ap.goal_for_text(
            index, text, grid, gaussians.means, object_ids, standoff, robot, self.settings.shape.robot_height
        )

    def _grid_of(self, index, gaussians) -> ap.FreeSpaceGrid:
        with self._grid_lock:
            if self._grid is None or self._grid[0] is not gaussians:
                grid = ap.free_space(
                    gaussians.means, gaussians.opacities, index.up_vector(), index.floor_height(), self.settings.shape
                )
                self._grid = (gaussians, grid)
            return self._grid[1]

    def _pose_msg(self, goal: ap.Goal) -> Any:
        from geometry_msgs.msg import PoseStamped

        msg = PoseStamped()
        msg.header = ma.make_header(self.frame_id, self.host.clock.now().nanoseconds)
        a = goal.approach
        if a.success:
            msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in a.position)
            q = msg.pose.orientation
            q.x, q.y, q.z, q.w = (float(v) for v in a.orientation)
        return msg

    def _publish_marker(self, goal: ap.Goal, pose: Any) -> None:
        from visualization_msgs.msg import Marker, MarkerArray

        marker = Marker()
        marker.header = pose.header
        marker.ns, marker.id, marker.type = "monovoc/approach", 0, Marker.ARROW
        marker.action = Marker.ADD if goal.approach.success else Marker.DELETE
        marker.pose = pose.pose
        marker.scale.x, marker.scale.y, marker.scale.z = 0.4, 0.06, 0.06
        marker.color.r, marker.color.g, marker.color.b, marker.color.a = 0.1, 0.8, 0.2, 1.0
        self.marker.publish(MarkerArray(markers=[marker]))

    # ------------------------------------------------------------------ the service

    def _on_approach(self, request: Any, response: Any) -> Any:
        try:
            goal = self.plan(request.text, request.standoff)
        except QueryError as exc:
            goal = ap.Goal(ap.Approach(False, str(exc)))
        response.success, response.message = goal.approach.success, goal.approach.message
        response.pose = self._pose_msg(goal)
        if goal.record is not None:
            response.object = semantic_objects([(goal.record, goal.score)])[0]
        self._publish_marker(goal, response.pose)
        return response

    # ------------------------------------------------------------------ the action

    def _on_goal(self, request: Any) -> Any:
        from rclpy.action import GoalResponse

        # Busy: cancel the goal in progress first. A blank text names nothing: no goal to accept.
        why = "a go_to goal is in progress" if self._active.locked() else None
        if not request.text.strip():
            why = "its text is blank"
        if self._stopping.is_set() or why is not None:
            self.goals["rejected"] += 1
            if why is not None:
                self.log.warning(f"go_to goal rejected: {why}", throttle_duration_sec=5.0)
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _on_cancel(self, _goal_handle: Any) -> Any:
        from rclpy.action import CancelResponse

        return CancelResponse.ACCEPT

    def _execute(self, goal_handle: Any) -> Any:
        from monovoc_interfaces.action import GoTo

        if not self._active.acquire(blocking=False):  # accepted while another began: ends at once
            return self._end(goal_handle, GoTo.Result(message="another go_to goal is in progress"), "failed")
        try:
            return self._execute_one(goal_handle)
        finally:
            self._active.release()

    def _execute_one(self, goal_handle: Any) -> Any:
        from monovoc_interfaces.action import GoTo

        request = goal_handle.request
        result = GoTo.Result()
        try:
            goal = self.plan(request.text, request.standoff)
        except QueryError as exc:
            goal = ap.Goal(ap.Approach(False, str(exc)))
        pose = self._pose_msg(goal)
        self._publish_marker(goal, pose)
        result.pose, result.message = pose, goal.approach.message
        result.object_id = 0 if goal.record is None else int(goal.record.id)
        if not goal.approach.success:
            return self._end(goal_handle, result, "failed")
        label = goal.record.label if goal.record is not None else ""
        feedback = GoTo.Feedback(object_id=result.object_id, object_label=label, pose=pose, state="planned")
        feedback.distance_remaining = -1.0
        goal_handle.publish_feedback(feedback)
        if goal_handle.is_cancel_requested:
            return self._end(goal_handle, result, "canceled", "canceled before navigation")
        if self.settings.mode == "goal_topic":
            self._goal_publisher.publish(pose)
            result.message += f"; published on {self.settings.goal_topic}"
        elif self.settings.mode == "nav2":
            return self._navigate_there(goal_handle, result, feedback)
        return self._end(goal_handle, result, "succeeded")

    def _navigate_there(self, goal_handle: Any, result: Any, feedback: Any) -> Any:
        client, name, wait_s = self._navigate, self.settings.nav2_action, self.settings.nav2_wait_s
        if not client.wait_for_server(timeout_sec=wait_s):
            return self._end(goal_handle, result, "failed", f"Nav2's {name} is not available")
        nav_goal = self._navigate_type.Goal(pose=result.pose)
        lock = threading.Lock()  # Nav2's feedback arrives on another thread than this one's state changes

        def relay(msg: Any) -> None:
            with lock:
                feedback.state = "navigating"
                feedback.distance_remaining = float(msg.feedback.distance_remaining)
                goal_handle.publish_feedback(feedback)

        sending = client.send_goal_async(nav_goal, feedback_callback=relay)
        sent = self._wait(sending, goal_handle, wait_s)
        if sent is None:
            # Canceled or stopping before Nav2 answered: if it accepts after all, its goal is canceled too.
            late = self._wait(sending, None, wait_s)
            note = self._cancel_nav2(late, wait_s) if late is not None and late.accepted else ""
            if goal_handle.is_cancel_requested or self._stopping.is_set():
                return self._end(goal_handle, result, "canceled", note or "canceled before Nav2 started")
            return self._end(goal_handle, result, "failed", f"Nav2's {name} did not answer in {wait_s:g} s")
        if not sent.accepted:
            return self._end(goal_handle, result, "failed", f"Nav2 rejected the goal ({name})")
        with lock:
            if feedback.state != "navigating":
                feedback.state = "sent"
                goal_handle.publish_feedback(feedback)
        outcome = self._wait(sent.get_result_async(), goal_handle)
        if outcome is None:  # canceled (or the node stopping)
            return self._end(goal_handle, result, "canceled", self._cancel_nav2(sent, wait_s))
        from action_msgs.msg import GoalStatus

        status = outcome.status
        if status == GoalStatus.STATUS_SUCCEEDED:
            return self._end(goal_handle, result, "succeeded", "Nav2 reached the pose")
        why = {GoalStatus.STATUS_CANCELED: "Nav2 canceled the goal", GoalStatus.STATUS_ABORTED: "Nav2 aborted the goal"}
        return self._end(goal_handle, result, "failed", why.get(status, f"Nav2 ended with status {status}"))

    def _cancel_nav2(self, sent: Any, wait_s: float) -> str:
        """Cancels Nav2's accepted goal (`sent`, its goal handle); what go_to's result says of it. The same whether
        go_to's cancel came before or after Nav2's acceptance reached this node."""
        canceling = self._wait(sent.cancel_goal_async(), None, wait_s)
        if canceling is not None and len(canceling.goals_canceling) > 0:
            return "canceled; Nav2's goal canceled too"
        return "canceled; Nav2 did not confirm its cancel"

    def _wait(self, future: Any, goal_handle: Any | None, timeout_s: float | None = None) -> Any:
        """The future's result once done; None when `goal_handle` is canceled first, the node stops or
        `timeout_s` passes."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not future.done():
            if goal_handle is not None and (goal_handle.is_cancel_requested or self._stopping.is_set()):
                return None
            if deadline is not None and time.monotonic() > deadline:
                return None
            time.sleep(POLL_S)
        return future.result()

    def _end(self, goal_handle: Any, result: Any, state: str, note: str = "") -> Any:
        if note:
            result.message = f"{result.message}; {note}" if result.message else note
        result.success = state == "succeeded"
        self.goals[state] += 1
        if state == "succeeded":
            goal_handle.succeed()
        elif state == "canceled":
            goal_handle.canceled()
        else:
            goal_handle.abort()
        return result
