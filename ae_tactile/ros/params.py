# SPDX-License-Identifier: Apache-2.0
"""Node parameters from one table: descriptors, validation, run-time changes.

Each node lists its parameters as `Param`s. `ParamSet(node, table, prefix, on_change)`
declares them (description with unit and range, read-only flag with its reason),
validates the start-up values (raising `ParameterError` naming the parameter and why, so
the node refuses to start with a clear message), and installs a parameter callback:
`ros2 param set` on a tunable parameter is validated against the same table and handed
to ``on_change({name: value})``, which applies it at once (a ValueError from it rejects
the change with its message). Integers are accepted for floating-point parameters.
`warn_unknown_parameters` warns once about names given to a node that it does not have
(rclpy ignores them silently).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from dataclasses import dataclass
from typing import Any, Callable

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)

from ae_tactile.localization import available_methods
from ae_tactile.pipeline import LocalizationConfig, PacketLocalizer
from ae_tactile.slip import SlipConfig

#: Why structural parameters cannot change while the node runs.
RESTART = "read-only: takes effect at start-up (restart the node to change it)"


class ParameterError(ValueError):
    """An invalid parameter value: message names the parameter and why."""


def unit_of(name: str) -> str:
    """SI unit from a parameter name's suffix ('' when dimensionless)."""
    for suffix, unit in (
        ("_hz", "Hz"),
        ("_m_s", "m/s"),
        ("_m2", "m^2"),
        ("_s", "s"),
        ("_m", "m"),
        ("_n", "N"),
        ("_db", "dB"),
        ("_v", "V"),
    ):
        if name.endswith(suffix):
            return unit
    return ""


@dataclass(frozen=True)
class Param:
    name: str
    default: Any
    description: str
    lo: float | None = None  # inclusive range for numbers
    hi: float | None = None
    choices: tuple | None = None  # allowed values (strings)
    check: Callable[[Any], str | None] | None = None  # returns an error text or None
    read_only: bool = True  # False: tunable with `ros2 param set`
    unit: str | None = None  # None: from the name's suffix
    allow_zero_as_none: bool = False  # 0 means "unknown / device's own" (documented in text)
    numbers_as_text: bool = False  # a text parameter that may be a number (`cpus:=3`)

    @property
    def si_unit(self) -> str:
        return unit_of(self.name) if self.unit is None else self.unit


#: The handful of parameters a user sets, with what each trades (README.md's table); every
#: other parameter is expert: its descriptor says so and docs/parameters.md lists it apart.
USER_PARAMS = {
    "port": "which fingertip: its serial device or socket:// URL",
    "medium": "the body's fill (its sound speed): a wrong one shifts every position",
    "sample_rate_hz": "finer delays (better positions) against more bytes per packet on the "
    "link; 0 keeps the device's",
    "threshold_counts": "lower triggers on fainter touches, and on more noise; 0 keeps the "
    "device's",
    "localization.min_snr_db": "lower keeps fainter touches, and more false ones from noise",
    "localization.front_end": "the fingertip's analog front end as its maker states it (e.g. "
    "'highpass_hz=50e3 highpass_order=1 lowpass_hz=800e3 lowpass_order=2'): calibrated on "
    "its touches, then every point refined to the Cramer-Rao bound where the anti-alias "
    "filter lets the pulse alias, at 0.2-0.4 ms a packet; empty: no refinement",
    "slip.release_confirm_s": "how long after a release's emission its contact ends (its "
    "DETOUCH): shorter frees the contact sooner, longer keeps it through an emission that "
    "only looked like a release",
    "initial_force_n": "the grip before any slip (a firmer hold, more pressure "
    "on the object)",
    "gain": "force factor per slip precursor (fewer slips, a harder squeeze)",
    "max_force_n": "the reflex's ceiling (protects the object, limits the grip)",
}


def is_expert(full_name: str) -> bool:
    """Only an expert should change it: not one of `USER_PARAMS`."""
    return full_name not in USER_PARAMS


def tunable(p: Param) -> Param:
    return dataclasses.replace(p, read_only=False)


def describe(p: Param, full_name: str | None = None) -> str:
    """Description with unit and range, as the descriptor and the docs show it (marked
    ``[expert]`` when ``full_name`` is given and not one of `USER_PARAMS`)."""
    parts = [("[expert] " if full_name and is_expert(full_name) else "") + p.description]
    if p.si_unit:
        parts.append(f"unit: {p.si_unit}")
    if p.choices:
        parts.append("one of: " + ", ".join(map(str, p.choices)))
    elif p.lo is not None and p.hi is not None:
        parts.append(f"range: [{p.lo:g}, {p.hi:g}]")
    if p.read_only:
        parts.append(RESTART)
    return "; ".join(parts)


