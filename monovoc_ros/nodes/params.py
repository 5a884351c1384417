"""The parameters of the `semantic_mapper` node: one table of names, defaults and meanings, and their validation.

`PARAMETERS` is the single source of truth: the node declares exactly these, `config/semantic_mapper.yaml`
lists them with the same defaults (a test checks it), and `NodeParams.from_values` turns a name -> value
dict into a checked `NodeParams` with the core configurations (MapperConfig, IngestConfig). Invalid values
raise `ParameterError` naming the parameter, so the node fails at start with one clear line instead of
misbehaving later.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from monovoc_ros.core.datasets import read_labels
from monovoc_ros.core.mapping import MapperConfig
from monovoc_ros.core.palette import pack_rgb
from monovoc_ros.ingest import IngestConfig

TRANSPORTS = ("raw", "compressed")
RELIABILITIES = ("reliable", "best_effort")


class ParameterError(ValueError):
    """An invalid node parameter; the message starts with the parameter's name."""


@dataclass(frozen=True)
class ParameterSpec:
    name: str
    default: Any
    description: str


# Order = order in config/semantic_mapper.yaml and in the README table.
PARAMETERS: tuple[ParameterSpec, ...] = (
    # Inputs
    ParameterSpec("image_transport", "compressed", "'compressed' (sensor_msgs/CompressedImage) or 'raw' (Image) on `image`"),
    ParameterSpec("mask_transport", "compressed", "'compressed' (CompressedImage, PNG) or 'raw' (Image rgb8/mono8/mono16) on `mask`"),
    ParameterSpec("pose_type", "pose", "message on `pose`: 'pose' (PoseStamped), 'odometry' (Odometry), 'transform' (TransformStamped)"),
    ParameterSpec("frame_convention", "optical", "pose of the camera optical frame ('optical') or of a REP-103 body frame ('body')"),
    ParameterSpec("sync_tolerance_s", 0.02, "max stamp difference (s) between a mask and its image / camera_info / pose"),
    ParameterSpec("sync_max_pending", 32, "messages buffered per input stream while waiting for their partners"),
    ParameterSpec("reorder_wait_s", 3.0, "max time a message waits for the other topics so all reach the synchronizer in stamp order"),
    ParameterSpec("max_stamp_lead_s", 30.0, "stamps further ahead of every other input topic are rejected (stamp_future); 0 = off"),
    ParameterSpec("use_image", True, "subscribe to `image` (RGB is only needed by object views; SCD needs mask + pose)"),
    ParameterSpec("rectified", False, "CameraInfo describes rectified images: use P instead of K"),
    ParameterSpec("allow_distortion", False, "accept CameraInfo with non-zero distortion (ignored: pinhole rendering)"),
    ParameterSpec("input_reliability", "reliable", "QoS reliability of the keyframe inputs: 'reliable' or 'best_effort'"),
    ParameterSpec("input_depth", 100, "QoS history depth of the keyframe input subscriptions"),
    ParameterSpec("map_ply", "", "3DGS PLY loaded as the Gaussian map at start (empty: wait for `gaussians`)"),
    # Processing
    ParameterSpec("impl", "numba", "SCD rasterizer implementation: 'numba', 'torch' or 'reference'"),
    ParameterSpec("device", "", "torch device when impl is 'torch' (e.g. 'cuda'); empty = default"),
    ParameterSpec("metric", "cmc", "palette quantization color distance: cmc, ciede2000, cie94, cam16ucs, din99o, rgb"),
    ParameterSpec("void_policy", "skip", "white (void) mask pixels: 'skip' (no evidence) or 'include' (white is a color)"),
    ParameterSpec("semantic_mode", "vote", "per-Gaussian evidence: 'vote' (per-object weighted votes) or 'scd' (the paper's color deblending + palette quantization)"),
    ParameterSpec("weight_power", 4, "exponent k of the evidence weights w^k: 1 = the paper's SCD, 4 = fewest boundary errors (1..4)"),
    ParameterSpec("vote_slots", 4, "vote mode: objects kept per Gaussian (exact up to this many; the rest pooled) (1..16)"),
    ParameterSpec("min_snap_margin", 0.5, "vote mode: non-palette mask colors snap to the nearest palette color when (d2 - d1) / (d2 + d1) >= this, else no evidence"),
    ParameterSpec("association_scale", 2, "per_frame: the map is rendered at 1/this of the mask resolution to associate segments (1 = full: slower, more exact under noisy segments)"),
    ParameterSpec("mask_ids", "global", "mask ids: 'global' (a color names the same object in every mask) or 'per_frame' (segmenter ids per image, associated with the map's objects; vote mode)"),
    ParameterSpec("reassociation_tolerance", 0.01, "map updates without ids: max distance (m) for evidence to follow a Gaussian"),
    ParameterSpec("map_update_max_shrink", 0.5, "map updates removing a larger share of the Gaussians are refused (counted); 1 = allow all"),
    ParameterSpec("queue_size", 100, "keyframes waiting for the worker (~1.3 MB each at 616x344 with RGB); when full the oldest is dropped (counted)"),
    # Outputs
    ParameterSpec("frame_id", "map", "frame of the semantic cloud, markers and objects (the SLAM map frame)"),
    ParameterSpec("publish_rate_hz", 1.0, "max rate of semantic cloud / objects updates; 0 = whenever the queue is empty"),
    ParameterSpec("labels_file", "", "JSON list [{color: [r, g, b], class_name: ...}] naming objects (empty: no labels)"),
    ParameterSpec("labels_define_palette", False, "vote mode: labels_file's colors are the objects; every mask pixel is one of them or snaps to one (lossy masks)"),
    ParameterSpec("marker_up", [0.0, 0.0, 1.0], "up direction of the map frame, for marker labels ([0, -1, 0] for a y-down SLAM world)"),
    ParameterSpec("diagnostics_period_s", 1.0, "period of /diagnostics messages (s)"),
    # Persistence and services
    ParameterSpec("map_directory", "", "snapshot directory for save_map / load_map defaults, periodic and final saves"),
    ParameterSpec("save_period_s", 30.0, "periodic snapshot when there is new evidence (s); 0 = off"),
    ParameterSpec("resume", False, "start from map_directory's snapshot when it has one"),
    ParameterSpec("service_timeout_s", 60.0, "how long a service waits for its turn on the worker before answering failure"),
)  # fmt: skip

