"""The live mapper seen from outside: its node as a child process, and a client that watches and calls it.

Used by `monovoc demo` and the live-node benchmark; tests keep their own helpers (tests/rosutil.py).

    with MapperProcess(params, log_path) as mapper, MapperClient() as client:
        client.service(TextQuery, "/monovoc/query", 60.0, mapper.check)
        client.wait_diagnostics(lambda d: d["keyframes_processed"] == "60", 120.0, mapper.check, "60 keyframes")
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from monovoc_ros.contract import DEFAULT_NAMESPACE as NAMESPACE
from monovoc_ros.nodes import service_call

WITH_OBJECTS = "monovoc_ros.nodes.object_query"  # semantic_mapper + object database + query service
MAPPING_ONLY = "monovoc_ros.nodes.semantic_mapper"


class MapperError(RuntimeError):
    """The node exited, or an answer or a condition did not come in time; the message says which."""


def loopback_environment(log_dir: Path) -> None:
    """Confines this process and its children to loopback unless the caller chose otherwise (rclpy reads
    these at init)."""
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("ROS_LOG_DIR", str(log_dir))


def settled(values: Mapping[str, str], masks_sent: int) -> bool:
    """Diagnostics say every sent mask reached the node and every keyframe made of them left the queue."""
    done = int(values["keyframes_processed"]) + int(values["keyframes_dropped"])
    return (
        int(values.get("messages_received.mask", 0)) >= masks_sent
        and int(values["inputs_waiting"]) == 0
        and int(values["queue_length"]) == 0
        and done >= int(values["keyframes_received"])
    )


class MapperProcess:
    """``python -m <module> --ros-args -p k:=v ...`` with its output in ``log_path``; stopped with SIGINT
    (final snapshot), then SIGKILL after 30 s."""

    def __init__(self, params: Mapping[str, Any], log_path: Path, module: str = WITH_OBJECTS) -> None:
        command = [sys.executable, "-m", module, "--ros-args"]
        for key, value in params.items():
            command += ["-p", f"{key}:={value}"]
        self.log_path = log_path
        self._log = open(log_path, "w")
        self.process = subprocess.Popen(command, stdout=self._log, stderr=subprocess.STDOUT, env=os.environ.copy())

    def check(self) -> None:
        """Raises MapperError when the node has exited."""
        if self.process.poll() is not None:
            raise MapperError(f"the semantic_mapper exited with code {self.process.returncode} (log: {self.log_path})")

    def stop(self) -> int:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._log.close()
        return self.process.returncode

    def __enter__(self) -> MapperProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class MapperClient:
    """A node in its own context, spun in a background thread: the mapper's /diagnostics status, its
    semantic cloud (with arrival times, by header stamp) and service calls."""

    def __enter__(self) -> MapperClient:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.signals import SignalHandlerOptions
        from sensor_msgs.msg import PointCloud2

        from monovoc_ros.bags.rosnode import spinning
        from monovoc_ros.nodes.qos import latched_qos

        self._context = rclpy.Context()
        rclpy.init(context=self._context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("monovoc_mapper_client", context=self._context)
        self._lock = threading.Lock()
        self._diagnostics: dict[str, str] = {}
        self._cloud = None
        self.cloud_arrivals: dict[int, float] = {}  # header stamp (ns) -> time.monotonic() of its first cloud
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)
        self.node.create_subscription(PointCloud2, f"{NAMESPACE}/semantic_cloud", self._on_cloud, latched_qos())
        self._spin = spinning(self.node)
        self._spin.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._spin.__exit__(None, None, None)
        self.node.destroy_node()
        self._context.try_shutdown()

    def _on_diagnostics(self, msg: Any) -> None:
        for status in msg.status:
            if "semantic mapping" in status.name:
                with self._lock:
                    self._diagnostics = {kv.key: kv.value for kv in status.values}

    def _on_cloud(self, msg: Any) -> None:
        now = time.monotonic()
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        with self._lock:
            self._cloud = msg
            self.cloud_arrivals.setdefault(stamp, now)

    def latest_cloud(self):
        """The newest semantic cloud as msg_adapters.SemanticCloud, or None."""
        import msg_adapters as ma

        with self._lock:
            msg = self._cloud
        return None if msg is None else ma.semantic_cloud_to_arrays(msg)

    def wait_diagnostics(
        self, predicate: Callable[[dict[str, str]], bool], timeout: float, alive: Callable[[], None], what: str
    ) -> dict[str, str]:
        """The first diagnostics values (key -> text) for which predicate holds; MapperError after timeout."""
        deadline = time.monotonic() + timeout
        values: dict[str, str] = {}
        while time.monotonic() < deadline:
            alive()
            with self._lock:
                values = dict(self._diagnostics)
            if values and predicate(values):
                return values
            time.sleep(0.05)
        raise MapperError(f"timed out after {timeout:g} s waiting for {what}; last diagnostics: {values}")

    def service(self, kind: type, name: str, timeout: float, alive: Callable[[], None]) -> Any:
        """A client of service ``name`` once the service is there."""
        client = self.node.create_client(kind, name)
        deadline = time.monotonic() + timeout
        while not client.wait_for_service(timeout_sec=0.5):
            alive()
            if time.monotonic() > deadline:
                raise MapperError(f"service {name} did not appear within {timeout:g} s")
        return client

    def call(
        self, client: Any, request: Any, timeout: float, alive: Callable[[], None], *, resend_s: float | None = 2.0
    ) -> Any:
        """The response; the request is sent again while unanswered unless ``resend_s`` is None (see service_call)."""
        response = service_call.call_service(client, request, timeout, time.sleep, resend_s=resend_s, poll=alive)
        if response is None:
            raise MapperError(f"no answer from {client.srv_name} within {timeout:g} s")
        return response
