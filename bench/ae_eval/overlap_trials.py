# SPDX-License-Identifier: Apache-2.0
"""Trials of overlapping emissions for the overlap benchmark and tests: windows holding two
or three emissions rendered by the simulator (`simulate_overlaps`), with their truth."""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.sim import SimConfig, render_triggered, signal_power_v2
from ae_tactile.sim.frontend import noise_rms_for_snr, quantize

__all__ = ["simulate_overlaps"]


def simulate_overlaps(
    n,
    config=None,
    *,
    separation_s,
    n_sources=2,
    amplitude_ratio=1.0,
    snr_db=25.0,
    snr_reference="weaker",
    min_distance_m=2e-3,
    max_polar_deg=60.0,
    rng=None,
    pretrigger_s=8e-6,
    window_s=40e-6,
):
    """``n`` windows holding ``n_sources`` (2 or 3) emissions, from the simulator
    (``ae_tactile.sim``). Linear acoustics: each emission is rendered alone, noise-free, by
    `render_triggered` (exact sub-sample arrival, wall echoes per ``config``), shifted to its
    emission time and summed; then white noise and the ADC.

    separation_s: time between successive emissions (scalar, (n,) or (n, J-1)).
    amplitude_ratio: strongest / weakest source strength (>= 1). Two emissions: which one
    is stronger is random; three: the strengths are log-uniform in [1/ratio, 1] with one
    of them at 1 and one at 1/ratio. snr_db: the SNR (docs/conventions.md, over each
    emission's own 30 us window) of the weakest (``snr_reference='weaker'``) or strongest
    emission. Points uniform by area over the cap polar <= max_polar_deg, pairwise at
    least ``min_distance_m`` apart; random polarities.

    Returns dict: samples_v (n, 4, M), clean_v, onset_index (n,), points_m (n, J, 3),
    emission_time_s (n, J) (window time), polarity (n, J), strength (n, J) relative,
    noise_rms_v (n,), arrival_times_s (n, J, 4), sample_rate_hz, config.
    """
    cfg = SimConfig(reflections=True) if config is None else config
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    geo = cfg.geometry
    fs = float(cfg.sample_rate_hz)
    n = int(n)
    J = int(n_sources)
    if J not in (2, 3):
        raise ValueError("n_sources must be 2 or 3")
    ratio = float(amplitude_ratio)
    if not ratio >= 1.0:
        raise ValueError("amplitude_ratio must be >= 1 (strongest / weakest)")
    if snr_reference not in ("weaker", "stronger"):
        raise ValueError("snr_reference must be 'weaker' or 'stronger'")
    sep = np.asarray(separation_s, float)
    sep = np.broadcast_to(sep[:, None] if sep.ndim == 1 else sep, (n, J - 1)).copy()

    def draw(m):
        cos_t = gen.uniform(math.cos(math.radians(max_polar_deg)), 1.0, m)
        phi = gen.uniform(0.0, 2 * math.pi, m)
        return geo.surface_point_from_angles(np.arccos(cos_t), phi)

    pts = [draw(n)]
    for _ in range(1, J):
        p = draw(n)
        close = np.min([np.linalg.norm(q - p, axis=1) for q in pts], axis=0) < min_distance_m
        while close.any():
            p[close] = draw(int(close.sum()))
            close = np.min([np.linalg.norm(q - p, axis=1) for q in pts], axis=0) < min_distance_m
        pts.append(p)
    pts = np.stack(pts, axis=1)
    if J == 2:
        strong_first = gen.random(n) < 0.5
        rel = np.where(strong_first[:, None], [1.0, 1.0 / ratio], [1.0 / ratio, 1.0])
    else:
        rel = np.exp(gen.uniform(-math.log(ratio), 0.0, (n, J)))
        perm = np.argsort(gen.random((n, J)), axis=1)
        rows = np.arange(n)
        rel[rows, perm[:, 0]] = 1.0
        rel[rows, perm[:, 1]] = 1.0 / ratio
    pol = gen.choice([-1.0, 1.0], size=(n, J))
    speed = 0.3 * np.sqrt(rel)
    clean_cfg = cfg.replace(quantization=False)
    first = render_triggered(
        pts[:, 0],
        clean_cfg,
        polarity=pol[:, 0],
        speed_m_s=speed[:, 0],
        pretrigger_s=pretrigger_s,
        window_s=window_s,
        rng=gen,
    )
    m_len = first.clean_v.shape[2]
    clean = first.clean_v.copy()
    powers = [signal_power_v2(first.clean_v, first.onset_index, fs)]
    t_emit = [first.emission_time_s]
    arrivals = [first.arrival_times_s]
    for j in range(1, J):
        te = t_emit[-1] + sep[:, j - 1]
        tf = te + geo.arrival_times_s(pts[:, j]).min(axis=1)
        n_int = np.floor(tf * fs).astype(np.int64)
        u = np.clip(tf * fs - n_int, 0.0, 1.0 - 1e-12)
        b = render_triggered(
            pts[:, j],
            clean_cfg,
            polarity=pol[:, j],
            speed_m_s=speed[:, j],
            pretrigger_s=0.0,
            window_s=window_s,
            subsample_offset=u,
            rng=gen,
        )
        for i in range(n):
            k = int(n_int[i])
            if 0 <= k < m_len:
                clean[i, :, k:] += b.clean_v[i, :, : m_len - k]
        powers.append(signal_power_v2(b.clean_v, b.onset_index, fs))
        t_emit.append(te)
        arrivals.append(te[:, None] + geo.arrival_times_s(pts[:, j]))
    powers = np.stack(powers, axis=1)
    p_ref = powers.min(axis=1) if snr_reference == "weaker" else powers.max(axis=1)
    sigma = noise_rms_for_snr(p_ref, np.broadcast_to(np.asarray(snr_db, float), (n,)))
    noisy = clean + sigma[:, None, None] * gen.standard_normal(clean.shape)
    if cfg.quantization:
        noisy, _ = quantize(noisy, cfg, out=noisy)
    arrivals = np.stack(arrivals, axis=1)
    onset = np.ceil(arrivals.min(axis=(1, 2)) * fs - 1e-9).astype(np.int64)
    return dict(
        samples_v=noisy,
        clean_v=clean,
        onset_index=onset,
        points_m=pts,
        emission_time_s=np.stack(t_emit, axis=1),
        polarity=pol,
        strength=rel,
        noise_rms_v=sigma,
        arrival_times_s=arrivals,
        sample_rate_hz=fs,
        config=cfg,
    )