DEFAULTS: dict[str, Any] = {p.name: p.default for p in PARAMETERS}


@dataclass(frozen=True)
class NodeParams:
    ingest: IngestConfig
    mapper: MapperConfig
    image_transport: str
    mask_transport: str
    input_reliability: str
    input_depth: int
    reorder_wait_s: float
    map_ply: str
    map_update_max_shrink: float
    queue_size: int
    frame_id: str
    publish_rate_hz: float
    labels: dict[int, str]  # packed palette color -> class name
    labels_file: str
    marker_up: tuple[float, float, float]
    diagnostics_period_s: float
    map_directory: str
    save_period_s: float
    resume: bool
    service_timeout_s: float

    @classmethod
    def from_values(cls, values: dict[str, Any]) -> NodeParams:
        """Checks every value (unknown names are ignored; missing ones take their defaults)."""
        v = {**DEFAULTS, **{k: values[k] for k in values if k in DEFAULTS}}
        for spec in PARAMETERS:  # integers are welcome where a float is expected (-p save_period_s:=10)
            if isinstance(spec.default, float):
                x = v[spec.name]
                if isinstance(x, bool) or not isinstance(x, (int, float)):
                    raise ParameterError(f"{spec.name}: must be a number, got {x!r}")
                v[spec.name] = float(x)

        def need(ok: bool, name: str, what: str) -> None:
            if not ok:
                raise ParameterError(f"{name}: {what}, got {v[name]!r}")

        def choice(name: str, options: tuple[str, ...]) -> str:
            need(v[name] in options, name, f"must be one of {list(options)}")
            return v[name]

        def positive(name: str, allow_zero: bool = False) -> float:
            x = float(v[name])
            need(
                math.isfinite(x) and (x >= 0 if allow_zero else x > 0),
                name,
                "must be " + (">= 0" if allow_zero else "> 0"),
            )
            return x

        lead = positive("max_stamp_lead_s", allow_zero=True)
        labels = load_labels(str(v["labels_file"]))
        need(
            not (v["labels_define_palette"] and not labels), "labels_define_palette", "needs a labels_file with colors"
        )
        try:
            ingest = IngestConfig(
                pose_type=v["pose_type"],
                frame_convention=v["frame_convention"],
                sync_tolerance_s=float(v["sync_tolerance_s"]),
                use_image=bool(v["use_image"]),
                rectified=bool(v["rectified"]),
                allow_distortion=bool(v["allow_distortion"]),
                max_pending=int(v["sync_max_pending"]),
                max_stamp_lead_s=lead,
            )
            mapper = MapperConfig(
                impl=v["impl"],
                device=v["device"] or None,
                metric=v["metric"],
                void_policy=v["void_policy"],
                reassociation_tolerance=float(v["reassociation_tolerance"]),
                weight_power=v["weight_power"],
                semantic_mode=v["semantic_mode"],
                vote_slots=v["vote_slots"],
                min_snap_margin=float(v["min_snap_margin"]),
                object_colors=tuple(labels) if v["labels_define_palette"] else (),
                mask_ids=v["mask_ids"],
                association_scale=v["association_scale"],
            )
        except ValueError as exc:
            raise ParameterError(str(exc).replace(" must be", ": must be", 1)) from None
        need(math.isfinite(ingest.sync_tolerance_s), "sync_tolerance_s", "must be finite")
        need(ingest.max_pending >= 1, "sync_max_pending", "must be >= 1")
        positive("reassociation_tolerance", allow_zero=True)
        need(int(v["queue_size"]) >= 1, "queue_size", "must be >= 1")
        need(int(v["input_depth"]) >= 1, "input_depth", "must be >= 1")
        need(bool(str(v["frame_id"]).strip()), "frame_id", "must not be empty")
        up = [float(x) for x in v["marker_up"]]
        need(len(up) == 3 and all(map(math.isfinite, up)) and any(up), "marker_up", "must be a non-zero 3-vector")
        shrink = float(v["map_update_max_shrink"])
        need(0.0 <= shrink <= 1.0, "map_update_max_shrink", "must be in [0, 1]")
        map_ply = str(v["map_ply"])
        need(not map_ply or Path(map_ply).is_file(), "map_ply", "file not found")
        map_directory = str(v["map_directory"])
        need(not (v["resume"] and not map_directory), "resume", "needs map_directory to be set")
        need(not map_directory or not Path(map_directory).is_file(), "map_directory", "is a file, not a directory")
        return cls(
            ingest=ingest,
            mapper=mapper,
            image_transport=choice("image_transport", TRANSPORTS),
            mask_transport=choice("mask_transport", TRANSPORTS),
            input_reliability=choice("input_reliability", RELIABILITIES),
            input_depth=int(v["input_depth"]),
            reorder_wait_s=positive("reorder_wait_s", allow_zero=True),
            map_ply=map_ply,
            map_update_max_shrink=shrink,
            queue_size=int(v["queue_size"]),
            frame_id=str(v["frame_id"]),
            publish_rate_hz=positive("publish_rate_hz", allow_zero=True),
            labels=labels,
            labels_file=str(v["labels_file"]),
            marker_up=(up[0], up[1], up[2]),
            diagnostics_period_s=positive("diagnostics_period_s"),
            map_directory=map_directory,
            save_period_s=positive("save_period_s", allow_zero=True),
            resume=bool(v["resume"]),
            service_timeout_s=positive("service_timeout_s"),
        )


def load_labels(path: str) -> dict[int, str]:
    """Object names from a Replica-style labels.json ({color: [r, g, b], class_name}); {} for no file."""
    if not path:
        return {}
    if not Path(path).is_file():
        raise ParameterError(f"labels_file: file not found, got {path!r}")
    try:
        entries = read_labels(path)
        out = {}
        for entry in entries:
            rgb = entry["color"]
            if len(rgb) != 3 or not all(isinstance(c, int) and 0 <= c <= 255 for c in rgb):
                raise ValueError(f"color {rgb!r} is not three integers 0..255")
            out[int(pack_rgb(np.array(rgb, np.uint8)))] = str(entry.get("class_name", ""))
        return out
    except (ValueError, KeyError) as exc:
        raise ParameterError(f"labels_file: {path}: {exc}") from None
