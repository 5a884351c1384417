"""The ROS environment of one test: its own random ``ROS_DOMAIN_ID``, ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``,
a temporary ``ROS_LOG_DIR`` and ``HOME``, and ``AMENT_PREFIX_PATH`` pointing at the project venv. Inherited
``ROS_LOCALHOST_ONLY``, ``ROS_STATIC_PEERS``, ``FASTRTPS_DEFAULT_PROFILES_FILE`` and ``RMW_FASTRTPS_PUBLICATION_MODE``
are dropped; a test that wants a Fast DDS profile or mode passes it in ``extra``. Processes, clients and waits
come from monovoc_ros.ros_harness, the harness the demo and the benchmarks use too::

    env = ros_environment(tmp_path)
    with NodeProcess.python(["-m", "my_pkg.my_node"], env, name="my_node") as server, ClientNode(env) as client:
        cli = client.node.create_client(TextQuery, "/monovoc/query")
        wait_for_service(cli, timeout=10.0, process=server)
        response = call_service(cli, TextQuery.Request(text="chair"), timeout=5.0, process=server)
"""

from __future__ import annotations

import os
import random
import sys
from collections.abc import Mapping
from pathlib import Path

from monovoc_ros.ros_harness import FOREIGN_ROS_VARIABLES

REPO = Path(__file__).resolve().parents[1]
VENV = REPO / ".venv"
VENV_PYTHON = VENV / "bin" / "python" if (VENV / "bin" / "python").exists() else Path(sys.executable)

# Fast DDS maps domain d to UDP ports 7400 + 250 * d (+ offsets): 0..232 are valid; skip 0 (the default).
_DOMAIN_RANGE = (1, 232)


def random_domain_id() -> int:
    """A domain id for one test run; random so concurrent runs on one machine do not meet."""
    return random.SystemRandom().randint(*_DOMAIN_RANGE)


def ros_environment(tmp_dir: Path, domain_id: int | None = None, extra: Mapping[str, str] | None = None) -> dict:
    """The environment for ROS processes of one test: loopback only, own domain, own log dir."""
    tmp_dir = Path(tmp_dir)
    log_dir = tmp_dir / "ros_log"
    home = tmp_dir / "home"
    log_dir.mkdir(parents=True, exist_ok=True)
    home.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    for key in FOREIGN_ROS_VARIABLES:
        env.pop(key, None)
    ament = env.get("AMENT_PREFIX_PATH", "")
    env.update(
        ROS_DOMAIN_ID=str(random_domain_id() if domain_id is None else domain_id),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_LOG_DIR=str(log_dir),
        HOME=str(home),
        AMENT_PREFIX_PATH=str(VENV) + (os.pathsep + ament if ament and ament != str(VENV) else ""),
        RCUTILS_COLORIZED_OUTPUT="0",
        PYTHONUNBUFFERED="1",
    )
    # Children import the project from the working tree even before it is pip-installed.
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    if extra:
        env.update(extra)
    return env
