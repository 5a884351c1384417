"""The live semantic mapping node: topics -> KeyframeAssembler -> SemanticMapper -> topics.

    mapping_node --ros-args --params-file config/semantic_mapper.yaml     (ros2 run monovoc_ros mapping_node)

runs it alone: mapping only, no objects database, no embeddings, no models needed. The full node
`semantic_mapper` (monovoc_ros.nodes.semantic_mapper) is this node with the object database and query
service composed beside it (``run(args, compose)``; the interface between them: monovoc_ros.nodes.component).

A thin adapter. Subscription callbacks validate and synchronize messages with the same KeyframeAssembler
that offline bag processing uses (so both give identical keyframes) and queue completed keyframes and
Gaussian maps (taken and decoded by a process of the node's own, monovoc_ros.nodes.map_reader, unless
`map_reader_process` is false) for the `MapWorker` thread, which runs the same MappingSession as offline mapping
(monovoc_ros.core.session: the SemanticMapper and its life), publishes the semantic cloud / objects /
markers and saves snapshots (monovoc_ros.nodes.worker). Services queue their
operations on the same worker, so they apply in order with keyframes, while separate callback groups on a
MultiThreadedExecutor keep callbacks and services responsive during a long integration.

Topics (relative, default namespace /monovoc; remap with `-r __ns:=/x` or `-r image:=/camera/image`):
    in:  image, mask, camera_info, pose, [segments], gaussians   out: semantic_cloud, objects, objects/markers,
    services: save_map, load_map, reset, publish            /diagnostics
Parameters: monovoc_ros.nodes.params.PARAMETERS (config/semantic_mapper.yaml lists them all). The ROS node
name is `semantic_mapper` whichever executable runs it.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import rclpy
from rclpy.callback_groups import CallbackGroup, MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future

import msg_adapters as ma
from monovoc_ros.contract import (
    DEFAULT_NAMESPACE,
    DIAGNOSTICS_TOPIC,
    KEYFRAME_POSES_ROLE,
    KEYFRAME_POSES_TYPE,
    keyframe_types,
    message_class,
)
from monovoc_ros.core.follow.map_updater import GivenMotion
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.map.ply import load_ply
from monovoc_ros.core.map_store import MapStoreError, current_snapshot, load_deferred, load_snapshot
from monovoc_ros.core.mapping import SemanticMapper
from monovoc_ros.core.session import KeyframeListener
from monovoc_ros.core.warm_up import kernels_cached, warm_up
from monovoc_ros.fastdds_profile import WRITER_HEARTBEAT_MS, writer_heartbeat
from monovoc_ros.fastdds_profile import describe as describe_dds
from monovoc_ros.ingest import KeyframeAssembler
from monovoc_ros.nodes.component import Component, MappingHost
from monovoc_ros.nodes.diagnostics import MapperStats, RejectionLog, diagnostic_status
from monovoc_ros.nodes.interpreter_watch import InterpreterWatch, freeze_startup_objects
from monovoc_ros.nodes.map_reader import MapReaderProcess, ReceivedMap, Refusal, supported
from monovoc_ros.nodes.outputs import SemanticOutputs
from monovoc_ros.nodes.param_spec import ParameterError, declare
from monovoc_ros.nodes.params import PARAMETERS, NodeParams
from monovoc_ros.nodes.qos import DIAGNOSTICS_QOS, SERVICE_QOS, input_qos, map_qos, output_events
from monovoc_ros.nodes.reorder import StampReorder
from monovoc_ros.nodes.services import guarded
from monovoc_ros.nodes.startup import StartupAborted, check_stop, compile_kernels, init_rclpy
from monovoc_ros.nodes.worker import CoalescedCall, MapWorker, ResultListener, WorkerSettings, WorkerStopped

NODE_NAME = "semantic_mapper"
# One per callback group (4 or 5 inputs, map, diagnostics) plus services, which may block waiting for the worker.
EXECUTOR_THREADS = 8
# What a stop leaves, after the final snapshot, for the components' stop (the indexing thread finishing its
# chunk of views), the executor's and the node's teardown: measured ~0.2 s on a 2-core machine with 2 busy
# processes beside the node.
TEARDOWN_RESERVE_S = 0.5
STOP_POLL_S = 0.1  # how soon a stop signal is noticed (s)


def _message_types(params: NodeParams) -> dict[str, type]:
    names = keyframe_types(
        params.image_transport, params.mask_transport, params.ingest.pose_type, segments=params.ingest.use_segments
    )
    return {role: message_class(name) for role, name in names.items()}


class MappingNode(Node):
    def __init__(self, stop: threading.Event | None = None, **node_kwargs: Any) -> None:
        """``stop``: set by a stop signal; start-up ends early with StartupAborted when it is set (the kernels'
        compilation is killed, nothing is written)."""
        node_kwargs.setdefault("namespace", DEFAULT_NAMESPACE)
        super().__init__(NODE_NAME, **node_kwargs)
        self.params = self._read_parameters()
        self.stats = MapperStats()
        self._ingest_lock = threading.Lock()
        self.assembler = KeyframeAssembler(self.params.ingest, clock=self._clock_ns)
        self._reorder = StampReorder(
            self.assembler.roles,
            self.params.reorder_wait_s,
            max_lead_s=self.params.ingest.max_stamp_lead_s,
            clock_ns=self._clock_ns,
            max_held=self.params.ingest.max_pending,
        )
        self._reject_log = RejectionLog(self.get_logger().warning)
        self._warned_frame: set[str] = set()
        self._map_reader: MapReaderProcess | None = None
        self._diagnostics_sources: list[Callable[[], dict[str, Any]]] = []
        # What keeps every thread of the node waiting (and, when asked, who).
        trace_ms = self.params.interpreter_hold_trace_ms
        trace = None
        if trace_ms:
            trace = str(Path(rclpy.logging.get_logging_directory()) / f"monovoc_interpreter_holds_{os.getpid()}.txt")
        self._interpreter_watch = InterpreterWatch(trace_after_ms=trace_ms, trace_path=trace)
        self._diagnostics_sources.append(self._interpreter_watch.diagnostics)
        # Named so that plugins can put their own callbacks beside ours.
        # One group per input topic: each topic's messages are handled one at a time, in order (what the
        # assembler needs), while the topics progress side by side. In one shared mutually exclusive group
        # the executor keeps picking the first ready subscription, so during a burst (a bag replayed with
        # --fast) one topic ran ahead of the others by more than the synchronizer buffers, losing keyframes.
        self.callback_groups: dict[str, CallbackGroup] = {
            **{f"input.{role}": MutuallyExclusiveCallbackGroup() for role in self.assembler.roles},
            "map": MutuallyExclusiveCallbackGroup(),  # decoding a big map must not hold up keyframes
            "services": ReentrantCallbackGroup(),  # handlers wait for the worker; several may wait at once
            "timers": MutuallyExclusiveCallbackGroup(),
        }
        self.outputs = SemanticOutputs(
            self,
            frame_id=self.params.frame_id,
            labels=self.params.labels,
            up=self.params.marker_up,
            on_cloud_subscriber=lambda: self._publish_for_subscriber(),  # set once the worker exists, below
        )
        p = self.params
        settings = WorkerSettings(
            queue_size=p.queue_size,
            publish_period_s=1.0 / p.publish_rate_hz if p.publish_rate_hz > 0 else 0.0,
            map_directory=p.map_directory,
            save_period_s=p.save_period_s,
            map_update_max_shrink=p.map_update_max_shrink,
            map_update_ahead_s=p.map_update_ahead_s,
        )
        self.worker = MapWorker(
            p.mapper,
            settings,
            stats=self.stats,
            sink=self.outputs,
            log=self.get_logger(),
            mapper=self._initial_mapper(),
        )
        self.worker.add_reset_listener(self._reset_ingest)
        self._republish = CoalescedCall(self.worker, self.outputs.republish_objects, "republish_objects",
                                        self._report_failure)  # fmt: skip
        self._publish_for_subscriber = CoalescedCall(self.worker, self.worker.publish_now, "publish_cloud",
                                                     self._report_failure)  # fmt: skip
        self.add_diagnostics_source(lambda: {"clouds_skipped": self.outputs.clouds_skipped})
        try:
            check_stop(stop, "loading the map")
            self._queue_deferred()
            self._map_reader = self._create_map_reader()  # its start-up overlaps the kernels' loading
            self._prepare_kernels(stop)
        except StartupAborted:
            self.destroy_node()  # nothing subscribed or written yet
            raise
        self._create_subscriptions()
        self._create_services()
        self._diagnostics = self.create_publisher(
            _diagnostic_array_type(), DIAGNOSTICS_TOPIC, DIAGNOSTICS_QOS, event_callbacks=output_events()
        )
        timers = self.callback_groups["timers"]
        # Wall-clock (steady) timers: with use_sim_time, ROS-time timers stop when /clock stops (a bag's end)
        # or never start (no /clock yet), and with them diagnostics and the flush of held inputs.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(p.diagnostics_period_s, self._publish_diagnostics, callback_group=timers, clock=steady)
        # Armed only while inputs are held (`_on_input`): ticking at 10 Hz with nothing to release, it woke the
        # executor twenty times a second (the tick and its callback's end), each wake-up Python holding the
        # interpreter while the worker waited for it between its kernels.
        self._flush_timer = None
        if p.reorder_wait_s > 0:
            self._flush_timer = self.create_timer(
                min(0.1, p.reorder_wait_s), self._flush_stale_inputs, callback_group=timers, clock=steady,
                autostart=False,
            )  # fmt: skip

    # ------------------------------------------------------------------ hooks for other components

    def _create_component_service(self, srv_type: Any, name: str, handler: Callable, qos: Any) -> Any:
        """A component's service on this node, in its own group: it runs beside keyframes and other services."""
        group = self.callback_groups.setdefault(f"component.{name}", MutuallyExclusiveCallbackGroup())
        return self.create_service(srv_type, name, handler, qos_profile=qos, callback_group=group)

    def _create_action_server(
        self, action_type: Any, name: str, execute: Callable, goal: Callable, cancel: Callable
    ) -> Any:
        from rclpy.action import ActionServer

        group = self.callback_groups.setdefault("actions", ReentrantCallbackGroup())
        return ActionServer(
            self, action_type, name, execute, goal_callback=goal, cancel_callback=cancel, callback_group=group
        )

    def _create_action_client(self, action_type: Any, name: str) -> Any:
        from monovoc_ros.nodes.action_client import LockedActionClient

        group = self.callback_groups.setdefault("actions", ReentrantCallbackGroup())
        return LockedActionClient(self, action_type, name, callback_group=group)

    def host(self) -> MappingHost:
        """What this node offers the components composed with it (monovoc_ros.nodes.component)."""
        p, worker = self.params, self.worker
        return MappingHost(
            logger=self.get_logger(),
            clock=self.get_clock(),
            create_publisher=self.create_publisher,
            create_service=self._create_component_service,
            create_action_server=self._create_action_server,
            create_action_client=self._create_action_client,
            frame_id=p.frame_id,
            marker_up=tuple(p.marker_up),
            labels=dict(p.labels),
            map_directory=p.map_directory,
            resume=p.resume,
            mapper=lambda: worker.mapper,
            busy=worker.busy,
            add_keyframe_listener=self.add_keyframe_listener,
            add_result_listener=self.add_result_listener,
            add_reset_listener=worker.add_reset_listener,
            add_save_listener=worker.add_save_listener,
            add_load_check=worker.add_load_check,
            add_diagnostics_source=self.add_diagnostics_source,
            set_label_provider=self.outputs.set_label_provider,
            republish_objects=self.republish_objects,
        )

    def add_keyframe_listener(self, fn: KeyframeListener) -> None:
        """fn(keyframe, mapper) on the worker thread after each integrated keyframe."""
        self.worker.add_keyframe_listener(fn)

    def add_result_listener(self, fn: ResultListener) -> None:
        """fn(mapper, result) on the worker thread each time the semantic result is recomputed (before publishing)."""
        self.worker.add_result_listener(fn)

    def add_diagnostics_source(self, fn: Callable[[], dict[str, Any]]) -> None:
        """fn() -> key/value pairs added to every /diagnostics status (timer thread; keep it cheap)."""
        self._diagnostics_sources.append(fn)

    def republish_objects(self) -> None:
        """Queues a republication of the objects and markers with the current labels on the worker thread
        (the `publish` service's path, without the cloud); one request at a time, later ones coalesce."""
        self._republish()

    def _report_failure(self, future: concurrent.futures.Future) -> None:
        """Done-callback of the worker tasks nobody waits for: a failure is logged with its traceback and counted
        (a task discarded by a stopping worker is not a failure)."""
        exc = None if future.cancelled() else future.exception()
        if exc is None or isinstance(exc, WorkerStopped):
            return
        self.stats.add(worker_errors=1)
        self.get_logger().error(
            f"worker task failed: {type(exc).__name__}: {exc}\n" + "".join(traceback.format_exception(exc))
        )

    def submit(self, fn: Callable[[SemanticMapper | None], Any]) -> concurrent.futures.Future:
        """Runs fn(mapper) on the worker thread, in order with keyframes and map updates."""
        return self.worker.submit(fn)

    # ------------------------------------------------------------------ life cycle

    def start(self) -> None:
        self._interpreter_watch.start()
        self.worker.start()
        if self._map_reader is not None:
            self._map_reader.start()
        p = self.params
        self.get_logger().info(
            f"ready: {self.get_namespace()} inputs {list(self.assembler.roles)} (image {p.image_transport}, mask "
            f"{p.mask_transport}, pose {p.ingest.pose_type}), impl {p.mapper.impl}, queue {p.queue_size}, "
            f"map directory {p.map_directory or '-'}"
        )

    def stop(self, since: float | None = None) -> None:
        """Stops the worker so that the node can exit shutdown_timeout_s after `since` (the stop signal's
        time.monotonic(); None: now): what is queued is integrated while the final snapshot (when map_directory
        is set) and the components' stop (TEARDOWN_RESERVE_S) still fit, the rest deferred to the snapshot.
        Call before the components' stop and destroy_node()."""
        end = (time.monotonic() if since is None else since) + self.params.shutdown_timeout_s
        if self._map_reader is not None:  # no map arrives while the worker drains
            self._map_reader.stop()
        self.worker.stop(within_s=end - TEARDOWN_RESERVE_S - time.monotonic())
        self._interpreter_watch.stop()

    def destroy_node(self) -> None:
        self._interpreter_watch.stop()
        if self._map_reader is not None:  # stopped already unless start-up was cut short
            self._map_reader.stop()
        super().destroy_node()

    # ------------------------------------------------------------------ set-up

    def _read_parameters(self) -> NodeParams:
        return NodeParams.from_values(declare(self, PARAMETERS))

    def _initial_mapper(self) -> SemanticMapper | None:
        p, log = self.params, self.get_logger()
        snapshot = current_snapshot(p.map_directory) if p.map_directory else None
        if p.resume and snapshot is not None:
            mapper = load_snapshot(p.map_directory, p.mapper)
            log.info(f"resumed {snapshot}: {mapper.n_keyframes} keyframes, {len(mapper.gaussians)} Gaussians")
            if p.map_ply:
                log.warning(f"map_ply {p.map_ply} ignored: resumed from a snapshot")
            return mapper
        if snapshot is not None:
            log.warning(f"{p.map_directory} holds a saved map but resume is false: new snapshots will supersede it")
        if p.map_ply:
            gaussians = load_ply(p.map_ply)
            log.info(f"map_ply {p.map_ply}: {len(gaussians)} Gaussians")
            return SemanticMapper(gaussians, p.mapper)
        return None

    def _queue_deferred(self) -> None:
        """Keyframes the last run received but did not integrate (saved with its final snapshot) go first."""
        p = self.params
        if not (p.resume and p.map_directory and self.worker.mapper is not None):
            return
        try:
            deferred = load_deferred(p.map_directory)
        except MapStoreError as exc:  # auxiliary: the map itself resumed; keep the file for inspection
            self.get_logger().error(f"deferred keyframes not resumed: {exc}")
            return
        for keyframe in deferred:
            self.worker.submit_keyframe(keyframe, bounded=False)
        if deferred:
            self.get_logger().info(f"resumed {len(deferred)} keyframes the last run deferred: integrated first")

    def _prepare_kernels(self, stop: threading.Event | None) -> None:
        """The mapping kernels compiled (in a child, when numba's cache is empty) and loaded before the node
        subscribes: a replay that waits for subscribers then waits for a node that can integrate."""
        log = self.get_logger()
        if not kernels_cached():
            log.info("mapping kernels not in numba's cache (`monovoc warm-up` fills it at install): compiling them now")
            try:
                seconds = compile_kernels(stop)
            except (RuntimeError, OSError) as exc:  # the first keyframes compile in this process instead
                log.warning(f"{exc}; the kernels compile on first use")
                return
            else:
                self.stats.update(kernel_compile_ms=1e3 * seconds)
                log.info(f"mapping kernels compiled in {seconds:.1f} s")
        check_stop(stop, "the kernels were compiling")
        try:
            seconds = warm_up(self.params.mapper)
        except Exception as exc:  # the real keyframes will show the same error, counted; mapping goes on
            log.warning(f"kernel warm-up failed: {type(exc).__name__}: {exc}")
            return
        self.stats.update(warm_up_ms=1e3 * seconds)
        log.info(f"mapping kernels loaded in {seconds:.1f} s")

    def _create_map_reader(self) -> MapReaderProcess | None:
        """The map topic's reader process (map_reader_process), or None: the map is taken in this process."""
        if not self.params.map_reader_process:
            return None
        if not supported():
            self.get_logger().warning("map_reader_process: not supported on this platform (Linux only)")
            return None
        return MapReaderProcess(
            self.resolve_topic_name("gaussians"),
            f"_{self.get_name()}_map_reader",
            self.get_namespace(),
            on_map=self._on_received_map,
            on_refused=self._on_reader_refusal,
            on_restart=self._map_reader_restarted,
        )

    def _create_subscriptions(self) -> None:
        from sensor_msgs.msg import PointCloud2

        types = _message_types(self.params)
        qos = input_qos(self.params.input_depth, self.params.input_reliability)
        for role in self.assembler.roles:
            self.create_subscription(
                types[role],
                role,
                lambda msg, role=role: self._on_input(role, msg),
                qos,
                callback_group=self.callback_groups[f"input.{role}"],
            )
        if self._map_reader is None:
            ma.prepare_point_cloud_decoder()  # not in the first map's callback
            self.create_subscription(
                PointCloud2,
                "gaussians",
                self._on_gaussians,
                map_qos(),
                callback_group=self.callback_groups["map"],
                raw=True,  # decoded as the map reader decodes it (msg_adapters.gaussian_map_from_cdr)
            )
        # Volatile, so that a SLAM publishing its path either way (latched or not) matches.
        self.create_subscription(
            message_class(KEYFRAME_POSES_TYPE),
            KEYFRAME_POSES_ROLE,
            self._on_keyframe_poses,
            input_qos(5),
            callback_group=self.callback_groups["map"],
        )

    def _create_services(self) -> None:
        from std_srvs.srv import Trigger

        from monovoc_interfaces.srv import LoadMap, Reset, SaveMap

        group = self.callback_groups["services"]
        self.create_guarded_service(SaveMap, "save_map", self._on_save, group)
        self.create_guarded_service(LoadMap, "load_map", self._on_load, group)
        self.create_guarded_service(Reset, "reset", self._on_reset, group)
        self.create_guarded_service(Trigger, "publish", self._on_publish, group)

    def create_guarded_service(
        self, srv_type: type, name: str, handler: Callable[[Any, Any], Any], group: CallbackGroup, qos: Any = None
    ) -> Any:
        """A service whose every failure answers success=false (monovoc_ros.nodes.services.guarded), counted
        as `service_errors` in diagnostics, with a request queue deep enough for bursts (SERVICE_QOS).
        Components (the query service) use it too."""

        def count() -> None:
            self.stats.add(service_errors=1)

        callback = guarded(srv_type, name, handler, log=self.get_logger().error, on_error=count)
        qos = SERVICE_QOS if qos is None else qos
        return self.create_service(srv_type, name, callback, callback_group=group, qos_profile=qos)

    # ------------------------------------------------------------------ inputs

    def _clock_ns(self) -> int | None:
        """ROS time (``/clock`` under sim time; 0 until it arrives): a stamp far ahead of it is refused."""
        return self.get_clock().now().nanoseconds or None

    def _on_input(self, role: str, msg: Any) -> None:
        with self._ingest_lock:  # topics arrive on several threads; the assembler takes them one at a time
            self._push(self._reorder.add(role, msg))
            if len(self._reorder) and self._flush_timer is not None and self._flush_timer.is_canceled():
                self._flush_timer.reset()

    def _flush_stale_inputs(self) -> None:
        # Messages held for a topic that went quiet are released after reorder_wait_s even without traffic.
        with self._ingest_lock:
            if len(self._reorder):
                self._push(self._reorder.due())
            if not len(self._reorder):
                self._flush_timer.cancel()

    def _push(self, messages: list[tuple[str, Any]]) -> None:
        """Assembler -> worker queue, in stamp order (called with the ingest lock held)."""
        for role, msg in messages:
            try:
                keyframes, rejections = self.assembler.push(role, msg)
            except Exception as exc:  # a bug must cost one message, not the subscription, and show as a bug
                keyframes, rejections = [], []
                self._ingest_bug(f"{role}: the keyframe assembler failed", exc)
            for r in rejections:
                self.stats.reject(r.reason)
                self._reject_log(r.reason, f"{r.role} stamp {r.stamp_ns}: {r.detail}")
            for keyframe in keyframes:
                self.stats.add(keyframes_received=1)
                dropped = self.worker.submit_keyframe(keyframe)
                if dropped is not None:
                    self._reject_log("queue_full", f"keyframe {dropped.stamp_ns} dropped: queue_size reached")

    def _on_gaussians(self, data: bytes) -> None:
        start = time.perf_counter()
        # Counted once queued or refused: a --fast replay waits for the count before the keyframes after it.
        try:
            try:
                gaussians, frame_id = ma.gaussian_map_from_cdr(data)
            except ValueError as exc:
                self._refuse_map(f"Gaussian map ignored: {exc}")
                return
            self._accept_map(gaussians, gaussians.stamp_ns, frame_id, time.perf_counter() - start)
        except Exception as exc:  # a bug must cost one map, not the node (the executor would end it), and show as one
            self._ingest_bug("gaussians: handling a map failed", exc)
        finally:
            self.stats.add(maps_received=1)

    def _ingest_bug(self, what: str, exc: Exception) -> None:
        """An input dropped by a bug, not by bad input: counted as ingest_errors and logged with its traceback."""
        self._ingest_error(
            f"{what} ({type(exc).__name__}: {exc}); message dropped\n" + "".join(traceback.format_exception(exc))
        )

    def _ingest_error(self, message: str) -> None:
        self.stats.add(ingest_errors=1)
        self.get_logger().error(message)

    def _on_received_map(self, received: ReceivedMap) -> None:
        self.stats.add(maps_coalesced=received.superseded)  # replaced in the reader before the worker saw them
        try:
            self._accept_map(
                received.gaussians, received.stamp_ns, received.frame_id, received.decode_s, received.motion
            )
        except Exception as exc:  # a bug must cost one map, not the map reader's thread, and show as a bug
            self._ingest_bug("gaussians: handling a map failed", exc)
        finally:  # once queued (a --fast replay waits for the count), with those it replaced in the reader
            self.stats.add(maps_received=1 + received.superseded)

    def _accept_map(
        self, gaussians: GaussianMap, stamp_ns: int, frame: str, decode_s: float, given: GivenMotion | None = None
    ) -> None:
        """A decoded map message (from the map callback or the map reader process, with the motion it estimates)
        -> the worker."""
        self.stats.add(map_decode_s=decode_s, maps_decoded=1)
        if frame and frame != self.params.frame_id and frame not in self._warned_frame:
            self._warned_frame.add(frame)
            self.get_logger().warning(f"Gaussian map frame {frame!r} differs from frame_id {self.params.frame_id!r}")
        self.worker.submit_map(gaussians, f"stamp {stamp_ns}", given)

    def _refuse_map(self, message: str) -> None:
        self.stats.reject("bad_gaussians")
        self._reject_log("bad_gaussians", message)

    def _on_reader_refusal(self, refusal: Refusal) -> None:
        self.stats.add(maps_received=int(refusal.of_map))
        if refusal.bad_input:
            self._refuse_map(refusal.message)
        else:  # the reader's own failure, its traceback in the message
            self._ingest_error(refusal.message)

    def _map_reader_restarted(self, message: str) -> None:
        self.stats.add(map_reader_restarts=1)
        self.get_logger().error(message)

    def _on_keyframe_poses(self, msg: Any) -> None:
        try:
            poses = ma.path_to_keyframe_poses(msg, self.params.ingest.frame_convention)
        except ValueError as exc:
            self.stats.reject("bad_keyframe_poses")
            self._reject_log("bad_keyframe_poses", f"keyframe poses ignored: {exc}")
            return
        future = self.worker.submit_keyframe_poses(poses, f"stamp {ma.header_stamp_ns(msg)}")
        future.add_done_callback(self._report_failure)

    def _reset_ingest(self) -> None:
        # A reset forgets the stamps seen so far, so the same sequence can be sent again.
        with self._ingest_lock:
            self.assembler = KeyframeAssembler(self.params.ingest, clock=self._clock_ns)
            self._reorder.clear()

    # ------------------------------------------------------------------ services

    def _wait(self, future: concurrent.futures.Future, what: str) -> tuple[bool, Any]:
        """(True, result) or (False, message) for a worker call."""
        timeout = self.params.service_timeout_s
        try:
            return True, future.result(timeout=timeout)
        except concurrent.futures.TimeoutError:
            return False, f"{what}: timed out after {timeout:g} s waiting for the worker (still queued; it will run)"
        except WorkerStopped as exc:
            return False, str(exc)
        except (ValueError, OSError) as exc:  # expected failures (MapStoreError, PlyError, ...): their message
            return False, f"{what}: {exc}"
        except Exception as exc:  # anything else still answers, with its type
            return False, f"{what}: {type(exc).__name__}: {exc}"

    def _directory(self, requested: str) -> str:
        directory = requested or self.params.map_directory
        if not directory:
            raise ValueError("no directory given and parameter map_directory is not set")
        try:
            return str(Path(directory).expanduser().resolve())
        except (OSError, RuntimeError) as exc:  # a symlink loop (RuntimeError before Python 3.13), no home
            raise ValueError(f"{directory}: {exc}") from None

    def _on_save(self, request: Any, response: Any) -> Any:
        try:
            directory = self._directory(request.directory)
        except ValueError as exc:
            response.success, response.message = False, str(exc)
            return response
        ok, out = self._wait(self.worker.call(lambda: self.worker.save(directory), "save_map"), "save_map")
        response.success = ok
        response.directory = directory if ok else ""
        response.message = f"saved {out.keyframes} keyframes, {out.gaussians} Gaussians to {out.path}" if ok else out
        return response

    def _on_load(self, request: Any, response: Any) -> Any:
        try:
            path = self._directory(request.directory)
        except ValueError as exc:
            response.success, response.message = False, str(exc)
            return response

        def load() -> tuple[int, int, int]:
            mapper = self.worker.load(path)
            return len(mapper.gaussians), self.worker.objects_now(), mapper.n_keyframes

        ok, out = self._wait(self.worker.call(load, "load_map"), "load_map")
        response.success = ok
        if ok:
            response.directory = path
            response.num_gaussians, response.num_objects, keyframes = out
            response.message = f"loaded {path}: {keyframes} keyframes, {out[0]} Gaussians, {out[1]} objects"
        else:
            response.message = out
        return response

    def _on_reset(self, request: Any, response: Any) -> Any:
        keep = bool(request.keep_gaussians)
        ok, out = self._wait(self.worker.call(lambda: self.worker.reset(keep), "reset"), "reset")
        response.success = ok
        response.message = (
            ("semantic state cleared" if keep else "map cleared; waiting for a Gaussian map") if ok else out
        )
        return response

    def _on_publish(self, request: Any, response: Any) -> Any:
        ok, out = self._wait(self.worker.call(self.worker.publish_now, "publish"), "publish")
        response.success = ok
        if ok:
            result, objects = out
            points = 0 if result is None else int((result.object_ids != 0xFFFFFFFF).sum())
            response.message = f"published {points} labelled Gaussians, {objects} objects"
        else:
            response.message = out
        return response

    # ------------------------------------------------------------------ diagnostics

    def _publish_diagnostics(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        snapshot = self.stats.snapshot()
        snapshot["queue_length"] = self.worker.keyframes_waiting
        snapshot["inputs_waiting"] = len(self._reorder)
        snapshot["inputs_released_early"] = self._reorder.released_early
        snapshot["map_reader_motion_s"] = self._map_reader.motion_seconds if self._map_reader is not None else 0.0
        with self._ingest_lock:
            sync = self.assembler.sync.stats
            extra: dict[str, Any] = {f"sync_unmatched.{r}": n for r, n in sync.unmatched.items()}
            extra.update({f"sync_overflow.{r}": n for r, n in sync.overflow.items()})
            extra.update({f"messages_received.{r}": n for r, n in self.assembler.received.items()})
            # Streams that resumed far ahead of their last stamps (a pause), and far-future messages held aside.
            extra["stamp_epochs"] = self.assembler.epochs.epochs
            extra["stamps_held"] = self.assembler.epochs.held + self._reorder.epochs.held
        for source in self._diagnostics_sources:
            extra.update(source())
        status = diagnostic_status(
            snapshot, name=f"{self.get_fully_qualified_name()}: semantic mapping", hardware_id=NODE_NAME, extra=extra
        )
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._diagnostics.publish(msg)


def _diagnostic_array_type() -> type:
    from diagnostic_msgs.msg import DiagnosticArray

    return DiagnosticArray


def run(args: list[str] | None = None, compose: Callable[[MappingNode], list[Component]] | None = None) -> int:
    """Runs the mapping node, and the components ``compose(node)`` creates beside it, until SIGINT/SIGTERM."""
    # The executor's callbacks, the worker and the components hand the GIL to each other many times per
    # keyframe and per query; with the default 5 ms switch interval each handoff could wait up to 5 ms
    # behind another thread's Python code (the tails of query and keyframe-to-cloud latency).
    sys.setswitchinterval(0.001)
    stop = StopSignals()
    try:
        return _run(args, compose, stop)
    finally:
        # Stopped: the process only exits now, and a late signal must not turn that into exit code -2.
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, signal.SIG_IGN)


