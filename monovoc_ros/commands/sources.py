"""Where the subcommands read keyframes from: the source options of `monovoc map`, `eval` and `bag convert`,
and opening the sequence they name."""

from __future__ import annotations

import argparse

from monovoc_ros.commands.argument_types import at_least

SOURCE_HELP = "a dataset folder (plain, nice-slam or hislam2 layout) or synthetic[:VARIANT]"


def add_sequence_options(parser: argparse.ArgumentParser, noise_note: str) -> None:
    """How to read a sequence SOURCE (layout, separate folders, how many keyframes) and how to corrupt its
    masks; `noise_note` says what becomes of the clean masks in the command."""
    parser.add_argument("--layout", default="auto", choices=("auto", "plain", "nice-slam", "hislam2"))
    parser.add_argument("--gaussians", help="Gaussian map PLY (nice-slam / hislam2 layouts)")
    parser.add_argument("--masks", help="mask folder (nice-slam / hislam2 layouts)")
    parser.add_argument("--rgb", help="RGB folder (hislam2 layout)")
    parser.add_argument("--max-keyframes", type=at_least(1), default=None)
    parser.add_argument(
        "--mask-noise",
        default=None,
        help="corrupt the input masks as a segmenter would: 'shuffled' (every mask renumbered), merge=P, "
        f"split=P, drop=P, small=F, comma-separated (core.segments.segment_noise; {noise_note})",
    )
    parser.add_argument("--noise-seed", type=int, default=0, help="seed of --mask-noise (default 0)")


def add_segment_names_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--segments-from-labels",
        action="store_true",
        help="give every keyframe the segment class names a perfect segmenter would (from the source's "
        "labels.json), before --mask-noise",
    )


def add_source_options(parser: argparse.ArgumentParser) -> None:
    """A sequence SOURCE or --bag, with the sequence options and the segment names of a perfect segmenter."""
    parser.add_argument("source", nargs="?", help=SOURCE_HELP)
    parser.add_argument("--bag", help="read keyframes and the Gaussian map from an MCAP bag instead")
    add_sequence_options(parser, "references stay clean")
    add_segment_names_option(parser)


def input_errors() -> tuple[type[Exception], ...]:
    """What `monovoc map` and `eval` say in one line as the operator's input: a missing or unreadable source, map or
    bag, a source or bag without a Gaussian map, an OUT it cannot write. Any other error is a bug: its traceback stays.
    (Imported when asked: building the parser stays light.)"""
    from monovoc_ros.bags.reader import BagError
    from monovoc_ros.core.evaluation.datasets import SequenceError
    from monovoc_ros.core.map.ply import PlyError
    from monovoc_ros.core.map_store import MapStoreError
    from monovoc_ros.offline import NoMapError

    return BagError, SequenceError, PlyError, MapStoreError, NoMapError, OSError


def check_source_options(args: argparse.Namespace) -> None:
    """Refuses options that would be ignored (a bag carries its own Gaussian map, masks and RGB)."""
    if args.bag:
        ignored = [f"--{k}" for k in ("gaussians", "masks", "rgb") if getattr(args, k)]
        if args.layout != "auto":
            ignored.append("--layout")
        if ignored:
            raise SystemExit(
                f"monovoc: {', '.join(ignored)} cannot be used with --bag (the bag carries its own Gaussian "
                "map, masks and images)"
            )


def source_options(args: argparse.Namespace) -> dict:
    """The separate folders and files given for SOURCE (--gaussians, --masks, --rgb)."""
    return {k: getattr(args, k) for k in ("gaussians", "masks", "rgb") if getattr(args, k)}


def open_source_args(args: argparse.Namespace):
    """The sequence SOURCE names: with segment names by --segments-from-labels (where the command has it),
    its masks corrupted by --mask-noise."""
    from monovoc_ros import offline

    sequence = offline.open_source(args.source, args.layout, **source_options(args))
    if getattr(args, "segments_from_labels", False):
        from monovoc_ros.core.evaluation.datasets import PaletteSegments

        sequence = PaletteSegments(sequence)
    if args.mask_noise:
        from monovoc_ros.core.evaluation.datasets import CorruptedMasks
        from monovoc_ros.core.segments.segment_noise import parse_mask_noise

        shuffled, rates = parse_mask_noise(args.mask_noise)
        sequence = CorruptedMasks(sequence, shuffled=shuffled, rates=rates, seed=args.noise_seed)
    return sequence
