"""Objects, language embeddings and the text-query service: a component beside the mapping node.

The full node `semantic_mapper` (monovoc_ros.nodes.semantic_mapper) composes it with the mapping node
(monovoc_ros.nodes.mapping_node) through the interface of monovoc_ros.nodes.component. It adds:

* service ``query`` (monovoc_interfaces/srv/TextQuery; /monovoc/query by default) of the mapping node
  (`ros2 node info` lists it there), in a callback group of its own, with a keep-last-1000 request queue
  (SERVICE_QOS), answered from an immutable snapshot of the object index, so it stays responsive while
  the worker integrates keyframes and while objects are being embedded (recent query texts are cached).
  It used to live on a second node with its own executor, for latency: once the mapping node's executor
  no longer fought BLAS threads for the cores, both gave the same tails (benchmarks/bench_query.py), and
  the second node had cost a second name under `__node` remaps and `ros2 node info` the service;
* service ``ask`` (monovoc_interfaces/srv/Ask): questions answered from the same index
  (monovoc_ros.objects.questions: how many, what is on, where is, is there);
* topics ``query/highlight`` (PointCloud2 in the semantic-cloud schema: the Gaussians of the objects of
  the last successful query; built only while something subscribes, then sent to a late subscriber) and
  ``query/markers`` (MarkerArray: their boxes and labels), both latched;
* ``objects.db`` (monovoc_ros.objects.database) beside the map snapshots, written whenever the node
  writes a snapshot (save_map, periodic and final saves), and read back on resume and load_map. What it
  holds is taken on the worker thread; the views' images are encoded and the file written on a thread of
  its own (331 new views took the worker 2.25 s at 1M Gaussians): save_map and the final save wait for it.

Its parameters (PARAMETERS) are declared on the mapping node, beside the node's own.

Threads: the keyframe hook (worker thread) only offers views (~5-10 ms); the result hook (worker thread)
only hands the newest result over; this component's own thread refreshes summaries and re-embeds dirty
objects in bounded chunks (``objects.max_objects_per_refresh``), so the worker never waits for the image
encoder, and only while the worker is idle (at least one chunk every REFRESH_DEFER_S). A reset clears the
objects; a load_map restores those saved with that map (if any). Geometry
(centroids, boxes) is the mapping result's own (``SemanticResult.objects``): the objects topic, its markers
and the answers agree. So do labels (core.segments.object_labels): this component gives the host the labels its
records carry (``MappingHost.set_label_provider``: restored names and the embedding model's guesses, which
exist only after embedding) and asks for the objects and markers again when they change.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import msg_adapters as ma
from monovoc_ros.core.segments.object_labels import ObjectLabel, display
from monovoc_ros.embed.backend import backend_class
from monovoc_ros.embed.model_store import ModelMissingError
from monovoc_ros.nodes.component import MappingHost
from monovoc_ros.nodes.diagnostics import Longest
from monovoc_ros.nodes.navigation import NavigationSettings
from monovoc_ros.nodes.object_query_params import PARAMETERS
from monovoc_ros.nodes.outputs import semantic_objects
from monovoc_ros.nodes.param_spec import declare
from monovoc_ros.nodes.qos import SERVICE_QOS
from monovoc_ros.nodes.serialized_publisher import SerializedPublisher
from monovoc_ros.nodes.services import guarded
from monovoc_ros.objects import questions, spatial
from monovoc_ros.objects.database import (
    DB_NAME,
    ObjectDatabase,
    ObjectDatabaseError,
    PreparedSave,
    load_object_index,
    prepare_save,
)
from monovoc_ros.objects.index import IndexConfig, ObjectIndex, lazy_backend
from monovoc_ros.objects.records import QueryError

REFRESH_DEFER_S = 5.0  # longest time embedding waits while the worker is busy
IDLE_WAIT_S = 1.0  # the indexing thread's wait for a new result with nothing to embed
YIELD_POLL_S = 0.05  # its wait while objects wait to be embedded: it looks for the worker's idle moments
SLOW_ANSWER_MS = 50.0  # answers slower than this in the handler are counted (issue 25's query p99 target)
# Added to the nice value of the indexing thread (and its encoder threads) and of the objects.db writer.
BACKGROUND_NICENESS = 10


class HandlerTimes:
    """How long the query and ask handlers took: the node's own part of an answer's latency (the rest is the
    request's and the answer's way through DDS and the executor), to tell the two apart in /diagnostics."""

    def __init__(self) -> None:
        # Handlers run side by side (a reentrant callback group); the time kept is when the slowest began.
        keys = ("queries.handler_ms_max", "queries.handler_slowest_at", f"queries.handler_over_{SLOW_ANSWER_MS:.0f}ms")
        self._longest = Longest(keys, SLOW_ANSWER_MS)

    def timed(self, handler: Callable[[Any, Any], Any]) -> Callable[[Any, Any], Any]:
        def call(request: Any, response: Any) -> Any:
            began, start = time.time(), time.perf_counter()
            try:
                return handler(request, response)
            finally:
                self._longest.add(1e3 * (time.perf_counter() - start), began)

        return call

    def diagnostics(self) -> dict[str, Any]:
        return self._longest.values()


def _lower_priority() -> None:
    """This thread below the mapping worker in the scheduler (Linux niceness is per thread; threads it
    creates inherit it)."""
    with contextlib.suppress(OSError, AttributeError):
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), BACKGROUND_NICENESS)


# Metres from the map's origin beyond which a request's viewpoint is refused (a robot's pose is far closer).
MAX_VIEWPOINT_M = 1e6


@dataclass(frozen=True)
class QuerySettings:
    top_k: int
    max_text_chars: int
    highlight: bool
    highlight_rate_hz: float
    backend: str
    model_dir: str
    max_objects_per_refresh: int
    index: IndexConfig
    navigation: NavigationSettings


def read_settings(node: Any, labels: Mapping[int, str] | None = None) -> QuerySettings:
    """Declares PARAMETERS on ``node`` (the mapping node) and reads them; ``labels``: its labels_file."""
    values = declare(node, PARAMETERS)  # ParameterError on a bad value
    index = IndexConfig(
        crop_mode=str(values["objects.crop_mode"]),
        views_per_object=int(values["objects.views_per_object"]),
        description_weight=float(values["objects.description_weight"]),
        label_weight=float(values["objects.label_weight"]),
        labels=dict(labels) if labels else None,
        min_gaussians=int(values["objects.min_gaussians"]),
        up_axis=str(values["objects.up_axis"]),
        default_top_k=int(values["query.top_k"]),
        max_query_chars=int(values["query.max_text_chars"]),
    )
    return QuerySettings(
        top_k=int(values["query.top_k"]),
        max_text_chars=int(values["query.max_text_chars"]),
        highlight=bool(values["query.highlight"]),
        highlight_rate_hz=float(values["query.highlight_rate_hz"]),
        backend=str(values["objects.backend"]),
        model_dir=str(values["objects.model_dir"]),
        max_objects_per_refresh=int(values["objects.max_objects_per_refresh"]),
        index=index,
        navigation=NavigationSettings.from_values(values),
    )


class ObjectQueryComponent:
    """See the module docstring: ``start()`` before the mapping worker starts, ``stop()`` after it stopped
    (monovoc_ros.nodes.component)."""

    def __init__(self, host: MappingHost, settings: QuerySettings, backend: object | None = None) -> None:
        from sensor_msgs.msg import PointCloud2
        from visualization_msgs.msg import MarkerArray

        from monovoc_interfaces.srv import Ask, TextQuery
        from monovoc_ros.nodes.qos import latched_qos, output_events
        from monovoc_ros.nodes.subscribed_output import SubscribedOutput

        self.host = host
        self.settings = settings
        self.log = host.logger
        options = {"model_dir": settings.model_dir} if settings.model_dir else {}
        self._backend_source = backend if backend is not None else lazy_backend(settings.backend, **options)
        self._index_lock = threading.Lock()
        self.index = ObjectIndex(self._backend_source, settings.index)
        # newest (gaussians, result, segment labels, their confidence) from the worker
        self._pending: tuple[Any, Any, Any, Any] | None = None
        # The labels of the index's records, as last given to the host (replaced, never changed in place:
        # the worker thread reads it).
        self._labels: Mapping[int, ObjectLabel] = {}
        self._labelled: tuple[Any, np.ndarray] | None = None  # newest (gaussians, per-Gaussian ids)
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self.backend_error: str | None = None
        self.queries_answered = 0
        self._last_refresh = time.monotonic()
        self.queries_failed = 0

        def count_error() -> None:
            self.queries_failed += 1

        self.handler_times = HandlerTimes()
        handler = guarded(TextQuery, "query", self._on_query, log=self.log.error, on_error=count_error)
        self.service = host.create_service(TextQuery, "query", self.handler_times.timed(handler), SERVICE_QOS)
        handler = guarded(Ask, "ask", self._on_ask, log=self.log.error, on_error=count_error, text_field="answer")
        self.ask_service = host.create_service(Ask, "ask", self.handler_times.timed(handler), SERVICE_QOS)
        self.restore_errors = 0  # objects.db files that could not be read (kept aside, never overwritten)
        self.save_errors = 0  # objects.db writes that failed (logged; the next save writes what the file lacks)
        # The highlight cloud is built only while something subscribes (a 1M map's objects: the isin and the cloud
        # took its thread 0.15 of a core at 5 queries/s with nobody to receive them); a late subscriber gets the
        # newest answer's.
        self._highlight_output = SubscribedOutput(self._highlight_subscribed)
        self.highlight = host.create_publisher(
            PointCloud2, "query/highlight", latched_qos(), event_callbacks=self._highlight_output.events()
        )
        self._highlight_output.publisher = self.highlight
        self._highlight_bytes = SerializedPublisher(self.highlight)  # sent without holding the interpreter
        self.markers = host.create_publisher(
            MarkerArray, "query/markers", latched_qos(), event_callbacks=output_events()
        )
        self._thread = threading.Thread(target=self._run, name="monovoc-object-index", daemon=True)
        # Highlights are published off the service callback, so the answer goes out first (a big
        # object's cloud takes a few ms to build and send), and at a bounded rate: the newest wins.
        self._highlight_request: tuple[ObjectIndex, list] | None = None
        self._highlight_wake = threading.Event()
        self._highlighter = threading.Thread(target=self._run_highlights, name="monovoc-query-highlight", daemon=True)
        # objects.db writes, one at a time, in order (`save`).
        self._db_writer = ThreadPoolExecutor(1, "monovoc-objects-db", initializer=_lower_priority)
        self._db_write: Future | None = None

    # ------------------------------------------------------------------ life cycle

    def start(self) -> None:
        """Registers the listeners, restores objects.db on resume and starts the threads."""
        host = self.host
        host.add_keyframe_listener(self._on_keyframe)
        host.add_result_listener(self._on_result)
        host.add_diagnostics_source(self.diagnostics)
        host.add_reset_listener(self._on_reset)
        # objects.db is written with every snapshot and read back with load_map.
        host.add_save_listener(self._on_saved)
        host.add_load_check(self._check_load)
        host.set_label_provider(lambda: self._labels)
        # The backend's modules imported now, before the worker and the executor run: importing them held the
        # interpreter 0.1-0.26 s, and the queries of a robot run's first second waited for it (docs/results.md,
        # robot scale, eleventh session). The models themselves load on the indexing thread.
        name = getattr(self._backend_source, "backend_name", None)
        if name is not None:
            try:
                backend_class(name)
            except Exception as exc:  # a broken optional dependency: the indexing thread reports it too
                self.log.warning(f"embedding backend {name!r} could not be imported: {type(exc).__name__}: {exc}")
        if host.resume and host.map_directory:
            self._restore(host.map_directory)
            mapper = host.mapper()
            ids = self.index.object_ids
            if mapper is not None and ids is not None and len(ids) == len(mapper.gaussians):
                self._labelled = (mapper.gaussians, ids)  # highlights work before the first result
        self._thread.start()
        self._highlighter.start()

    def _on_saved(self, directory: str, info: Any, mapper: Any) -> Future | None:
        return self.save(directory, snapshot=info.path.name, keyframes=info.keyframes, mapper=mapper)

    def _check_load(self, path: str, mapper: Any) -> Callable[[], None]:
        """load_map: reads the map directory's objects.db before anything is swapped; an unreadable one fails
        the load (ObjectDatabaseError), so the current objects and every file stay as they are."""
        index = None
        db = Path(path) / DB_NAME
        self._finish_save()  # the file may be the one being written
        if Path(path).is_dir() and db.is_file():
            try:
                index = load_object_index(db, backend=self._current_backend(), config=self.settings.index)
            except Exception as exc:  # whatever the defect, the load fails with its reason
                self.restore_errors += 1
                raise ObjectDatabaseError(f"objects not restored, map not loaded: {type(exc).__name__}: {exc}") from exc
            ids = index.object_ids
            if ids is not None and len(ids) != len(mapper.gaussians):
                self.restore_errors += 1
                raise ObjectDatabaseError(
                    f"{db}: its per-Gaussian index has {len(ids)} entries, the map {len(mapper.gaussians)} Gaussians"
                )

        def commit() -> None:
            self._replace_index(index)
            # The loaded map's Gaussians with its objects (none known yet without objects.db): never the old map's.
            ids = None if index is None else index.object_ids
            self._labelled = (mapper.gaussians, ids) if ids is not None else None
            if index is not None:
                self.log.info(f"restored {len(index)} objects from {db}")

        return commit

    def stop(self) -> None:
        self._stopping.set()
        self._wake.set()
        self._highlight_wake.set()
        for thread in (self._thread, self._highlighter):
            if thread.is_alive():
                thread.join(10.0)
        self._finish_save()  # the worker's final save waited for its own; a periodic one may still be written
        self._db_writer.shutdown(wait=True)

    def diagnostics(self) -> dict[str, Any]:
        """The object index's part of the node's /diagnostics status."""
        index = self.index
        return {
            "objects.indexed": len(index),
            "objects.pending": index.pending(),
            "objects.backend_error": self.backend_error or "",
            "queries.answered": self.queries_answered,
            "queries.failed": self.queries_failed,
            "queries.highlights_skipped": self._highlight_output.skipped,
            **self.handler_times.diagnostics(),
            "objects.restore_errors": self.restore_errors,
            "objects.save_errors": self.save_errors,
        }

    # ------------------------------------------------------------------ hooks (worker thread)

    def _on_keyframe(self, keyframe: Any, mapper: Any) -> None:
        self.index.keyframe_listener(keyframe, mapper)

    def _on_result(self, mapper: Any, result: Any) -> None:
        # Gaussian maps and results are immutable snapshots: safe to hand to another thread.
        self._pending = (mapper.gaussians, result, mapper.object_labels(), mapper.object_label_confidence())
        self._labelled = (mapper.gaussians, result.object_ids)
        self._wake.set()

    def labelled_map(self, index: ObjectIndex | None = None) -> tuple[Any, Any]:
        """The newest (Gaussian map, (N,) per-Gaussian object ids): the worker's last result, else the index's
        (None, None before any); both immutable snapshots."""
        index = index if index is not None else self.index
        return self._labelled or (index.gaussians, index.object_ids)

    def _on_reset(self) -> None:
        self._labelled = None
        self._replace_index(None)

    # ------------------------------------------------------------------ indexing thread

    def _run(self) -> None:
        _lower_priority()  # background work, as are onnxruntime's pool threads, created with the models below
        try:
            _ = self.index.backend  # load the models now, so the first query does not pay for it
        except (ModelMissingError, ValueError, OSError, ImportError) as exc:  # bad clip_onnx files: ValueError
            self._backend_failed(exc)
        wait_s = IDLE_WAIT_S
        while not self._stopping.is_set():
            self._wake.wait(wait_s)
            self._wake.clear()
            if self._stopping.is_set():
                break
            wait_s = IDLE_WAIT_S
            if self._pending is None and not self.index.pending():
                continue
            if self._yield_to_mapping():
                # Looked at again soon: the worker's idle moments are when the objects catch up.
                wait_s = YIELD_POLL_S
                continue
            pending, self._pending = self._pending, None
            try:
                self._refresh(pending)
            except ModelMissingError as exc:
                self._backend_failed(exc)
            except Exception as exc:  # one bad refresh must not end the indexing thread
                self.log.error(f"object index refresh failed: {type(exc).__name__}: {exc}")
            else:
                if self.index.pending():  # left for the worker's idle moments
                    wait_s = YIELD_POLL_S

    def _refresh(self, pending: tuple[Any, Any, Any, Any] | None) -> None:
        index = self.index
        geometry = {}
        if pending is not None:
            gaussians, result, names, confidence = pending
            geometry = {
                "gaussians": gaussians,
                "result": result,
                "segment_labels": names,
                "label_confidence": confidence,
            }
        if not geometry and index.pending() == 0:
            return
        # Between chunks of views: stop for a stopping node, and leave the rest for later while the worker is busy.
        bounded = {
            "max_objects": self.settings.max_objects_per_refresh,
            "should_stop": lambda: self._stopping.is_set() or self._yield_to_mapping(),
        }
        report = index.refresh(**geometry, **bounded)
        self.backend_error = None
        self._last_refresh = time.monotonic()
        self._update_labels(index)
        # Keep going in bounded chunks until everything is embedded, a newer result arrives or the worker is busy.
        while report.pending and not self._stopping.is_set() and self._pending is None and index is self.index:
            if self._yield_to_mapping():
                return
            report = index.refresh(**bounded)
            self._last_refresh = time.monotonic()
            self._update_labels(index)

    def _update_labels(self, index: ObjectIndex) -> None:
        """Hands the index's labels to the host's outputs; when they changed, the objects and markers go out
        again (a guess appears only once an object is embedded, after the result was published)."""
        labels = index.labels()
        with self._index_lock:  # a reset or load_map (worker thread) may replace the index meanwhile
            if index is not self.index or labels == self._labels:
                return  # replaced: _replace_index gave the host the new index's labels
            self._labels = labels
        self.host.republish_objects()

    def _yield_to_mapping(self) -> bool:
        """True while the worker is busy (keyframes wait, or it is on a task), for up to REFRESH_DEFER_S since the
        last refresh: on two cores the encoder halved the mapping rate (62 -> 130-150 ms per keyframe) during a
        burst, and beside a 1M robot run's keyframes it took a quarter of each (docs/results.md, twentieth
        session), so mapping goes first and the objects catch up in the worker's idle moments."""
        return self.host.busy() and time.monotonic() - self._last_refresh < REFRESH_DEFER_S

    def _backend_failed(self, exc: Exception) -> None:
        message = str(exc)
        if message != self.backend_error:
            self.log.error(f"object embeddings unavailable: {message}")
        self.backend_error = message

    # ------------------------------------------------------------------ persistence

    def save(
        self, directory: str, *, snapshot: str | None = None, keyframes: int | None = None, mapper=None
    ) -> Future | None:
        """objects.db into ``directory``: what it holds is taken now (worker thread), the views' images encoded
        and the file written on this component's writer thread, after any write before it; returns that
        write's Future (None when nothing could be taken). Errors are logged: a snapshot must not fail for
        them."""
        self._finish_save()
        if self._stopping.is_set():  # the writer is gone (a worker still busy after the node's stop)
            return None
        index = self.index
        if mapper is not None and index.object_ids is None:
            index.object_ids = mapper.result().object_ids
        prepared = prepare_save(index, snapshot=snapshot, map_version=getattr(mapper, "map_version", None),
                                keyframes=keyframes)  # fmt: skip
        self._db_write = self._db_writer.submit(self._write, directory, prepared)
        return self._db_write

    def _write(self, directory: str, prepared: PreparedSave) -> None:
        try:
            report = ObjectDatabase(directory).write(prepared)
        except Exception as exc:  # logged and counted here: nobody may wait for this write (a periodic one)
            self.save_errors += 1
            self.log.error(f"could not save objects to {directory}: {type(exc).__name__}: {exc}")
            return
        self.log.info(
            f"{report.path}: {report.objects} objects, {report.views_written} new views in {report.seconds:.2f} s"
        )

    def _finish_save(self) -> None:
        """Waits for the objects.db write in progress, if any (its errors were logged)."""
        write, self._db_write = self._db_write, None
        if write is not None:
            write.result()

    def _restore(self, directory: str) -> None:
        """Resume: objects.db of the map directory. An unreadable one is renamed aside (kept for inspection,
        never overwritten by the next save) and the objects are rebuilt from the keyframes that follow."""
        path = Path(directory) / DB_NAME
        if not path.is_file():
            self._replace_index(None)
            return
        try:
            index = load_object_index(path, backend=self._current_backend(), config=self.settings.index)
        except Exception as exc:  # a start-up must survive any defect of the file
            self.restore_errors += 1
            kept = path.with_name(f"{DB_NAME}.unreadable-{time.strftime('%Y%m%d-%H%M%S')}")
            for suffix in ("", "-wal", "-shm"):
                source = path.with_name(path.name + suffix)
                if source.exists():
                    source.replace(kept.with_name(kept.name + suffix))
            self.log.error(f"could not restore objects from {path} ({type(exc).__name__}: {exc}); kept as {kept}")
            self._replace_index(None)
            return
        self._replace_index(index)
        self.log.info(f"restored {len(index)} objects from {path}")

    def _current_backend(self) -> object:
        return self.index.backend if self.index.backend_loaded else self._backend_source

    def _replace_index(self, index: ObjectIndex | None) -> None:
        with self._index_lock:
            self.index = index if index is not None else ObjectIndex(self._current_backend(), self.settings.index)
            self._labels = self.index.labels()

    # ------------------------------------------------------------------ the service

    def _on_query(self, request: Any, response: Any) -> Any:
        response = self._answer(request, response)
        if response.success:
            self.queries_answered += 1
        else:
            self.queries_failed += 1
        return response

    def _answer(self, request: Any, response: Any) -> Any:
        index = self.index
        response.header = ma.make_header(self.host.frame_id, self.host.clock.now().nanoseconds)
        try:
            view = self._viewpoint(request.viewpoint)
            result = spatial.answer(index, request.text, int(request.top_k), float(request.min_score), view)
        except QueryError as exc:
            response.success, response.message = False, str(exc)
            return response
        except Exception as exc:  # the service must answer, whatever went wrong
            response.success, response.message = False, f"query failed: {type(exc).__name__}: {exc}"
            return response
        if not result.answered:
            response.success = False
            response.message = result.message
            if self.backend_error:
                response.message += f"; embedding backend unavailable: {self.backend_error}"
            return response
        response.success = True
        response.message = result.message
        response.objects = semantic_objects(result.matches)
        if self.settings.highlight:
            self._highlight_request = (index, result.matches)
            self._highlight_wake.set()
        return response

    def _viewpoint(self, pose: Any) -> spatial.Viewpoint | None:
        """A request's robot pose (REP-103 body, map frame) as a viewpoint; None when it gives none. Raises
        QueryError for a pose in another frame (there is no tf here) or an invalid one."""
        frame = str(pose.header.frame_id)
        if not frame:
            return None
        if frame != self.host.frame_id:
            raise QueryError(f"viewpoint in frame {frame!r}, the map is {self.host.frame_id!r} (no tf here)")
        try:
            matrix = ma.pose_stamped_to_matrix(pose, "body")
        except ValueError as exc:
            raise QueryError(f"viewpoint: {exc}") from None
        farthest = float(np.abs(matrix[:3, 3]).max())  # not the norm: it overflows to inf for 1e300
        if farthest > MAX_VIEWPOINT_M:  # finite, but no robot's in this map: answers would read "inf m"
            raise QueryError(f"viewpoint: {farthest:.3g} m from the map's origin (at most {MAX_VIEWPOINT_M:g} m)")
        return spatial.Viewpoint(matrix)

    def _on_ask(self, request: Any, response: Any) -> Any:
        response.header = ma.make_header(self.host.frame_id, self.host.clock.now().nanoseconds)
        response.count = -1
        try:
            answer = questions.ask(self.index, request.question, self._viewpoint(request.viewpoint))
        except QueryError as exc:
            response.success, response.answer = False, str(exc)
        else:
            response.success, response.answer = answer.success, answer.answer
            response.count = -1 if answer.count is None else int(answer.count)
            response.objects = semantic_objects(answer.objects)
        if response.success:
            self.queries_answered += 1
        else:
            self.queries_failed += 1
        return response

    def _run_highlights(self) -> None:
        while not self._stopping.is_set():
            self._highlight_wake.wait()
            self._highlight_wake.clear()
            request, self._highlight_request = self._highlight_request, None
            if request is None or self._stopping.is_set():
                continue
            try:
                self._publish_highlight(*request)
            except Exception as exc:  # a failed highlight must not end the thread
                self.log.error(f"query highlight failed: {type(exc).__name__}: {exc}")
            # Rate limit: building and sending a big cloud competes with the service for the GIL
            # (at 100 queries/s with a highlight each, the answer's p50 went from 10 to 22 ms).
            self._stopping.wait(1.0 / self.settings.highlight_rate_hz)

    def _highlight_subscribed(self, request: tuple[ObjectIndex, list]) -> None:
        """A subscriber appeared after a highlight was left out (executor thread): it is published now, unless a
        newer answer's is on its way."""
        if self._highlight_request is None:
            self._highlight_request = request
            self._highlight_wake.set()

    def _publish_highlight(self, index: ObjectIndex, matches: list) -> None:
        ids = np.array([r.id for r, _ in matches], np.uint32)
        stamp = self.host.clock.now().nanoseconds
        gaussians, object_ids = self.labelled_map(index)
        wanted = self._highlight_output.wanted((index, matches))
        if wanted and gaussians is not None and object_ids is not None and len(object_ids) == len(gaussians):
            pick = np.isin(object_ids, ids)
            picked = object_ids[pick]
            order = np.argsort(ids)
            score_of = np.array([s for _, s in matches], np.float32)[order]
            scores = score_of[np.searchsorted(ids[order], picked)] if picked.size else np.zeros(0, np.float32)
            self._highlight_bytes.publish(
                ma.serialized_semantic_cloud(
                    gaussians.means[pick],
                    picked,
                    picked,
                    np.clip(scores, 0, 1),
                    frame_id=self.host.frame_id,
                    stamp=stamp,
                )
            )
        records = [r for r, _ in matches]
        self.markers.publish(
            ma.object_markers(
                ids.astype(np.int64),
                [f"{display(ObjectLabel.stored(r.label, r.label_source))} {s:.2f}" for r, s in matches],
                np.array([r.centroid for r in records]).reshape(-1, 3),
                np.array([r.extent for r in records]).reshape(-1, 3),
                ids,
                frame_id=self.host.frame_id,
                stamp=stamp,
                namespace="monovoc/query",
                up=self.host.marker_up,
            )
        )
