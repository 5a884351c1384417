"""The Gaussian map topic read in a process of its own, its maps handed over in shared memory.

Why: rclpy takes a message holding the interpreter lock. A 1M-Gaussian map (a 56 MB PointCloud2) held it
60-130 ms per message in the node's process (docs/results.md, "where the query tail goes"), and every query
that arrived meanwhile waited: the query p99 of the 1M robot runs was 4x the one without map updates. (A map is now
taken serialized, without rclpy's deserializing, which removed most of that hold; the decoding's copies and the
registration below still make a process of its own worth it.)

The child (``python -m monovoc_ros.nodes.map_reader``, a hidden node ``_<node>_map_reader`` in the node's
namespace) subscribes to the map topic with the node's QoS, takes each message serialized and decodes it with the
node's own adapters (msg_adapters.point_cloud_from_cdr and cloud_to_gaussian_map: the same checks and the same arrays
as the in-process subscription and offline mapping), and writes the arrays into an anonymous shared-memory file
(memfd), sealed against writes and resizing. It sends the file descriptor (SCM_RIGHTS) with a small JSON header
over a Unix socket; the node checks the header against the file, maps it read-only and builds the GaussianMap on it
without a copy. Nothing is ever in the file system, so whichever process dies, no memory is left behind: the file
lives as long as the map's arrays do. The node asks for each map (a credit byte) as soon as it has queued the one
before; until then the child keeps only the newest (NewestMap), so a node starting up or falling behind never
has a backlog of maps waiting in the socket.

The child also registers each map it hands over against the one it handed over before (core.follow.map_follow.
map_motion, the motion a plan estimates: by registration without Gaussian ids, 0.15-0.2 s of a 1M-Gaussian update's
plan in a process of its own, ~0.35 s beside a busy node; from the ids when both maps have them) and sends that motion
right after the map (a MapMotion's arrays in a sealed memfd too; "none" when it could not estimate it). The node's
plan of that update takes it when the map before is the one the update starts from (core.follow.map_updater.
GivenMotion: the same function of the same two maps, so the same plan) instead of estimating it beside the worker,
which waits for the motion before the keyframes after the map go ahead of it. The node attaches a motion only to a map
that directly follows the one it received before from the same child (`seq`): after a message it could not read, the
next map's plan estimates its motion itself.

Lifetime: the child ends when the node closes its end of the socket (a stop, or the node dying in any way),
destroying its participant first (Fast DDS removes its shared-memory files then), and ignores SIGINT and
SIGTERM (a terminal's Ctrl-C or a signal to the process group reaches it too; the node decides when it
stops). If the child dies while the node runs, or sends no heartbeat for SILENT_S (stopped, hung), the node
kills it, logs it, counts it (``map_reader_restarts``) and starts another after a back-off. The latched map that
the new child receives again is the map in use: the session skips it as it skips any map sent again
(``maps_unchanged``).
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import json
import mmap
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from monovoc_ros.core.clipped_text import clipped
from monovoc_ros.core.follow.map_follow import map_motion
from monovoc_ros.core.follow.map_motion import MapMotion, MotionConfig
from monovoc_ros.core.follow.map_updater import GivenMotion
from monovoc_ros.core.freed_memory import keep_freed_memory
from monovoc_ros.core.map.gaussians import GaussianMap, same_geometry
from monovoc_ros.core.thread_pools import single_threaded_blas
from monovoc_ros.fastdds_profile import child_environment

# The arrays of a GaussianMap that a map message carries (cloud_to_gaussian_map fills no others), as the
# GaussianMap holds them: the only dtypes a header may name.
_DTYPES = {"means": "<f4", "scales": "<f4", "quats": "<f4", "opacities": "<f4", "colors": "<f4", "ids": "<i8"}
# A MapMotion's arrays: name -> (dtype, shape; -1 for any length).
_MOTION_ARRAYS = {
    "rotation": ("<f8", (3, 3)),
    "translation": ("<f8", (3,)),
    "origin": ("<f8", (3,)),
    "offsets": ("<f8", (-1, -1, -1, 3)),
}
_MOTION_BY = ("identity", "registration", "ids")
# The registration the child runs (core.follow.map_follow.map_motion): the node's plans use the default, which no
# parameter changes; a plan compares it with its own (GivenMotion.motion_for).
READER_MOTION = MotionConfig()
_ALIGN = 64
# A header names six arrays and a frame id of at most msg_adapters.gaussian_cloud.MAX_FRAME_ID characters.
_HEADER_BYTES = 1 << 16
# Characters of a refusal's message (JSON escapes a character in at most 12 bytes: it fits _HEADER_BYTES).
MAX_REFUSAL_CHARS = 4096
# Sealed before it is sent: the node's arrays can then neither change nor lose their memory (a shrunk file
# would be a SIGBUS in the node) whatever else holds the descriptor.
_SEALS = (
    fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW | fcntl.F_SEAL_WRITE | fcntl.F_SEAL_SEAL
    if hasattr(fcntl, "F_SEAL_SEAL")
    else 0
)
_CREDIT = b"+"  # the node asks for one map (the newest the child holds)
RESTART_DELAY_S = (1.0, 30.0)  # first and longest back-off before starting a child again
HEALTHY_RUN_S = 60.0  # a child that ran this long before it exited was no crash loop: the back-off starts over
STOP_WAIT_S = 0.5  # how long a stop waits for the child to exit on its own (~0.1 s) before killing it
_POLL_S = 0.05  # the child looks for the end of the socket this often between messages
# The child says it is alive this often (s); a node that hears nothing from it for SILENT_S takes it for hung (a
# SIGSTOP, a deadlock) and replaces it as it replaces one that exited. Generous: a decode or a registration runs
# beside the heartbeat's thread, which only waits for the interpreter between their numpy and numba calls.
HEARTBEAT_S = 1.0
SILENT_S = 15.0


def supported() -> bool:
    """Whether this platform can hand maps over (Linux: memfd with seals, SCM_RIGHTS)."""
    return hasattr(os, "memfd_create") and hasattr(socket, "send_fds") and _SEALS != 0


@dataclass(frozen=True)
class Refusal:
    """A map message the child did not hand over: ``bad_input`` when the message was at fault (what the node
    counts as bad_gaussians), else the reader failed on it (a bug, or no shared memory for it). ``of_map`` False:
    not a map but a map's motion the node could not read (its plan estimates the motion itself)."""

    message: str
    bad_input: bool
    of_map: bool = True


