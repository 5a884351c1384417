"""A node's start-up that a stop signal can cut short, and the kernels ready before the node subscribes.

numba compiles a kernel inside the calling thread and cannot be interrupted there: a node that compiled
its kernels on the first keyframe (25-40 s into an empty cache on 2 cores) could neither integrate nor stop
meanwhile (`ros2 launch` escalated to SIGKILL, and nothing was saved), while a replay that only waited for
subscribers ran ahead. So a node whose cache is empty compiles in a child process (`monovoc warm-up`),
which a stop signal kills at once, and only then loads the kernels itself and subscribes.
"""

from __future__ import annotations

import re
import subprocess
import sys
import tempfile
import threading
import time

from monovoc_ros.fastdds_profile import child_environment

POLL_S = 0.05


def init_rclpy(args: list[str] | None) -> None:
    """rclpy.init without its signal handlers; --ros-args rcl cannot take (a parameter file that is no YAML, a remapping
    rule that is none) are the operator's ValueError, one line without rcl's source locations (`, at ./src/x.c:12` or
    `, at /project/src/x.c:12`, by how rcl was built), where rclpy raises RCLError."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except RuntimeError as exc:  # rclpy's RCLError
        raise ValueError(" ".join(re.sub(r", at \S+:\d+", "", str(exc)).split())) from None


class StartupAborted(Exception):
    """A stop signal arrived during start-up: the node ends before it subscribed or wrote anything."""


def check_stop(stop: threading.Event | None, during: str) -> None:
    if stop is not None and stop.is_set():
        raise StartupAborted(f"stop requested during start-up ({during})")


def compile_kernels(stop: threading.Event | None) -> float:
    """Runs `monovoc warm-up` in a child process (the cache it fills is this process's too) and waits for it;
    returns its seconds. Raises StartupAborted (the child killed) when `stop` is set meanwhile, and
    RuntimeError with the child's last line when it fails."""
    start = time.monotonic()
    with tempfile.TemporaryFile("w+") as log:  # a pipe left unread could fill and block the child
        child = subprocess.Popen(
            [sys.executable, "-m", "monovoc_ros.cli", "warm-up"],
            stdout=log,
            stderr=subprocess.STDOUT,
            text=True,
            env=child_environment(),
        )
        try:
            while child.poll() is None:
                if stop is not None and stop.wait(POLL_S):
                    break
                if stop is None:
                    time.sleep(POLL_S)
        finally:
            if child.poll() is None:
                child.kill()
            child.wait()
        # A terminal's Ctrl-C reaches the child too: a stop explains its exit.
        check_stop(stop, "the kernels were compiling")
        if child.returncode != 0:
            log.seek(0)
            last = next((line for line in reversed(log.read().splitlines()) if line.strip()), "no output")
            raise RuntimeError(f"monovoc warm-up failed (exit {child.returncode}): {last}")
    return time.monotonic() - start
