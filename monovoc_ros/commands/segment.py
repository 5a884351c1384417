"""`monovoc segment SEQ_DIR -o OUT_DIR`: a sequence's RGB keyframes through the segmenter, written as a
plain-layout copy whose masks are the segmenter's per-frame instances (for `monovoc map --mask-ids per-frame`)."""

from __future__ import annotations

import argparse
import json
from dataclasses import fields

from monovoc_ros.core.evaluation.datasets import SequenceError, open_sequence
from monovoc_ros.segment.backend import BACKENDS, SegmenterModelError, load_segmenter
from monovoc_ros.segment.model_files import CHECKPOINTS, DEFAULT_MODEL
from monovoc_ros.segment.options import OPTION_SPECS, SegmenterOptions, option_defaults


def add_segmenter_options(parser: argparse.ArgumentParser) -> None:
    """The segmenter's flags (``--score-threshold`` ...), one per option of segment.options."""
    defaults = option_defaults()
    types = {f.name: f.type for f in fields(SegmenterOptions)}
    for spec in OPTION_SPECS:
        flag = "--" + spec.name.replace("_", "-")
        default = defaults[spec.name]
        if isinstance(default, bool):
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=default, help=spec.description)
        else:
            kind = int if "int" in str(types[spec.name]) else float
            parser.add_argument(flag, type=kind, default=default, help=f"{spec.description} (default {default})")
    parser.add_argument(
        "--class-map",
        action="append",
        default=[],
        metavar="CLASS=NAME",
        help="rename a class ('dining table=table'); 'CLASS=' drops it; repeatable",
    )
    parser.add_argument(
        "--model",
        default=DEFAULT_MODEL,
        help=f"{' or '.join(CHECKPOINTS)} (exported at install) or a YOLO-seg .onnx file (default {DEFAULT_MODEL})",
    )
    parser.add_argument("--names-file", default=None, help="class names (txt one per line, JSON or YAML)")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")


def segmenter_from_args(args: argparse.Namespace):
    options = SegmenterOptions(
        **{spec.name: getattr(args, spec.name) for spec in OPTION_SPECS}, class_map=args.class_map
    )
    return load_segmenter(
        BACKENDS[0], model=args.model, options=options, names_file=args.names_file, threads=args.threads
    )


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "segment",
        help="segment a sequence's RGB keyframes into per-frame instance masks (plain layout)",
        description="Runs the segmenter on every RGB keyframe of SEQ_DIR and writes OUT_DIR in the plain layout: "
        "the same poses, intrinsics, RGB and Gaussian map, masks/ with a fresh color per instance and frame (white "
        "void) and segments/ with each instance's class name and score. Map it with `monovoc map OUT_DIR "
        "--mask-ids per-frame --min-support 0.5 --min-object-score 0.5 --objects -o MAP`.",
    )
    p.add_argument("source", help="sequence folder with RGB images (plain, NICE-SLAM or HI-SLAM2 layout)")
    p.add_argument("-o", "--out", required=True, help="folder to write (must be empty unless --overwrite)")
    p.add_argument("--overwrite", action="store_true", help="replace the sequence files of a non-empty OUT")
    add_segmenter_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from monovoc_ros.segment.sequence import segment_sequence

    try:
        segmenter = segmenter_from_args(args)
        summary = segment_sequence(open_sequence(args.source), segmenter, args.out, overwrite=args.overwrite)
    except (SegmenterModelError, SequenceError, ValueError, OSError) as exc:
        raise SystemExit(f"monovoc segment: {exc}") from None
    print(json.dumps(summary, indent=1))
    return 0
