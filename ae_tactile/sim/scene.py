# SPDX-License-Identifier: Apache-2.0
"""YAML scene format, validation and loading.

A scene file (all values SI, the unit is in the key name)::

    generator: single_touch     # which built-in generator (see GENERATORS)
    duration_s: 0.01            # length of the scene
    seed: 0                     # all randomness of the scene (emissions and noise)
    sensor: {...}               # optional SimConfig overrides (SENSOR_KEYS)
    effects: {...}              # optional switches (EFFECT_KEYS)
    noise: {snr_db: 30}         # optional, exactly one of snr_db / rms_v / density_v_per_rthz
    params: {...}               # generator parameters (GENERATORS[name] schema)

``load_scene(path_or_dict)`` validates everything and fails with a ValueError naming the
offending key: unknown keys (with the allowed ones), missing required keys, values of
the wrong type or given with units as strings ("10 mm"), implausible magnitudes (e.g. a
radius in millimetres), and contact points off the sensing surface.

noise.snr_db is relative to the scene's reference emission: a default touch (0.3 m/s,
a_c = 1/mm) at the apex, with the SNR definition of docs/conventions.md; rms_v is the
per-channel sigma; density_v_per_rthz gives sigma = density sqrt(fs/2).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np
import yaml

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.sim import generators as G
from ae_tactile.sim.config import MEDIUM_PRESETS, SimConfig
from ae_tactile.sim.emission import DEFAULT_ALPHA_1_S, DEFAULT_CURVATURE_1_M, DEFAULT_SPEED_M_S
from ae_tactile.sim.frontend import noise_rms_for_snr, noise_rms_from_density
from ae_tactile.sim.kernels import warm_up
from ae_tactile.sim.stream import StreamingSource, TriggeredSource
from ae_tactile.sim.triggered import render_triggered

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
        "int", "auto", "low-pass order; auto: 4, or 8 for an auto cut-off below 1 MHz", 1, 8,
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
            "taps_before": Key("int", 0, "taps away from the apex before it all (every 30 ms)",
                               0, 1000),
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


PART_KEYS = {
    "at_s": _f(REQUIRED, "start of this part on the scene's timeline (s)", 0.0, 3600.0),
    "name": Key("str", None, "label of the part"),
    "generator": Key("str", REQUIRED, "a built-in generator other than composite"),
    "params": Key("map", {}, "that generator's parameters"),
}


def composite(ctx, p):
    """Parts ``[{at_s, generator, params, name}]`` played on one timeline (CompositeProcess)."""
    parts = p["parts"]
    if not isinstance(parts, list) or not parts:
        raise SceneError("params.parts: expected a non-empty list of {at_s, generator, params}")
    built = []
    for i, raw in enumerate(parts):
        where = f"params.parts[{i}]"
        part = _validate_map(where, raw, PART_KEYS)
        gen = part["generator"]
        if gen not in GENERATORS or gen == "composite":
            raise SceneError(
                f"{where}.generator: {gen!r} is not one of "
                f"{sorted(g for g in GENERATORS if g != 'composite')}"
            )
        factory, schema = GENERATORS[gen]
        params = _validate_map(f"{where}.params", part["params"], schema)
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


def _check_value(where, key, spec: Key, v):
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
        return [_check_value(where, f"{key}[{i}]", item, x) for i, x in enumerate(v)]
    elif spec.kind == "xy_list":
        if (
            not isinstance(v, (list, tuple))
            or not v
            or not all(isinstance(x, (list, tuple)) and len(x) == 2 for x in v)
        ):
            raise SceneError(f"{where}.{key}: expected a list of [x, y] pairs in metres")
        item = Key("float", 0.0, spec.doc, spec.lo, spec.hi)
        return [
            [_check_value(where, f"{key}[{i}][{j}]", item, c) for j, c in enumerate(x)]
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


def _validate_map(where, data, schema, required_ok=True):
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
                _check_value(where, key, spec, data[key]) if spec.kind != "map" else data[key]
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


@dataclass
class Scene:
    """A validated scene: config, noise level, and the emission process with ground truth."""

    name: str
    generator: str
    duration_s: float
    seed: int
    config: SimConfig
    noise_rms_v: float
    effects: dict
    params: dict
    process: object
    spec: dict = field(repr=False, default_factory=dict)
    cost: SceneCost | None = field(repr=False, default=None)

    @property
    def n_samples(self) -> int:
        return int(round(self.duration_s * self.config.sample_rate_hz))

    @property
    def truth(self) -> dict:
        """Scene-level ground truth (e.g. gross_slip_time_ns)."""
        return self.process.scene_truth()

    def streaming_source(self, **kw) -> StreamingSource:
        """A fresh stream of this scene (the process is shared: build the scene again for
        an independent replay)."""
        return StreamingSource(
            self.process, self.config, noise_rms_v=self.noise_rms_v, seed=self.seed, **kw
        )

    def triggered_source(self, **kw) -> TriggeredSource:
        """Packets of this scene's emissions before its end (``end_ns`` = duration_s)."""
        kw.setdefault("end_ns", int(round(self.duration_s * 1e9)))
        return TriggeredSource(
            self.process, self.config, noise_rms_v=self.noise_rms_v, seed=self.seed, **kw
        )


