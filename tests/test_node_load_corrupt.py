"""load_map and resume against corrupt map directories (issue 9, cases 1, 2 and 7), in a live node.

Every corrupt snapshot, objects.db and PLY of the corpus is refused by the live load_map service with
`success: false` and a message naming the file and the problem; the node keeps running with its map and
objects unchanged (same answers to a query), and the next save does not overwrite the good objects.db
with an empty one. A node resumed from a directory whose objects.db is unreadable keeps that file aside.
"""

from __future__ import annotations

import json
import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from monovoc_ros.objects.database import DB_NAME, ObjectDatabase
from monovoc_ros.ros_harness import ClientNode, NodeProcess, call_service, ros_args, wait_for_service, wait_until
from tests.object_room import copy_directory, room_directory
from tests.test_query_service import NODE, _environment, _query

pytestmark = pytest.mark.ros


def _snap(directory: Path) -> Path:
    return directory / (directory / "CURRENT").read_text().strip()


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _flip(path: Path) -> None:
    data = bytearray(path.read_bytes())
    for pos in range(len(data) // 3, len(data) // 3 + 64):
        data[pos] ^= 0xFF
    path.write_bytes(bytes(data))


def _meta(directory: Path, edit) -> None:
    meta = _snap(directory) / "meta.json"
    meta.write_text(edit(json.loads(meta.read_text())))


def _foreign_db(path: Path) -> None:
    path.unlink()
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE other (x INTEGER)")


def _ply(content: bytes):
    return lambda path: path.write_bytes(content)


_NAMES = b"x y z opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3".split()
REQUIRED = b"".join(b"property float %s\n" % n for n in _NAMES)
# name -> (what to break in a copy of a good map directory, or a PLY writer for a .ply path; words of the answer)
CORPUS = {
    "gaussians_truncated": (lambda d: _truncate(_snap(d) / "gaussians.npz"), "gaussians.npz"),
    "gaussians_flipped": (lambda d: _flip(_snap(d) / "gaussians.npz"), "gaussians.npz"),
    "gaussians_missing": (lambda d: (_snap(d) / "gaussians.npz").unlink(), "gaussians.npz"),
    "palette_truncated": (lambda d: _truncate(_snap(d) / "palette.npz"), "palette.npz"),
    "palette_flipped": (lambda d: _flip(_snap(d) / "palette.npz"), "palette.npz"),
    "state_truncated": (lambda d: _truncate(_snap(d) / "state.npz"), "state.npz"),
    "meta_not_an_object": (lambda d: _meta(d, lambda m: "[1, 2, 3]"), "meta.json holds a list, not an object"),
    "meta_without_config": (lambda d: _meta(d, lambda m: json.dumps({k: v for k, v in m.items() if k != "config"})),
                            "meta.json has no 'config' object"),
    "meta_not_json": (lambda d: _meta(d, lambda m: "{"), "meta.json: unreadable snapshot file (JSONDecodeError"),
    "meta_bad_config": (lambda d: _meta(d, lambda m: json.dumps({**m, "config": {"no_such_option": 1}})),
                        "invalid saved config"),
    "meta_wrong_count": (lambda d: _meta(d, lambda m: json.dumps({**m, "gaussians": 7})), "meta.json says 7"),
    "current_dangling": (lambda d: (d / "CURRENT").write_text("snap-999999\n"), "not a complete snapshot"),
    "no_current": (lambda d: (d / "CURRENT").unlink(), "no saved map"),
    "objects_db_garbage": (lambda d: (d / DB_NAME).write_bytes(bytes(range(256)) * 64), "objects not restored"),
    "objects_db_truncated": (lambda d: _truncate(d / DB_NAME), "objects not restored"),
    "objects_db_foreign": (lambda d: _foreign_db(d / DB_NAME), "not a MonoVoc object database"),
    "ply_huge_count": (_ply(b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\n" + REQUIRED
                            + b"end_header\n" + bytes(88)), "1000000000000 vertices"),
    "ply_bare_property": (_ply(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty\nend_header\n0\n"),
                          "bad property line"),
}  # fmt: skip


def _answers(service, node) -> list[tuple[int, str, int]]:
    """Every object the node answers with (id, label, Gaussians), by id."""
    answer = _query(service, "an object", top_k=1000, process=node)
    assert answer.success, answer.message
    return sorted((int(o.id), o.label, int(o.num_gaussians)) for o in answer.objects)


def test_corrupt_snapshots_through_load_map(tmp_path):
    from monovoc_interfaces.srv import LoadMap, SaveMap, TextQuery

    good = room_directory()
    records = len(ObjectDatabase(good / DB_NAME, create=False).records())
    directory = copy_directory(good, tmp_path / "map")
    env = _environment(tmp_path)
    params = {"map_directory": str(directory), "resume": True, "save_period_s": 0.0, "diagnostics_period_s": 5.0,
              "labels_file": str(good / "labels.json")}  # fmt: skip
    with NodeProcess.python([*NODE, *ros_args(params)], env, name="object_query") as node, ClientNode(env) as client:
        service = client.node.create_client(TextQuery, "/monovoc/query")
        load = client.node.create_client(LoadMap, "/monovoc/load_map")
        save = client.node.create_client(SaveMap, "/monovoc/save_map")
        for cli in (service, load, save):
            wait_for_service(cli, 30.0, process=node)
        before = _answers(service, node)
        assert len(before) == records

        for name, (corrupt, words) in CORPUS.items():
            if name.startswith("ply_"):
                target = tmp_path / f"{name}.ply"
                corrupt(target)
            else:
                target = copy_directory(good, tmp_path / name)
                corrupt(target)
            response = call_service(load, LoadMap.Request(directory=str(target)), 60.0, process=node)
            assert not response.success, f"{name}: {response.message}"
            assert str(target) in response.message and words in response.message, f"{name}: {response.message}"
            node.check_running()
            assert _answers(service, node) == before, name  # map and objects untouched

        # The next save writes the objects the node still holds, not an empty index.
        saved = call_service(save, SaveMap.Request(), 60.0, process=node)
        assert saved.success, saved.message
        assert len(ObjectDatabase(directory / DB_NAME, create=False).records()) == records
        # And a good directory still loads.
        response = call_service(load, LoadMap.Request(directory=str(good)), 60.0, process=node)
        assert response.success and response.num_objects > 0, response.message
        assert _answers(service, node) == before
        assert "Traceback" not in node.output()


def test_resume_keeps_an_unreadable_objects_db_aside(tmp_path):
    from monovoc_interfaces.srv import SaveMap, TextQuery

    directory = copy_directory(room_directory(), tmp_path / "map")
    _truncate(directory / DB_NAME)
    damaged = (directory / DB_NAME).read_bytes()
    env = _environment(tmp_path)
    params = {"map_directory": str(directory), "resume": True, "save_period_s": 0.0, "diagnostics_period_s": 5.0}
    with NodeProcess.python([*NODE, *ros_args(params)], env, name="object_query") as node, ClientNode(env) as client:
        save = client.node.create_client(SaveMap, "/monovoc/save_map")
        service = client.node.create_client(TextQuery, "/monovoc/query")
        for cli in (save, service):
            wait_for_service(cli, 30.0, process=node)

        # The services are announced when they are created, before the object component restores
        # objects.db: wait for the file to be kept aside, not for the services alone.
        def kept_aside():
            found = sorted(directory.glob(f"{DB_NAME}.unreadable-*"))
            return [p for p in found if not p.name.endswith(("-wal", "-shm"))]

        wait_until(kept_aside, 30.0, "objects.db kept aside", process=node)
        kept = kept_aside()
        assert len(kept) == 1 and kept[0].read_bytes() == damaged
        assert call_service(save, SaveMap.Request(), 60.0, process=node).success
        node.check_running()
    assert kept[0].read_bytes() == damaged  # never overwritten
    db = ObjectDatabase(directory / DB_NAME, create=False)  # a fresh, readable database beside it
    assert np.asarray(db.gaussian_index().object_ids).size > 0
    shutil.rmtree(directory)
