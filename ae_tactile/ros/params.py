"""Declaring and validating node parameters from one table (descriptions, ranges, defaults).

Each node lists its parameters as `Param`s; `declare(node, params)` declares them with
a ParameterDescriptor (description, range, read-only flag) and returns their values as
a dict, raising `ParameterError` naming the parameter and the reason when a value is
invalid, so the node can refuse to start with a clear message.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor


class ParameterError(ValueError):
    """An invalid parameter value: message names the parameter and why."""


@dataclass(frozen=True)
class Param:
    name: str
    default: Any
    description: str
    lo: float | None = None            # inclusive range for numbers
    hi: float | None = None
    choices: tuple | None = None       # allowed values (strings)
    check: Callable[[Any], str | None] | None = None   # returns an error text or None
    read_only: bool = True


def _descriptor(p: Param) -> ParameterDescriptor:
    d = ParameterDescriptor(description=p.description, read_only=p.read_only)
    if p.choices:
        d.additional_constraints = "one of: " + ", ".join(map(str, p.choices))
    if p.lo is not None and p.hi is not None and not isinstance(p.default, bool):
        if isinstance(p.default, int):
            d.integer_range = [IntegerRange(from_value=int(p.lo), to_value=int(p.hi), step=0)]
        elif isinstance(p.default, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(p.lo), to_value=float(p.hi), step=0.0)]
    return d


def validate(p: Param, value: Any) -> Any:
    """The checked value, or ParameterError('<name>: <why>')."""
    if isinstance(p.default, float) and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if isinstance(p.default, float):
        if not isinstance(value, float) or not math.isfinite(value):
            raise ParameterError(f"parameter '{p.name}' must be a finite number, got {value!r}")
    if p.lo is not None and isinstance(value, (int, float)) and not isinstance(value, bool):
        if not p.lo <= value <= p.hi:
            raise ParameterError(f"parameter '{p.name}' = {value!r} is outside [{p.lo}, {p.hi}]")
    if p.choices is not None and value not in p.choices:
        raise ParameterError(f"parameter '{p.name}' = {value!r} is not one of {list(p.choices)}")
    if p.check is not None:
        why = p.check(value)
        if why:
            raise ParameterError(f"parameter '{p.name}' = {value!r}: {why}")
    return value


def declare(node, params: list[Param]) -> dict[str, Any]:
    """Declare every parameter on ``node`` and return {name: validated value}.

    rclpy itself rejects values outside a declared range or of the wrong type when set
    from a YAML file or the command line; those errors are re-raised as ParameterError.
    """
    values = {}
    for p in params:
        try:
            node.declare_parameter(p.name, p.default, _descriptor(p))
        except Exception as exc:   # rclpy's InvalidParameterValueException, type errors
            raise ParameterError(f"parameter '{p.name}': {exc}") from exc
        values[p.name] = validate(p, node.get_parameter(p.name).value)
    return values