def reference_noise_rms(config: SimConfig, snr_db: float) -> float:
    """sigma giving ``snr_db`` (conventions.md) for the reference touch at the apex."""
    apex = np.array([[0.0, 0.0, config.geometry.radius_m]])
    pk = render_triggered(apex, config.replace(quantization=False), subsample_offset=0.0)
    return float(noise_rms_for_snr(pk.signal_power_v2[0], snr_db))


def build_config(sensor: dict, effects: dict) -> SimConfig:
    s = dict(sensor)
    medium = s.pop("medium")
    c = s.pop("sound_speed_m_s")
    geo_kw = {k: s.pop(k) for k in ("radius_m", "element_offset_m")}
    if c is None:
        if medium == "custom":
            raise SceneError("sensor.sound_speed_m_s is required with medium: custom")
        c = MEDIUM_PRESETS[medium].sound_speed_m_s
    try:
        geo = FingertipGeometry(sound_speed_m_s=c, **geo_kw)
        kw = {k: v for k, v in s.items() if v is not None or k == "lowpass_hz"}
        return SimConfig(
            geometry=geo,
            medium=medium,
            attenuation=effects["attenuation"],
            reflections=effects["reflections"],
            quantization=effects["quantization"],
            **kw,
        )
    except ValueError as e:
        raise SceneError(f"sensor: {e}") from None


# ---------------------------------------------------------------------- cost budget
@dataclass(frozen=True)
class Budget:
    """Limits checked before a scene is built (docs/simulator.md, "Scene budget").

    max_memory_bytes  estimated peak memory of building and rendering the scene
                      (None: unchecked); default 1 GiB
    max_output_bytes  estimated size of the rendered .npz (None: unchecked); the command
                      line checks 16 GiB by default, `load_scene` does not (a scene played
                      by the virtual device writes no file)
    """

    max_memory_bytes: int | None = 1 << 30
    max_output_bytes: int | None = None


DEFAULT_BUDGET = Budget()
#: The command line's default (an .npz of <= 16 GiB: ~215 s of 4 x 10 MS/s int16).
CLI_BUDGET = Budget(max_memory_bytes=1 << 30, max_output_bytes=16 << 30)
#: Estimated bytes per emission: the EmissionList columns (81 B), the generators'
#: temporaries (draws, sorting, concatenation) and the ground truth kept by a render.
BYTES_PER_EMISSION = 400


@dataclass(frozen=True)
class SceneCost:
    """What rendering a scene will take, estimated from its validated keys alone.

    n_emissions   expected number of emissions (packets, for interference bursts)
    n_samples     samples per channel over duration_s
    memory_bytes  n_emissions x BYTES_PER_EMISSION + the config's exponential tables
                  (filter poles and event poles over the response support) + the work
                  arrays of one rendered chunk (1e6 samples x 4 channels x float64, x3)
    output_bytes  the .npz of the command line: 4 n_samples x (2 B int16 when quantizing
                  with <= 16 bits, else 4 B float32) + 81 B per emission of ground truth
    """

    n_emissions: float
    n_samples: int
    memory_bytes: float
    output_bytes: float

    def check(self, budget: Budget | None = None) -> "SceneCost":
        """SceneError when an estimate exceeds the budget (before anything is allocated)."""
        b = DEFAULT_BUDGET if budget is None else budget
        gib = float(1 << 30)
        if b.max_memory_bytes is not None and self.memory_bytes > b.max_memory_bytes:
            raise SceneError(
                f"scene too costly: ~{self.memory_bytes / gib:.3g} GiB of memory"
                f" ({self.n_emissions:.3g} emissions expected, {self.n_samples:.3g} samples per"
                f" channel) exceeds the budget of {b.max_memory_bytes / gib:.3g} GiB; shorten"
                " duration_s or lower the emission rates, sample rate or max_support_s (or"
                " raise the budget: load_scene(..., budget=Budget(max_memory_bytes=...)),"
                " command line --max-memory-gib)"
            )
        if b.max_output_bytes is not None and self.output_bytes > b.max_output_bytes:
            raise SceneError(
                f"scene too costly: the rendered file would be ~{self.output_bytes / gib:.3g} GiB"
                f" ({self.n_samples:.3g} samples x 4 channels) > the budget of"
                f" {b.max_output_bytes / gib:.3g} GiB; shorten duration_s or lower"
                " sensor.sample_rate_hz (or raise the budget: command line --max-output-gib)"
            )
        return self


