"""PLY files: standard 3DGS Gaussian maps (read and write) and any PLY's vertex table (read and write; the
semantic point cloud of a map directory is core.map_store's).

Gaussian PLYs follow the graphdeco-inria convention (METHOD.md section 1): float vertex properties
`x y z [nx ny nz] f_dc_0..2 [f_rest_*] opacity scale_0..2 rot_0..3` with `rot_0` = w, opacity as a
logit and scales as logs. Optional: `semantics_0..2` (HI-SLAM2's semantic branch) and `id` (a stable
per-Gaussian id from the SLAM front-end). Properties are found by name in any order; binary little
endian, binary big endian and ASCII bodies are read.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from monovoc_ros.core.map.gaussians import GaussianMap

SH_C0 = 0.28209479177387814

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_NUMPY_TO_PLY = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int",
                 "u4": "uint", "f4": "float", "f8": "double"}  # fmt: skip
_REQUIRED = ["x", "y", "z", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
_REST_COUNTS = {0: 0, 9: 1, 24: 2, 45: 3}  # number of f_rest fields -> SH degree


class PlyError(ValueError):
    """A PLY file that cannot be read as what was asked; the message names the file."""


_MAX_HEADER_LINE = 4096  # bytes: a longer "header line" is binary garbage, not a PLY header
_MAX_HEADER_LINES = 100_000


def _parse_header(path: Path, fh) -> tuple[str, list[tuple[str, int, list[tuple[str, str]]]]]:
    if fh.readline(16).strip() != b"ply":
        raise PlyError(f"{path}: not a PLY file (missing 'ply' magic)")
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for _ in range(_MAX_HEADER_LINES):
        raw = fh.readline(_MAX_HEADER_LINE + 1)
        if not raw:
            raise PlyError(f"{path}: header ends before 'end_header'")
        if len(raw) > _MAX_HEADER_LINE:
            raise PlyError(f"{path}: header line longer than {_MAX_HEADER_LINE} bytes (not a PLY header)")
        words = raw.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            try:
                count = int(words[2])
            except ValueError:
                raise PlyError(f"{path}: bad element line {raw!r}") from None
            if count < 0:
                raise PlyError(f"{path}: element {words[1]!r} has a negative count {count}")
            elements.append((words[1], count, []))
        elif words[0] == "property" and elements:
            if len(words) == 5 and words[1] == "list":
                elements[-1][2].append((words[-1], "list"))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise PlyError(f"{path}: bad property line {raw!r}")
        else:
            raise PlyError(f"{path}: unexpected header line {raw!r}")
    else:
        raise PlyError(f"{path}: more than {_MAX_HEADER_LINES} header lines")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise PlyError(f"{path}: unsupported format {fmt!r}")
    return fmt, elements


def read_ply_vertices(path: str | os.PathLike) -> np.ndarray:
    """The `vertex` element of a PLY file as a structured array (native byte order).

    The header's vertex count is checked against the file's size before anything is read, so a header
    that claims 10^12 vertices is a PlyError, not an allocation.
    """
    path = Path(path)
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise PlyError(f"{path}: cannot open ({exc.strerror})") from exc
    with fh:
        fmt, elements = _parse_header(path, fh)
        if not elements or elements[0][0] != "vertex":
            raise PlyError(f"{path}: the first element must be 'vertex', got {[e[0] for e in elements]}")
        _, count, props = elements[0]
        if not props:
            raise PlyError(f"{path}: the 'vertex' element has no properties")
        if any(kind == "list" for _, kind in props):
            raise PlyError(f"{path}: list properties in 'vertex' are not supported")
        names = [name for name, _ in props]
        if len(set(names)) != len(names):
            raise PlyError(f"{path}: duplicate vertex property names")
        body = os.fstat(fh.fileno()).st_size - fh.tell()  # bytes after the header
        if fmt == "ascii":
            # Every value takes at least one digit and one separator.
            if count * 2 * len(props) > body:
                raise PlyError(
                    f"{path}: truncated: {count} vertices of {len(props)} values declared, the body has {body} bytes"
                )
            dtype = np.dtype([(name, kind) for name, kind in props])
            rows = []
            for i in range(count):
                line = fh.readline()
                if not line:
                    raise PlyError(f"{path}: truncated: {count} vertices declared, {i} found")
                rows.append(line.split())
            try:
                table = np.array(rows, dtype=np.float64)
            except ValueError:
                raise PlyError(f"{path}: malformed ASCII vertex rows") from None
            if count and (table.ndim != 2 or table.shape[1] != len(props)):
                raise PlyError(f"{path}: ASCII vertex rows do not have {len(props)} values each")
            out = np.empty(count, dtype=dtype)
            for j, name in enumerate(names):
                out[name] = table[:, j] if count else []
            return out
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(name, order + kind) for name, kind in props])
        if dtype.itemsize * count > body:
            raise PlyError(
                f"{path}: truncated: {count} vertices of {dtype.itemsize} bytes declared, {body} bytes present"
            )
        data = fh.read(dtype.itemsize * count)
        if len(data) < dtype.itemsize * count:
            raise PlyError(
                f"{path}: truncated: {count} vertices of {dtype.itemsize} bytes declared, {len(data)} bytes present"
            )
        return np.frombuffer(data, dtype=dtype).astype(dtype.newbyteorder("="))


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x.astype(np.float64)))


def load_ply(path: str | os.PathLike) -> GaussianMap:
    """A 3DGS PLY as a GaussianMap with activated values (see module docstring).

    Every malformed file raises one PlyError naming the file and the problem; NaN/inf values (and
    log-scales whose exponential overflows) are rejected as on the Gaussian PointCloud2 path.
    """
    try:
        return _load_ply(path)
    except PlyError:
        raise
    except Exception as exc:  # one error type for every malformed file
        raise PlyError(f"{path}: unreadable Gaussian PLY ({type(exc).__name__}: {exc})") from exc


def _load_ply(path: str | os.PathLike) -> GaussianMap:
    v = read_ply_vertices(path)
    names = set(v.dtype.names)
    missing = [n for n in _REQUIRED if n not in names]
    if missing:
        raise PlyError(f"{path}: not a Gaussian map, missing vertex properties {missing}")

    def stack(fields: list[str], what: str) -> np.ndarray:
        out = np.stack([v[f].astype(np.float64) for f in fields], axis=1)
        bad = ~np.isfinite(out)
        if bad.any():
            rows, cols = np.nonzero(bad)
            raise PlyError(
                f"{path}: {rows.size} NaN/inf values in {what} properties "
                f"{sorted({fields[c] for c in cols})} (first at vertex {rows[0]})"
            )
        return out

    rest_names = [n for n in names if n.startswith("f_rest_")]
    malformed = sorted(n for n in rest_names if not n[7:].isdigit())
    if malformed:
        raise PlyError(f"{path}: malformed f_rest property names {malformed}")
    rest = sorted(rest_names, key=lambda n: int(n[7:]))
    if len(rest) not in _REST_COUNTS or rest != [f"f_rest_{k}" for k in range(len(rest))]:
        raise PlyError(f"{path}: {len(rest)} f_rest fields match no SH degree 0..3 (f_rest_0..f_rest_8/23/44)")
    quats = stack(["rot_0", "rot_1", "rot_2", "rot_3"], "rotation")
    with np.errstate(over="ignore"):  # a huge component is a valid direction, not an error
        bad = ~np.isfinite(np.linalg.norm(quats, axis=1)) | (np.linalg.norm(quats, axis=1) == 0)
    if bad.any():
        raise PlyError(f"{path}: {int(bad.sum())} Gaussians have a zero or non-finite rotation")
    means = stack(["x", "y", "z"], "position")
    log_scales = stack(["scale_0", "scale_1", "scale_2"], "scale")
    if log_scales.size and log_scales.max() > 80.0:  # exp overflows float32: not a log-scale of a real map
        raise PlyError(f"{path}: log-scale {log_scales.max():g} is not finite once activated")
    opacity = stack(["opacity"], "opacity")[:, 0]
    colors = None
    if {"f_dc_0", "f_dc_1", "f_dc_2"} <= names:
        colors = np.clip(0.5 + SH_C0 * stack(["f_dc_0", "f_dc_1", "f_dc_2"], "color"), 0.0, 1.0)
    semantics = None
    if {"semantics_0", "semantics_1", "semantics_2"} <= names:
        semantics = stack(["semantics_0", "semantics_1", "semantics_2"], "semantics")
    ids = None
    if "id" in names:
        raw_ids = v["id"]
        if raw_ids.dtype.kind == "f" and (not np.isfinite(raw_ids).all() or np.any(raw_ids != np.round(raw_ids))):
            raise PlyError(f"{path}: property 'id' holds non-integer values")
        ids = raw_ids.astype(np.int64)
    extra = {"f_rest": stack(rest, "f_rest").astype(np.float32)} if rest else {}
    try:
        return GaussianMap(
            means=means,
            scales=np.exp(log_scales),
            quats=quats,
            opacities=_sigmoid(opacity),
            colors=colors,
            ids=ids,
            semantics=semantics,
            extra=extra,
        )
    except ValueError as exc:
        raise PlyError(f"{path}: {exc}") from exc


def write_ply_vertices(path: Path, columns: dict[str, np.ndarray], comment: str = "") -> None:
    """Binary little-endian PLY with one vertex element; written to a temp file then renamed."""
    n = len(next(iter(columns.values())))
    dtype = np.dtype([(name, "<" + col.dtype.str[1:]) for name, col in columns.items()])
    table = np.empty(n, dtype=dtype)
    for name, col in columns.items():
        table[name] = col
    header = ["ply", "format binary_little_endian 1.0"]
    if comment:
        header.append(f"comment {comment}")
    header.append(f"element vertex {n}")
    header += [f"property {_NUMPY_TO_PLY[dtype[name].str[1:]]} {name}" for name in columns]
    header.append("end_header")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(table.tobytes())
    os.replace(tmp, path)


def save_ply(path: str | os.PathLike, gmap: GaussianMap) -> None:
    """Writes a GaussianMap as a standard 3DGS PLY (inverse activations, SH degree from f_rest)."""
    f32 = np.float32
    cols: dict[str, np.ndarray] = {
        "x": gmap.means[:, 0], "y": gmap.means[:, 1], "z": gmap.means[:, 2],
        "nx": np.zeros(len(gmap), f32), "ny": np.zeros(len(gmap), f32), "nz": np.zeros(len(gmap), f32),
    }  # fmt: skip
    colors = gmap.colors if gmap.colors is not None else np.full((len(gmap), 3), 0.5, f32)
    f_dc = (colors.astype(np.float64) - 0.5) / SH_C0
    for k in range(3):
        cols[f"f_dc_{k}"] = f_dc[:, k].astype(f32)
    rest = gmap.extra.get("f_rest")
    if rest is not None:
        for k in range(rest.shape[1]):
            cols[f"f_rest_{k}"] = rest[:, k].astype(f32)
    o = np.clip(gmap.opacities.astype(np.float64), 1e-7, 1 - 1e-7)
    cols["opacity"] = np.log(o / (1 - o)).astype(f32)
    log_s = np.log(gmap.scales.astype(np.float64))
    for k in range(3):
        cols[f"scale_{k}"] = log_s[:, k].astype(f32)
    for k in range(4):
        cols[f"rot_{k}"] = gmap.quats[:, k]
    if gmap.semantics is not None:
        for k in range(3):
            cols[f"semantics_{k}"] = gmap.semantics[:, k]
    if gmap.ids is not None:
        if gmap.ids.min(initial=0) < 0 or gmap.ids.max(initial=0) > np.iinfo(np.uint32).max:
            raise ValueError(f"{path}: Gaussian ids must fit in uint32 to be written to PLY")
        cols["id"] = gmap.ids.astype(np.uint32)
    write_ply_vertices(Path(path), cols)
