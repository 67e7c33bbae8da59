# SPDX-License-Identifier: Apache-2.0
"""YAML scene format and loading.

A scene file (all values SI, the unit is in the key name)::

    generator: single_touch     # which built-in generator (see GENERATORS)
    duration_s: 0.01            # length of the scene
    seed: 0                     # all randomness of the scene (emissions and noise)
    sensor: {...}               # optional SimConfig overrides (SENSOR_KEYS)
    effects: {...}              # optional switches (EFFECT_KEYS)
    noise: {snr_db: 30}         # optional, exactly one of snr_db / rms_v / density_v_per_rthz
    params: {...}               # generator parameters (GENERATORS[name] schema)

``load_scene(path_or_dict)`` validates everything (the keys: `scene_schema.py`) and fails
with a `SceneError` (a ValueError) naming the offending key: unknown keys (with the
allowed ones), missing required keys, values of the wrong type or given with units as
strings ("10 mm"), implausible magnitudes (e.g. a radius in millimetres), and contact
points off the sensing surface. A scene whose estimated cost exceeds the budget is
refused before anything is generated (`scene_budget.py`).

noise.snr_db is relative to the scene's reference emission: a default touch (0.3 m/s,
a_c = 1/mm) at the apex, with the SNR definition of docs/conventions.md; rms_v is the
per-channel sigma; density_v_per_rthz gives sigma = density sqrt(fs/2).

Re-exported here for the scene's users: `SceneError`, `GENERATORS`, `Budget`,
`DEFAULT_BUDGET`, `CLI_BUDGET`, `SceneCost`, `scene_schema_markdown`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
import yaml

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.sim.config import MEDIUM_PRESETS, SimConfig
from ae_tactile.sim.frontend import noise_rms_for_snr, noise_rms_from_density
from ae_tactile.sim.kernels import warm_up
from ae_tactile.sim.scene_budget import (
    CLI_BUDGET,
    DEFAULT_BUDGET,
    Budget,
    SceneCost,
    estimate_cost,
)
from ae_tactile.sim.scene_schema import (
    EFFECT_KEYS,
    GENERATORS,
    NOISE_KEYS,
    SENSOR_KEYS,
    TOP_KEYS,
    SceneContext,
    SceneError,
    check_event_times,
    scene_schema_markdown,
    validate_map,
)
from ae_tactile.sim.stream import StreamingSource, TriggeredSource
from ae_tactile.sim.triggered import render_triggered

__all__ = [
    "Scene",
    "SceneError",
    "load_scene",
    "reference_noise_rms",
    "build_config",
    "GENERATORS",
    "Budget",
    "DEFAULT_BUDGET",
    "CLI_BUDGET",
    "SceneCost",
    "scene_schema_markdown",
]


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
        """Samples per channel over ``duration_s``."""
        return int(round(self.duration_s * self.config.sample_rate_hz))

    @property
    def truth(self) -> dict:
        """Scene-level ground truth (e.g. gross_slip_time_ns)."""
        return self.process.scene_truth()

    def streaming_source(self, **kw) -> StreamingSource:
        """A fresh stream of this scene (the process is shared: build the scene again for
        an independent replay).

        Parameters
        ----------
        **kw
            `StreamingSource` options (``start_index``, ``keep_clean``).

        Returns
        -------
        StreamingSource
        """
        return StreamingSource(
            self.process, self.config, noise_rms_v=self.noise_rms_v, seed=self.seed, **kw
        )

    def triggered_source(self, **kw) -> TriggeredSource:
        """Packets of this scene's emissions before its end (``end_ns`` = duration_s).

        Parameters
        ----------
        **kw
            `TriggeredSource` options (``pretrigger_s``, ``window_s``, ``render_path``,
            ``engine``, ``keep_clean``, ``end_ns``).

        Returns
        -------
        TriggeredSource
        """
        kw.setdefault("end_ns", int(round(self.duration_s * 1e9)))
        return TriggeredSource(
            self.process, self.config, noise_rms_v=self.noise_rms_v, seed=self.seed, **kw
        )


def reference_noise_rms(config: SimConfig, snr_db: float) -> float:
    """The noise sigma giving ``snr_db`` (docs/conventions.md) for the reference touch at
    the apex (default event parameters, noise-free and unquantized).

    Parameters
    ----------
    config : SimConfig
        The simulated sensor.
    snr_db : float
        SNR of the reference touch [dB].

    Returns
    -------
    float
        Noise sigma per channel [V].
    """
    apex = np.array([[0.0, 0.0, config.geometry.radius_m]])
    pk = render_triggered(apex, config.replace(quantization=False), subsample_offset=0.0)
    return float(noise_rms_for_snr(pk.signal_power_v2[0], snr_db))


def build_config(sensor: dict, effects: dict) -> SimConfig:
    """The `SimConfig` of validated ``sensor`` and ``effects`` sections (SceneError if the
    combination does not validate)."""
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


def _read_spec(source) -> dict:
    """The scene mapping of a dict, a YAML file path or a YAML string (a file's name, without
    its extension, becomes the scene's default name)."""
    if isinstance(source, dict):
        return dict(source)
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
    return spec


def _noise_rms_v(noise_spec, config: SimConfig) -> float:
    """Per-channel noise sigma [V] of a scene's ``noise`` section (0 without one)."""
    if noise_spec is None:
        return 0.0
    noise = validate_map("noise", noise_spec, NOISE_KEYS)
    given = [k for k, v in noise.items() if v is not None]
    if len(given) != 1:
        raise SceneError(f"noise: give exactly one of {sorted(NOISE_KEYS)}, got {given}")
    k = given[0]
    if k == "snr_db":
        return reference_noise_rms(config, noise[k])
    if k == "rms_v":
        return noise[k]
    return noise_rms_from_density(noise[k], config.sample_rate_hz)


def load_scene(source, overrides: dict | None = None, *, budget: Budget | None = None) -> Scene:
    """Load and validate a scene, ready to play.

    Parameters
    ----------
    source : str, os.PathLike or dict
        A YAML file path, a YAML string, or the scene mapping itself.
    overrides : dict, optional
        Top-level keys replacing the file's (e.g. ``duration_s``, ``seed``); None values
        are ignored.
    budget : Budget, optional
        The limits the scene's estimated cost (`SceneCost`, ``scene.cost``) must meet before
        anything is generated (default `DEFAULT_BUDGET`: 1 GiB of memory).

    Returns
    -------
    Scene
        The validated scene (config, noise level, emission process); the compiled
        renderer is warmed up (`kernels.warm_up`) so that the first packet is not delayed.

    Raises
    ------
    SceneError
        When the scene does not validate or exceeds the budget (the message names the key).
    """
    spec = _read_spec(source)
    if overrides:
        spec.update({k: v for k, v in overrides.items() if v is not None})
    top = validate_map("scene", spec, TOP_KEYS)
    gen = top["generator"]
    if gen not in GENERATORS:
        raise SceneError(
            f"scene.generator: unknown generator {gen!r}; choose one of {sorted(GENERATORS)}"
        )
    sensor = validate_map("sensor", top["sensor"], SENSOR_KEYS)
    effects = validate_map("effects", top["effects"], EFFECT_KEYS)
    factory, schema = GENERATORS[gen]
    params = validate_map("params", top["params"], schema)
    check_event_times("params", top["params"], params, top["duration_s"])
    config = build_config(sensor, effects)
    cost = estimate_cost(gen, params, top["duration_s"], config, effects).check(budget)
    noise_rms = _noise_rms_v(top["noise"], config)
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
