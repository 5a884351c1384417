"""rclpy's ActionClient with its requests and the taking of their answers under one lock.

rclpy 7.1.6 (Jazzy's wheels here) sends a goal, cancel or result request first and records its sequence
number after. An executor thread that takes the answer in between finds no request waiting for it, logs
"Ignoring unexpected goal response. There may be more than one action server" and drops it: the caller's
future never completes (ros2/rclpy#1123; fixed upstream by ros2/rclpy#1308 in later releases). A server on
the same machine answers within that window: CI saw a go_to goal wait 30 s for the mapping node's
acceptance, and the node's own navigate_to_pose client, whose answers an executor thread takes while another
sends, would report "Nav2 did not answer". Here a request is sent and recorded, and an answer taken, under
one lock, so an answer is only taken once its request is recorded.
"""

from __future__ import annotations

import threading
from typing import Any

from rclpy.action import ActionClient


class LockedActionClient(ActionClient):
    """ActionClient whose answers are never taken before their request is recorded (same constructor)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._request_lock = threading.Lock()  # before super(): the executor may take data once constructed
        super().__init__(*args, **kwargs)

    def take_data(self) -> dict:
        with self._request_lock:
            return super().take_data()

    def send_goal_async(self, goal: Any, feedback_callback: Any = None, goal_uuid: Any = None) -> Any:
        with self._request_lock:
            return super().send_goal_async(goal, feedback_callback=feedback_callback, goal_uuid=goal_uuid)

    def _cancel_goal_async(self, goal_handle: Any) -> Any:
        with self._request_lock:
            return super()._cancel_goal_async(goal_handle)

    def _get_result_async(self, goal_handle: Any) -> Any:
        with self._request_lock:
            return super()._get_result_async(goal_handle)
