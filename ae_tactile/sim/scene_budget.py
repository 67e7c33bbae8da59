# SPDX-License-Identifier: Apache-2.0
"""Scene budget: what a scene will cost (emissions, memory, output size), estimated from
its validated keys alone and checked before anything is generated or allocated
(docs/simulator.md, "Scene budget").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ae_tactile.sim.config import SimConfig
from ae_tactile.sim.incipient_slip import hertz_contact_radius_m
from ae_tactile.sim.scene_schema import GENERATORS, PART_KEYS, SceneError, validate_map


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
        return float(len(p["xs_m"])) * (rel if p.get("hold_s", 0.0) > 0 else 1.0)
    if gen == "three_pins":
        return float(len(p["times_s"])) * (rel if p.get("hold_s", 0.0) > 0 else 1.0)
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
                hertz_contact_radius_m(
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
            part = validate_map(w, raw, PART_KEYS)
            sub = part["generator"]
            if sub not in GENERATORS or sub == "composite":
                raise SceneError(
                    f"{w}.generator: {sub!r} is not one of "
                    f"{sorted(g for g in GENERATORS if g != 'composite')}"
                )
            sp = validate_map(f"{w}.params", part["params"], GENERATORS[sub][1])
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
