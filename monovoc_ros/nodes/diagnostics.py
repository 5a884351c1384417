"""Counters of the live mapper, their /diagnostics message, and throttled rejection logging.

`MapperStats` is written by the subscription callbacks (keyframes received, rejections) and by the worker
thread (processed, dropped, timings, map size), and read by the diagnostics timer, so every access goes
through its lock. `diagnostic_status` turns a snapshot of it into one diagnostic_msgs/DiagnosticStatus.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from monovoc_ros.contract import REJECTION_REASONS
from monovoc_ros.core.clipped_text import clipped
from monovoc_ros.core.session import SESSION_REASONS, SessionStats

# Rejections the mapper adds to the ingest reasons (monovoc_ros.contract.REJECTION_REASONS): the session's
# (monovoc_ros.core.session.SESSION_REASONS) and
#   bad_gaussians       a Gaussian map cloud that cannot be read (missing fields, NaN, a header that lies, ...)
MAPPER_REASONS = tuple(r for r in (*SESSION_REASONS, "bad_gaussians") if r not in REJECTION_REASONS)
ALL_REASONS = REJECTION_REASONS + MAPPER_REASONS


@dataclass
class MapperStats(SessionStats):
    """The session's counters (monovoc_ros.core.session.SessionStats) and those of the node around it."""

    keyframes_received: int = 0  # keyframes completed by the KeyframeAssembler
    queue_length: int = 0  # keyframes waiting for the worker
    publish_ms_last: float = 0.0  # result + outputs
    warm_up_ms: float = 0.0  # loading the mapping kernels at start (0 until done)
    kernel_compile_ms: float = 0.0  # compiling them first, when numba's cache was empty (0: it was not)
    objects: int = 0
    observed_gaussians: int = 0
    maps_coalesced: int = 0  # pending maps replaced by a newer one before being applied
    snapshot_errors: int = 0
    publishes: int = 0
    worker_errors: int = 0  # tasks, listeners or background calls that raised (logged with a traceback)
    ingest_errors: int = 0  # messages the keyframe assembler raised on (a bug, not bad input: logged with a traceback)
    service_errors: int = 0  # service callbacks that failed unexpectedly (answered success=false)
    # Seconds of the worker thread by activity since start (their sum over wall time is its load), and of
    # decoding Gaussian map messages (in the map callback's thread, beside the worker).
    worker_s_keyframes: float = 0.0  # integration, association and the keyframe listeners (object views)
    worker_s_map_updates: float = 0.0  # checks, registration and evidence transfer of new SLAM maps
    map_update_wait_s: float = 0.0  # of which waiting for the motion or the plan prepared beside the worker
    worker_s_reintegration: float = 0.0  # re-integration steps after a map update that bent the map
    reintegration_steps: int = 0  # logged keyframes integrated again (one per step)
    worker_s_labels: float = 0.0  # the semantic result (labels of every Gaussian) for a publication
    worker_s_objects: float = 0.0  # the object geometry of a publication (after a map update: waiting for its seed)
    worker_s_publish: float = 0.0  # the cloud, objects and markers messages and the result listeners
    worker_s_snapshots: float = 0.0  # periodic snapshots into map_directory
    worker_s_calls: float = 0.0  # services and other calls run on the worker (save, load, queries of it)
    map_decode_s: float = 0.0
    # Map messages taken from the topic: decoded (maps_decoded), refused, or replaced in the map reader by a newer one.
    maps_received: int = 0
    maps_decoded: int = 0
    map_reader_restarts: int = 0  # map reader processes that exited while the node ran (another was started)
    map_prepare_s: float = 0.0  # preparing map updates (MappingSession.plan_map) on a thread beside the worker


def diagnostic_status(stats: dict[str, Any], *, name: str, hardware_id: str, extra: dict[str, Any] | None = None):
    """A diagnostic_msgs/DiagnosticStatus of a `MapperStats.snapshot()`.

    Level: WARN while keyframes wait without a map or after keyframes were dropped, else OK. Every
    ingest and mapper rejection reason is listed (as `rejected.<reason>`), zeros included, so
    monitors can rely on the keys.
    """
    from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

    values = dict(stats)
    rejected = values.pop("rejected")
    if not values["has_map"] and values["queue_length"]:
        level, message = DiagnosticStatus.WARN, f"{values['queue_length']} keyframes waiting for a Gaussian map"
    elif values["keyframes_dropped"]:
        level, message = DiagnosticStatus.WARN, f"{values['keyframes_dropped']} keyframes dropped (queue full)"
    elif not values["has_map"]:
        level, message = DiagnosticStatus.OK, "waiting for a Gaussian map"
    else:
        level, message = DiagnosticStatus.OK, f"{values['keyframes_processed']} keyframes, {values['objects']} objects"
    for reason in sorted(set(ALL_REASONS) | set(rejected)):
        values[f"rejected.{reason}"] = rejected.get(reason, 0)
    values["rejected_total"] = sum(rejected.values())
    values.update(extra or {})

    def text(v: Any) -> str:
        if isinstance(v, bool):
            return str(v).lower()
        if isinstance(v, float):
            return f"{v:.3f}"
        return str(v)

    return DiagnosticStatus(
        level=level,
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=[KeyValue(key=k, value=text(v)) for k, v in values.items()],
    )


class Longest:
    """The longest of a series of durations, when it was, and how many passed `limit_ms`; for /diagnostics under
    `keys` (longest ms, its time.time(), how many over). Thread-safe (several threads add)."""

    def __init__(self, keys: tuple[str, str, str], limit_ms: float) -> None:
        self._keys = keys
        self.limit_ms = limit_ms
        self._lock = threading.Lock()
        self.reset()

    def reset(self) -> None:
        with self._lock:
            self._max_ms, self._at, self._over = 0.0, 0.0, 0

    def add(self, ms: float, at: float) -> None:
        """One duration of `ms`; `at`: its time.time() (start or end, as the keys say)."""
        with self._lock:
            self._over += ms > self.limit_ms
            if ms > self._max_ms:
                self._max_ms, self._at = ms, at

    def values(self) -> dict[str, Any]:
        with self._lock:
            return dict(zip(self._keys, (round(self._max_ms, 1), round(self._at, 3), self._over), strict=True))


# Characters of a rejection's detail in the log.
MAX_DETAIL_CHARS = 1000


class RejectionLog:
    """Logs rejections per reason: the first at once, then at most one line per `interval_s` per reason
    with the number suppressed since, so a stream of bad messages cannot flood the log."""

    def __init__(
        self, log: Callable[[str], None], interval_s: float = 5.0, clock: Callable[[], float] = time.monotonic
    ):
        self._log = log
        self._interval = interval_s
        self._clock = clock
        self._last: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()
        self._lock = threading.Lock()

    def __call__(self, reason: str, detail: str) -> bool:
        """Logs (or counts) one rejection; returns whether a line was written."""
        now = self._clock()
        with self._lock:
            last = self._last.get(reason)
            if last is not None and now - last < self._interval:
                self._suppressed[reason] += 1
                return False
            more = self._suppressed.pop(reason, 0)
            self._last[reason] = now
        suffix = f" (+{more} more since the last report)" if more else ""
        self._log(f"rejected ({reason}): {clipped(detail, MAX_DETAIL_CHARS)}{suffix}")
        return True