def _span(start_s, length_s, duration_s) -> float:
    """Overlap (s) of [start, start + length) with the scene [0, duration)."""
    return max(0.0, min(duration_s, start_s + length_s) - start_s)


def expected_emissions(
    gen: str, p: dict, duration_s: float, config: SimConfig, effects: dict, where: str = "params"
) -> float:
    """Expected emission count of generator ``gen`` with validated params ``p`` (an upper
    estimate where the count depends on the play, e.g. a controlled grip). Generators
    without a rule here: the sum of their ``*_hz`` rates x duration plus the lengths of
    their list parameters plus 2."""
    D = duration_s
    rel = 2.0 if effects.get("release_emissions", True) else 1.0
    if gen == "single_touch":
        return 1.0
    if gen == "paper_positions":
        return float(len(p["xs_m"]))
    if gen == "three_pins":
        return float(len(p["times_s"]))
    if gen == "touch_hold_release":
        return 2.0
    if gen == "plane_slip":
        return p["rate_hz"] * _span(p["start_s"], p["slip_duration_s"], D)
    if gen == "random_touches":
        return rel * p["rate_hz"] * D
    if gen == "texture":
        return p["slide_speed_m_s"] / p["period_m"] * _span(p["start_s"], p["slide_duration_s"], D)
    if gen == "stylus":
        return math.floor(p["path_m"] / p["period_m"]) + 2.0
    if gen == "interference":
        return p["rate_hz"] * _span(p["start_s"], p["burst_duration_s"], D) + 2.0
    if gen == "incipient_slip":
        # one front over the Hertz contact area at the initial load, plus both rates over
        # the whole duration (a controlled grip may move the front again: an estimate)
        front = p.get("micro_slip_count")
        if front is None:
            rf = config.geometry.radius_m
            r_obj = p["object_radius_m"]
            r_eff = rf if r_obj is None else 1.0 / (1.0 / rf + 1.0 / r_obj)
            a_h = float(
                G.hertz_contact_radius_m(
                    p["normal_load_n"], r_eff, p["youngs_modulus_pa"], p["poisson_ratio"]
                )
            )
            front = p["front_density_per_m2"] * math.pi * a_h * a_h
        return front + (p["background_rate_hz"] + p["slip_rate_hz"]) * D
    if gen == "composite":
        parts = p["parts"]
        if not isinstance(parts, list) or not parts:
            raise SceneError(
                "params.parts: expected a non-empty list of {at_s, generator, params}"
            )
        total = 0.0
        for i, raw in enumerate(parts):
            w = f"{where}.parts[{i}]"
            part = _validate_map(w, raw, PART_KEYS)
            sub = part["generator"]
            if sub not in GENERATORS or sub == "composite":
                raise SceneError(
                    f"{w}.generator: {sub!r} is not one of "
                    f"{sorted(g for g in GENERATORS if g != 'composite')}"
                )
            sp = _validate_map(f"{w}.params", part["params"], GENERATORS[sub][1])
            total += expected_emissions(
                sub, sp, max(D - part["at_s"], 1e-6), config, effects, f"{w}.params"
            )
        return total
    n = 2.0
    for k, v in p.items():
        if k.endswith("_hz") and isinstance(v, (int, float)):
            n += float(v) * D
        elif isinstance(v, list):
            n += len(v)
    return n


