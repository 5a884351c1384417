"""Helpers for tests that run real ROS 2 processes on loopback.

Every test run gets its own environment (``ros_environment``): a random ``ROS_DOMAIN_ID``,
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, a temporary ``ROS_LOG_DIR`` and ``HOME``, and
``AMENT_PREFIX_PATH`` pointing at the project venv. Children are started with the venv's python
(``RosProcess``, output captured to a file so failures can show it); the test process itself joins
the same domain through ``RosClientNode``. Waiting is always polling with a timeout, never a fixed sleep.
Inherited ``ROS_LOCALHOST_ONLY``, ``ROS_STATIC_PEERS`` and ``FASTRTPS_DEFAULT_PROFILES_FILE`` are
dropped; a test that wants a Fast DDS profile passes it in ``extra``.

Typical use::

    env = ros_environment(tmp_path)
    with RosProcess.python(["-m", "my_pkg.my_node"], env, name="my_node") as server, \\
            RosClientNode(env) as client:
        cli = client.node.create_client(TextQuery, "/monovoc/query")
        wait_for_service(cli, timeout=10.0, process=server)
        response = call_service(cli, TextQuery.Request(text="chair"), timeout=5.0, process=server)
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
VENV = REPO / ".venv"
VENV_PYTHON = VENV / "bin" / "python" if (VENV / "bin" / "python").exists() else Path(sys.executable)

# Fast DDS maps domain d to UDP ports 7400 + 250 * d (+ offsets): 0..232 are valid; skip 0 (the default).
_DOMAIN_RANGE = (1, 232)


def random_domain_id() -> int:
    """A domain id for one test run; random so concurrent runs on one machine do not meet."""
    return random.SystemRandom().randint(*_DOMAIN_RANGE)


def ros_environment(tmp_dir: Path, domain_id: int | None = None, extra: Mapping[str, str] | None = None) -> dict:
    """The environment for ROS processes of one test: loopback only, own domain, own log dir."""
    tmp_dir = Path(tmp_dir)
    log_dir = tmp_dir / "ros_log"
    home = tmp_dir / "home"
    log_dir.mkdir(parents=True, exist_ok=True)
    home.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    for key in ("ROS_LOCALHOST_ONLY", "ROS_STATIC_PEERS", "FASTRTPS_DEFAULT_PROFILES_FILE"):
        env.pop(key, None)
    ament = env.get("AMENT_PREFIX_PATH", "")
    env.update(
        ROS_DOMAIN_ID=str(random_domain_id() if domain_id is None else domain_id),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_LOG_DIR=str(log_dir),
        HOME=str(home),
        AMENT_PREFIX_PATH=str(VENV) + (os.pathsep + ament if ament and ament != str(VENV) else ""),
        RCUTILS_COLORIZED_OUTPUT="0",
        PYTHONUNBUFFERED="1",
    )
    # Children import the project from the working tree even before it is pip-installed.
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    if extra:
        env.update(extra)
    return env


class RosProcess:
    """A child process with captured output (stdout and stderr interleaved in one file).

    Stop it with ``stop()`` (SIGINT, then SIGTERM, then SIGKILL) or use it as a context manager.
    """

    def __init__(self, args: Sequence[str], env: Mapping[str, str], *, name: str = "process", cwd: Path = REPO):
        self.name = name
        self.args = [str(a) for a in args]
        log_dir = Path(env.get("ROS_LOG_DIR", REPO / ".ros_log"))
        log_dir.mkdir(parents=True, exist_ok=True)
        self.output_path = log_dir / f"{name}-{os.getpid()}-{time.monotonic_ns()}.out"
        self._out = open(self.output_path, "wb")
        self.proc = subprocess.Popen(self.args, env=dict(env), cwd=cwd, stdout=self._out, stderr=subprocess.STDOUT)

    @classmethod
    def python(cls, args: Sequence[str], env: Mapping[str, str], **kwargs: Any) -> RosProcess:
        """The venv's python with ``args`` (e.g. ``["-m", "pkg.node", "--ros-args", ...]``)."""
        return cls([str(VENV_PYTHON), *args], env, **kwargs)

    @property
    def pid(self) -> int:
        return self.proc.pid

    @property
    def returncode(self) -> int | None:
        return self.proc.poll()

    def running(self) -> bool:
        return self.proc.poll() is None

    def output(self) -> str:
        """Everything the child wrote so far."""
        if not self._out.closed:
            self._out.flush()
        return self.output_path.read_text(errors="replace")

    def describe(self, tail: int = 4000) -> str:
        """Status and the tail of the output, for assertion messages."""
        state = "running" if self.running() else f"exited with {self.proc.returncode}"
        text = self.output()
        return f"[{self.name} pid {self.pid} {state}; output:]\n{text[-tail:]}"

    def check_running(self) -> None:
        """Raises AssertionError with the child's output when it has exited."""
        if not self.running():
            raise AssertionError(f"{self.name} exited early\n{self.describe()}")

    def wait_for_output(self, text: str, timeout: float) -> None:
        """Polls the output for ``text`` (e.g. a 'ready' line), failing early if the child exits."""
        wait_until(lambda: text in self.output(), timeout, f"{self.name} to print {text!r}", process=self)

    def stop(self, timeout: float = 10.0) -> int:
        """SIGINT (clean shutdown), then SIGTERM, then SIGKILL; returns the exit code."""
        for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 3.0)):
            if self.proc.poll() is not None:
                break
            self._signal(sig)
            try:
                self.proc.wait(wait)
            except subprocess.TimeoutExpired:
                continue
        if self.proc.poll() is None:
            self._signal(signal.SIGKILL)
            self.proc.wait(5.0)
        self._out.close()
        return self.proc.returncode

    def _signal(self, sig: int) -> None:
        try:
            self.proc.send_signal(sig)
        except ProcessLookupError:
            pass

    def __enter__(self) -> RosProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        if not self._out.closed:
            self.stop()


