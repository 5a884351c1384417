"""`monovoc record`: record live topics into an MCAP bag (there is no `ros2 bag record` here)."""

from __future__ import annotations

import argparse
import json
import sys
import threading

from monovoc_ros.commands.argument_types import at_least, non_negative


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "record",
        help="record live ROS 2 topics into an MCAP bag or a rosbag2 bag directory",
        description="Subscribes (raw, types from the graph, QoS adapted to the publishers) to each topic once it "
        "has a publisher and writes a ROS 2 MCAP bag; stops on Ctrl-C, --duration or --count and finalizes the "
        "file. Prints a JSON summary.",
    )
    p.add_argument("topics", nargs="+", metavar="TOPIC")
    p.add_argument(
        "-o", "--out", required=True, help="output .mcap file, or bag directory with --format rosbag2 (must not exist)"
    )
    p.add_argument(
        "--format",
        choices=("mcap", "rosbag2"),
        default="mcap",
        help="mcap: one .mcap file (default); rosbag2: a new directory with metadata.yaml and <name>_0.mcap, "
        "as `ros2 bag record -s mcap` writes",
    )
    p.add_argument("--duration", type=non_negative, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--count", type=at_least(1), default=None, metavar="N", help="stop after N messages in all")
    p.add_argument(
        "--log-time",
        choices=("receive", "header"),
        default="receive",
        help="MCAP log time: receive time (default, as rosbag2) or the header stamp",
    )
    p.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from monovoc_ros.bags.recorder import record
    from monovoc_ros.bags.rosnode import install_stop_signals

    stop = threading.Event()
    install_stop_signals(stop)

    def subscribed(topic: str, type_name: str) -> None:
        print(f"monovoc record: subscribed {topic} [{type_name}]", file=sys.stderr, flush=True)

    def ready() -> None:
        print(f"monovoc record: recording {' '.join(args.topics)} to {args.out}", file=sys.stderr, flush=True)

    try:
        summary = record(
            args.out,
            args.topics,
            duration=args.duration,
            count=args.count,
            log_time=args.log_time,
            compression=args.compression,
            stop_event=stop,
            on_subscribed=subscribed,
            on_ready=ready,
            bag_format=args.format,
        )
    except (LookupError, ValueError, OSError) as exc:  # OSError: an OUT that cannot be written
        print(f"monovoc record: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # before recording started; the file is finalized all the same
        return 130
    print(json.dumps(summary.as_dict(), indent=1), flush=True)
    return 0