def estimate_cost(
    gen: str, params: dict, duration_s: float, config: SimConfig, effects: dict
) -> SceneCost:
    """`SceneCost` of a validated scene (no generator is run, nothing big allocated)."""
    n_em = expected_emissions(gen, params, duration_s, config, effects)
    n_samples = int(round(duration_s * config.sample_rate_hz))
    support = config.max_support_samples
    lookback = support + int(
        math.ceil(
            4.0
            * config.geometry.radius_m
            / config.geometry.sound_speed_m_s
            * config.sample_rate_hz
        )
    )
    n_fast = config.highpass_order + (config.lowpass_order if config.lowpass_hz else 0)
    # filter-pole tables (re, im and the stacked basis), event-pole tables (two alphas)
    tables = 8.0 * (4 * n_fast * support + 2 * 2 * (lookback + 2))
    n_paths = 1 + (config.n_reflections if config.reflections else 0)
    work = 8.0 * 2 * 32 * 4 * n_paths * support  # numpy engine's per-batch arrays
    chunk = 3 * 8.0 * 4 * min(max(n_samples, 1), 1_000_000)
    memory = n_em * BYTES_PER_EMISSION + tables + work + chunk
    per_sample = 2 if config.quantization and config.adc_bits <= 16 else 4
    output = 4.0 * n_samples * per_sample + 81.0 * n_em
    return SceneCost(
        n_emissions=n_em, n_samples=n_samples, memory_bytes=memory, output_bytes=output
    )


def load_scene(source, overrides: dict | None = None, *, budget: Budget | None = None) -> Scene:
    """Load and validate a scene from a YAML path, a YAML string, or a dict.

    ``overrides`` (optional) are top-level keys replacing the file's (e.g. duration_s, seed).
    ``budget``: the limits its estimated cost (`SceneCost`, ``scene.cost``) must meet
    before anything is generated (default `DEFAULT_BUDGET`: 1 GiB of memory).
    """
    if isinstance(source, dict):
        spec = dict(source)
    else:
        text = source
        name_hint = None
        if isinstance(source, (str, os.PathLike)) and os.path.exists(str(source)):
            with open(source, encoding="utf-8") as fh:
                text = fh.read()
            name_hint = os.path.splitext(os.path.basename(str(source)))[0]
        elif isinstance(source, os.PathLike) or (
            isinstance(source, str)
            and "\n" not in source
            and source.strip().endswith((".yaml", ".yml"))
        ):
            raise SceneError(f"scene file not found: {source}")
        try:
            spec = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise SceneError(f"scene is not valid YAML: {e}") from None
        except RecursionError:
            raise SceneError(
                "scene YAML is nested too deeply (a scene is a mapping of"
                " scalars, lists and mappings a few levels deep)"
            ) from None
        if not isinstance(spec, dict):
            raise SceneError(
                "a scene must be a YAML mapping with at least 'generator' and 'duration_s'"
            )
        if name_hint and "name" not in spec:
            spec["name"] = name_hint
    if overrides:
        spec.update({k: v for k, v in overrides.items() if v is not None})
    top = _validate_map("scene", spec, TOP_KEYS)
    gen = top["generator"]
    if gen not in GENERATORS:
        raise SceneError(
            f"scene.generator: unknown generator {gen!r}; choose one of {sorted(GENERATORS)}"
        )
    sensor = _validate_map("sensor", top["sensor"], SENSOR_KEYS)
    effects = _validate_map("effects", top["effects"], EFFECT_KEYS)
    factory, schema = GENERATORS[gen]
    params = _validate_map("params", top["params"], schema)
    config = build_config(sensor, effects)
    cost = estimate_cost(gen, params, top["duration_s"], config, effects).check(budget)
    noise_rms = 0.0
    if top["noise"] is not None:
        noise = _validate_map("noise", top["noise"], NOISE_KEYS)
        given = [k for k, v in noise.items() if v is not None]
        if len(given) != 1:
            raise SceneError(f"noise: give exactly one of {sorted(NOISE_KEYS)}, got {given}")
        k = given[0]
        if k == "snr_db":
            noise_rms = reference_noise_rms(config, noise[k])
        elif k == "rms_v":
            noise_rms = noise[k]
        else:
            noise_rms = noise_rms_from_density(noise[k], config.sample_rate_hz)
    ctx = SceneContext(
        config=config, seed=top["seed"], duration_s=top["duration_s"], effects=effects
    )
    try:
        process = factory(ctx, params)
    except SceneError:
        raise
    except ValueError as e:
        raise SceneError(f"params ({gen}): {e}") from None
    warm_up()  # compiled renderer ready now, not at the first packet played
    return Scene(
        name=top["name"] or gen,
        generator=gen,
        duration_s=top["duration_s"],
        seed=top["seed"],
        config=config,
        noise_rms_v=float(noise_rms),
        effects=effects,
        params=params,
        process=process,
        spec=spec,
        cost=cost,
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