def wait_until(
    predicate: Callable[[], bool],
    timeout: float,
    what: str,
    *,
    process: RosProcess | Sequence[RosProcess] | None = None,
    interval: float = 0.02,
) -> None:
    """Polls ``predicate`` until it is true; on timeout (or a watched child exiting) fails with context."""
    processes = [] if process is None else [process] if isinstance(process, RosProcess) else list(process)
    deadline = time.monotonic() + timeout
    while True:
        if predicate():
            return
        for p in processes:
            p.check_running()
        if time.monotonic() >= deadline:
            details = "\n".join(p.describe() for p in processes)
            raise AssertionError(f"timed out after {timeout:.1f} s waiting for {what}\n{details}")
        time.sleep(interval)


class RosClientNode:
    """An rclpy node in the test process, on the domain of ``env``, spun by a background executor.

    rclpy reads the discovery range and log directory from the process environment at init, so
    this sets those variables (and restores them on exit). Signal handlers are left to pytest.
    """

    def __init__(self, env: Mapping[str, str], name: str = "test_client"):
        self._env = env
        self._name = name
        self._saved: dict[str, str | None] = {}
        self.context = None
        self.node = None
        self.executor = None
        self._thread: threading.Thread | None = None

    def __enter__(self) -> RosClientNode:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOG_DIR", "HOME", "AMENT_PREFIX_PATH"):
            self._saved[key] = os.environ.get(key)
            os.environ[key] = self._env[key]
        for key in ("ROS_LOCALHOST_ONLY", "ROS_STATIC_PEERS", "FASTRTPS_DEFAULT_PROFILES_FILE"):
            self._saved[key] = os.environ.pop(key, None)
        self.context = rclpy.Context()
        rclpy.init(
            context=self.context,
            domain_id=int(self._env["ROS_DOMAIN_ID"]),
            signal_handler_options=SignalHandlerOptions.NO,
        )
        self.node = rclpy.create_node(self._name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name=f"{self._name}-spin", daemon=True)
        self._thread.start()
        return self

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def __exit__(self, *exc: object) -> None:
        # Stop the executor and join its thread before destroying the node: the other order aborts.
        if self.executor is not None:
            self.executor.shutdown(timeout_sec=5.0)
        if self._thread is not None:
            self._thread.join(5.0)
        if self.node is not None:
            self.node.destroy_node()
        if self.context is not None:
            self.context.try_shutdown()
        for key, value in self._saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def wait_for_service(client: Any, timeout: float = 10.0, *, process: Any = None) -> None:
    """Waits until the service of ``client`` is available (discovery takes 0 to ~3 s on loopback)."""
    wait_until(client.service_is_ready, timeout, f"service {client.srv_name}", process=process, interval=0.05)


