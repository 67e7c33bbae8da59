# SPDX-License-Identifier: Apache-2.0
"""Scene keys: the schema of every section and generator, its validation, and the
generator registry (`GENERATORS`: name -> (factory, parameter schema)).

Validation fails with a `SceneError` naming the offending key: unknown keys (with the
allowed ones), missing required keys, values of the wrong type or given with units as
strings ("10 mm"), and implausible magnitudes (e.g. a radius in millimetres).
`scene_schema_markdown()` renders the tables of docs/simulator.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ae_tactile.sim import generators as G
from ae_tactile.sim.config import MEDIUM_PRESETS, SimConfig
from ae_tactile.sim.emission import DEFAULT_ALPHA_1_S, DEFAULT_CURVATURE_1_M, DEFAULT_SPEED_M_S

REQUIRED = object()


@dataclass(frozen=True)
class Key:
    """One schema entry: kind in {'float', 'int', 'bool', 'str', 'xy_list', 'float_list',
    'float_or_null'}, default (REQUIRED if none), plausibility bounds [lo, hi], and
    whether the string "auto" is accepted (resolved by SimConfig)."""

    kind: str
    default: object
    doc: str
    lo: float | None = None
    hi: float | None = None
    choices: tuple | None = None
    auto: bool = False


def _f(default, doc, lo=None, hi=None):
    return Key("float", default, doc, lo, hi)


TOP_KEYS = {
    "generator": Key("str", REQUIRED, "name of a built-in generator"),
    "duration_s": _f(REQUIRED, "scene length (s)", 1e-6, 3600.0),
    "seed": Key("int", 0, "seed of every random draw in the scene (integer >= 0)", 0, 2**63 - 1),
    "name": Key("str", None, "free-form scene name"),
    "description": Key("str", None, "free-form description"),
    "sensor": Key("map", {}, "SimConfig overrides"),
    "effects": Key("map", {}, "effect switches"),
    "noise": Key("map", None, "noise level (absent: noise off)"),
    "params": Key("map", {}, "generator parameters"),
}

SENSOR_KEYS = {
    "medium": Key(
        "str", "water_skin", "medium preset", choices=tuple(MEDIUM_PRESETS) + ("custom",)
    ),
    "radius_m": _f(10e-3, "fingertip sphere radius R (m)", 1e-3, 0.1),
    "element_offset_m": _f(1.5e-3, "element centre offset a (m)", 1e-4, 0.05),
    "sound_speed_m_s": _f(None, "sound speed (m/s); default: the medium's", 100.0, 10000.0),
    "density_kg_m3": _f(None, "density rho (kg/m^3); default: the medium's", 100.0, 20000.0),
    "attenuation_db_per_m_at_1mhz": _f(
        None, "loss at 1 MHz (dB/m); default: the medium's", 0.0, 1e5
    ),
    "sensitivity_v_per_pa": _f(0.01, "PVDF + amplifier gain (V/Pa)", 1e-9, 1e3),
    "highpass_hz": _f(100e3, "high-pass cut-off (Hz)", 1.0, 1e8),
    "highpass_order": Key("int", 2, "high-pass order", 1, 8),
    "lowpass_hz": Key(
        "float_or_null",
        "auto",
        "anti-alias low-pass cut-off (Hz); auto: min(1 MHz, 0.3 sample rate); null disables",
        1.0,
        1e9,
        auto=True,
    ),
    "lowpass_order": Key(
        "int",
        "auto",
        "low-pass order; auto: 4, or 8 for an auto cut-off below 1 MHz",
        1,
        8,
        auto=True,
    ),
    "sample_rate_hz": _f(10e6, "ADC sample rate (Hz, integer)", 1e3, 1e9),
    "adc_bits": Key("int", 12, "ADC resolution (bits)", 2, 24),
    "adc_full_scale_v": _f(1.0, "ADC full scale (V)", 1e-6, 1e3),
    "reflection_coefficient": _f(-0.5, "wall echo amplitude ratio per bounce", -0.999, 0.999),
    "n_reflections": Key("int", 2, "number of wall echoes", 0, 16),
    "support_rel_tol": _f(1e-6, "response truncation tolerance (relative)", 1e-12, 0.1),
    "max_support_s": _f(200e-6, "response length cap (s)", 1e-6, 0.1),
}

EFFECT_KEYS = {
    "attenuation": Key("bool", False, "frequency-dependent loss of the medium"),
    "reflections": Key("bool", False, "wall echoes"),
    "quantization": Key("bool", True, "ADC rounding and clipping"),
    "release_emissions": Key("bool", True, "releases (detouch) emit, opposite polarity"),
}

NOISE_KEYS = {
    "snr_db": _f(None, "SNR of the reference touch (dB)", -40.0, 120.0),
    "rms_v": _f(None, "noise sigma per channel (V)", 0.0, 100.0),
    "density_v_per_rthz": _f(None, "noise density (V/sqrt(Hz)), white to fs/2", 0.0, 1.0),
}

_EV = {
    "speed_m_s": _f(DEFAULT_SPEED_M_S, "contact speed v0 (m/s)", 1e-4, 20.0),
    "curvature_1_m": _f(DEFAULT_CURVATURE_1_M, "object curvature a_c (1/m)", 1.0, 1e6),
    "alpha_1_s": _f(DEFAULT_ALPHA_1_S, "indentation rate alpha (1/s)", 1.0, 1e6),
}
_HOLD = {  # touches released after a hold (0: held to the end of the scene)
    "hold_s": _f(0.0, "each touch released this long after it (s); 0: never", 0.0, 3600.0),
    "release_speed_m_s": _f(0.15, "separation speed (m/s)", 1e-4, 20.0),
}
_XY = {"x_m": _f(0.0, "contact x (m)", -0.1, 0.1), "y_m": _f(0.0, "contact y (m)", -0.1, 0.1)}

GENERATORS = {
    "single_touch": (
        G.single_touch,
        {**_XY, "time_s": _f(1e-3, "touch time (s)", 0.0, 3600.0), **_EV},
    ),
    "paper_positions": (
        G.paper_positions,
        {
            "xs_m": Key(
                "float_list", [0.0, 2.5e-3, 5.0e-3], "touch x positions (m), y = 0", -0.1, 0.1
            ),
            "start_s": _f(1e-3, "first touch (s)", 0.0, 3600.0),
            "interval_s": _f(5e-3, "time between touches (s)", 1e-6, 3600.0),
            **_HOLD,
            **_EV,
        },
    ),
    "three_pins": (
        G.three_pins,
        {
            "points_xy_m": Key(
                "xy_list", [[-3e-3, 2e-3], [3e-3, 2e-3], [0.0, -3e-3]], "pin (x, y) (m)", -0.1, 0.1
            ),
            "times_s": Key(
                "float_list", [1e-3, 1.7e-3, 2.9e-3], "pin touch times (s)", 0.0, 3600.0
            ),
            **_HOLD,
            **_EV,
        },
    ),
    "plane_slip": (
        G.plane_slip,
        {
            **_XY,
            "start_s": _f(1e-3, "slip start (s)", 0.0, 3600.0),
            "slip_duration_s": _f(10e-3, "slip duration (s)", 0.0, 3600.0),
            "rate_hz": _f(300.0, "slip emission rate (1/s)", 0.0, 1e6),
            "contact_radius_m": _f(3e-3, "contact disc radius (m)", 0.0, 0.05),
            "drift_m_s": _f(0.0, "contact centre drift along x (m/s)", -10.0, 10.0),
            **{**_EV, "speed_m_s": _f(0.15, "local slip speed (m/s)", 1e-4, 20.0)},
        },
    ),
    "random_touches": (
        G.random_touches,
        {
            "rate_hz": _f(20.0, "touch rate (1/s)", 0.0, 1e6),
            "max_polar_deg": _f(60.0, "touches within this polar angle (deg)", 0.0, 90.0),
            "speed_min_m_s": _f(0.1, "min touch speed (m/s)", 1e-4, 20.0),
            "speed_max_m_s": _f(0.5, "max touch speed (m/s)", 1e-4, 20.0),
            "hold_min_s": _f(5e-3, "min hold time (s)", 0.0, 3600.0),
            "hold_max_s": _f(50e-3, "max hold time (s)", 0.0, 3600.0),
            "release_speed_ratio": _f(0.5, "release speed / touch speed", 1e-3, 10.0),
            "curvature_1_m": _EV["curvature_1_m"],
            "alpha_1_s": _EV["alpha_1_s"],
        },
    ),
    "touch_hold_release": (
        G.touch_hold_release,
        {
            **_XY,
            "time_s": _f(1e-3, "touch time (s)", 0.0, 3600.0),
            "hold_s": _f(20e-3, "hold time (s)", 0.0, 3600.0),
            "release_speed_m_s": _f(0.15, "separation speed (m/s)", 1e-4, 20.0),
            **_EV,
        },
    ),
    "incipient_slip": (
        G.incipient_slip,
        {
            **_XY,
            "normal_load_n": _f(1.0, "normal load P (N)", 1e-4, 1e3),
            "object_radius_m": Key(
                "float_or_null", None, "object radius (m); null = plane", 1e-4, 10.0
            ),
            "youngs_modulus_pa": _f(1.0e6, "fingertip Young's modulus E (Pa)", 1e3, 1e11),
            "poisson_ratio": _f(0.5, "fingertip Poisson ratio", 0.0, 0.5),
            "friction_coefficient": _f(1.0, "Coulomb friction mu", 1e-3, 10.0),
            "start_s": _f(0.0, "tangential ramp start (s)", 0.0, 3600.0),
            "tangential_load_start_n": _f(0.0, "Q at the ramp start (N)", 0.0, 1e3),
            "tangential_load_rate_n_per_s": _f(1.0, "dQ/dt (N/s)", 0.0, 1e4),
            "tangential_load_max_n": Key(
                "float_or_null", None, "Q stops growing here (N); null: never", 0.0, 1e3
            ),
            "front_density_per_m2": _f(
                20e6, "micro-slip emissions per m^2 of newly slipping area", 0.0, 1e12
            ),
            "background_rate_hz": _f(
                100.0, "micro-slip rate at full slip fraction (1/s)", 0.0, 1e6
            ),
            "slip_rate_hz": _f(500.0, "emission rate during gross slip (1/s)", 0.0, 1e6),
            "micro_slip_speed_m_s": _f(0.1, "local speed of a micro-slip event (m/s)", 1e-4, 20.0),
            "slip_speed_m_s": _f(0.2, "local speed of a gross-slip event (m/s)", 1e-4, 20.0),
            "curvature_1_m": _EV["curvature_1_m"],
            "alpha_1_s": _EV["alpha_1_s"],
            "step_s": _f(10e-3, "random-draw time step (s)", 1e-6, 1.0),
            "micro_slip_count": Key(
                "float_or_null",
                None,
                "mean micro-slips of the front over a whole ramp "
                "(replaces front_density_per_m2); null: from the density",
                0.0,
                1e6,
            ),
            "micro_slip_polarity": Key(
                "str",
                "random",
                "micro-slip / slip emission polarity",
                choices=("random", "compression", "rarefaction"),
            ),
        },
    ),
    "stylus": (
        G.stylus,
        {
            **_XY,
            "heading_deg": _f(0.0, "sliding direction, from +x toward +y (deg)", -360.0, 360.0),
            "slide_speed_m_s": _f(0.02, "sliding speed along the surface v (m/s)", 1e-5, 10.0),
            "period_m": _f(0.5e-3, "texture spatial period lambda (m)", 1e-6, 0.1),
            "path_m": _f(8e-3, "sliding distance along the surface (m)", 1e-5, 0.05),
            "jitter_fraction": _f(0.05, "timing jitter, std / period", 0.0, 1.0),
            "miss_fraction": _f(0.0, "fraction of silent ridges", 0.0, 0.9),
            "start_s": _f(0.01, "touch-down and sliding start (s)", 0.0, 3600.0),
            "contact_radius_m": _f(0.5e-3, "contact patch radius (m)", 0.0, 0.01),
            "touch_speed_m_s": _f(0.3, "touch-down speed (m/s)", 1e-4, 20.0),
            "polarity": Key(
                "str",
                "random",
                "texture emission polarity",
                choices=("random", "compression", "rarefaction"),
            ),
            **{**_EV, "speed_m_s": _f(0.1, "local impact speed per ridge (m/s)", 1e-4, 20.0)},
        },
    ),
    "interference": (
        G.interference,
        {
            "rate_hz": _f(1000.0, "burst rate (1/s)", 1e-3, 1e5),
            "periodic": Key("bool", True, "periodic bursts (else Poisson)"),
            "jitter_s": _f(0.0, "timing jitter of periodic bursts (s)", 0.0, 1.0),
            "start_s": _f(0.0, "first burst (s)", 0.0, 3600.0),
            "burst_duration_s": _f(3600.0, "bursts stop after this long (s)", 0.0, 1e6),
            "shared_clock": Key(
                "bool",
                False,
                "bursts on the host's monotonic clock, the same for every simulated "
                "fingertip of the machine with the same shared_seed (one source under a "
                "hand's fingertips; real time)",
            ),
            "shared_seed": Key("int", 0, "seed of the shared-clock bursts", 0, 2**31 - 1),
            "kind": Key("str", "mixed", "waveform", choices=("mixed", "spike", "edge", "ringing")),
            "coupling": Key(
                "str",
                "adc",
                "where it enters: after the filters (adc) or at the amplifier input",
                choices=("adc", "input"),
            ),
            "amplitude_snr_db": _f(30.0, "burst peak over the noise sigma (dB)", -20.0, 120.0),
            **_XY,
            "touch_time_s": _f(1e-3, "held touch: touch time (s)", 0.0, 3600.0),
            "hold_s": _f(0.0, "held touch: hold time (s); 0: no touch", 0.0, 3600.0),
            "release_speed_m_s": _f(0.15, "held touch: separation speed (m/s)", 1e-4, 20.0),
            "taps_before": Key(
                "int", 0, "taps away from the apex before it all (every 30 ms)", 0, 1000
            ),
            **_EV,
        },
    ),
    "texture": (
        G.texture,
        {
            **_XY,
            "slide_speed_m_s": _f(0.02, "sliding speed v (m/s)", 1e-6, 10.0),
            "period_m": _f(0.5e-3, "texture spatial period lambda (m)", 1e-6, 0.1),
            "jitter_fraction": _f(0.05, "timing jitter, std / period", 0.0, 10.0),
            "start_s": _f(0.0, "sliding start (s)", 0.0, 3600.0),
            "slide_duration_s": _f(3600.0, "sliding duration (s)", 0.0, 1e6),
            "contact_radius_m": _f(1e-3, "contact patch radius (m)", 0.0, 0.05),
            "random_polarity": Key("bool", True, "random emission polarity"),
            **{**_EV, "speed_m_s": _f(0.1, "local impact speed per ridge (m/s)", 1e-4, 20.0)},
        },
    ),
}


class SceneError(ValueError):
    """A scene that does not validate (a ValueError with the offending key in the message)."""


def check_value(where, key, spec: Key, v):
    if spec.auto and v == "auto":
        return v
    if v is None:
        if spec.kind == "float_or_null" or spec.default is None:
            return None
        raise SceneError(f"{where}.{key}: null is not allowed ({spec.doc})")
    if isinstance(v, str) and spec.kind in ("float", "int", "float_or_null"):
        try:
            v = float(v)  # YAML 1.1 reads 1e-3 as a string; accept plain numbers
        except ValueError:
            raise SceneError(
                f"{where}.{key}: expected a number in SI units ({spec.doc}),"
                f" got {v!r}; write the value in the unit of the key name,"
                " without a unit string"
            ) from None
    if spec.kind in ("float", "float_or_null"):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise SceneError(f"{where}.{key}: expected a number ({spec.doc}), got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise SceneError(f"{where}.{key}: must be finite, got {v!r}")
    elif spec.kind == "int":
        if isinstance(v, bool) or not isinstance(v, (int, float)) or float(v) != int(v):
            raise SceneError(f"{where}.{key}: expected an integer ({spec.doc}), got {v!r}")
        v = int(v)
    elif spec.kind == "bool":
        if not isinstance(v, bool):
            raise SceneError(f"{where}.{key}: expected true or false, got {v!r}")
        return v
    elif spec.kind == "str":
        if not isinstance(v, str):
            raise SceneError(f"{where}.{key}: expected a string, got {v!r}")
        if spec.choices and v not in spec.choices:
            raise SceneError(f"{where}.{key}: {v!r} is not one of {list(spec.choices)}")
        return v
    elif spec.kind == "float_list":
        if not isinstance(v, (list, tuple)) or not v:
            raise SceneError(f"{where}.{key}: expected a non-empty list of numbers ({spec.doc})")
        item = Key("float", 0.0, spec.doc, spec.lo, spec.hi)
        return [check_value(where, f"{key}[{i}]", item, x) for i, x in enumerate(v)]
    elif spec.kind == "xy_list":
        if (
            not isinstance(v, (list, tuple))
            or not v
            or not all(isinstance(x, (list, tuple)) and len(x) == 2 for x in v)
        ):
            raise SceneError(f"{where}.{key}: expected a list of [x, y] pairs in metres")
        item = Key("float", 0.0, spec.doc, spec.lo, spec.hi)
        return [
            [check_value(where, f"{key}[{i}][{j}]", item, c) for j, c in enumerate(x)]
            for i, x in enumerate(v)
        ]
    if spec.lo is not None and v < spec.lo or spec.hi is not None and v > spec.hi:
        unit_hint = ""
        if key.endswith("_m") and v > (spec.hi or 0):
            unit_hint = " (units are metres: 10 mm is 0.01)"
        raise SceneError(
            f"{where}.{key}={v!r} is outside the plausible range"
            f" [{spec.lo}, {spec.hi}] ({spec.doc}){unit_hint}"
        )
    return v


def validate_map(where, data, schema):
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise SceneError(f"{where}: expected a mapping of key: value, got {type(data).__name__}")
    unknown = sorted(set(data) - set(schema))
    if unknown:
        raise SceneError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(schema)}")
    out = {}
    for key, spec in schema.items():
        if key in data:
            out[key] = (
                check_value(where, key, spec, data[key]) if spec.kind != "map" else data[key]
            )
        elif spec.default is REQUIRED:
            raise SceneError(f"{where}: missing required key {key!r} ({spec.doc})")
        else:
            out[key] = spec.default
    return out


@dataclass
class SceneContext:
    config: SimConfig
    seed: int
    duration_s: float
    effects: dict


PART_KEYS = {
    "at_s": _f(REQUIRED, "start of this part on the scene's timeline (s)", 0.0, 3600.0),
    "name": Key("str", None, "label of the part"),
    "generator": Key("str", REQUIRED, "a built-in generator other than composite"),
    "params": Key("map", {}, "that generator's parameters"),
}


#: Parameters that place an event on the scene's timeline [s] (lists: every element).
EVENT_TIME_KEYS = ("time_s", "times_s", "start_s", "touch_time_s", "at_s")


def check_event_times(where: str, raw: dict, values: dict, duration_s: float) -> None:
    """Refuse an event placed at or after the end of its timeline (nothing of it would be
    played or rendered, without a word).

    Parameters
    ----------
    where : str
        Name of the mapping in messages (``params``, ``params.parts[1]``).
    raw : dict
        The mapping as written (only keys given there are checked: defaults are not the
        writer's choice).
    values : dict
        The validated mapping.
    duration_s : float
        Length of the timeline [s].

    Raises
    ------
    SceneError
        The message names the key, its value and the duration.
    """
    if not isinstance(raw, dict):
        return
    for key in EVENT_TIME_KEYS:
        if key not in raw or key not in values:
            continue
        v = values[key]
        times = v if isinstance(v, (list, tuple)) else [v]
        late = [float(t) for t in times if t is not None and float(t) >= duration_s]
        if late:
            raise SceneError(
                f"{where}.{key}: {late[0]:g} s is at or after the end of the scene"
                f" (duration_s = {duration_s:g} s here): nothing of it would be played;"
                " lengthen duration_s or move the event"
            )


def composite(ctx, p):
    """Parts ``[{at_s, generator, params, name}]`` played on one timeline (CompositeProcess)."""
    parts = p["parts"]
    if not isinstance(parts, list) or not parts:
        raise SceneError("params.parts: expected a non-empty list of {at_s, generator, params}")
    built = []
    for i, raw in enumerate(parts):
        where = f"params.parts[{i}]"
        part = validate_map(where, raw, PART_KEYS)
        check_event_times(where, raw, part, ctx.duration_s)
        gen = part["generator"]
        if gen not in GENERATORS or gen == "composite":
            raise SceneError(
                f"{where}.generator: {gen!r} is not one of "
                f"{sorted(g for g in GENERATORS if g != 'composite')}"
            )
        factory, schema = GENERATORS[gen]
        params = validate_map(f"{where}.params", part["params"], schema)
        check_event_times(f"{where}.params", part["params"], params, ctx.duration_s - part["at_s"])
        sub = SceneContext(
            config=ctx.config,
            seed=ctx.seed + 1000 * (i + 1),
            duration_s=max(ctx.duration_s - part["at_s"], 1e-6),
            effects=ctx.effects,
        )
        try:
            proc = factory(sub, params)
        except SceneError:
            raise
        except ValueError as e:
            raise SceneError(f"{where} ({gen}): {e}") from None
        built.append((int(round(part["at_s"] * 1e9)), proc, part["name"] or gen))
    return G.CompositeProcess(built)


GENERATORS["composite"] = (
    composite,
    {"parts": Key("map", REQUIRED, "list of {at_s, generator, params, name}")},
)


def scene_schema_markdown() -> str:
    """Markdown tables of every scene key with its default and meaning (for the docs)."""
    lines = []

    def table(title, schema):
        lines.append(f"\n**{title}**\n")
        lines.append("| key | default | meaning |")
        lines.append("|---|---|---|")
        for k, s in schema.items():
            d = (
                "required"
                if s.default is REQUIRED
                else ("null" if s.default is None else repr(s.default))
            )
            lines.append(f"| `{k}` | {d} | {s.doc} |")

    table("top level", TOP_KEYS)
    table("sensor", SENSOR_KEYS)
    table("effects", EFFECT_KEYS)
    table("noise (exactly one)", NOISE_KEYS)
    for name, (_, schema) in GENERATORS.items():
        table(f"params of `{name}`", schema)
    return "\n".join(lines)
