"""Running ROS nodes as child processes and talking to them from this process: one harness for the demo,
the benchmarks and the tests.

* ``NodeProcess``: a child (e.g. ``python -m monovoc_ros.nodes.semantic_mapper --ros-args ...``) with its
  stdout and stderr in one file, stopped with SIGINT (the node's final snapshot), then SIGTERM, then SIGKILL.
* ``ClientNode``: an rclpy node in its own context, spun by a background executor, on the domain and
  discovery range of this process's environment (set them before entering, as ``loopback_environment`` does).
* ``wait_until`` polls a condition with a timeout and fails early when a watched child exits; every wait
  here is on a condition, never on a log line or a fixed sleep.
* ``DiagnosticsMonitor`` (the mapper's /diagnostics values), ``MessageCollector`` (every message of a topic),
  ``CloudMonitor`` (the newest semantic cloud and when each keyframe stamp first arrived; with
  ``KeyframePublishTimes`` the keyframe -> cloud latencies of a replay), ``call_service``
  (with the resend of monovoc_ros.nodes.service_call), ``ros_args``.

    with NodeProcess.python(["-m", SEMANTIC_MAPPER, *ros_args(params)], name="mapper") as node, ClientNode() as c:
        query = c.node.create_client(TextQuery, "/monovoc/query")
        wait_for_service(query, 30.0, process=node)
        answer = call_service(query, TextQuery.Request(text="a chair"), 30.0, process=node)
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from monovoc_ros.contract import DEFAULT_NAMESPACE as NAMESPACE
from monovoc_ros.contract import DIAGNOSTICS_TOPIC, KEYFRAME_ROLES, topic_names
from monovoc_ros.fastdds_profile import PROFILES_ENV, PUBLICATION_MODE_ENV
from monovoc_ros.nodes import service_call

SEMANTIC_MAPPER = "monovoc_ros.nodes.semantic_mapper"  # mapping + object database + query service
MAPPING_ONLY = "monovoc_ros.nodes.mapping_node"
# Variables that would take a child off loopback or onto a profile the caller did not choose.
FOREIGN_ROS_VARIABLES = ("ROS_LOCALHOST_ONLY", "ROS_STATIC_PEERS", PROFILES_ENV, PUBLICATION_MODE_ENV)


class HarnessError(RuntimeError):
    """A child exited, or an answer or a condition did not come in time; the message says which (and shows
    the tail of the child's output)."""


def loopback_environment(log_dir: Path) -> None:
    """Confines this process and its children to loopback unless the caller chose otherwise (rclpy reads
    these at init)."""
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("ROS_LOG_DIR", str(log_dir))


class NodeProcess:
    """A child process with captured output (stdout and stderr interleaved in ``output_path``)."""

    def __init__(
        self,
        args: Sequence[str],
        env: Mapping[str, str] | None = None,
        *,
        name: str = "process",
        output_path: Path | None = None,
        cwd: Path | None = None,
        process_group: bool = False,
    ):
        env = dict(os.environ if env is None else env)
        self.name = name
        self.args = [str(a) for a in args]
        if output_path is None:
            log_dir = Path(env.get("ROS_LOG_DIR") or Path.cwd() / ".ros_log")
            log_dir.mkdir(parents=True, exist_ok=True)
            output_path = log_dir / f"{name}-{os.getpid()}-{time.monotonic_ns()}.out"
        self.output_path = Path(output_path)
        self._out = open(self.output_path, "wb")
        # process_group: the child leads a new process group and every signal goes to the whole group, as a
        # terminal's Ctrl-C reaches a foreground job (`ros2 launch` and the nodes it started alike).
        self.process_group = process_group
        self.proc = subprocess.Popen(
            self.args, env=env, cwd=cwd, stdout=self._out, stderr=subprocess.STDOUT, start_new_session=process_group
        )

    @classmethod
    def python(cls, args: Sequence[str], env: Mapping[str, str] | None = None, *, python: str | Path = sys.executable,
               **kwargs: Any) -> NodeProcess:  # fmt: skip
        """``python args...`` (e.g. ``["-m", "pkg.node", "--ros-args", ...]``)."""
        return cls([str(python), *args], env, **kwargs)

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
        """Status and the tail of the output, for error messages."""
        state = "running" if self.running() else f"exited with {self.proc.returncode}"
        return f"[{self.name} pid {self.pid} {state}; output ({self.output_path}):]\n{self.output()[-tail:]}"

    def check_running(self) -> None:
        """Raises HarnessError with the child's output when it has exited."""
        if not self.running():
            raise HarnessError(f"{self.name} exited early\n{self.describe()}")

    def wait_for_output(self, text: str, timeout: float) -> None:
        """Polls the output for ``text`` that the child is sure to print (a tool's own status line)."""
        wait_until(lambda: text in self.output(), timeout, f"{self.name} to print {text!r}", process=self)

    def stop(self, timeout: float = 30.0) -> int:
        """SIGINT (clean shutdown, up to ``timeout`` s), then SIGTERM, then SIGKILL; returns the exit code."""
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
            if self.process_group:
                os.killpg(self.proc.pid, sig)
            else:
                self.proc.send_signal(sig)
        except ProcessLookupError:
            pass

    def __enter__(self) -> NodeProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        if not self._out.closed:
            self.stop()


Watched = NodeProcess | Sequence[NodeProcess] | Callable[[], None] | None


def _poller(process: Watched) -> Callable[[], None]:
    """One callable that raises when a watched child has exited (``process`` may also be such a callable)."""
    if callable(process) and not isinstance(process, NodeProcess):
        return process
    processes = [] if process is None else [process] if isinstance(process, NodeProcess) else list(process)

    def poll() -> None:
        for p in processes:
            p.check_running()

    return poll


def _details(process: Watched) -> str:
    if isinstance(process, NodeProcess):
        return "\n" + process.describe()
    if isinstance(process, Sequence):
        return "".join("\n" + p.describe() for p in process)
    return ""


def wait_until(
    predicate: Callable[[], bool], timeout: float, what: str, *, process: Watched = None, interval: float = 0.02
) -> None:
    """Polls ``predicate`` until it is true; on timeout (or a watched child exiting) raises HarnessError."""
    poll = _poller(process)
    deadline = time.monotonic() + timeout
    while True:
        if predicate():
            return
        poll()
        if time.monotonic() >= deadline:
            raise HarnessError(f"timed out after {timeout:.1f} s waiting for {what}{_details(process)}")
        time.sleep(interval)


class ClientNode:
    """An rclpy node in its own context, spun by a background executor; rclpy's signal handlers are left to
    the program (tests, the demo).

    With ``env`` (a child's environment, e.g. a test's own domain) the node joins that domain: rclpy reads the
    discovery range and log directory from the process environment at init, so those variables are set for
    the life of the node and restored on exit. Without it, the node uses this process's environment.

    The node is created under fastdds_profile.writer_heartbeat: when it is the process's first participant,
    every writer of the process (a bag replay's too) gets the 50 ms Fast DDS heartbeat.
    """

    _ENV_KEYS = ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOG_DIR", "HOME", "AMENT_PREFIX_PATH")

    def __init__(self, env: Mapping[str, str] | None = None, name: str = "monovoc_client"):
        self._env = env
        self._name = name
        self._saved: dict[str, str | None] = {}
        self.context = None
        self.node = None
        self._spin = None

    def __enter__(self) -> ClientNode:
        import rclpy
        from rclpy.signals import SignalHandlerOptions

        from monovoc_ros.bags.rosnode import spinning
        from monovoc_ros.fastdds_profile import WRITER_HEARTBEAT_MS, writer_heartbeat

        if self._env is not None:
            for key in self._ENV_KEYS:
                self._saved[key] = os.environ.get(key)
                if key in self._env:
                    os.environ[key] = self._env[key]
            for key in FOREIGN_ROS_VARIABLES:
                self._saved[key] = os.environ.pop(key, None)
        try:
            self.context = rclpy.Context()
            domain = os.environ.get("ROS_DOMAIN_ID")
            # A replay in this process (tests, the demo, benchmarks) gets its writers' short heartbeat
            # only if the process's first participant (its first node) was created with it (fastdds_profile).
            with writer_heartbeat(WRITER_HEARTBEAT_MS):
                rclpy.init(context=self.context, domain_id=int(domain) if domain else None,
                           signal_handler_options=SignalHandlerOptions.NO)  # fmt: skip
                self.node = rclpy.create_node(self._name, context=self.context)
            spin = spinning(self.node)
            spin.__enter__()
            self._spin = spin
        except BaseException:
            self.__exit__(None, None, None)  # the environment restored, the context shut down
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        # Stop the executor and join its thread before destroying the node: the other order aborts.
        if self._spin is not None:
            self._spin.__exit__(None, None, None)
        if self.node is not None:
            self.node.destroy_node()
        if self.context is not None:
            self.context.try_shutdown()
        for key, value in self._saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def wait_for_service(client: Any, timeout: float = 10.0, *, process: Watched = None) -> None:
    """Waits until the service of ``client`` is available (discovery takes 0 to ~3 s on loopback)."""
    wait_until(client.service_is_ready, timeout, f"service {client.srv_name}", process=process, interval=0.05)


_DEFAULT = object()


def call_service(
    client: Any, request: Any, timeout: float = 10.0, *, process: Watched = None, resend_s: Any = _DEFAULT
) -> Any:
    """The response (the client's node must be spinning elsewhere, as in ClientNode). An unanswered cheap
    read-only request is sent again (monovoc_ros.nodes.service_call.default_resend); ``resend_s`` overrides
    (None: send once)."""
    resend = service_call.default_resend(request) if resend_s is _DEFAULT else resend_s
    response = service_call.call_service(client, request, timeout, time.sleep, resend_s=resend,
                                         poll=_poller(process))  # fmt: skip
    if response is None:
        what = f"a response from {client.srv_name}"
        raise HarnessError(f"timed out after {timeout:.1f} s waiting for {what}{_details(process)}")
    return response


def node_endpoints(node: Any, kind: str, name: str, namespace: str) -> dict[str, list[str]]:
    """Names -> types of the ``kind`` ("publishers" or "clients") of the node ``namespace``/``name`` as ``node``'s
    graph shows them; empty until ``node`` has discovered that node (rclpy raises NodeNameNonExistentError then)."""
    from rclpy.node import NodeNameNonExistentError

    query = {
        "publishers": node.get_publisher_names_and_types_by_node,
        "clients": node.get_client_names_and_types_by_node,
    }[kind]
    try:
        return dict(query(name, namespace))
    except NodeNameNonExistentError:
        return {}


def wait_for_subscribers(publisher: Any, count: int = 1, timeout: float = 10.0, *, process: Watched = None) -> None:
    """Waits until ``publisher`` is matched with at least ``count`` subscriptions."""
    what = f"{count} subscriber(s) on {publisher.topic_name}"
    wait_until(lambda: publisher.get_subscription_count() >= count, timeout, what, process=process, interval=0.05)


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


class MessageCollector:
    """A subscription callback that stores messages; ``wait_for(n)`` polls until n have arrived."""

    def __init__(self) -> None:
        self.messages: list[Any] = []
        self._lock = threading.Lock()

    def __call__(self, msg: Any) -> None:
        with self._lock:
            self.messages.append(msg)

    def wait_for(self, count: int = 1, timeout: float = 10.0, *, process: Watched = None) -> list[Any]:
        wait_until(lambda: len(self.messages) >= count, timeout, f"{count} message(s)", process=process)
        with self._lock:
            return list(self.messages)


class DiagnosticsMonitor:
    """Keeps the newest ``/diagnostics`` status whose name contains ``name``; ``values()`` is its key -> value
    dict (strings), ``wait_for(pred)`` polls pred(values)."""

    def __init__(self, node: Any, name: str = "", topic: str = DIAGNOSTICS_TOPIC):
        from diagnostic_msgs.msg import DiagnosticArray

        self.name = name
        self._newest: Any = None
        self._lock = threading.Lock()
        self.subscription = node.create_subscription(DiagnosticArray, topic, self._on_message, 10)

    def _on_message(self, msg: Any) -> None:
        with self._lock:
            for status in msg.status:
                if self.name in status.name:
                    self._newest = status

    def values(self) -> dict[str, str]:
        with self._lock:
            newest = self._newest
        return {} if newest is None else {kv.key: kv.value for kv in newest.values}

    def wait_for(
        self,
        predicate: Callable[[dict[str, str]], bool],
        timeout: float = 10.0,
        *,
        what: str = "",
        process: Watched = None,
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
        except HarnessError as exc:
            raise HarnessError(f"{exc}\nlatest diagnostics: {self.values()}") from None
        return found


def keyframes_settled(values: Mapping[str, str], masks_sent: int) -> bool:
    """The mapper's diagnostics say every sent mask reached the node and every keyframe made of them left
    the queue."""
    done = int(values["keyframes_processed"]) + int(values["keyframes_dropped"])
    return (
        int(values.get("messages_received.mask", 0)) >= masks_sent
        and int(values["inputs_waiting"]) == 0
        and int(values["queue_length"]) == 0
        and done >= int(values["keyframes_received"])
    )


class KeyframePublishTimes:
    """`replay(on_published=...)`: per log time (ns) when the last of a keyframe's messages (`KEYFRAME_ROLES`,
    the segmenter's input included) was published, time.monotonic(): the keyframe -> cloud latency counts from
    then, not from the bag's schedule, so a replay that falls behind (reading and publishing a 56 MB map
    message) is not charged to the node."""

    def __init__(self, namespace: str = NAMESPACE) -> None:
        topics = topic_names(namespace)
        self.topics = frozenset(topics[r] for r in KEYFRAME_ROLES)
        self.at: dict[int, float] = {}

    def __call__(self, topic: str, log_time_ns: int) -> None:
        if topic in self.topics:
            self.at[log_time_ns] = time.monotonic()


def cloud_latencies_ms(
    published: Mapping[int, float], arrivals: Mapping[int, float], *, after: float = -math.inf
) -> list[float]:
    """Per keyframe stamp of `published` (stamp ns -> when it was published: `KeyframePublishTimes.at`) the ms
    until the first cloud holding it arrived (`CloudMonitor.arrivals`): one stamped with it or with a later
    keyframe's stamp. Keyframes no cloud held are left out; so are clouds stamped after the last keyframe (the
    node's own, on a map alone), and keyframes published before `after` (`first_cloud_at`: those that waited for
    the node's first map)."""
    last = max(published, default=0)
    out = []
    for stamp, at in sorted(published.items()):
        held = _first_holding(stamp, last, arrivals)
        if held is not None and at >= after:
            out.append(1e3 * (held - at))
    return out


def first_cloud_at(published: Mapping[int, float], arrivals: Mapping[int, float]) -> float | None:
    """When the first cloud holding a keyframe of `published` arrived (as `cloud_latencies_ms`), None if none did:
    the keyframes published before it waited for the node's start (its first map), not for their integration."""
    return _first_holding(min(published, default=0), max(published, default=0), arrivals)


def _first_holding(stamp: int, last: int, arrivals: Mapping[int, float]) -> float | None:
    """The first arrival of a cloud holding the keyframe stamped `stamp` (stamped from it to `last`), or None."""
    return min((t for s, t in arrivals.items() if stamp <= s <= last), default=None)


class CloudMonitor:
    """The newest semantic cloud of ``topic`` and, per header stamp (ns), when its first cloud arrived
    (time.monotonic()): the live-latency benchmark measures keyframe -> cloud with it."""

    def __init__(self, node: Any, topic: str = f"{NAMESPACE}/semantic_cloud"):
        from sensor_msgs.msg import PointCloud2

        from monovoc_ros.nodes.qos import latched_qos

        self._lock = threading.Lock()
        self._cloud = None
        self.arrivals: dict[int, float] = {}
        self.subscription = node.create_subscription(PointCloud2, topic, self._on_cloud, latched_qos())

    def _on_cloud(self, msg: Any) -> None:
        now = time.monotonic()
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        with self._lock:
            self._cloud = msg
            self.arrivals.setdefault(stamp, now)

    def arrivals_now(self) -> dict[int, float]:
        """A copy of ``arrivals`` (stamp ns -> time.monotonic()), safe while clouds keep arriving."""
        with self._lock:
            return dict(self.arrivals)

    def latest(self):
        """The newest semantic cloud as msg_adapters.SemanticCloud, or None."""
        import msg_adapters as ma

        with self._lock:
            msg = self._cloud
        return None if msg is None else ma.semantic_cloud_to_arrays(msg)
