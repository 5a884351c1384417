"""`monovoc map`: keyframes + a Gaussian map -> a semantic map directory."""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path

from monovoc_ros.commands.sources import add_source_options, check_source_options, input_errors, open_source_args
from monovoc_ros.core.evidence.palette import labels_from_entries
from monovoc_ros.core.evidence.quantize import METRICS
from monovoc_ros.core.follow.map_ahead import DEFAULT_AHEAD_S, MAX_AHEAD_S
from monovoc_ros.core.map_store import save_snapshot
from monovoc_ros.core.mapping import SEMANTIC_MODES, VOID_POLICIES, MapperConfig
from monovoc_ros.core.raster import IMPLEMENTATIONS, WEIGHT_POWERS
from monovoc_ros.core.segments.association import MASK_ID_MODES


def add_mapper_options(parser: argparse.ArgumentParser) -> None:
    defaults = MapperConfig()
    parser.add_argument(
        "--impl", choices=IMPLEMENTATIONS, default=defaults.impl, help=f"rasterizer (default {defaults.impl})"
    )
    parser.add_argument("--device", default=defaults.device, help="torch device for --impl torch (e.g. cuda)")
    parser.add_argument(
        "--metric",
        choices=METRICS,
        default=defaults.metric,
        help=f"palette quantization metric (default {defaults.metric})",
    )
    parser.add_argument(
        "--weight-power",
        type=int,
        choices=WEIGHT_POWERS,
        default=defaults.weight_power,
        help=f"exponent k of the evidence weights w^k (1 = the paper's SCD; default {defaults.weight_power})",
    )
    parser.add_argument(
        "--void-policy",
        choices=VOID_POLICIES,
        default=defaults.void_policy,
        help="white (void) mask pixels: skip = no evidence; include = evidence for white "
        f"(default {defaults.void_policy})",
    )
    parser.add_argument(
        "--min-support",
        type=float,
        default=defaults.min_support,
        help="vote mode: a Gaussian keeps its object only where the object's share of its votes, void counted "
        "against it, is at least this times the object's median share; 0 = off, 0.5 for a segmenter's masks "
        f"(default {defaults.min_support})",
    )
    parser.add_argument(
        "--max-depth",
        type=float,
        default=defaults.max_depth_m,
        help="metres of camera depth beyond which Gaussians take no evidence from a keyframe; 0 = no limit "
        f"(default {defaults.max_depth_m:g})",
    )
    parser.add_argument(
        "--min-object-score",
        type=float,
        default=defaults.min_object_score,
        help="vote mode: objects whose segment names add up to less than this are no objects (the fragments "
        f"of a segmenter's unsure masks); 0 = off, 0.5 for a segmenter's masks (default {defaults.min_object_score})",
    )
    parser.add_argument(
        "--semantic-mode",
        choices=SEMANTIC_MODES,
        default=defaults.semantic_mode,
        help=f"vote = per-object weighted votes; scd = the paper's color deblending (default {defaults.semantic_mode})",
    )
    parser.add_argument(
        "--vote-slots",
        type=int,
        default=defaults.vote_slots,
        help=f"objects kept per Gaussian in vote mode (default {defaults.vote_slots})",
    )
    parser.add_argument(
        "--min-snap-margin",
        type=float,
        default=defaults.min_snap_margin,
        help="vote mode: margin below which a non-palette mask color adds no evidence "
        f"(default {defaults.min_snap_margin})",
    )
    parser.add_argument(
        "--palette-from-labels",
        action="store_true",
        help="vote mode: the labels' colors are the objects; every mask pixel is one of them or snaps to one "
        "(for lossy masks, e.g. JPEG)",
    )
    parser.add_argument(
        "--mask-ids",
        choices=[mode.replace("_", "-") for mode in MASK_ID_MODES],
        default=defaults.mask_ids.replace("_", "-"),
        help="global = a mask color names the same object in every keyframe; per-frame = segment ids hold "
        f"for one mask only and are associated with the map's objects (default {defaults.mask_ids})",
    )
    parser.add_argument(
        "--association-scale",
        type=int,
        choices=(1, 2, 3, 4),
        default=defaults.association_scale,
        help="per-frame ids: render the map at 1/N of the mask resolution to associate segments "
        f"(1 = full: slower, more exact under noisy segments; default {defaults.association_scale})",
    )


def _object_index(args: argparse.Namespace, labels: list[dict]):
    """The object index to fill while mapping (None without --objects), named from the source's labels."""
    if not args.objects:
        return None
    from monovoc_ros.objects.index import IndexConfig, ObjectIndex, lazy_backend

    return ObjectIndex(
        lazy_backend("conse"), IndexConfig(crop_mode=args.crop_mode, labels=labels_from_entries(labels) or None)
    )


