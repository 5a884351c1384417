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
from dataclasses import dataclass, field, fields
from typing import Any

from monovoc_ros.contract import REJECTION_REASONS

# Rejections the mapper itself adds to the ingest reasons (monovoc_ros.contract.REJECTION_REASONS):
#   duplicate_stamp     a keyframe whose stamp is already in the state (e.g. replayed after a resume);
#                       counted under the same name as the ingest reason, as `monovoc map` counts it
#   integration_error   the rasterizer refused a keyframe (state untouched)
#   bad_gaussians       a Gaussian map cloud that cannot be read (missing fields, NaN, a header that lies, ...)
#   empty_gaussians     a Gaussian map without a single Gaussian (the map in use is kept)
#   map_shrink          a map update that would remove more than map_update_max_shrink of the Gaussians
MAPPER_REASONS = ("integration_error", "bad_gaussians", "empty_gaussians", "map_shrink")
ALL_REASONS = REJECTION_REASONS + MAPPER_REASONS


@dataclass
class MapperStats:
    keyframes_received: int = 0  # keyframes completed by the KeyframeAssembler
    keyframes_processed: int = 0  # integrated into the semantic state
    keyframes_dropped: int = 0  # pushed out of the full worker queue (oldest first)
    queue_length: int = 0  # keyframes waiting for the worker
    ms_per_keyframe_last: float = 0.0  # SCD integration time
    ms_per_keyframe_total: float = 0.0
    publish_ms_last: float = 0.0  # result + outputs
    objects: int = 0
    observed_gaussians: int = 0
    gaussians: int = 0
    has_map: bool = False
    map_version: int = 0
    map_updates: int = 0  # maps applied with update_gaussians
    maps_coalesced: int = 0  # pending maps replaced by a newer one before being applied
    maps_unchanged: int = 0  # maps identical to the current one (skipped)
    snapshots_saved: int = 0
    snapshot_errors: int = 0
    publishes: int = 0
    last_stamp_ns: int = 0  # newest integrated keyframe
    worker_errors: int = 0
    service_errors: int = 0  # service callbacks that failed unexpectedly (answered success=false)
    rejected: Counter = field(default_factory=Counter)
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def update(self, **values: Any) -> None:
        with self.lock:
            for key, value in values.items():
                setattr(self, key, value)

    def add(self, **increments: float) -> None:
        with self.lock:
            for key, value in increments.items():
                setattr(self, key, getattr(self, key) + value)

    def reject(self, reason: str, count: int = 1) -> None:
        with self.lock:
            self.rejected[reason] += count

    def snapshot(self) -> dict[str, Any]:
        """A consistent copy of every counter (plus the derived mean time per keyframe)."""
        with self.lock:
            out = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("lock", "rejected")}
            out["rejected"] = dict(self.rejected)
        processed = out["keyframes_processed"]
        out["ms_per_keyframe_mean"] = out.pop("ms_per_keyframe_total") / processed if processed else 0.0
        return out


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


def status_values(status: Any) -> dict[str, str]:
    """key -> value of a DiagnosticStatus (for clients and tests)."""
    return {kv.key: kv.value for kv in status.values}


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
        self._log(f"rejected ({reason}): {detail}{suffix}")
        return True
