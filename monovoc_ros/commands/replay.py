"""`monovoc replay`: publish a bag's messages on live topics (there is no `ros2 bag play` here)."""

from __future__ import annotations

import argparse
import json
import sys
import threading

from monovoc_ros.commands.argument_types import at_least, non_negative, positive

# The exit code of a replay that published nothing (the launch file ends the launch on it: nothing will come).
NOT_STARTED = 3


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "replay",
        help="publish an MCAP bag on live ROS 2 topics",
        description="Publishes the bag's raw CDR messages at the recorded rate (or --rate R times it, or --fast "
        "as fast as possible without losing messages: reliable QoS, waits for acknowledgements). The Gaussian "
        "map topic is transient-local, so nodes that start late still get the map. Prints a JSON summary. "
        f"Exit codes: 0 done; {NOT_STARTED} nothing was replayed (no such bag, not a bag, no message, no subscriber "
        "in time); 1 it failed while replaying; 2 messages went out to no subscriber or were not acknowledged.",
    )
    p.add_argument("bag", help="MCAP bag (e.g. bags/synthetic_room.mcap)")
    speed = p.add_mutually_exclusive_group()
    speed.add_argument("--rate", type=positive, default=1.0, help="multiple of the recorded rate (default 1)")
    speed.add_argument(
        "--fast",
        action="store_true",
        help="as fast as possible, without losing messages; after each Gaussian map it waits until the node reports "
        "it taken (/diagnostics maps_received), so the keyframes posed in it do not overtake it",
    )
    p.add_argument("--clock", action="store_true", help="publish /clock (rosgraph_msgs/Clock) with the bag time")
    p.add_argument("--clock-hz", type=positive, default=40.0, help="/clock rate between messages (default 40)")
    p.add_argument(
        "--remap", nargs="+", action="extend", default=[], metavar="FROM:=TO", help="rename topics, e.g. /a:=/b"
    )
    p.add_argument(
        "--topics", nargs="+", action="extend", default=None, metavar="TOPIC", help="replay only these bag topics"
    )
    p.add_argument(
        "--wait-subscribers",
        type=at_least(0),
        default=None,
        metavar="N",
        help="start once every replayed topic has N subscribers (0: start at once; default: once each of the bag's "
        "keyframe and map topics, the node's inputs, has one, so a node still starting misses nothing)",
    )
    p.add_argument(
        "--wait-timeout", type=non_negative, default=30.0, help="seconds to wait for subscribers (default 30)"
    )
    p.add_argument("--loop", action="store_true", help="replay again and again until Ctrl-C")
    p.add_argument(
        "--hold",
        type=non_negative,
        default=0.0,
        metavar="S",
        help="keep the publishers (latched map) alive S s at the end",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from monovoc_ros.bags.map_gate import FIND_S, WAIT_S
    from monovoc_ros.bags.reader import BagError
    from monovoc_ros.bags.replayer import ReplayError, replay
    from monovoc_ros.bags.rosnode import install_stop_signals

    stop = threading.Event()
    install_stop_signals(stop)

    publishing = threading.Event()

    def started() -> None:
        publishing.set()
        print(f"monovoc replay: publishing {args.bag}", file=sys.stderr, flush=True)

    def done(summary) -> None:
        # Printed before --hold, so callers know playback has ended while the map stays latched.
        print(json.dumps(summary.as_dict(), indent=1), flush=True)
        if summary.maps_unconfirmed:
            print(
                f"monovoc replay: WARNING: {summary.maps_unconfirmed} map(s) not reported taken within "
                f"{WAIT_S:g} s: the replay stopped waiting for maps, and keyframes may overtake them",
                file=sys.stderr,
                flush=True,
            )
        elif summary.map_gate is False:
            print(
                f"monovoc replay: note: no node reported its maps on /diagnostics (maps_received) within {FIND_S:g} "
                "s: the keyframes after a map may overtake it",
                file=sys.stderr,
                flush=True,
            )
        if summary.unmatched:
            print(
                f"monovoc replay: WARNING: no subscriber on {summary.unmatched} when their first message went out: "
                "those messages reached no one",
                file=sys.stderr,
                flush=True,
            )

    try:
        summary = replay(
            args.bag,
            rate=args.rate,
            fast=args.fast,
            clock=args.clock,
            clock_hz=args.clock_hz,
            remap=args.remap,
            topics=args.topics,
            wait_subscribers=args.wait_subscribers,
            wait_timeout=args.wait_timeout,
            loop=args.loop,
            hold=args.hold,
            stop_event=stop,
            on_started=started,
            on_done=done,
        )
    except (BagError, ReplayError, ValueError) as exc:
        print(f"monovoc replay: {exc}", file=sys.stderr)
        return 1 if publishing.is_set() else NOT_STARTED
    except KeyboardInterrupt:  # before publishing started (e.g. while waiting for subscribers)
        return 130
    return 0 if not (summary.unacked or summary.unmatched) else 2
