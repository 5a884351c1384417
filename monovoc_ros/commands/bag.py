"""`monovoc bag convert | info | make-bundled`: dataset sequences to MCAP bags, and what a bag holds."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from monovoc_ros.commands.argument_types import at_least, ros_namespace
from monovoc_ros.commands.sources import SOURCE_HELP, add_segment_names_option, add_sequence_options, open_source_args
from monovoc_ros.contract import DEFAULT_NAMESPACE


def register(subparsers) -> None:
    p = subparsers.add_parser("bag", help="convert datasets to MCAP bags, show bag contents, rebuild bundled bags")
    sub = p.add_subparsers(dest="bag_command", required=True, metavar="BAG_COMMAND")

    c = sub.add_parser(
        "convert",
        help="write a dataset sequence or a synthetic scene as a ROS 2 MCAP bag",
        description="Writes the Gaussian map (once, before the first keyframe) and per keyframe pose, "
        "camera_info, image and mask under /monovoc (topics: docs/interfaces.md), the segment class names "
        "(segments, when the source has them) and the palette labels as metadata. Deterministic: the same "
        "input gives the same file.",
    )
    c.add_argument("source", help=SOURCE_HELP)
    c.add_argument("-o", "--out", required=True, help="output .mcap file")
    add_sequence_options(c, "the bag holds only the corrupted masks: map a shuffled one with --mask-ids per-frame")
    add_segment_names_option(c)  # a segments topic (SegmentArray per mask) then; also from segments/*.json
    c.add_argument("--rgb-format", choices=("jpeg", "png", "raw"), default="jpeg", help="image topic (default jpeg)")
    c.add_argument(
        "--mask-format",
        choices=("png", "raw", "none"),
        default="png",
        help="mask topic (default png); none: no masks and no segments, a camera-only bag for segmenter:=true",
    )
    c.add_argument("--jpeg-quality", type=at_least(1, 100), default=95)
    c.add_argument("--namespace", type=ros_namespace, default=DEFAULT_NAMESPACE)
    c.add_argument("--no-map", action="store_true", help="leave the Gaussian map out")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    c.set_defaults(func=run_convert)

    i = sub.add_parser("info", help="topics, types, counts, duration and metadata of a bag")
    i.add_argument("bag")
    i.add_argument("--json", action="store_true", help="print JSON")
    i.set_defaults(func=run_info)

    m = sub.add_parser(
        "make-bundled",
        help="regenerate the bundled bags in bags/ (deterministic)",
        description="Writes bags/synthetic_room.mcap (the default synthetic scene). With --replica also "
        "bags/replica_office0.mcap from the Replica office_0 plain folder: research-only data, so that bag "
        "is git-ignored and made on demand, never committed.",
    )
    m.add_argument(
        "--replica",
        nargs="?",
        const="",
        default=None,
        metavar="PATH",
        help="also write replica_office0.mcap (from PATH, default ../shared/data/replica_office0)",
    )
    m.add_argument("--no-synthetic", action="store_true", help="skip synthetic_room.mcap")
    m.add_argument(
        "--per-frame",
        action="store_true",
        help="also write synthetic_room_per_frame.mcap (a small room, every mask renumbered: mask_ids per_frame)",
    )
    m.add_argument("--out-dir", default=None, help="output folder (default: the repository's bags/)")
    m.add_argument("--quiet", action="store_true", help="no progress bar")
    m.set_defaults(func=run_make_bundled)


def run_convert(args: argparse.Namespace) -> int:
    from monovoc_ros.bags.convert import sequence_to_bag
    from monovoc_ros.core.evaluation.datasets import SequenceError

    try:
        sequence = open_source_args(args)
        report = sequence_to_bag(
            sequence,
            args.out,
            rgb_format=args.rgb_format,
            mask_format=args.mask_format,
            jpeg_quality=args.jpeg_quality,
            max_keyframes=args.max_keyframes,
            namespace=args.namespace,
            include_map=not args.no_map,
            progress=not args.quiet,
        )
    except (SequenceError, ValueError) as exc:
        print(f"monovoc bag convert: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(report.summary(), indent=1))
    return 0


def run_info(args: argparse.Namespace) -> int:
    from monovoc_ros.bags.reader import BagError, bag_info

    try:
        info = bag_info(args.bag)
    except BagError as exc:
        print(f"monovoc bag info: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(info.as_dict(), indent=1))
        return 0
    print(f"file:       {info.path} ({info.size_bytes / 1e6:.2f} MB, {info.profile}, {info.library})")
    print(f"messages:   {info.message_count} in {info.duration_s:.3f} s (compression: {', '.join(info.compression)})")
    if not info.finished:
        print("unfinished: no summary (the recording stopped or the file was cut); complete messages found by a scan")
    if info.start_ns is not None:
        print(f"time:       {info.start_ns / 1e9:.9f} .. {info.end_ns / 1e9:.9f}")
    print("topics:")
    width = max((len(t) for t in info.topics), default=0)
    for t in info.topics.values():
        latched = "  transient-local" if t.transient_local else ""
        print(f"  {t.name:<{width}}  {t.count:>6}  {t.type_name}{latched}")
    for name, values in info.metadata.items():
        text = values.get("json")
        detail = f"{len(json.loads(text))} entries" if text and name == "monovoc_labels" else ", ".join(values)
        print(f"metadata:   {name} ({detail})")
    return 0


def run_make_bundled(args: argparse.Namespace) -> int:
    from monovoc_ros.bags import bundled
    from monovoc_ros.core.evaluation.datasets import SequenceError

    out_dir = Path(args.out_dir) if args.out_dir else bundled.BUNDLED_DIR
    reports = []
    try:
        if not args.no_synthetic:
            reports.append(bundled.make_synthetic_bag(out_dir, progress=not args.quiet))
        if args.per_frame:
            reports.append(bundled.make_per_frame_bag(out_dir, progress=not args.quiet))
        if args.replica is not None:
            source = args.replica or bundled.DEFAULT_REPLICA_SOURCE
            reports.append(bundled.make_replica_bag(source, out_dir, progress=not args.quiet))
    except (SequenceError, ValueError) as exc:
        print(f"monovoc bag make-bundled: {exc}", file=sys.stderr)
        return 1
    print(json.dumps([r.summary() for r in reports], indent=1))
    return 0
