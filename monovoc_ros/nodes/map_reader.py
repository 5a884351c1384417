"""The Gaussian map topic read in a process of its own, its maps handed over in shared memory.

Why: rclpy takes a message holding the interpreter lock. A 1M-Gaussian map (a 56 MB PointCloud2) held it
60-130 ms per message in the node's process (docs/results.md, "where the query tail goes"), and every query
that arrived meanwhile waited: the query p99 of the 1M robot runs was 4x the one without map updates.

The child (``python -m monovoc_ros.nodes.map_reader``, a hidden node ``_<node>_map_reader`` in the node's
namespace) subscribes to the map topic with the node's QoS, decodes each message with the node's own adapter
(msg_adapters.cloud_to_gaussian_map: the same checks and the same arrays as the in-process subscription and
offline mapping), and writes the arrays into an anonymous shared-memory file (memfd). It sends the file
descriptor (SCM_RIGHTS) with a small JSON header over a Unix socket; the node maps the file read-only and
builds the GaussianMap on it without a copy. Nothing is ever in the file system, so whichever process dies,
no memory is left behind: the file lives as long as the map's arrays do.

Lifetime: the child ends when the node closes its end of the socket (a stop, or the node dying in any way)
and ignores SIGINT (a terminal's Ctrl-C reaches the whole process group; the node decides when to stop). If
the child dies while the node runs, the node logs it, counts it (``map_reader_restarts``) and starts another
after a back-off; the latched map that the new child receives again is not applied twice.
"""

from __future__ import annotations

import argparse
import contextlib
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
from dataclasses import dataclass
from typing import Any

import numpy as np

from monovoc_ros.core.map.gaussians import GaussianMap

# Arrays of a GaussianMap that a map message carries (cloud_to_gaussian_map fills no others).
_ARRAYS = ("means", "scales", "quats", "opacities", "colors", "ids")
_ALIGN = 64
_HEADER_BYTES = 1 << 16  # a header names six arrays and a frame id: far below
RESTART_DELAY_S = (1.0, 30.0)  # first and longest back-off before starting a child again
STOP_WAIT_S = 2.0  # how long a stop waits for the child to exit on its own before killing it


def supported() -> bool:
    """Whether this platform can hand maps over (Linux: memfd and SCM_RIGHTS)."""
    return hasattr(os, "memfd_create") and hasattr(socket, "send_fds") and hasattr(socket, "AF_UNIX")


@dataclass(frozen=True)
class Refusal:
    """A map message the child did not hand over: ``bad_input`` when the message was at fault (what the node
    counts as bad_gaussians), else the reader failed on it (a bug, or no shared memory for it)."""

    message: str
    bad_input: bool


@dataclass(frozen=True)
class ReceivedMap:
    gaussians: GaussianMap
    stamp_ns: int
    frame_id: str
    decode_s: float  # the child's take-to-arrays time for this message

    @property
    def key(self) -> tuple[int, int, str]:
        """What identifies a message delivered again (a latched map, to a new child)."""
        return self.stamp_ns, len(self.gaussians), self.frame_id


# ---------------------------------------------------------------------------------------------- transport


