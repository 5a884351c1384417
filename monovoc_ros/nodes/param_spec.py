"""One specification per ROS parameter (name, default, meaning, range or choices), after the idea of
PickNikRobotics/generate_parameter_library: a component lists its parameters once as `Param`s, and from
that list `declare` declares them (read-only, with a descriptor whose `floating_point_range` /
`integer_range` and `additional_constraints` show in ``ros2 param describe``) and checks the values the
node was started with. Its YAML file and the README table are tested against the same list.

A default's type is the parameter's type; float parameters also take integers (``-p save_period_s:=10``).
Every float must be finite. Bounds are inclusive unless `above` is set (``> above``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

_INT_MAX = 2**63 - 1  # IntegerRange's int64 bounds stand for "unbounded"
_INT_MIN = -(2**63)


class ParameterError(ValueError):
    """An invalid node parameter; the message starts with the parameter's name."""


@dataclass(frozen=True)
class Param:
    name: str
    default: Any
    description: str
    choices: tuple[Any, ...] = ()
    low: float | None = None  # value >= low
    high: float | None = None  # value <= high
    above: float | None = None  # value > above (an open lower bound, e.g. a period)

    def constraints(self) -> str:
        """The allowed values in words (the descriptor's `additional_constraints`; error messages)."""
        if self.choices:
            return f"must be one of {list(self.choices)}"
        if self.above is not None:
            return f"must be > {self.above:g}" + (f" and <= {self.high:g}" if self.high is not None else "")
        if self.low is not None and self.high is not None:
            return f"must be in [{self.low:g}, {self.high:g}]"
        if self.low is not None:
            return f"must be >= {self.low:g}"
        if self.high is not None:
            return f"must be <= {self.high:g}"
        return ""

    def descriptor(self) -> Any:
        """The rcl_interfaces ParameterDescriptor: read-only, with the range and constraints."""
        from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

        floating = isinstance(self.default, float)
        descriptor = ParameterDescriptor(
            description=self.description,
            additional_constraints=self.constraints(),
            read_only=True,
            dynamic_typing=floating,  # integers are welcome where a float is expected
        )
        low = self.above if self.above is not None else self.low
        if self.choices and all(isinstance(c, int) for c in self.choices):
            low, high = min(self.choices), max(self.choices)
        else:
            high = self.high
        if low is None and high is None:
            return descriptor
        if floating:
            descriptor.floating_point_range = [
                FloatingPointRange(
                    from_value=-math.inf if low is None else float(low),
                    to_value=math.inf if high is None else float(high),
                )
            ]
        elif isinstance(self.default, int) and not isinstance(self.default, bool):
            if self.above is not None and not self.choices:
                low = math.floor(self.above) + 1  # integers: > above is >= the next one
            descriptor.integer_range = [
                IntegerRange(
                    from_value=_INT_MIN if low is None else math.ceil(low),
                    to_value=_INT_MAX if high is None else math.floor(high),
                )
            ]
        return descriptor

    def check(self, value: Any) -> Any:
        """The value in the parameter's type, or ParameterError naming the parameter."""

        def fail(what: str) -> ParameterError:
            return ParameterError(f"{self.name}: {what}, got {value!r}")

        default = self.default
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise fail("must be true or false")
        elif isinstance(default, float):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise fail("must be a number")
            value = float(value)
            if not math.isfinite(value):
                raise fail("must be finite")
        elif isinstance(default, int):
            if isinstance(value, bool) or not isinstance(value, int):
                raise fail("must be an integer")
        elif isinstance(default, str):
            if not isinstance(value, str):
                raise fail("must be a string")
        elif isinstance(default, list):
            if isinstance(value, (str, bytes)) or not isinstance(value, Iterable):
                raise fail("must be a list")
            value = list(value)
            if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value):
                raise fail("must be a list of numbers")
            value = [float(x) for x in value]
        if self.choices and value not in self.choices:
            raise fail(self.constraints())
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            too_low = (self.low is not None and value < self.low) or (self.above is not None and value <= self.above)
            if too_low or (self.high is not None and value > self.high):
                raise fail(self.constraints())
        return value


def defaults(params: Iterable[Param]) -> dict[str, Any]:
    return {p.name: p.default for p in params}


def validate(params: Iterable[Param], values: Mapping[str, Any]) -> dict[str, Any]:
    """name -> checked value for every parameter (missing ones take their defaults; unknown names are ignored)."""
    return {p.name: p.check(values.get(p.name, p.default)) for p in params}


def declare(node: Any, params: Iterable[Param]) -> dict[str, Any]:
    """Declares the parameters on an rclpy node and returns their checked values (ParameterError on a bad one)."""
    from rclpy.exceptions import InvalidParameterValueException, ParameterException

    params = tuple(params)
    values = {}
    for p in params:
        try:
            values[p.name] = node.declare_parameter(p.name, p.default, p.descriptor()).value
        except InvalidParameterValueException as exc:  # out of the descriptor's range
            raise ParameterError(f"{p.name}: {p.constraints()} ({exc})") from None
        except ParameterException as exc:  # a value of another type
            kind = type(p.default).__name__
            raise ParameterError(f"{p.name}: {exc} (expected a {kind} like {p.default!r})") from None
    return validate(params, values)
