# SPDX-License-Identifier: Apache-2.0
"""Simulated fingertip: what the four PVDF channels of the real sensor would output.

Pure Python (numpy/scipy/pyyaml), never imports rclpy. Physics in one line per stage:

* emission (emission.py): the paper's collision pulse, Eq. 10,
  p(t) = rho v0^2/(a_c l) (2 e^{-2 alpha tau} - e^{-alpha tau}), tau = t - l/c > 0;
  release = opposite polarity; Eq. 11 jump rho v0^2/(a_c l) = 9 Pa for the paper's numbers.
* propagation (propagation.py): exact straight paths l_k = |s - e_k| from the contact
  point to each element (geometry.py), 1/l spreading, optional wall echoes and
  frequency-dependent attenuation (medium presets 'water_skin', 'silicone').
* front end (frontend.py): PVDF + amplifier gain (V/Pa), Butterworth high-pass
  (100 kHz, order 2) and anti-alias low-pass (1 MHz, order 4; below 3.33 MS/s 0.3 fs,
  order 8), white Gaussian noise at
  a given SNR or rms, 12-bit ADC at 10 MS/s with clipping.
* response.py: the filtered response of every arrival is evaluated in closed form
  (partial fractions of a rational transfer function) at the sample instants: exact
  for any sub-sample delay, and the same sample values whatever window is rendered.

Triggered-packet API (for localization, CRLBs, benchmarks)
----------------------------------------------------------
    from ae_tactile.sim import SimConfig, render_triggered
    cfg = SimConfig()             # or SimConfig.for_medium('silicone', attenuation=True)
    pk = render_triggered(points_m, cfg, snr_db=30, rng=0)
    pk.samples_v        # (N, 4, M) volts, channel order of geometry.CHANNEL_XI_ETA
    pk.clean_v          # (N, 4, M) noise-free, unquantized
    pk.onset_index      # (N,) first sample at/after the earliest direct arrival
    pk.delays_s         # (N, 2) exact (tau_x, tau_y); pk.arrival_times_s (N, 4)
    pk.noise_rms_v, pk.snr_db, pk.signal_power_v2, pk.saturated, pk.points_m

``render_triggered(points_m (N, 3), config=None, *, snr_db=None | noise_rms_v=None,
polarity=+1|-1 or (N,), speed_m_s=0.3, curvature_1_m=1000, alpha_1_s=3000,
pretrigger_s=8e-6, window_s=40e-6, subsample_offset='random' | u in [0,1), rng=None)``
-> `TriggeredPackets`. Points must lie on the upper hemisphere
(``cfg.geometry.surface_point_from_xy(x, y)`` builds them). The default window is
400 samples: 80 before the trigger (+ a random sub-sample offset) and the 30 us SNR
window after it. SNR follows docs/conventions.md; the conversion lives in
`frontend.noise_rms_for_snr` / `frontend.signal_power_v2` for other modules to reuse.

`SimConfig` fields (SI units, validated with clear ValueErrors): geometry, medium,
density_kg_m3, attenuation_db_per_m_at_1mhz, sensitivity_v_per_pa (0.01),
highpass_hz (100e3), highpass_order (2), lowpass_hz ("auto": min(1e6, 0.3 fs); a number;
None), lowpass_order ("auto": 4, or 8 below 1 MHz), sample_rate_hz (10e6), adc_bits (12),
adc_full_scale_v (1.0),
attenuation (False), reflections (False), reflection_coefficient (-0.5), n_reflections (2),
quantization (True), support_rel_tol (1e-6), max_support_s (200e-6).

Streaming (`stream.py`): `EmissionList` (ground truth: time_ns, point_m, kind, signed
strength, event parameters, event_id), `StreamRenderer.render(emissions, n0, n1)` for any
window of absolute samples (bit-identical to a full render), `StreamingSource.next_chunk(n)`
(samples (4, n) + the emissions in them), `TriggeredSource.next_packets(n)` (windows cut
from the stream around each emission: the virtual device's path, which renders only the
window's samples and noise, bit-identical to the stream). Engines: compiled kernels
(kernels.py, numba; compiled or loaded from the cache by the first `load_scene`, or by
`kernels.warm_up()`) or numpy (the reference and the fallback without numba).

Scenes (`scene.py`): `load_scene('config/scenes/x.yaml')` -> `Scene` with
`.streaming_source()`, `.triggered_source()`, `.truth`; the incipient-slip scene's
`scene.process.set_normal_load(P, at_time_ns)` changes the grip while it plays. A scene
whose estimated cost (`scene.cost`: emissions, memory, output size) exceeds the budget
(1 GiB of memory; 16 GiB of output on the command line) is refused with a SceneError.
CLI: ``python3 -m ae_tactile.sim.cli scene.yaml -o out.npz``. Full description, scene
keys and benchmark: docs/simulator.md.

Modules, in import order (each imports only modules listed before it):

* physics: emission.py (Eqs. 6-11), propagation.py (paths, echoes, attenuation pole),
  kernels.py (the compiled sample formula), response.py (exact sampled responses),
  frontend.py (filters, SNR, ADC), config.py (`SimConfig`);
* rendering: triggered.py (batch triggered packets), emission_list.py (ground truth),
  renderer.py (`StreamRenderer`, the stream's noise), stream.py (the two sources),
  interference.py (common-mode interference packets);
* scenes: generator_tools.py, incipient_slip.py, generators.py (emission processes),
  scene_schema.py (keys, validation, generator registry), scene_budget.py (cost),
  scene.py (`load_scene`), cli.py (render a scene to .npz).
"""
from ae_tactile.sim.config import MEDIUM_PRESETS, Medium, SimConfig
from ae_tactile.sim.emission import (
    DEFAULT_ALPHA_1_S,
    DEFAULT_CURVATURE_1_M,
    DEFAULT_SPEED_M_S,
    collision_pressure_pa,
    peak_pressure_pa,
    source_strength_pa_m,
)
from ae_tactile.sim.frontend import (
    SNR_WINDOW_S,
    noise_rms_for_snr,
    noise_rms_from_density,
    signal_power_v2,
    snr_db_from_noise,
)
from ae_tactile.sim.stream import (
    KINDS,
    Chunk,
    EmissionList,
    StreamingSource,
    StreamPackets,
    StreamRenderer,
    TriggeredSource,
)
from ae_tactile.sim.triggered import TriggeredPackets, render_triggered, validate_surface_points

__all__ = [
    "SimConfig", "Medium", "MEDIUM_PRESETS",
    "DEFAULT_SPEED_M_S", "DEFAULT_CURVATURE_1_M", "DEFAULT_ALPHA_1_S",
    "collision_pressure_pa", "peak_pressure_pa", "source_strength_pa_m",
    "SNR_WINDOW_S", "noise_rms_for_snr", "noise_rms_from_density", "signal_power_v2",
    "snr_db_from_noise",
    "TriggeredPackets", "render_triggered", "validate_surface_points",
    "KINDS", "EmissionList", "StreamRenderer", "StreamingSource", "TriggeredSource", "Chunk",
    "StreamPackets",
]
