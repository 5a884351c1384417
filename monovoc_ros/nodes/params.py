"""The parameters of the `semantic_mapper` node: one specification each (nodes.param_spec), and their validation.

`PARAMETERS` is the single source of truth: the node declares exactly these (with their ranges), their
defaults are those of the core configurations (MapperConfig, IngestConfig) and the worker's settings,
`config/semantic_mapper.yaml` and the README table list them (a test checks both), and
`NodeParams.from_values` turns a name -> value dict into a checked `NodeParams` with the core
configurations. Invalid values raise `ParameterError` naming the parameter, so the node fails at start with
one clear line instead of misbehaving later.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from monovoc_ros.contract import IMAGE_MESSAGE_TYPES, MAP_FRAME
from monovoc_ros.core.evidence.palette import read_labels
from monovoc_ros.core.evidence.quantize import METRICS
from monovoc_ros.core.follow.map_ahead import MAX_AHEAD_S
from monovoc_ros.core.mapping import SEMANTIC_MODES, VOID_POLICIES, MapperConfig
from monovoc_ros.core.raster import IMPLEMENTATIONS, WEIGHT_POWERS
from monovoc_ros.core.segments.association import MASK_ID_MODES
from monovoc_ros.ingest import FRAME_CONVENTIONS, POSE_TYPES, IngestConfig
from monovoc_ros.nodes.interpreter_watch import MIN_HOLD_TRACE_MS
from monovoc_ros.nodes.param_spec import Param, ParameterError, defaults, validate
from monovoc_ros.nodes.worker import WorkerSettings

TRANSPORTS = tuple(IMAGE_MESSAGE_TYPES)
RELIABILITIES = ("reliable", "best_effort")
_INGEST, _MAPPER, _WORKER = IngestConfig(), MapperConfig(), WorkerSettings()

# Order = order in config/semantic_mapper.yaml and in the README table.
PARAMETERS: tuple[Param, ...] = (
    # Inputs
    Param("image_transport", "compressed", "'compressed' (sensor_msgs/CompressedImage) or 'raw' (Image) on `image`", choices=TRANSPORTS),
    Param("mask_transport", "compressed", "'compressed' (CompressedImage, PNG) or 'raw' (Image rgb8/mono8/mono16) on `mask`", choices=TRANSPORTS),
    Param("pose_type", _INGEST.pose_type, "message on `pose`: 'pose' (PoseStamped), 'odometry' (Odometry), 'transform' (TransformStamped)", choices=POSE_TYPES),
    Param("frame_convention", _INGEST.frame_convention, "pose of the camera optical frame ('optical') or of a REP-103 body frame ('body')", choices=FRAME_CONVENTIONS),
    Param("sync_tolerance_s", _INGEST.sync_tolerance_s, "max stamp difference (s) between a mask and its image / camera_info / pose", low=0),
    Param("sync_max_pending", _INGEST.max_pending, "messages buffered per input stream while waiting for their partners", low=1),
    Param("reorder_wait_s", 3.0, "max time a message waits for the other topics so all reach the synchronizer in stamp order", low=0),
    Param("max_stamp_lead_s", _INGEST.max_stamp_lead_s, "stamps further ahead of every other input topic wait until every topic resumes near them (a pause ended) or their own topic shows them outliers (stamp_future); further ahead of the node's clock: refused; 0 = off", low=0),
    Param("use_image", _INGEST.use_image, "subscribe to `image` (RGB is only needed by object views; SCD needs mask + pose)"),
    Param("use_segments", _INGEST.use_segments, "subscribe to `segments` (SegmentArray: class names of the mask's segments); every mask then waits for one of its stamp"),
    Param("rectified", _INGEST.rectified, "CameraInfo describes rectified images: use P instead of K"),
    Param("allow_distortion", _INGEST.allow_distortion, "accept CameraInfo with non-zero distortion (ignored: pinhole rendering)"),
    Param("input_reliability", "reliable", "QoS reliability of the keyframe inputs: 'reliable' or 'best_effort'", choices=RELIABILITIES),
    Param("input_depth", 100, "QoS history depth of the keyframe input subscriptions", low=1),
    Param("map_ply", "", "3DGS PLY loaded as the Gaussian map at start (empty: wait for `gaussians`)"),
    Param("map_reader_process", True, "take and decode `gaussians` in a child process that hands the maps over in shared memory (a 1M-Gaussian map held this process's interpreter 60-130 ms per message, delaying queries); false: in this process"),
    # Processing
    Param("impl", _MAPPER.impl, "SCD rasterizer implementation: 'numba', 'torch' or 'reference'", choices=IMPLEMENTATIONS),
    Param("device", _MAPPER.device or "", "torch device when impl is 'torch' (e.g. 'cuda'); empty = default"),
    Param("metric", _MAPPER.metric, "palette quantization color distance: cmc, ciede2000, cie94, cam16ucs, din99o, rgb", choices=METRICS),
    Param("void_policy", _MAPPER.void_policy, "white (void) mask pixels: 'skip' (no evidence) or 'include' (white is a color)", choices=VOID_POLICIES),
    Param("semantic_mode", _MAPPER.semantic_mode, "per-Gaussian evidence: 'vote' (per-object weighted votes) or 'scd' (the paper's color deblending + palette quantization)", choices=SEMANTIC_MODES),
    Param("weight_power", _MAPPER.weight_power, "exponent k of the evidence weights w^k: 1 = the paper's SCD, 4 = fewest boundary errors (1..4)", choices=WEIGHT_POWERS),
    Param("vote_slots", _MAPPER.vote_slots, "vote mode: objects kept per Gaussian (exact up to this many; the rest pooled) (1..16)", low=1, high=16),
    Param("min_snap_margin", _MAPPER.min_snap_margin, "vote mode: non-palette mask colors snap to the nearest palette color when (d2 - d1) / (d2 + d1) >= this, else no evidence", low=0, high=1),
    Param("association_scale", _MAPPER.association_scale, "per_frame: the map is rendered at 1/this of the mask resolution to associate segments (1 = full: slower, more exact under noisy segments)", low=1, high=4),
    Param("min_support", _MAPPER.min_support, "vote mode: a Gaussian keeps its object only where the object's share of its votes (void pixels counted against it) is at least this times the median share of the object's Gaussians; 0 = off (a segmenter's masks: 0.5)", low=0, high=1),
    Param("max_depth_m", _MAPPER.max_depth_m, "metres of camera depth beyond which Gaussians take no evidence from a keyframe (a depth integrator's range; in a building most of a view lies behind walls); 0 = no limit", low=0),
    Param("min_object_score", _MAPPER.min_object_score, "vote mode: objects whose segment names add up to less than this summed score are no objects (their Gaussians unlabelled): the fragments of a segmenter's unsure masks; objects never named are kept; 0 = off (a segmenter's masks: 0.5)", low=0),
    Param("mask_ids", _MAPPER.mask_ids, "mask ids: 'global' (a color names the same object in every mask) or 'per_frame' (segmenter ids per image, associated with the map's objects; vote mode)", choices=MASK_ID_MODES),
    Param("reassociation_tolerance", _MAPPER.reassociation_tolerance, "map updates: a new Gaussian takes the evidence of the nearest old one (moved with the map) within this (m) plus its own largest scale", low=0),
    Param("reintegrate_below", _MAPPER.reintegrate_below, "a map update carrying the evidence of less than this share of the labelled Gaussians, or bending the map by 2 cm or more, re-integrates the keyframe log (poses moved with the map); 0 = never", low=0, high=1),
    Param("keyframe_log_bytes", _MAPPER.keyframe_log_bytes, "bytes the keyframe log (masks, poses, segments kept for re-integration) may hold; the oldest are dropped beyond", low=0),
    Param("map_update_max_shrink", _WORKER.map_update_max_shrink, "map updates removing a larger share of the Gaussians are refused (counted); 1 = allow all", low=0, high=1),
    Param("map_update_ahead_s", _WORKER.map_update_ahead_s, "seconds of stamps after a map update whose keyframes go into the map in use, their poses taken back by its motion, while its update is prepared (~0.7 s at 1M Gaussians) instead of waiting for it; the update is applied before the first keyframe stamped later (offline mapping applies the same rule, monovoc map --map-update-ahead-s); 0 = they wait (in line)", low=0, high=MAX_AHEAD_S),
    Param("queue_size", _WORKER.queue_size, "keyframes waiting for the worker (~1.3 MB each at 616x344 with RGB); when full the oldest is dropped (counted)", low=1),
    # Outputs
    Param("frame_id", MAP_FRAME, "frame of the semantic cloud, markers and objects (the SLAM map frame)"),
    Param("publish_rate_hz", 1.0 / _WORKER.publish_period_s, "max rate of semantic cloud / objects updates; 0 = whenever the queue is empty, and about once a second while it never is", low=0),
    Param("labels_file", "", "JSON list [{color: [r, g, b], class_name: ...}] naming objects (empty: no labels)"),
    Param("labels_define_palette", False, "vote mode: labels_file's colors are the objects; every mask pixel is one of them or snaps to one (lossy masks)"),
    Param("marker_up", [0.0, 0.0, 1.0], "up direction of the map frame, for marker labels ([0, -1, 0] for a y-down SLAM world)"),
    Param("diagnostics_period_s", 1.0, "period of /diagnostics messages (s)", above=0),
    Param("interpreter_hold_trace_ms", 0.0, "whenever the Python interpreter is held longer than this (ms), every thread's stack is written to monovoc_interpreter_holds_<pid>.txt in the ROS log directory: what kept queries and keyframes waiting (0 = off; at least 20)", low=0),
    # Persistence and services
    Param("map_directory", _WORKER.map_directory, "snapshot directory for save_map / load_map defaults, periodic and final saves"),
    Param("save_period_s", _WORKER.save_period_s, "periodic snapshot when there is new evidence (s); 0 = off", low=0),
    Param("resume", False, "start from map_directory's snapshot when it has one"),
    Param("shutdown_timeout_s", 4.0, "on SIGINT/SIGTERM, the node exits about this long after the signal (s; ros2 launch sends SIGTERM at 5 s): queued keyframes are integrated while the final snapshot and the stop of the node's components still fit; the rest are saved with the snapshot and integrated on resume", low=0),
    Param("service_timeout_s", 60.0, "how long a service waits for its turn on the worker before answering failure", above=0),
)  # fmt: skip

DEFAULTS: dict[str, Any] = defaults(PARAMETERS)


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
    map_reader_process: bool
    map_update_max_shrink: float
    map_update_ahead_s: float
    queue_size: int
    frame_id: str
    publish_rate_hz: float
    labels: dict[int, str]  # packed palette color -> class name
    labels_file: str
    marker_up: tuple[float, float, float]
    diagnostics_period_s: float
    interpreter_hold_trace_ms: float
    map_directory: str
    save_period_s: float
    resume: bool
    shutdown_timeout_s: float
    service_timeout_s: float

    @classmethod
    def from_values(cls, values: dict[str, Any]) -> NodeParams:
        """Checks every value (unknown names are ignored; missing ones take their defaults)."""
        v = validate(PARAMETERS, values)

        def need(ok: bool, name: str, what: str) -> None:
            if not ok:
                raise ParameterError(f"{name}: {what}, got {v[name]!r}")

        labels = load_labels(v["labels_file"])
        need(
            not (v["labels_define_palette"] and not labels), "labels_define_palette", "needs a labels_file with colors"
        )
        try:
            ingest = IngestConfig(
                pose_type=v["pose_type"],
                frame_convention=v["frame_convention"],
                sync_tolerance_s=v["sync_tolerance_s"],
                use_image=v["use_image"],
                use_segments=v["use_segments"],
                rectified=v["rectified"],
                allow_distortion=v["allow_distortion"],
                max_pending=v["sync_max_pending"],
                max_stamp_lead_s=v["max_stamp_lead_s"],
            )
            mapper = MapperConfig(
                impl=v["impl"],
                device=v["device"] or None,
                metric=v["metric"],
                void_policy=v["void_policy"],
                reassociation_tolerance=v["reassociation_tolerance"],
                reintegrate_below=v["reintegrate_below"],
                keyframe_log_bytes=v["keyframe_log_bytes"],
                weight_power=v["weight_power"],
                semantic_mode=v["semantic_mode"],
                vote_slots=v["vote_slots"],
                min_snap_margin=v["min_snap_margin"],
                object_colors=tuple(labels) if v["labels_define_palette"] else (),
                mask_ids=v["mask_ids"],
                association_scale=v["association_scale"],
                min_support=v["min_support"],
                min_object_score=v["min_object_score"],
                max_depth_m=v["max_depth_m"],
            )
        except ValueError as exc:  # the settings that only fail together (e.g. per_frame ids in scd mode)
            raise ParameterError(str(exc).replace(" must be", ": must be", 1)) from None
        need(bool(v["frame_id"].strip()), "frame_id", "must not be empty")
        trace_ms = v["interpreter_hold_trace_ms"]
        need(
            trace_ms == 0 or trace_ms >= MIN_HOLD_TRACE_MS,
            "interpreter_hold_trace_ms",
            f"must be 0 or >= {MIN_HOLD_TRACE_MS:g}",
        )
        up = v["marker_up"]
        need(len(up) == 3 and any(up), "marker_up", "must be a non-zero 3-vector")
        need(not v["map_ply"] or Path(v["map_ply"]).is_file(), "map_ply", "file not found")
        map_directory = v["map_directory"]
        need(not (v["resume"] and not map_directory), "resume", "needs map_directory to be set")
        need(not map_directory or not Path(map_directory).is_file(), "map_directory", "is a file, not a directory")
        return cls(
            ingest=ingest,
            mapper=mapper,
            image_transport=v["image_transport"],
            mask_transport=v["mask_transport"],
            input_reliability=v["input_reliability"],
            input_depth=v["input_depth"],
            reorder_wait_s=v["reorder_wait_s"],
            map_ply=v["map_ply"],
            map_reader_process=v["map_reader_process"],
            map_update_max_shrink=v["map_update_max_shrink"],
            map_update_ahead_s=v["map_update_ahead_s"],
            queue_size=v["queue_size"],
            frame_id=v["frame_id"],
            publish_rate_hz=v["publish_rate_hz"],
            labels=labels,
            labels_file=v["labels_file"],
            marker_up=(up[0], up[1], up[2]),
            diagnostics_period_s=v["diagnostics_period_s"],
            interpreter_hold_trace_ms=v["interpreter_hold_trace_ms"],
            map_directory=map_directory,
            save_period_s=v["save_period_s"],
            resume=v["resume"],
            shutdown_timeout_s=v["shutdown_timeout_s"],
            service_timeout_s=v["service_timeout_s"],
        )


def load_labels(path: str) -> dict[int, str]:
    """labels_file: object id -> class name ("" for an unnamed color); {} for no file."""
    if not path:
        return {}
    if not Path(path).is_file():
        raise ParameterError(f"labels_file: file not found, got {path!r}")
    try:
        return read_labels(path)
    except ValueError as exc:
        raise ParameterError(f"labels_file: {exc}") from None