def call_service(
    client: Any, request: Any, timeout: float = 10.0, *, process: Any = None, resend_s: float | None = 2.0
) -> Any:
    """Calls the service and returns the response (the node's executor must be spinning). The request is sent
    again while unanswered (a lost first response, monovoc_ros.nodes.service_call); ``resend_s`` None for
    requests that must run once."""
    from monovoc_ros.nodes import service_call

    processes = [] if process is None else [process] if isinstance(process, RosProcess) else list(process)

    def poll() -> None:
        for p in processes:
            p.check_running()

    response = service_call.call_service(client, request, timeout, time.sleep, resend_s=resend_s, poll=poll)
    if response is None:
        details = "\n".join(p.describe() for p in processes)
        what = f"a response from {client.srv_name}"
        raise AssertionError(f"timed out after {timeout:.1f} s waiting for {what}\n{details}")
    return response


def wait_for_topic(node: Any, topic: str, timeout: float = 10.0, *, process: Any = None) -> list[str]:
    """Waits until ``topic`` appears in the graph; returns its type names."""
    found: list[str] = []

    def present() -> bool:
        for name, types in node.get_topic_names_and_types():
            if name == topic:
                found[:] = types
                return True
        return False

    wait_until(present, timeout, f"topic {topic}", process=process, interval=0.05)
    return found


def wait_for_publishers(node: Any, topic: str, count: int = 1, timeout: float = 10.0, *, process: Any = None) -> None:
    """Waits until ``topic`` has at least ``count`` publishers."""
    what = f"{count} publisher(s) on {topic}"
    wait_until(lambda: node.count_publishers(topic) >= count, timeout, what, process=process, interval=0.05)


def wait_for_subscribers(publisher: Any, count: int = 1, timeout: float = 10.0, *, process: Any = None) -> None:
    """Waits until ``publisher`` is matched with at least ``count`` subscriptions."""
    what = f"{count} subscriber(s) on {publisher.topic_name}"
    wait_until(lambda: publisher.get_subscription_count() >= count, timeout, what, process=process, interval=0.05)


class MessageCollector:
    """A subscription callback that stores messages; ``wait_for(n)`` polls until n have arrived."""

    def __init__(self) -> None:
        self.messages: list[Any] = []
        self._lock = threading.Lock()

    def __call__(self, msg: Any) -> None:
        with self._lock:
            self.messages.append(msg)

    def wait_for(self, count: int = 1, timeout: float = 10.0, *, process: Any = None) -> list[Any]:
        wait_until(lambda: len(self.messages) >= count, timeout, f"{count} message(s)", process=process)
        with self._lock:
            return list(self.messages)


def ros_args(params: Mapping[str, Any] | None = None, remaps: Mapping[str, str] | None = None) -> list[str]:
    """``--ros-args -p k:=v ... -r a:=b ...`` for a node's command line (floats keep their decimal point,
    lists are written as YAML lists, booleans as true/false)."""

    def text(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (list, tuple)):
            return "[" + ",".join(text(x) for x in v) + "]"
        return repr(v) if isinstance(v, float) else str(v)

    args = ["--ros-args"]
    for key, value in (params or {}).items():
        args += ["-p", f"{key}:={text(value)}"]
    for key, value in (remaps or {}).items():
        args += ["-r", f"{key}:={value}"]
    return args


class DiagnosticsMonitor:
    """Keeps the latest ``/diagnostics`` status per name; ``wait_for(pred)`` polls pred(values) where
    values is the key -> value dict (strings) of the newest status whose name contains ``name``."""

    def __init__(self, node: Any, name: str = "", topic: str = "/diagnostics"):
        from diagnostic_msgs.msg import DiagnosticArray

        self.name = name
        self.latest: dict[str, Any] = {}
        self._lock = threading.Lock()
        self.subscription = node.create_subscription(DiagnosticArray, topic, self._on_message, 10)

    def _on_message(self, msg: Any) -> None:
        with self._lock:
            for status in msg.status:
                if self.name in status.name:
                    self.latest[status.name] = status

    def values(self) -> dict[str, str]:
        with self._lock:
            statuses = list(self.latest.values())
        if not statuses:
            return {}
        return {kv.key: kv.value for kv in statuses[-1].values}

    def wait_for(
        self, predicate: Callable[[dict[str, str]], bool], timeout: float = 10.0, *, what: str = "", process: Any = None
    ) -> dict[str, str]:
        found: dict[str, str] = {}

        def check() -> bool:
            values = self.values()
            if values and predicate(values):
                found.update(values)
                return True
            return False

        try:
            wait_until(check, timeout, what or "a diagnostics status matching the predicate", process=process,
                       interval=0.05)  # fmt: skip
        except AssertionError as exc:
            raise AssertionError(f"{exc}\nlatest diagnostics: {self.values()}") from None
        return found
