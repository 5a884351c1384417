"""Malformed Gaussian PLYs (issue 9, case 7): every one raises one PlyError naming the file and the
problem, before any allocation the header asks for; non-finite values are rejected as on the cloud path."""

from __future__ import annotations

import numpy as np
import pytest

from monovoc_ros.core.map.ply import PlyError, load_ply
from tests.test_ply import N, raw_columns, write_ply

HEADER = b"ply\nformat binary_little_endian 1.0\n"


def _props(names) -> bytes:
    return b"".join(b"property float " + n.encode() + b"\n" for n in names)


REQUIRED = ["x", "y", "z", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


@pytest.mark.parametrize(
    ("name", "content", "problem"),
    [
        ("huge_binary", HEADER + b"element vertex 1000000000000\n" + _props(REQUIRED) + b"end_header\n" + bytes(44),
         "truncated: 1000000000000 vertices of 44 bytes declared, 44 bytes present"),
        ("huge_ascii", b"ply\nformat ascii 1.0\nelement vertex 1000000000000\n" + _props(REQUIRED) + b"end_header\n1\n",
         "truncated: 1000000000000 vertices of 11 values declared"),
        ("bare_property", HEADER + b"element vertex 1\nproperty\nend_header\n", "bad property line"),
        ("short_list", HEADER + b"element vertex 1\nproperty list uchar\nend_header\n", "bad property line"),
        ("negative_count", HEADER + b"element vertex -5\n" + _props(REQUIRED) + b"end_header\n", "negative count"),
        ("no_properties", HEADER + b"element vertex 0\nend_header\n", "has no properties"),
        ("binary_garbage", b"ply\n" + bytes(range(11, 256)) * 40, "header line longer than 4096 bytes"),
        ("float_count", HEADER + b"element vertex 1.5\nend_header\n", "bad element line"),
    ],
)  # fmt: skip
def test_malformed_headers(tmp_path, name, content, problem):
    path = tmp_path / f"{name}.ply"
    path.write_bytes(content)
    with pytest.raises(PlyError) as info:
        load_ply(path)
    assert str(info.value).startswith(f"{path}: ") and problem in str(info.value)


@pytest.mark.parametrize(
    ("field", "value", "problem"),
    [
        ("opacity", np.nan, "NaN/inf values in opacity properties ['opacity']"),
        ("opacity", np.inf, "NaN/inf values in opacity properties ['opacity']"),
        ("scale_1", np.inf, "NaN/inf values in scale properties ['scale_1']"),
        ("scale_0", 1000.0, "log-scale 1000 is not finite once activated"),
        ("f_dc_2", np.nan, "NaN/inf values in color properties ['f_dc_2']"),
        ("x", -np.inf, "NaN/inf values in position properties ['x']"),
        ("rot_3", np.nan, "NaN/inf values in rotation properties ['rot_3']"),
    ],
)
def test_non_finite_values_are_rejected(tmp_path, field, value, problem):
    cols = raw_columns()
    cols[field] = cols[field].copy()
    cols[field][7] = value
    path = write_ply(tmp_path / "bad_value.ply", cols)
    with pytest.raises(PlyError) as info:
        load_ply(path)
    assert str(info.value).startswith(f"{path}: ") and problem in str(info.value)


def test_malformed_property_names(tmp_path):
    cols = {**raw_columns(), "f_rest_abc": np.zeros(N, np.float32)}
    with pytest.raises(PlyError, match=r"rest_abc.ply: malformed f_rest property names \['f_rest_abc'\]"):
        load_ply(write_ply(tmp_path / "rest_abc.ply", cols))
    gap = raw_columns(rest=9)
    gap["f_rest_12"] = gap.pop("f_rest_8")
    with pytest.raises(PlyError, match="gap.ply: 9 f_rest fields match no SH degree"):
        load_ply(write_ply(tmp_path / "gap.ply", gap))
    ids = {**raw_columns(), "id": np.full(N, 0.5, np.float32)}
    with pytest.raises(PlyError, match="ids.ply: property 'id' holds non-integer values"):
        load_ply(write_ply(tmp_path / "ids.ply", ids))


def test_seeded_corruptions_raise_only_ply_error(tmp_path):
    """300 truncations and byte flips of valid files (binary and ASCII): a map or a PlyError, nothing else."""
    rng = np.random.default_rng(9)
    sources = [write_ply(tmp_path / f"good_{fmt}.ply", raw_columns(), fmt) for fmt in ("binary_little_endian", "ascii")]
    outcomes = {"map": 0, "PlyError": 0}
    for k in range(300):
        data = bytearray(sources[k % 2].read_bytes())
        if k % 3 == 0:
            data = data[: int(rng.integers(0, len(data)))]
        else:
            for pos in rng.integers(0, min(len(data), 900), size=int(rng.integers(1, 6))):
                data[pos] = int(rng.integers(0, 256))
        path = tmp_path / f"corrupt_{k}.ply"
        path.write_bytes(bytes(data))
        try:
            load_ply(path)
            outcomes["map"] += 1
        except PlyError as exc:
            assert str(exc).startswith(f"{path}: ")
            outcomes["PlyError"] += 1
    assert outcomes["PlyError"] >= 100, outcomes