class MalformedMessage(ValueError):
    """A message from the child that the node cannot read; ``kind`` as its header says, when it could be read;
    ``map_lost``: it may have been a map (one always comes with its descriptor), which spent the child's credit."""

    def __init__(self, message: str, kind: str | None, map_lost: bool) -> None:
        super().__init__(message)
        self.kind = kind
        self.map_lost = map_lost


@dataclass(frozen=True)
class ReceivedMap:
    gaussians: GaussianMap
    stamp_ns: int
    frame_id: str
    decode_s: float  # the child's take-to-arrays time for this message
    superseded: int = 0  # maps the child decoded but replaced by this newer one before the node asked
    seq: int = 0  # the child's count of maps handed over (from 1)
    # Its motion from the map the same child handed over before, estimated there and sent after it (None: it is
    # the child's first map).
    motion: GivenMotion | None = None


@dataclass(frozen=True)
class ReceivedMotion:
    """The motion of the child's map `seq` from the map it handed over before (None: not estimated, the same
    geometry again or the estimate failed)."""

    seq: int
    motion: MapMotion | None
    seconds: float  # the child's time estimating it


# ---------------------------------------------------------------------------------------------- transport


def send_map(
    sock: socket.socket,
    gmap: GaussianMap,
    *,
    stamp_ns: int,
    frame_id: str,
    decode_s: float,
    superseded: int = 0,
    seq: int = 0,
) -> None:
    """Writes ``gmap``'s arrays into a new sealed memfd and sends it with its header over ``sock``
    (SOCK_SEQPACKET)."""
    arrays = [(name, getattr(gmap, name)) for name in _DTYPES if getattr(gmap, name) is not None]
    header = {"kind": "map", "stamp_ns": int(stamp_ns), "frame_id": str(frame_id), "decode_s": float(decode_s),
              "superseded": int(superseded), "seq": int(seq)}  # fmt: skip
    _send_arrays(sock, header, arrays)


