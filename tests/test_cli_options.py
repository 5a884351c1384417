"""`monovoc map` / `monovoc eval` options are honoured or refused, never silently ignored (issue 9, case 10)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from monovoc_ros.cli import main
from monovoc_ros.core.map_store import load_snapshot

BAG = Path(__file__).resolve().parents[1] / "bags" / "synthetic_room.mcap"


def test_max_keyframes_is_honoured_for_bags(tmp_path):
    out = tmp_path / "map"
    assert main(["map", "--bag", str(BAG), "--max-keyframes", "3", "-o", str(out), "--quiet"]) == 0
    assert json.loads((out / "summary.json").read_text())["keyframes"] == 3
    assert load_snapshot(out).n_keyframes == 3


@pytest.mark.parametrize(
    ("extra", "problem"),
    [
        (["--gaussians", "map.ply"], "--gaussians cannot be used with --bag"),
        (["--masks", "m", "--rgb", "r"], "--masks, --rgb cannot be used with --bag"),
        (["--layout", "hislam2"], "--layout cannot be used with --bag"),
    ],
)
def test_options_a_bag_cannot_use_are_refused(tmp_path, extra, problem):
    for command in (["map", "--bag", str(BAG), "-o", str(tmp_path / "m")], ["eval", str(tmp_path), "--bag", str(BAG)]):
        with pytest.raises(SystemExit) as info:
            main([*command, *extra])
        assert problem in str(info.value)
    assert not (tmp_path / "m").exists()


@pytest.mark.parametrize(
    ("source", "window", "problem"),
    [
        (["--bag", str(BAG)], "-1", "--map-update-ahead-s must be in [0, 10], got -1.0"),
        (["--bag", str(BAG)], "inf", "--map-update-ahead-s must be in [0, 10], got inf"),
        (["synthetic"], "2", "--map-update-ahead-s needs --bag"),
    ],
)
def test_a_map_update_window_out_of_range_or_without_a_bag_is_refused(tmp_path, source, window, problem):
    with pytest.raises(SystemExit) as info:
        main(["map", *source, "-o", str(tmp_path / "m"), "--map-update-ahead-s", window])
    assert problem in str(info.value)
    assert not (tmp_path / "m").exists()


def test_map_input_errors_are_one_line(tmp_path):
    """A missing or unreadable source is the operator's mistake: one line naming it, no traceback."""
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"not a bag at all" * 64)
    half = tmp_path / "half.mcap"
    half.write_bytes(BAG.read_bytes()[:100_000])  # a cut inside the first chunk: no complete message, no map
    (tmp_path / "empty").mkdir()
    cases = [
        ([str(tmp_path / "nonexistent")], "no such sequence directory"),
        ([str(tmp_path / "empty")], str(tmp_path / "empty")),
        (["--bag", str(tmp_path / "nonexistent.mcap")], "nonexistent.mcap"),
        (["--bag", str(garbage)], "not a readable MCAP bag"),
        (["--bag", str(half)], "no Gaussian map"),
    ]
    for source, problem in cases:
        with pytest.raises(SystemExit) as info:
            main(["map", *source, "-o", str(tmp_path / "out"), "--quiet"])
        assert str(info.value).startswith("monovoc map: ") and problem in str(info.value), (source, info.value)


