"""3DGS PLY files: every encoding and property order, SH degrees 0..3, semantics fields, and clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.map.ply import PlyError, load_ply, save_ply

SH_C0 = 0.28209479177387814
N = 50


def raw_columns(rest: int = 0, semantics: bool = False, seed: int = 0) -> dict[str, np.ndarray]:
    """Stored (not activated) 3DGS vertex properties, graphdeco-inria names."""
    rng = np.random.default_rng(seed)
    cols = {name: rng.normal(size=N).astype(np.float32) for name in ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2")}
    cols.update({n: np.zeros(N, np.float32) for n in ("nx", "ny", "nz")})
    cols.update({f"f_rest_{k}": rng.normal(size=N).astype(np.float32) for k in range(rest)})
    cols["opacity"] = rng.normal(size=N).astype(np.float32)
    cols.update({f"scale_{k}": rng.uniform(-5, -3, N).astype(np.float32) for k in range(3)})
    cols.update({f"rot_{k}": rng.normal(size=N).astype(np.float32) for k in range(4)})
    if semantics:
        cols.update({f"semantics_{k}": rng.uniform(0, 1, N).astype(np.float32) for k in range(3)})
    return cols


def write_ply(path, cols: dict[str, np.ndarray], fmt: str = "binary_little_endian", count: int | None = None):
    """A PLY written independently of monovoc_ros.core.map.ply (as other tools write them)."""
    names = list(cols)
    header = ["ply", f"format {fmt} 1.0", "comment written by the test", f"element vertex {count or N}"]
    header += [f"property float {name}" for name in names] + ["end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode())
        if fmt == "ascii":
            for i in range(N):
                f.write((" ".join(repr(float(cols[k][i])) for k in names) + "\n").encode())
        else:
            order = "<" if fmt == "binary_little_endian" else ">"
            rows = np.empty(N, np.dtype([(k, f"{order}f4") for k in names]))
            for k in names:
                rows[k] = cols[k]
            f.write(rows.tobytes())
    return path


def expected_map(cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    def stack(names):
        return np.stack([cols[n].astype(np.float64) for n in names], axis=1)

    q = stack([f"rot_{k}" for k in range(4)])
    return {
        "means": stack(["x", "y", "z"]),
        "scales": np.exp(stack([f"scale_{k}" for k in range(3)])),
        "quats": q / np.linalg.norm(q, axis=1, keepdims=True),
        "opacities": 1.0 / (1.0 + np.exp(-cols["opacity"].astype(np.float64))),
        "colors": np.clip(0.5 + SH_C0 * stack(["f_dc_0", "f_dc_1", "f_dc_2"]), 0, 1),
    }


def assert_map(gmap: GaussianMap, cols: dict[str, np.ndarray]) -> None:
    for name, want in expected_map(cols).items():
        np.testing.assert_allclose(getattr(gmap, name), want, rtol=1e-5, atol=1e-6, err_msg=name)


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_every_encoding_and_any_property_order(tmp_path, fmt):
    cols = raw_columns()
    names = list(cols)
    shuffled = {names[i]: cols[names[i]] for i in np.random.default_rng(1).permutation(len(names))}
    assert list(shuffled) != list(cols)
    gmap = load_ply(write_ply(tmp_path / "map.ply", shuffled, fmt))
    assert len(gmap) == N and gmap.ids is None and gmap.semantics is None
    assert_map(gmap, cols)


@pytest.mark.parametrize("degree,rest", [(0, 0), (1, 9), (2, 24), (3, 45)])
def test_sh_degrees_0_to_3(tmp_path, degree, rest):
    cols = raw_columns(rest=rest)
    gmap = load_ply(write_ply(tmp_path / f"sh{degree}.ply", cols))
    assert_map(gmap, cols)
    if rest:
        np.testing.assert_array_equal(gmap.extra["f_rest"], np.stack([cols[f"f_rest_{k}"] for k in range(rest)], 1))
    else:
        assert "f_rest" not in gmap.extra


def test_semantics_fields_are_read(tmp_path):
    cols = raw_columns(semantics=True)
    gmap = load_ply(write_ply(tmp_path / "sem.ply", cols))
    want = np.stack([cols[f"semantics_{k}"] for k in range(3)], 1)
    np.testing.assert_allclose(gmap.semantics, want)


def test_save_load_round_trip_is_exact(tmp_path):
    gmap = load_ply(write_ply(tmp_path / "in.ply", raw_columns(rest=9)))
    with_ids = GaussianMap(
        means=gmap.means,
        scales=gmap.scales,
        quats=gmap.quats,
        opacities=gmap.opacities,
        colors=gmap.colors,
        ids=np.arange(N, dtype=np.int64) * 7 + 3,
        extra=gmap.extra,
    )
    save_ply(tmp_path / "out.ply", with_ids)
    back = load_ply(tmp_path / "out.ply")
    np.testing.assert_array_equal(back.means, with_ids.means)
    np.testing.assert_array_equal(back.quats, with_ids.quats)
    np.testing.assert_array_equal(back.ids, with_ids.ids)
    np.testing.assert_array_equal(back.extra["f_rest"], with_ids.extra["f_rest"])
    np.testing.assert_allclose(back.scales, with_ids.scales, rtol=1e-6)
    np.testing.assert_allclose(back.opacities, with_ids.opacities, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(back.colors, with_ids.colors, atol=1e-6)


def test_errors_name_the_file_and_the_problem(tmp_path):
    cols = raw_columns()
    missing = {k: v for k, v in cols.items() if k not in ("opacity", "rot_2")}
    with pytest.raises(PlyError, match=r"missing.ply: not a Gaussian map, missing vertex properties.*opacity.*rot_2"):
        load_ply(write_ply(tmp_path / "missing.ply", missing))
    with pytest.raises(PlyError, match="truncated.ply: truncated"):
        load_ply(write_ply(tmp_path / "truncated.ply", cols, count=N + 5))
    with pytest.raises(PlyError, match="truncated_ascii.ply: truncated"):
        load_ply(write_ply(tmp_path / "truncated_ascii.ply", cols, "ascii", count=N + 1))
    (tmp_path / "text.ply").write_text("hello\n")
    with pytest.raises(PlyError, match="text.ply: not a PLY file"):
        load_ply(tmp_path / "text.ply")
    (tmp_path / "open.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n")
    with pytest.raises(PlyError, match="open.ply: header ends before 'end_header'"):
        load_ply(tmp_path / "open.ply")
    bad_rest = raw_columns(rest=10)
    with pytest.raises(PlyError, match="bad_rest.ply: 10 f_rest fields match no SH degree"):
        load_ply(write_ply(tmp_path / "bad_rest.ply", bad_rest))
    zero_rot = {**cols, **{f"rot_{k}": np.zeros(N, np.float32) for k in range(4)}}
    with pytest.raises(PlyError, match="zero_rot.ply: 50 Gaussians have a zero or non-finite rotation"):
        load_ply(write_ply(tmp_path / "zero_rot.ply", zero_rot))
    with pytest.raises(PlyError, match="absent.ply: cannot open"):
        load_ply(tmp_path / "absent.ply")
