"""argparse types for the command line's arguments: a NaN timeout never passes (a command waited forever), a negative
duration or a zero step made no sense, a namespace with a space made a service name rclpy refused with a traceback;
each is refused with argparse's one line (exit code 2). And the options of the commands that call the node's
services."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

from monovoc_ros.contract import DEFAULT_NAMESPACE


def _number(text: str, kind: type, low: float, low_open: bool, high: float = math.inf) -> float | int:
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not {'an integer' if kind is int else 'a number'}: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    if value < low or (low_open and value == low) or value > high:
        bound = f"> {low:g}" if low_open else f">= {low:g}"
        raise argparse.ArgumentTypeError(
            f"must be {bound}" + (f" and <= {high:g}" if high < math.inf else "") + f", got {text!r}"
        )
    return value


def finite(text: str) -> float:
    """Any finite float (a score, a coordinate)."""
    return _number(text, float, -math.inf, False)


def non_negative(text: str) -> float:
    """A duration, a timeout, a distance: finite, >= 0."""
    return _number(text, float, 0.0, False)


def positive(text: str) -> float:
    """A rate, a size: finite, > 0."""
    return _number(text, float, 0.0, True)


def at_least(low: int, high: float = math.inf) -> Callable[[str], int]:
    """An integer in [low, high] (a step, a count)."""

    def parse(text: str) -> int:
        return _number(text, int, low, False, high)

    return parse


def ros_namespace(text: str) -> str:
    """A ROS namespace as rclpy validates one, made absolute (monovoc: /monovoc, as a node in / resolves it)."""
    name = text if text.startswith("/") else "/" + text
    if name == DEFAULT_NAMESPACE:  # argparse checks the default too: no rclpy import for it
        return name
    from rclpy.exceptions import InvalidNamespaceException
    from rclpy.validate_namespace import validate_namespace

    try:
        validate_namespace(name)
    except InvalidNamespaceException as exc:
        why = str(exc).splitlines()[0].rstrip(":")
        raise argparse.ArgumentTypeError(f"not a ROS namespace: {text!r} ({why})") from None
    return name


def add_service_options(parser: argparse.ArgumentParser) -> None:
    """--namespace and --timeout of a command that calls a service of the running node (query, ask)."""
    parser.add_argument(
        "--namespace",
        type=ros_namespace,
        default=DEFAULT_NAMESPACE,
        help=f"namespace of the node (default {DEFAULT_NAMESPACE})",
    )
    parser.add_argument(
        "--timeout", type=non_negative, default=10.0, help="seconds to wait for the service (default 10)"
    )
