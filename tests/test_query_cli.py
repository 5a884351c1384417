"""`monovoc query --map DIR`: the offline client on a saved map's objects.db."""

import json

import pytest

from monovoc_ros.cli import main as cli_main
from tests.object_room import room_directory, room_id


def test_offline_query_prints_the_ranking(capsys):
    assert cli_main(["query", "--map", str(room_directory()), "a sofa", "--top-k", "3"]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    # The room's labels name one sofa: it ranks by its label, and the message says so.
    assert lines[0] == "3 of 28 objects; 1 labelled 'sofa' ranked by label confidence"
    assert lines[1].split()[:3] == ["rank", "id", "label"]
    assert lines[2].split()[:3] == ["1", f"#{room_id('sofa'):06x}", "sofa"]


def test_offline_query_json_and_errors(capsys, tmp_path):
    assert cli_main(["query", "--map", str(room_directory()), "lamp", "--json", "--min-score", "0.5"]) == 0
    answer = json.loads(capsys.readouterr().out)
    assert answer["success"] and all(o["score"] >= 0.5 for o in answer["objects"])
    assert answer["objects"][0]["hex"] == f"#{room_id('lamp'):06x}"
    assert cli_main(["query", "--map", str(room_directory()), "  "]) == 1
    assert "empty query" in capsys.readouterr().err
    assert cli_main(["query", "--map", str(tmp_path), "a chair"]) == 2
    assert "no object database" in capsys.readouterr().err
    # A file that is no database: deleting it is advised for a map's own objects.db only, not for a bag.
    (tmp_path / "run.mcap").write_bytes(b"\x89MCAP0\r\n" + bytes(4096))
    (tmp_path / "objects.db").write_bytes(bytes(4096))
    assert cli_main(["query", "--map", str(tmp_path / "run.mcap"), "a chair"]) == 2
    err = capsys.readouterr().err
    assert "run.mcap: not a readable MonoVoc object database" in err and "delete" not in err
    assert cli_main(["query", "--map", str(tmp_path), "a chair"]) == 2
    err = capsys.readouterr().err
    assert "objects.db: not a readable MonoVoc object database" in err and "delete it to rebuild the objects" in err
    with pytest.raises(SystemExit) as info:  # refused while parsing (argparse's one line)
        cli_main(["query", "--map", str(room_directory()), "a chair", "--top-k", "-1"])
    assert info.value.code == 2 and "--top-k: must be >= 0" in capsys.readouterr().err


def test_offline_query_reads_spatial_language(capsys):
    assert cli_main(["query", "--map", str(room_directory()), "the chair right of the table", "--json"]) == 0
    answer = json.loads(capsys.readouterr().out)
    assert answer["objects"][0]["hex"] == "#ff00ff"  # from the viewpoint objects.db keeps: the last keyframe
    assert "read as 'chair' right of 'table'" in answer["message"] and "from the robot's viewpoint" in answer["message"]