def send_motion(sock: socket.socket, seq: int, motion: MapMotion | None, seconds: float) -> None:
    """Sends the motion of map ``seq`` (None: not estimated); its arrays in a sealed memfd (a smooth field over a
    building's floor is ~1 MB, more than one socket message holds)."""
    header = {"kind": "motion", "seq": int(seq), "seconds": float(seconds)}
    if motion is None:
        sock.send(json.dumps(header).encode())
        return
    header.update(spacing=float(motion.spacing), rms=float(motion.rms), inliers=float(motion.inliers),
                  converged=bool(motion.converged), by=str(motion.by))  # fmt: skip
    arrays = [(name, np.asarray(getattr(motion, name), np.float64)) for name in _MOTION_ARRAYS]
    _send_arrays(sock, header, arrays)


def _send_arrays(sock: socket.socket, header: dict[str, Any], arrays: list[tuple[str, np.ndarray]]) -> None:
    """Sends ``header`` with ``arrays`` written into a new sealed memfd (their layout added to the header)."""
    layout, offset = [], 0
    fd = os.memfd_create("monovoc_map", os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING)
    try:
        size = sum(_padded(a.nbytes) for _, a in arrays)
        os.ftruncate(fd, max(size, 1))
        for name, array in arrays:
            data = np.ascontiguousarray(array).reshape(-1).view(np.uint8)
            _write_all(fd, memoryview(data), offset)
            layout.append({"name": name, "dtype": array.dtype.str, "shape": list(array.shape), "offset": offset})
            offset += _padded(array.nbytes)
        fcntl.fcntl(fd, fcntl.F_ADD_SEALS, _SEALS)
        socket.send_fds(sock, [json.dumps({**header, "size": size, "arrays": layout}).encode()], [fd])
    finally:
        os.close(fd)  # the receiver holds its own descriptor from here


def send_alive(sock: socket.socket) -> None:
    """The child's heartbeat (HEARTBEAT_S)."""
    sock.send(b'{"kind": "alive"}')


def send_refusal(sock: socket.socket, refusal: Refusal) -> None:
    """Tells the node that a map message was not handed over, and why (at most MAX_REFUSAL_CHARS of it: one socket
    message must hold it, and a hostile message's error may quote anything)."""
    message = clipped(refusal.message, MAX_REFUSAL_CHARS)
    sock.send(json.dumps({"kind": "refusal", "message": message, "bad_input": refusal.bad_input}).encode())


def receive(sock: socket.socket) -> ReceivedMap | ReceivedMotion | Refusal | bool | None:
    """The next map from ``sock``, or a map's motion, or a refusal, True for a heartbeat, or None when the sender has
    gone. A malformed message (what our own child never sends) raises ValueError, its descriptor closed."""
    data, fds, flags, _addr = socket.recv_fds(sock, _HEADER_BYTES, 1)
    kind = None
    try:
        if not data and not fds:
            return None
        if flags & (socket.MSG_TRUNC | socket.MSG_CTRUNC):
            raise ValueError("message truncated")
        header = json.loads(data)
        kind = str(header["kind"])
        if kind == "alive" and not fds:
            return True
        if kind == "refusal":
            return Refusal(str(header["message"]), bool(header["bad_input"]))
        if kind == "motion" and not fds:
            return ReceivedMotion(int(header["seq"]), None, float(header["seconds"]))
        if kind not in ("map", "motion") or len(fds) != 1:
            raise ValueError(f"unexpected message {kind!r} with {len(fds)} descriptors")
        if kind == "motion":
            return ReceivedMotion(int(header["seq"]), _motion_of(fds[0], header), float(header["seconds"]))
        return ReceivedMap(
            _map_of(fds[0], header),
            int(header["stamp_ns"]),
            str(header["frame_id"]),
            float(header["decode_s"]),
            int(header["superseded"]),
            int(header["seq"]),
        )
    except Exception as exc:  # whatever the header holds, one clear error
        map_lost = kind in (None, "map") and bool(fds or flags & socket.MSG_CTRUNC)
        raise MalformedMessage(f"map reader: malformed message ({type(exc).__name__}: {exc})", kind, map_lost) from None
    finally:
        for fd in fds:
            os.close(fd)


def _map_of(fd: int, header: dict[str, Any]) -> GaussianMap:
    specs = {name: (dtype, None) for name, dtype in _DTYPES.items()}
    return GaussianMap(**_arrays_of(fd, header, specs), stamp_ns=max(0, int(header["stamp_ns"])))