def descriptor(p: Param, full_name: str) -> ParameterDescriptor:
    d = ParameterDescriptor(
        name=full_name, description=describe(p, full_name), read_only=p.read_only
    )
    if p.choices:
        d.additional_constraints = "one of: " + ", ".join(map(str, p.choices))
    if isinstance(p.default, float) or p.numbers_as_text:
        d.dynamic_typing = True  # so that an integer (`min_snr_db:=10`, `cpus:=3`) is accepted
    if p.lo is not None and p.hi is not None and not isinstance(p.default, bool):
        if isinstance(p.default, int):
            d.integer_range = [IntegerRange(from_value=int(p.lo), to_value=int(p.hi), step=0)]
        elif isinstance(p.default, float):
            d.floating_point_range = [
                FloatingPointRange(from_value=float(p.lo), to_value=float(p.hi), step=0.0)
            ]
    return d


def validate(p: Param, value: Any, full_name: str | None = None) -> Any:
    """The checked value (ints converted for float parameters), or ParameterError."""
    name = full_name or p.name
    if isinstance(p.default, float) and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if p.numbers_as_text and isinstance(value, int) and not isinstance(value, bool):
        value = str(value)
    if isinstance(p.default, float):
        if not isinstance(value, float) or not math.isfinite(value):
            raise ParameterError(f"parameter '{name}' must be a finite number, got {value!r}")
    elif isinstance(p.default, bool):
        if not isinstance(value, bool):
            raise ParameterError(f"parameter '{name}' must be true or false, got {value!r}")
    elif isinstance(p.default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ParameterError(f"parameter '{name}' must be an integer, got {value!r}")
    elif isinstance(p.default, str) and not isinstance(value, str):
        raise ParameterError(f"parameter '{name}' must be a string, got {value!r}")
    elif isinstance(p.default, list):
        try:
            value = [float(v) for v in value]
        except (TypeError, ValueError):
            raise ParameterError(
                f"parameter '{name}' must be a list of numbers, got {value!r}"
            ) from None
    if p.lo is not None and isinstance(value, (int, float)) and not isinstance(value, bool):
        if not p.lo <= value <= p.hi:
            raise ParameterError(f"parameter '{name}' = {value!r} is outside [{p.lo:g}, {p.hi:g}]")
    if p.choices is not None and value not in p.choices:
        raise ParameterError(f"parameter '{name}' = {value!r} is not one of {list(p.choices)}")
    if p.check is not None:
        why = p.check(value)
        if why:
            raise ParameterError(f"parameter '{name}' = {value!r}: {why}")
    return value


class ParamSet:
    """The parameters of one table on a node (names ``prefix + p.name``).

    ``values``: {p.name: validated value}. ``on_change(changes)`` is called with the
    validated new values of tunable parameters set at run time.
    """

    def __init__(
        self,
        node,
        table: list[Param],
        prefix: str = "",
        on_change: Callable[[dict], None] | None = None,
    ):
        self.node = node
        self.prefix = prefix
        self.table = {prefix + p.name: p for p in table}
        self.on_change = on_change
        self.values: dict[str, Any] = {}
        for full, p in self.table.items():
            try:
                node.declare_parameter(full, p.default, descriptor(p, full))
            except Exception as exc:  # rclpy's InvalidParameterValueException, type errors
                raise ParameterError(f"parameter '{full}': {exc}") from exc
            self.values[p.name] = validate(p, node.get_parameter(full).value, full)
        node.add_on_set_parameters_callback(self._on_set)

    def __getitem__(self, name: str):
        return self.values[name]

    def _on_set(self, params) -> SetParametersResult:
        changes = {}
        for prm in params:
            p = self.table.get(prm.name)
            if p is None:
                continue
            if p.read_only:
                return SetParametersResult(successful=False, reason=f"{prm.name}: {RESTART}")
            try:
                changes[p.name] = validate(p, prm.value, prm.name)
            except ParameterError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        if changes and self.on_change is not None:
            try:
                self.on_change(dict(changes))
            except (ValueError, TypeError) as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        self.values.update(changes)
        return SetParametersResult(successful=True)


def declare(
    node, params: list[Param], prefix: str = "", on_change: Callable[[dict], None] | None = None
) -> dict[str, Any]:
    """Declare ``params`` on ``node``; returns the live dict of validated values."""
    return ParamSet(node, params, prefix, on_change).values


# ---------------------------------------------------------------------- shared tables
def localization_params() -> list[Param]:
    """One tunable parameter per `LocalizationConfig` field (prefix 'localization.'), with
    its default, description, unit and range from the field metadata."""
    out = []
    for name, md in LocalizationConfig.describe().items():
        choices = tuple(available_methods()) if name == "method" else None
        out.append(
            tunable(
                Param(name, md["default"], md["doc"], md["lo"], md["hi"], choices=choices,
                      unit=md["unit"] or None)
            )
        )
    return out


#: In-process localization (driver, prefix 'localization.') and the localizer node.
LOCALIZATION_PARAMS = localization_params()
#: the localization parameters PacketLocalizer takes (all but the pipeline's
#: ``overlap_inline_max``)
LOCALIZER_SETTINGS = tuple(n for n in LocalizationConfig.describe() if n != "overlap_inline_max")


def make_packet_localizer(lp: dict, **kwargs) -> PacketLocalizer:
    """A PacketLocalizer from the localization parameters ``lp`` (plus ``kwargs``)."""
    return PacketLocalizer(**{k: lp[k] for k in LOCALIZER_SETTINGS}, **kwargs)


def changes_for_localizer(changes: dict) -> dict:
    """Localization parameter changes as PacketLocalizer.update() arguments."""
    return {k: v for k, v in changes.items() if k in LOCALIZER_SETTINGS}


def slip_params() -> list[Param]:
    """One parameter per SlipConfig field, with its description, unit and range from the
    field metadata (prefix 'slip.'); run-time fields are tunable."""
    out = []
    for f in dataclasses.fields(SlipConfig):
        md = f.metadata or {}
        default = f.default
        text = md.get("doc") or f"SlipConfig.{f.name} (docs/slip.md)"
        if default is None or (f.name == "sliding_speed_m_s"):
            default = 0.0 if default is None else default
            text += "; 0 = unknown"
        if md.get("kind") == "int":
            default = int(default)
        elif isinstance(default, (int, float)) and not isinstance(default, bool):
            default = float(default)
        if not isinstance(default, (bool, int, float)):
            continue
        lo, hi = md.get("lo"), md.get("hi")
        if md.get("allow_none") and lo is not None:
            lo = min(lo, 0.0)
        out.append(
            Param(
                f.name,
                default,
                text,
                lo,
                hi,
                unit=md.get("unit"),
                read_only=not md.get("runtime", True),
            )
        )
    return out


def slip_config_kwargs(values: dict) -> dict:
    """SlipConfig keyword arguments from slip parameter values (0 speed = unknown)."""
    kw = dict(values)
    if kw.get("sliding_speed_m_s", 0.0) <= 0.0:
        kw["sliding_speed_m_s"] = None
    return kw


def unknown_overrides(node, known=()) -> list[str]:
    """Names given to ``node`` (``-p``, a parameter file, ``parameter_overrides``) that it
    did not declare and that are not in ``known``: rclpy ignores them without a word
    (``allow_undeclared_parameters`` is off).

    Parameters
    ----------
    node : rclpy.node.Node
        The node, after it declared all its parameters.
    known : iterable of str
        Names the node knows but did not declare this time (a table it left out).

    Returns
    -------
    list of str
        The unknown names, sorted.
    """
    overrides = getattr(node, "_parameter_overrides", None) or {}  # rclpy keeps no public copy
    known = set(known)
    return sorted(n for n in overrides if n not in known and not node.has_parameter(n))


def warn_unknown_parameters(node, known=()) -> list[str]:
    """Log one WARN through the node's logger naming every parameter given to it that it
    does not have (`unknown_overrides`), with the closest declared name of each.

    Parameters
    ----------
    node : rclpy.node.Node
        The node, after it declared all its parameters.
    known : iterable of str
        Names the node knows but did not declare this time (not warned about).

    Returns
    -------
    list of str
        The names warned about (empty: no warning).
    """
    names = unknown_overrides(node, known)
    node._ae_tactile_names_checked = True  # run_node checks every node once, this one done
    if not names:
        return names
    declared = list(node._parameters) + list(known)
    parts = []
    for name in names:
        close = difflib.get_close_matches(name, declared, n=1, cutoff=0.75)
        parts.append(f"'{name}'" + (f" (did you mean '{close[0]}'?)" if close else ""))
    node.get_logger().warning(
        f"ignoring {len(names)} unknown parameter(s): {', '.join(parts)}: not parameters of "
        f"this node (misspelt, or an old name); `--help` lists them"
    )
    return names