def _run(args: list[str] | None, compose: Callable[[MappingNode], list[Component]] | None, stop: StopSignals) -> int:
    # rclpy's own handlers would shut the context down under the final snapshot's feet: ours only ask to stop.
    node = None
    try:
        # The participant comes with the first node: its reliable writers (the query's answers among them)
        # repair a lost sample within 50 ms, not Fast DDS's 3 s (monovoc_ros.fastdds_profile).
        with writer_heartbeat(WRITER_HEARTBEAT_MS) as ours:
            init_rclpy(args)
            node = MappingNode(stop=stop.requested)
        node.get_logger().info(describe_dds(ours))
        components = compose(node) if compose is not None else []
        check_stop(stop.requested, "starting components")
    except StartupAborted as exc:
        print(f"{NODE_NAME}: {exc}: exiting, nothing written", file=sys.stderr)
        _abort(node)
        return 0
    except ParameterError as exc:
        print(f"{NODE_NAME}: invalid parameter {exc}", file=sys.stderr)
        _abort(node)
        return 2
    except (MapStoreError, OSError, ValueError) as exc:
        print(f"{NODE_NAME}: cannot start: {exc}", file=sys.stderr)
        _abort(node)
        return 1
    executor = MultiThreadedExecutor(num_threads=EXECUTOR_THREADS)
    executor.add_node(node)
    freeze_startup_objects()
    for component in components:
        component.start()
    node.start()
    try:
        stop.spin(executor)
    finally:
        # Order matters (ROS_WHEELS.md): worker (final snapshot), components, executor, then node and context.
        node.stop(since=stop.requested_at)
        for component in reversed(components):
            component.stop()
        executor.shutdown(timeout_sec=5.0)
        if stop.requested_at is not None:
            node.get_logger().info(f"stopped {time.monotonic() - stop.requested_at:.2f} s after the signal")
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