def mapper_config(args: argparse.Namespace, labels: list[dict] | None = None) -> MapperConfig:
    """The mapper settings of the command line; `labels` (the source's labels.json entries) become the
    known object colors with --palette-from-labels."""
    colors: tuple[int, ...] = ()
    if getattr(args, "palette_from_labels", False):
        if not labels:
            raise SystemExit("monovoc map: --palette-from-labels needs labels (labels.json, or the bag's labels)")
        colors = tuple(labels_from_entries(labels))
    return MapperConfig(
        object_colors=colors,
        impl=args.impl,
        device=args.device,
        metric=args.metric,
        void_policy=args.void_policy,
        weight_power=args.weight_power,
        semantic_mode=args.semantic_mode,
        vote_slots=args.vote_slots,
        min_snap_margin=args.min_snap_margin,
        mask_ids=args.mask_ids.replace("-", "_"),
        association_scale=args.association_scale,
        min_support=args.min_support,
        min_object_score=args.min_object_score,
        max_depth_m=args.max_depth,
    )


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "map",
        help="build a semantic map from keyframes (dataset folder, synthetic scene or bag)",
        description="Runs Semantic Color Deblending over every keyframe, quantizes to the mask palette and "
        "writes a map directory: the snapshot (map, accumulators, palette), semantic.ply (x y z rgb "
        "object_id confidence, for any point-cloud viewer) and summary.json.",
    )
    add_source_options(p)
    add_mapper_options(p)
    p.add_argument("-o", "--out", required=True, help="map directory to write")
    p.add_argument(
        "--objects",
        action="store_true",
        help="also build the object database (objects.db: views, embeddings) as the live node does",
    )
    p.add_argument("--crop-mode", choices=("soft", "hard"), default="soft", help="object crops with --objects")
    p.add_argument(
        "--map-update-ahead-s",
        type=float,
        default=None,
        help="--bag: seconds of stamps after a map update whose keyframes go ahead of it into the map in use, as "
        f"the live node's map_update_ahead_s (docs/map_updates.md; default {DEFAULT_AHEAD_S:g}, the node's); give "
        "the node's value to get its map; 0 = in line",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        return _map(args)
    except input_errors() as exc:
        raise SystemExit(f"monovoc map: {exc}") from None


def _map(args: argparse.Namespace) -> int:
    from monovoc_ros import offline

    if bool(args.source) == bool(args.bag):
        raise SystemExit("monovoc map: give either SOURCE or --bag BAG")
    if args.map_update_ahead_s is not None and not args.bag:
        raise SystemExit("monovoc map: --map-update-ahead-s needs --bag (a dataset folder has one map)")
    ahead_s = DEFAULT_AHEAD_S if args.map_update_ahead_s is None else args.map_update_ahead_s
    if not 0 <= ahead_s <= MAX_AHEAD_S:
        raise SystemExit(f"monovoc map: --map-update-ahead-s must be in [0, {MAX_AHEAD_S:g}], got {ahead_s}")
    check_source_options(args)
    if args.bag:
        from monovoc_ros.bags import bag_labels

        sequence, name, labels = None, Path(args.bag).name, bag_labels(args.bag)
    else:
        sequence = open_source_args(args)
        name, labels = sequence.name, sequence.labels()
    config = mapper_config(args, labels)
    if config.mask_ids == "per_frame":
        labels = []  # a labels file names global mask colors, which per-frame masks do not have
    index = _object_index(args, labels)
    hook = index.keyframe_listener if index is not None else None
    if sequence is None:
        mapper, stats = offline.map_bag(
            args.bag,
            config,
            max_keyframes=args.max_keyframes,
            progress=not args.quiet,
            on_keyframe=hook,
            ahead_s=ahead_s,
        )
    else:
        mapper, stats = offline.map_sequence(
            sequence, config, max_keyframes=args.max_keyframes, progress=not args.quiet, on_keyframe=hook
        )
    snapshot = save_snapshot(mapper, args.out)
    objects_db = None
    if index is not None:
        from monovoc_ros.objects.database import save_object_index

        index.refresh(mapper)  # reads the segmenter's names too (source "segments"; labels.json names win)
        report = save_object_index(
            index, args.out, snapshot=snapshot.path.name, map_version=mapper.map_version, keyframes=mapper.n_keyframes
        )
        objects_db = str(report.path)
    result = mapper.result()
    objects = result.objects(mapper.gaussians).objects
    summary = {
        "source": name,
        **stats.summary(),
        "gaussians": len(mapper.gaussians),
        "observed_gaussians": int(result.observed.sum()),
        "palette_colors": len(result.palette),
        "rejected_palette_colors": len(result.palette.rejected_ids),
        "objects": len(objects),
        "config": asdict(config),
        "snapshot": str(snapshot.path),
        "semantic_ply": str(Path(args.out) / "semantic.ply"),
        "objects_db": objects_db,
    }
    (Path(args.out) / "summary.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1))
    return 0