def send_map(sock: socket.socket, gmap: GaussianMap, *, stamp_ns: int, frame_id: str, decode_s: float) -> None:
    """Writes ``gmap``'s arrays into a new memfd and sends it with its header over ``sock`` (SOCK_SEQPACKET)."""
    layout, offset = [], 0
    for name in _ARRAYS:
        array = getattr(gmap, name)
        if array is None:
            continue
        layout.append({"name": name, "dtype": array.dtype.str, "shape": list(array.shape), "offset": offset})
        offset += -(-array.nbytes // _ALIGN) * _ALIGN
    fd = os.memfd_create("monovoc_map", os.MFD_CLOEXEC)
    try:
        os.ftruncate(fd, max(offset, 1))
        for entry in layout:
            data = np.ascontiguousarray(getattr(gmap, entry["name"])).reshape(-1).view(np.uint8)
            _write_all(fd, memoryview(data), entry["offset"])
        header = {"kind": "map", "stamp_ns": int(stamp_ns), "frame_id": str(frame_id), "decode_s": float(decode_s),
                  "size": offset, "arrays": layout}  # fmt: skip
        socket.send_fds(sock, [json.dumps(header).encode()], [fd])
    finally:
        os.close(fd)  # the receiver holds its own descriptor from here


def send_refusal(sock: socket.socket, refusal: Refusal) -> None:
    """Tells the node that a map message was not handed over, and why."""
    sock.send(json.dumps({"kind": "refusal", "message": refusal.message, "bad_input": refusal.bad_input}).encode())


def receive(sock: socket.socket) -> ReceivedMap | Refusal | None:
    """The next map from ``sock``, or a refusal, or None when the sender has gone. A malformed message raises
    ValueError (its descriptor closed)."""
    data, fds, _flags, _addr = socket.recv_fds(sock, _HEADER_BYTES, 1)
    try:
        if not data:
            return None
        header = json.loads(data)
        if header.get("kind") == "refusal":
            return Refusal(str(header["message"]), bool(header["bad_input"]))
        if header.get("kind") != "map" or len(fds) != 1:
            raise ValueError(f"map reader: unexpected message {header.get('kind')!r} with {len(fds)} descriptors")
        return ReceivedMap(
            _map_of(fds[0], header), int(header["stamp_ns"]), str(header["frame_id"]), float(header["decode_s"])
        )
    except (KeyError, TypeError, json.JSONDecodeError) as exc:
        raise ValueError(f"map reader: malformed header ({type(exc).__name__}: {exc})") from None
    finally:
        for fd in fds:
            os.close(fd)


def _map_of(fd: int, header: dict[str, Any]) -> GaussianMap:
    size = int(header["size"])
    if os.fstat(fd).st_size < size:
        raise ValueError(f"map reader: shared file of {os.fstat(fd).st_size} bytes, header says {size}")
    memory = mmap.mmap(fd, max(size, 1), access=mmap.ACCESS_READ)  # the arrays keep it mapped, the fd is not needed
    arrays: dict[str, np.ndarray] = {}
    for entry in header["arrays"]:
        name = entry["name"]
        if name not in _ARRAYS:
            raise ValueError(f"map reader: unknown array {name!r}")
        dtype, shape = np.dtype(entry["dtype"]), tuple(int(s) for s in entry["shape"])
        count = int(np.prod(shape))
        arrays[name] = np.frombuffer(memory, dtype, count, int(entry["offset"])).reshape(shape)
    return GaussianMap(**arrays)


def _write_all(fd: int, data: memoryview, offset: int) -> None:
    while data:
        written = os.pwrite(fd, data, offset)
        data, offset = data[written:], offset + written


# ---------------------------------------------------------------------------------------------- node side


class MapReaderProcess:
    """Runs a child reading ``topic`` from construction on; from ``start()`` until ``stop()`` calls, on a
    thread of its own, ``on_map(ReceivedMap)`` / ``on_refused(Refusal)`` for every message,
    ``on_restart(message)`` when a child exited and another starts, and ``on_redelivered(map)`` for the latched
    map a new child received again (not applied)."""

    def __init__(
        self,
        topic: str,
        node_name: str,
        namespace: str,
        *,
        on_map: Callable[[ReceivedMap], None],
        on_refused: Callable[[Refusal], None],
        on_restart: Callable[[str], None],
        on_redelivered: Callable[[ReceivedMap], None],
    ) -> None:
        self.topic, self.node_name, self.namespace = topic, node_name, namespace
        self._on_map, self._on_refused, self._on_restart = on_map, on_refused, on_restart
        self._on_redelivered = on_redelivered
        self._stopping = threading.Event()
        self._lock = threading.Lock()
        self._child: subprocess.Popen | None = None
        self._sock: socket.socket | None = None
        self._last_key: tuple[int, int, str] | None = None
        self._thread = threading.Thread(target=self._run, name="map_reader", daemon=True)
        # The first child starts now: its start-up (~1 s of imports and discovery) overlaps the node's own,
        # and its maps wait in the socket until start().
        with contextlib.suppress(OSError):  # the thread tries again, and says why
            self._child, self._sock = self._spawn()

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
            child = self._child
        if child is not None and child.poll() is None:
            child.kill()
            child.wait()

    def _spawn(self) -> tuple[subprocess.Popen, socket.socket]:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            command = [sys.executable, "-m", "monovoc_ros.nodes.map_reader", "--fd", str(theirs.fileno()),
                       "--topic", self.topic, "--node-name", self.node_name, "--namespace", self.namespace]  # fmt: skip
            child = subprocess.Popen(command, pass_fds=[theirs.fileno()], stdin=subprocess.DEVNULL)
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()
        return child, ours

    def _run(self) -> None:
        delay = RESTART_DELAY_S[0]
        redelivered = False
        while not self._stopping.is_set():
            with self._lock:
                pair = (self._child, self._sock) if self._sock is not None else None
            if pair is None:
                try:
                    pair = self._spawn()
                except OSError as exc:
                    self._on_restart(f"cannot start the map reader ({exc}); trying again in {delay:g} s")
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
            self._serve(sock, skip_key=self._last_key if redelivered else None)
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
            if time.monotonic() - started > 60.0:  # it had run a while: not a crash loop
                delay = RESTART_DELAY_S[0]
            self._on_restart(f"the map reader exited (code {child.returncode}); starting another in {delay:g} s")
            redelivered = True
            self._stopping.wait(delay)
            delay = min(2 * delay, RESTART_DELAY_S[1])

    def _serve(self, sock: socket.socket, skip_key: tuple[int, int, str] | None) -> None:
        while True:
            try:
                item = receive(sock)
            except ValueError as exc:
                self._on_refused(Refusal(str(exc), bad_input=False))
                continue
            except OSError:
                return
            if item is None:
                return
            if isinstance(item, Refusal):
                self._on_refused(item)
                continue
            if skip_key is not None and item.key == skip_key:
                skip_key = None  # the latched map the previous child had handed over already
                self._on_redelivered(item)
                continue
            skip_key = None
            self._last_key = item.key
            self._on_map(item)


# ---------------------------------------------------------------------------------------------- child


def _failure(during: str, exc: BaseException) -> str:
    trace = "".join(traceback.format_exception(exc))
    return f"map reader: {during} a map failed ({type(exc).__name__}: {exc}); map dropped\n{trace}"


def _child_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Reads a Gaussian map topic for a monovoc node (internal).")
    parser.add_argument("--fd", type=int, required=True)
    parser.add_argument("--topic", required=True)
    parser.add_argument("--node-name", required=True)
    parser.add_argument("--namespace", default="/")
    args = parser.parse_args(argv)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the node decides when its reader stops
    sock = socket.socket(fileno=args.fd)

    def watch_node() -> None:  # the node closed its end (a stop, or it died): nothing is left to do
        with contextlib.suppress(OSError):
            while sock.recv(16):
                pass
        os._exit(0)

    threading.Thread(target=watch_node, name="node_watch", daemon=True).start()

    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import PointCloud2

    import msg_adapters as ma
    from monovoc_ros.nodes.qos import latched_qos

    def on_map(msg: Any) -> None:
        # Whatever a message does to the reader costs that message only: a crash would be a crash loop on a
        # latched topic.
        start = time.perf_counter()
        try:
            gmap = ma.cloud_to_gaussian_map(msg)
        except ValueError as exc:
            send_refusal(sock, Refusal(f"Gaussian map ignored: {exc}", bad_input=True))
            return
        except Exception as exc:
            send_refusal(sock, Refusal(_failure("decoding", exc), bad_input=False))
            return
        try:
            send_map(sock, gmap, stamp_ns=ma.header_stamp_ns(msg), frame_id=str(msg.header.frame_id),
                     decode_s=time.perf_counter() - start)  # fmt: skip
        except ConnectionError:  # the node is gone
            raise
        except Exception as exc:  # no shared memory for it, most likely
            send_refusal(sock, Refusal(_failure("handing over", exc), bad_input=False))

    # rclpy's handlers would end the child on a terminal's Ctrl-C, under the node's feet.
    rclpy.init(args=["--ros-args", "--disable-rosout-logs"], signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(args.node_name, namespace=args.namespace)
    node.create_subscription(PointCloud2, args.topic, on_map, latched_qos())  # the node's own QoS for `gaussians`
    try:
        rclpy.spin(node)
    except (OSError, rclpy.executors.ExternalShutdownException):  # the node's end closed mid-send
        pass
    os._exit(0)


if __name__ == "__main__":
    sys.exit(_child_main())
