"""The Fast DDS profile our processes create their participant under: a short heartbeat for reliable writers.

A reliable reader delivers samples in order, and asks again for a lost one only when the writer's heartbeat
says what it sent; Fast DDS's heartbeat period is 3 s. So one lost sample holds back everything after it for
up to 3 s:
* the final ``wait_for_all_acked`` of a fast replay idled up to 3 s (2.9 s of a 3.3 s replay of the bundled bag;
  0.5 s with 50 ms);
* the node's answers to queries: in three of eight 1M robot runs (docs/results.md, robot scale, eleventh
  session) the answers to a few consecutive queries came 1.8-2.9 s late, all at once, while no handler took
  over 40 ms.
WRITER_HEARTBEAT_MS bounds that wait. Heartbeats go out only while a writer has unacknowledged samples.

Fast DDS reads its default profiles file once per process, when the first participant is created; rmw creates
a context's participant with its first node (not at ``rclpy.init``). So the profile must be in place around the
process's first ``create_node`` (``writer_heartbeat``), and is gone afterwards: children started meanwhile get
``child_environment()``, without it (its file may be gone before they read it). A profile of the user's
(``FASTRTPS_DEFAULT_PROFILES_FILE``, or DEFAULT_FASTRTPS_PROFILES.xml in the working directory unless
``SKIP_DEFAULT_XML=1``: what Jazzy's Fast DDS 2.14 reads) or another middleware wins: nothing is changed then.

The publication mode is left as rmw_fastrtps sets it (synchronous in Jazzy) unless the user sets
RMW_FASTRTPS_PUBLICATION_MODE; the node's log says which. Asynchronous publication took away the interpreter
holds of a blocked ``publish()`` in 1M-Gaussian runs but not the query tails (docs/results.md, twelfth and
seventeenth sessions).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

PROFILES_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"
PUBLICATION_MODE_ENV = "RMW_FASTRTPS_PUBLICATION_MODE"
WRITER_HEARTBEAT_MS = 50
_DEFAULT_FILE = "DEFAULT_FASTRTPS_PROFILES.xml"  # Fast DDS reads it from the working directory
_FILE_PREFIX = "monovoc_fastdds_"
_WRITER_PROFILE = """<?xml version="1.0" encoding="UTF-8"?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <data_writer profile_name="monovoc_writer" is_default_profile="true">
    <times><heartbeatPeriod><sec>0</sec><nanosec>{ns}</nanosec></heartbeatPeriod></times>
  </data_writer>
</profiles>
"""


def _users_profile() -> str | None:
    """The profiles file Fast DDS reads without us, if any."""
    if os.environ.get(PROFILES_ENV):
        return os.environ[PROFILES_ENV]
    if os.environ.get("SKIP_DEFAULT_XML") != "1" and Path(_DEFAULT_FILE).exists():
        return _DEFAULT_FILE
    return None


def profile_xml(period_ms: int | None) -> str | None:
    """The profile for this heartbeat in this environment, or None when nothing is to change."""
    if period_ms is None or os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") != "rmw_fastrtps_cpp":
        return None
    if _users_profile() is not None:
        return None
    return _WRITER_PROFILE.format(ns=int(period_ms) * 1_000_000)


@contextlib.contextmanager
def writer_heartbeat(period_ms: int | None) -> Iterator[bool]:
    """Around the process's first ``create_node``: our profile as Fast DDS's default; yields whether it is."""
    xml = profile_xml(period_ms)
    if xml is None:
        yield False
        return
    fd, name = tempfile.mkstemp(prefix=_FILE_PREFIX, suffix=".xml")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(xml)
        os.environ[PROFILES_ENV] = name
        yield True
    finally:
        os.environ.pop(PROFILES_ENV, None)
        Path(name).unlink(missing_ok=True)


def publication_mode() -> str:
    """The rmw_fastrtps publication mode this process and its children run under (the user's, or Jazzy's default)."""
    return os.environ.get(PUBLICATION_MODE_ENV) or "SYNCHRONOUS (rmw_fastrtps default)"


def describe(applied: bool) -> str:
    """What the process's participant runs under, for its log."""
    user = _users_profile()
    if applied:
        line = f"Fast DDS: reliable writers' heartbeat {WRITER_HEARTBEAT_MS} ms (monovoc_ros.fastdds_profile)"
    elif user is not None:
        line = f"Fast DDS: the user's profile {user}, as it is"
    else:
        return f"DDS: {os.environ.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')} as configured"
    return line + f"; publication mode {publication_mode()}"


def child_environment() -> dict[str, str]:
    """This process's environment for a child, less our profile; a user's profile is passed on."""
    env = dict(os.environ)
    if Path(env.get(PROFILES_ENV, "")).name.startswith(_FILE_PREFIX):
        del env[PROFILES_ENV]
    return env