def test_map_into_a_directory_it_cannot_write_is_one_line(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("in the way")
    with pytest.raises(SystemExit) as info:
        main(["map", "--bag", str(BAG), "--max-keyframes", "2", "-o", str(blocker / "map"), "--quiet"])
    assert str(info.value).startswith("monovoc map: ") and "a_file" in str(info.value)


@pytest.mark.parametrize(
    ("argv", "problem"),
    [
        (["replay", "--fast", "--wait-timeout", "nan", "b.mcap"], "--wait-timeout: must be a finite number"),
        (["query", "--timeout", "nan", "sofa"], "--timeout: must be a finite number"),
        (["ask", "--timeout", "-1", "how many chairs"], "--timeout: must be >= 0"),
        (["record", "-o", "x.mcap", "--duration", "inf", "/a"], "--duration: must be a finite number"),
        (["record", "-o", "x.mcap", "--count", "0", "/a"], "--count: must be >= 1"),
        (["eval", "m", "--every", "0"], "--every: must be >= 1"),
        (["eval", "m", "--every", "1.5"], "--every: not an integer: '1.5'"),
        (["map", "synthetic", "-o", "out", "--max-keyframes", "0"], "--max-keyframes: must be >= 1"),
        (["bag", "convert", "d", "-o", "b.mcap", "--max-keyframes", "-2"], "--max-keyframes: must be >= 1"),
        (["replay", "--wait-subscribers", "-1", "b.mcap"], "--wait-subscribers: must be >= 0"),
        (["eval", "m", "--point-size", "nan"], "--point-size: must be a finite number"),
        (["demo", "--top-k", "-1"], "--top-k: must be >= 1"),
        (["replay", "--rate", "0", "b.mcap"], "--rate: must be > 0"),
        (["bag", "convert", "d", "-o", "b.mcap", "--jpeg-quality", "500"], "--jpeg-quality: must be >= 1 and <= 100"),
        (["approach", "sofa", "--map", "m", "--robot-radius", "abc"], "--robot-radius: not a number"),
        (["query", "--namespace", "bad ns", "sofa"], "--namespace: not a ROS namespace: 'bad ns'"),
        (["ask", "--namespace", "/a//b", "how many chairs"], "--namespace: not a ROS namespace: '/a//b'"),
        (["bag", "convert", "d", "-o", "b.mcap", "--namespace", "/x/"], "--namespace: not a ROS namespace: '/x/'"),
    ],
)
def test_numbers_and_names_are_checked_before_anything_runs(tmp_path, capsys, monkeypatch, argv, problem):
    """A NaN timeout never passes (replay, query, ask and record waited forever): refused with argparse's one line,
    before anything is written (the relative paths above would land in tmp_path)."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2 and problem in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_paths_a_command_cannot_write_or_read_are_one_line(tmp_path, capsys):
    """A file where a folder goes, a map that is not there, a source without a Gaussian map: one line, no traceback,
    and no report left as if the command had finished."""
    from monovoc_ros.core.evaluation.datasets import write_plain
    from monovoc_ros.synthetic import SceneConfig, generate_scene

    blocker = tmp_path / "a_file"
    blocker.write_text("in the way")
    assert main(["demo", "-o", str(blocker / "demo")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("monovoc demo: ") and "Not a directory" in err
    (tmp_path / "bag_dir").mkdir()
    assert main(["bag", "convert", "synthetic", "-o", str(tmp_path / "bag_dir"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("monovoc bag convert: ") and "Traceback" not in err and "Is a directory" in err
    with pytest.raises(SystemExit) as info:
        main(["eval", str(tmp_path / "no_map"), "--bag", str(BAG)])
    assert str(info.value).startswith("monovoc eval: ") and "no saved map" in str(info.value)
    cfg = SceneConfig(width=64, height=48, fx=60.0, fy=60.0, cx=32.0, cy=24.0)
    cfg.n_gaussians, cfg.n_keyframes = 500, 3
    scene = generate_scene(cfg)
    write_plain(scene, tmp_path / "no_ply", gaussians=None)
    (tmp_path / "no_ply" / "gaussians.ply").unlink(missing_ok=True)
    with pytest.raises(SystemExit) as info:
        main(["map", str(tmp_path / "no_ply"), "-o", str(tmp_path / "out"), "--quiet"])
    assert str(info.value).startswith("monovoc map: ") and "no Gaussian map" in str(info.value)
    assert not (tmp_path / "out" / "summary.json").exists()


def test_a_namespace_without_its_slash_is_taken_as_absolute():
    from monovoc_ros.cli import build_parser

    assert build_parser().parse_args(["query", "--namespace", "robot1/monovoc", "x"]).namespace == "/robot1/monovoc"
    assert build_parser().parse_args(["query", "x"]).namespace == "/monovoc"
