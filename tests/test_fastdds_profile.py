"""The Fast DDS profile of our processes (monovoc_ros.fastdds_profile): a 50 ms heartbeat for reliable writers,
set only around the first node, never over a user's profile, never passed to children; the mapping node runs
under it and says so."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from monovoc_ros import fastdds_profile as fp

USER_PROFILE = """<?xml version="1.0" encoding="UTF-8"?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <data_writer profile_name="users_writer" is_default_profile="true">
    <times><heartbeatPeriod><sec>0</sec><nanosec>200000000</nanosec></heartbeatPeriod></times>
  </data_writer>
</profiles>
"""


@pytest.fixture
def clean_env(monkeypatch, tmp_path):
    for key in ("FASTRTPS_DEFAULT_PROFILES_FILE", "SKIP_DEFAULT_XML", "RMW_IMPLEMENTATION", fp.PUBLICATION_MODE_ENV):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.chdir(tmp_path)  # no DEFAULT_FASTRTPS_PROFILES.xml here
    return monkeypatch


def test_the_profile_and_when_a_users_settings_win(clean_env, tmp_path):
    assert "<nanosec>50000000</nanosec>" in fp.profile_xml(fp.WRITER_HEARTBEAT_MS)
    assert fp.profile_xml(None) is None
    clean_env.setenv("RMW_IMPLEMENTATION", "rmw_cyclonedds_cpp")
    assert fp.profile_xml(50) is None and fp.describe(False) == "DDS: rmw_cyclonedds_cpp as configured"
    clean_env.delenv("RMW_IMPLEMENTATION")
    clean_env.setenv("FASTRTPS_DEFAULT_PROFILES_FILE", "/etc/mine.xml")
    assert fp.profile_xml(50) is None
    assert fp.describe(False) == (
        "Fast DDS: the user's profile /etc/mine.xml, as it is; publication mode SYNCHRONOUS (rmw_fastrtps default)"
    )
    clean_env.setenv(fp.PUBLICATION_MODE_ENV, "ASYNCHRONOUS")  # a user's mode is named
    assert fp.describe(False).endswith("; publication mode ASYNCHRONOUS")
    clean_env.delenv(fp.PUBLICATION_MODE_ENV)
    clean_env.delenv("FASTRTPS_DEFAULT_PROFILES_FILE")
    # Fast DDS 2.14 (Jazzy) reads the working directory's file too, unless told to skip it.
    (tmp_path / "DEFAULT_FASTRTPS_PROFILES.xml").write_text(USER_PROFILE)
    assert fp.profile_xml(50) is None
    assert fp.describe(False).startswith("Fast DDS: the user's profile DEFAULT_FASTRTPS_PROFILES.xml, as it is;")
    clean_env.setenv("SKIP_DEFAULT_XML", "1")
    assert "<nanosec>50000000</nanosec>" in fp.profile_xml(50)


def test_the_profile_is_set_only_inside_and_children_do_not_inherit_it(clean_env):
    with fp.writer_heartbeat(fp.WRITER_HEARTBEAT_MS) as applied:
        assert applied
        path = Path(os.environ[fp.PROFILES_ENV])
        assert "heartbeatPeriod" in path.read_text()
        assert fp.PROFILES_ENV not in fp.child_environment()
    assert fp.PROFILES_ENV not in os.environ and not path.exists()
    clean_env.setenv(fp.PROFILES_ENV, "/etc/mine.xml")  # a user's profile is passed on, and left alone
    assert fp.child_environment()[fp.PROFILES_ENV] == "/etc/mine.xml"
    with fp.writer_heartbeat(fp.WRITER_HEARTBEAT_MS) as applied:
        assert not applied and os.environ[fp.PROFILES_ENV] == "/etc/mine.xml"


LARGE_CLOUDS = Path(__file__).resolve().parents[1] / "config" / "fastdds_large_clouds.xml"


def test_the_large_clouds_profile_repeats_the_nodes_heartbeat():
    """A user's profile replaces ours whole: the shipped one must carry the node's writer heartbeat itself."""
    assert f"<nanosec>{fp.WRITER_HEARTBEAT_MS * 1_000_000}</nanosec>" in LARGE_CLOUDS.read_text()
    assert "<segment_size>67108864</segment_size>" in LARGE_CLOUDS.read_text()


def shm_mappings_mb(pid: int) -> list[float]:
    """Sizes (MB) of the Fast DDS shared-memory segments a process has mapped."""
    sizes = []
    for line in Path(f"/proc/{pid}/maps").read_text().splitlines():
        fields = line.split()
        if len(fields) >= 6 and "/dev/shm/fastrtps_" in fields[5] and "_port" not in fields[5]:
            lo, hi = (int(x, 16) for x in fields[0].split("-"))
            sizes.append((hi - lo) / 2**20)
    return sizes


@pytest.mark.ros
@pytest.mark.parametrize("profile", ["ours", "users", "large_clouds"])
def test_the_mapping_node_runs_under_the_profile_or_the_users(tmp_path, profile):
    """The node says which it runs under, takes a map and keyframes under it, and its map reader child starts
    without our profile (a user's is passed on). The shipped config/fastdds_large_clouds.xml gives the node's
    participant its 64 MB shared-memory segment (Fast DDS's own: 512 KB) where /dev/shm has room for it."""
    import psutil

    from tests.node_scene import running_mapper, scene_messages, small_scene

    node_env = {}
    if profile == "users":
        (tmp_path / "mine.xml").write_text(USER_PROFILE)
        node_env[fp.PROFILES_ENV] = str(tmp_path / "mine.xml")
        node_env[fp.PUBLICATION_MODE_ENV] = "ASYNCHRONOUS"
    elif profile == "large_clouds":
        node_env[fp.PROFILES_ENV] = str(LARGE_CLOUDS)
    room = shutil.disk_usage("/dev/shm").free >= 128 * 2**20
    with running_mapper(tmp_path, {"publish_rate_hz": 0.0, "map_reader_process": True}, node_env) as mapper:
        mapper.publisher.publish_map(small_scene().gaussians)
        for msgs in scene_messages()[:2]:
            mapper.publisher.publish_messages(msgs)
        mapper.diagnostics.wait_for(lambda v: v["keyframes_processed"] == "2", 30.0, process=mapper.node)
        readers = [c for c in psutil.Process(mapper.node.pid).children() if "map_reader" in " ".join(c.cmdline())]
        assert len(readers) == 1
        environ = dict(
            entry.split("=", 1)
            for entry in Path(f"/proc/{readers[0].pid}/environ").read_text().split("\0")
            if "=" in entry
        )
        segments = shm_mappings_mb(mapper.node.pid)
        output = mapper.node.output()
    if profile == "large_clouds":
        assert f"Fast DDS: the user's profile {LARGE_CLOUDS}, as it is" in output
        assert environ.get(fp.PROFILES_ENV) == str(LARGE_CLOUDS)
        # Without room for the segment Fast DDS goes on over UDPv4: the node took its map and keyframes above.
        assert max(segments) >= 64 if room else max(segments, default=0) < 2, segments
    elif profile == "users":
        mine = tmp_path / "mine.xml"
        assert f"Fast DDS: the user's profile {mine}, as it is; publication mode ASYNCHRONOUS" in output
        assert environ.get(fp.PROFILES_ENV) == str(mine) and environ.get(fp.PUBLICATION_MODE_ENV) == "ASYNCHRONOUS"
    else:
        ours = f"heartbeat {fp.WRITER_HEARTBEAT_MS} ms (monovoc_ros.fastdds_profile); publication mode SYNCHRONOUS"
        assert ours in output
        assert fp.PROFILES_ENV not in environ
        assert segments and max(segments) < 2, segments  # Fast DDS's 512 KB segments