def _motion_of(fd: int, header: dict[str, Any]) -> MapMotion:
    arrays = _arrays_of(fd, header, _MOTION_ARRAYS)
    if set(arrays) != set(_MOTION_ARRAYS):
        raise ValueError(f"a motion of arrays {sorted(arrays)}")
    spacing, by = float(header["spacing"]), str(header["by"])
    if not (np.isfinite(spacing) and spacing > 0) or by not in _MOTION_BY:
        raise ValueError(f"a motion by {by!r} with a field spacing of {spacing}")
    if not all(np.isfinite(a).all() for a in arrays.values()):
        raise ValueError("a motion that is not finite")
    copies = {name: np.array(a) for name, a in arrays.items()}  # a few kB: not worth keeping the file mapped
    return MapMotion(**copies, spacing=spacing, rms=float(header["rms"]), inliers=float(header["inliers"]),
                     converged=bool(header["converged"]), by=by)  # fmt: skip


def _arrays_of(
    fd: int, header: dict[str, Any], specs: dict[str, tuple[str, tuple[int, ...] | None]]
) -> dict[str, np.ndarray]:
    """The arrays the header lays out in the sealed file ``fd``, read-only views of it; ``specs``: name -> (dtype,
    shape; None: one or two dimensions of any length; -1: a dimension of any length)."""
    if fcntl.fcntl(fd, fcntl.F_GET_SEALS) & _SEALS != _SEALS:
        raise ValueError("the shared file is not sealed")
    size, actual = int(header["size"]), os.fstat(fd).st_size
    if not 0 <= size <= actual:
        raise ValueError(f"shared file of {actual} bytes, header says {size}")
    memory = mmap.mmap(fd, max(size, 1), access=mmap.ACCESS_READ)  # the arrays keep it mapped, the fd is not needed
    arrays: dict[str, np.ndarray] = {}
    for entry in header["arrays"]:
        name, dtype, offset = entry["name"], np.dtype(entry["dtype"]), int(entry["offset"])
        shape = tuple(int(s) for s in entry["shape"])
        if name not in specs or name in arrays or dtype.str != specs[name][0]:
            raise ValueError(f"array {name!r} of {dtype.str} not expected")
        expected = specs[name][1]
        if expected is None:
            fits = 1 <= len(shape) <= 2
        else:
            fits = len(shape) == len(expected) and all(e in (-1, s) for e, s in zip(expected, shape, strict=True))
        if not fits:
            raise ValueError(f"array {name!r} of shape {shape} not expected")
        count = 1
        for s in shape:  # Python integers: no overflow
            count *= s
        if min(shape) < 0 or offset < 0 or offset + count * dtype.itemsize > size:
            raise ValueError(f"array {name!r} of shape {shape} at {offset} outside the {size} bytes")
        arrays[name] = np.frombuffer(memory, dtype, count, offset).reshape(shape)
    return arrays