class StopSignals:
    """SIGINT / SIGTERM handler: the first signal asks the node to stop, later ones are only logged. A
    terminal's Ctrl-C reaches both the node and `ros2 launch`, which forwards one more. Raising
    KeyboardInterrupt instead (as rclpy's default does) lands wherever the main thread happens to be: in
    the worker's join it cut the final snapshot short, inside the executor it left half-built rclpy Tasks
    whose __del__ printed a traceback."""

    def __init__(self, node_name: str = NODE_NAME) -> None:
        self.node_name = node_name
        self.requested = threading.Event()
        self.requested_at: float | None = None  # the first signal's time.monotonic()
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, self)

    def spin(self, executor: Any) -> None:
        """Spins ``executor`` until a stop is asked or the context shuts down, on a thread of its own while this
        (the main) thread sleeps in slices: a signal lands in the sleep, never inside the executor, and is noticed
        within STOP_POLL_S. The executor then waits without a timeout, so it wakes only for work: spinning in
        0.1 s slices on this thread made ten more wake-ups a second, each building a timeout timer and the wait
        set in Python, holding the interpreter while the worker waited for it between its kernels. Once it
        returns, no callback runs until the executor spins again (none does: the node stops). A callback's
        exception is raised here, as the executor raises it."""
        stopped = Future()
        failure: list[BaseException] = []

        def run() -> None:
            try:
                executor.spin_until_future_complete(stopped)
            except ExternalShutdownException:
                pass
            except BaseException as exc:  # raised again on the main thread
                failure.append(exc)

        thread = threading.Thread(target=run, name="monovoc-executor", daemon=True)
        thread.start()
        while thread.is_alive() and not self.requested.is_set():
            time.sleep(STOP_POLL_S)
        if thread.is_alive():  # else the context shut down
            stopped.set_result(None)  # wakes the executor (its done callback), which returns
        thread.join()
        if failure:
            raise failure[0]

    def __call__(self, signum: int, _frame: Any) -> None:
        if not self.requested.is_set():
            self.requested_at = time.monotonic()
            self.requested.set()
            return
        with contextlib.suppress(OSError):  # a closed stderr must not raise in the main thread
            print(
                f"{self.node_name}: {signal.Signals(signum).name} again: already shutting down",
                file=sys.stderr,
                flush=True,
            )


def _abort(node: MappingNode | None) -> None:
    if node is not None:
        node.destroy_node()
    rclpy.try_shutdown()


def main(args: list[str] | None = None) -> int:
    """The mapping node alone (console script `mapping_node`)."""
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