def _padded(nbytes: int) -> int:
    return -(-nbytes // _ALIGN) * _ALIGN


def _write_all(fd: int, data: memoryview, offset: int) -> None:
    while data:
        written = os.pwrite(fd, data, offset)
        data, offset = data[written:], offset + written


class NewestMap:
    """The child's one map slot: a newer map replaces the one not asked for yet (counted), so a node that is
    busy or not started yet never has more than one map waiting for it; ``take`` waits for a map and a credit."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: Any = None
        self._credits = 0
        self._superseded = 0

    def put(self, item: Any) -> None:
        with self._cond:
            self._superseded += self._item is not None
            self._item = item
            self._cond.notify_all()

    def credit(self, count: int = 1) -> None:
        with self._cond:
            self._credits += count
            self._cond.notify_all()

    def take(self, timeout: float | None = None) -> tuple[Any, int] | None:
        """(the newest map, how many it replaced), or None after ``timeout``."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._item is not None and self._credits > 0, timeout):
                return None
            item, superseded = self._item, self._superseded
            self._item, self._superseded, self._credits = None, 0, self._credits - 1
            return item, superseded


# ---------------------------------------------------------------------------------------------- node side


class MapReaderProcess:
    """Runs a child reading ``topic`` from construction on; from ``start()`` until ``stop()`` calls, on a
    thread of its own, ``on_map(ReceivedMap)`` / ``on_refused(Refusal)`` for every message, and
    ``on_restart(message)`` when a child exited and another starts. The child holds at most one map the node
    has not asked for (NewestMap): maps decoded while the node starts up or is busy are replaced by newer ones."""

    def __init__(
        self,
        topic: str,
        node_name: str,
        namespace: str,
        *,
        on_map: Callable[[ReceivedMap], None],
        on_refused: Callable[[Refusal], None],
        on_restart: Callable[[str], None],
    ) -> None:
        self.topic, self.node_name, self.namespace = topic, node_name, namespace
        self._on_map, self._on_refused, self._on_restart = on_map, on_refused, on_restart
        self._stopping = threading.Event()
        self._lock = threading.Lock()
        # The current child's map handed over last, and the motion awaited for it (MotionHandover).
        self._motions = MotionHandover()
        self._child: subprocess.Popen | None = None
        self._sock: socket.socket | None = None
        self._thread = threading.Thread(target=self._run, name="map_reader", daemon=True)
        # The first child starts now: its start-up (~1 s of imports and discovery) overlaps the node's own.
        with contextlib.suppress(OSError):  # the thread tries again, and says why
            self._child, self._sock = self._spawn()

    @property
    def motion_seconds(self) -> float:
        """The children's time estimating the motions of the maps they handed over."""
        return self._motions.seconds

    def start(self) -> None:
        """Hands the maps over from now on."""
        self._thread.start()

    def stop(self) -> None:
        """Ends the child (closing the socket; killed if it does not exit within STOP_WAIT_S) and the thread."""
        self._stopping.set()
        with self._lock:
            if self._sock is not None:
                with contextlib.suppress(OSError):
                    self._sock.shutdown(socket.SHUT_RDWR)
        if self._thread.ident is not None:
            self._thread.join(timeout=STOP_WAIT_S + 1.0)
        with self._lock:
            child, sock = self._child, self._sock
        if child is not None and child.poll() is None:
            child.kill()
            child.wait()
        if sock is not None and self._thread.ident is None:  # never served: the thread did not close it
            sock.close()

    def _spawn(self) -> tuple[subprocess.Popen, socket.socket]:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            command = [sys.executable, "-m", "monovoc_ros.nodes.map_reader", "--fd", str(theirs.fileno()),
                       "--topic", self.topic, "--node-name", self.node_name, "--namespace", self.namespace]  # fmt: skip
            child = subprocess.Popen(
                command, pass_fds=[theirs.fileno()], stdin=subprocess.DEVNULL, env=child_environment()
            )
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()
        return child, ours

    def _run(self) -> None:
        delay = RESTART_DELAY_S[0]
        while not self._stopping.is_set():
            with self._lock:
                pair = (self._child, self._sock) if self._sock is not None else None
            if pair is None:
                try:
                    pair = self._spawn()
                except OSError as exc:
                    self._report_restart(f"cannot start the map reader ({exc}); trying again in {delay:g} s")
                    self._stopping.wait(delay)
                    delay = min(2 * delay, RESTART_DELAY_S[1])
                    continue
                with self._lock:
                    self._child, self._sock = pair
                    stopping = self._stopping.is_set()
                if stopping:  # a stop that came while the child started: its shutdown missed this socket
                    pair[1].shutdown(socket.SHUT_RDWR)
            child, sock = pair
            started = time.monotonic()
            silent = self._serve(sock)
            with self._lock:
                self._sock = None
            sock.close()
            try:
                child.wait(timeout=STOP_WAIT_S)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()
            if self._stopping.is_set():
                return
            if time.monotonic() - started > HEALTHY_RUN_S:
                delay = RESTART_DELAY_S[0]
            ended = silent or f"the map reader exited (code {child.returncode})"
            self._report_restart(f"{ended}; starting another in {delay:g} s")
            self._stopping.wait(delay)
            delay = min(2 * delay, RESTART_DELAY_S[1])

    def _report_restart(self, message: str) -> None:
        with contextlib.suppress(Exception):  # the node's callback must not end the hand-over either
            self._on_restart(message)

    def _serve(self, sock: socket.socket) -> str | None:
        """Receives until the child's end closes, or until it was silent for SILENT_S (hung: `_run` kills it; the
        reason returned)."""
        try:
            sock.settimeout(SILENT_S)
            sock.send(_CREDIT)
        except OSError:
            return None
        try:
            return self._receive_all(sock)
        finally:  # a new child starts over: its first map has no motion, and none comes for this one's last
            self._motions.reset()

    def _receive_all(self, sock: socket.socket) -> str | None:
        while True:
            try:
                item = receive(sock)
            except TimeoutError:
                return f"the map reader was silent for {SILENT_S:g} s (stopped or hung) and was killed"
            except MalformedMessage as exc:
                # A map or a motion lost: the next map's motion may not be of the map the node has before it.
                self._motions.reset()
                item = Refusal(str(exc), bad_input=False, of_map=exc.kind != "motion")
                if exc.map_lost:  # it may have been a map, which spent the child's credit: give another
                    with contextlib.suppress(OSError):
                        sock.send(_CREDIT)
            except OSError:
                return
            if item is None:
                return
            if item is True:  # a heartbeat: the socket's timeout starts over
                continue
            try:
                if isinstance(item, Refusal):
                    self._on_refused(item)
                    continue
                if isinstance(item, ReceivedMotion):
                    self._motions.arrived(item)
                    continue
                sock.send(_CREDIT)  # the next map, as soon as there is one: this one goes to the worker's queue
                self._on_map(self._motions.handed_over(item))
            except OSError:
                return
            except Exception as exc:  # a bug in the node's callbacks costs one message, not the hand-over
                with contextlib.suppress(Exception):
                    self._on_refused(Refusal(_failure("handling", exc), bad_input=False))


class MotionHandover:
    """The node's side of the motions: each map a child hands over gets a GivenMotion from the map that child handed
    over right before it (the previous `seq`), whose Future the motion message sent after the map completes.
    Completed with None (the plan then estimates the motion itself) when the child sends none or a newer map comes
    first; after a message the node could not read, or the child's end (`reset`), the next map gets none.
    Thread-safe."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._last: tuple[int, GaussianMap] | None = None  # (seq, map) received last from the current child
        self._awaited: tuple[int, Future] | None = None
        self.seconds = 0.0  # the children's time estimating motions

    def handed_over(self, received: ReceivedMap) -> ReceivedMap:
        """``received`` with the motion to come for it (none for a child's first map, or after a gap)."""
        future: Future = Future()
        with self._lock:
            last, self._last = self._last, (received.seq, received.gaussians)
            base = last[1] if last is not None and last[0] == received.seq - 1 else None
            awaited, self._awaited = self._awaited, (received.seq, future) if base is not None else None
        if awaited is not None:
            awaited[1].set_result(None)
        return received if base is None else replace(received, motion=GivenMotion(base, READER_MOTION, future))

    def arrived(self, motion: ReceivedMotion) -> None:
        with self._lock:
            awaited = self._awaited
            if awaited is None or awaited[0] != motion.seq:
                return  # of a map the node never had (our child sends none)
            self._awaited = None
            self.seconds += motion.seconds
        awaited[1].set_result(motion.motion)

    def reset(self) -> None:
        with self._lock:
            awaited, self._awaited, self._last = self._awaited, None, None
        if awaited is not None:
            awaited[1].set_result(None)


# ---------------------------------------------------------------------------------------------- child


def _failure(during: str, exc: BaseException) -> str:
    trace = "".join(traceback.format_exception(exc))
    return f"map reader: {during} a map failed ({type(exc).__name__}: {exc}); map dropped\n{trace}"


def _estimated_motion(old: GaussianMap, new: GaussianMap) -> tuple[MapMotion | None, float]:
    """(the motion of `old` to `new` a node's plan would estimate, the seconds it took); None for the same geometry
    again (a node prepares no update for it) or when the estimate failed (printed: the child's stderr is the
    node's)."""
    start = time.perf_counter()
    try:
        motion = None if same_geometry(old, new) else map_motion(old, new, READER_MOTION)
    except Exception:
        traceback.print_exc()
        motion = None
    return motion, time.perf_counter() - start


def _child_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Reads a Gaussian map topic for a monovoc node (internal).")
    parser.add_argument("--fd", type=int, required=True)
    parser.add_argument("--topic", required=True)
    parser.add_argument("--node-name", required=True)
    parser.add_argument("--namespace", default="/")
    args = parser.parse_args(argv)
    # The node decides when its reader stops (closing the socket): a terminal's Ctrl-C or a SIGTERM to the
    # whole process group would otherwise end the reader first and count as a crash.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    keep_freed_memory()  # each map's 57 MB buffers (DDS's reassembly, the take) reuse the last one's pages
    single_threaded_blas()  # as in the node (core.thread_pools): the registration's numpy hands BLAS small matrices
    sock = socket.socket(fileno=args.fd)
    newest = NewestMap()
    node_gone = threading.Event()

    def listen_to_node() -> None:  # credits; the end of the socket is the end of the node: nothing left to do
        with contextlib.suppress(OSError):
            while data := sock.recv(16):
                newest.credit(data.count(_CREDIT))
        node_gone.set()

    def hand_over() -> None:
        seq, previous = 0, None
        while True:
            (gmap, stamp_ns, frame_id, decode_s), superseded = newest.take()
            try:
                send_map(sock, gmap, stamp_ns=stamp_ns, frame_id=frame_id, decode_s=decode_s, superseded=superseded,
                         seq=seq + 1)  # fmt: skip
            except ConnectionError:  # the node is gone
                node_gone.set()
                return
            except Exception as exc:  # no shared memory for it, most likely
                with contextlib.suppress(OSError):
                    send_refusal(sock, Refusal(_failure("handing over", exc), bad_input=False))
                continue
            seq += 1
            if previous is not None:
                motion, seconds = _estimated_motion(previous, gmap)
                try:
                    send_motion(sock, seq, motion, seconds)
                except ConnectionError:
                    node_gone.set()
                    return
                except Exception:  # no shared memory for its arrays, most likely: the node estimates it itself
                    traceback.print_exc()
                    with contextlib.suppress(OSError):
                        send_motion(sock, seq, None, seconds)  # needs no descriptor
            previous = gmap

    def heartbeat() -> None:
        with contextlib.suppress(OSError):
            while not node_gone.wait(HEARTBEAT_S):
                send_alive(sock)

    threading.Thread(target=listen_to_node, name="node", daemon=True).start()
    threading.Thread(target=hand_over, name="hand_over", daemon=True).start()
    threading.Thread(target=heartbeat, name="heartbeat", daemon=True).start()

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import PointCloud2

    import msg_adapters as ma
    from monovoc_ros.nodes.qos import map_qos

    def on_map(data: bytes) -> None:
        # Whatever a message does to the reader costs that message only: a crash would be a crash loop on a
        # latched topic.
        start = time.perf_counter()
        try:
            gmap, frame_id = ma.gaussian_map_from_cdr(data)
            newest.put((gmap, gmap.stamp_ns, frame_id, time.perf_counter() - start))
        except ValueError as exc:
            with contextlib.suppress(OSError):
                send_refusal(sock, Refusal(f"Gaussian map ignored: {exc}", bad_input=True))
        except Exception as exc:
            with contextlib.suppress(OSError):
                send_refusal(sock, Refusal(_failure("decoding", exc), bad_input=False))

    # rclpy's handlers would end the child on a signal, under the node's feet.
    rclpy.init(args=["--ros-args", "--disable-rosout-logs"], signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(args.node_name, namespace=args.namespace)
    # The node's own QoS for `gaussians`; raw: the serialized message, decoded without rclpy's two copies of it.
    ma.prepare_point_cloud_decoder()
    node.create_subscription(PointCloud2, args.topic, on_map, map_qos(), raw=True)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    with contextlib.suppress(Exception):
        while not node_gone.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=_POLL_S)
    # Fast DDS deletes a participant's shared-memory files (/dev/shm/fastrtps_*) only when the participant is
    # destroyed: an os._exit alone left them behind at every stop of the node (0.5 MB each; 64 MB under
    # config/fastdds_large_clouds.xml, which a child inherits). os._exit then, not the interpreter's teardown:
    # the hand-over thread may be waiting for a map.
    with contextlib.suppress(Exception):
        executor.shutdown(timeout_sec=STOP_WAIT_S / 2)
        node.destroy_node()
        rclpy.try_shutdown()
    os._exit(0)


if __name__ == "__main__":
    sys.exit(_child_main())
