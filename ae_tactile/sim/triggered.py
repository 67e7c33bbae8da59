# SPDX-License-Identifier: Apache-2.0
"""Batch triggered renderer: one short 4-channel window per emission, as a hardware
trigger would capture it. Vectorized over packets.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ae_tactile.sim.config import SimConfig
from ae_tactile.sim.emission import (
    COMPRESSION,
    DEFAULT_CURVATURE_1_M,
    DEFAULT_SPEED_M_S,
    source_strength_pa_m,
)
from ae_tactile.sim.frontend import SNR_WINDOW_S, noise_rms_for_snr, quantize, signal_power_v2
from ae_tactile.sim.propagation import apply_power_law, compute_arrivals, path_lengths
from ae_tactile.sim.response import arrival_coefficients, evaluate

_BATCH = 1024
#: Padding of each side of a window rendered with the power loss law [s]: the loss's
#: impulse response (and its circular wrap in the FFT) is far shorter.
_LOSS_PAD_S = 10e-6


@dataclass(frozen=True)
class TriggeredPackets:
    """Rendered packets and their ground truth. All times relative to each window's first
    sample (sample m is at t = m / fs).

    samples_v       (N, 4, M) float64 ADC output in volts (codes * LSB when quantizing)
    clean_v         (N, 4, M) noise-free, unquantized front-end output (for CRLBs)
    sample_rate_hz  float
    onset_index     (N,) int64 first sample at or after the earliest direct arrival
    points_m        (N, 3) true contact points
    delays_s        (N, 2) exact (tau_x, tau_y) of the direct wave (geometry.py definition)
    twist_s         (N,) the exact geometry's twist term
    arrival_times_s (N, 4) direct-wave arrival time at each element
    emission_time_s (N,) emission instant (may be negative: before the window)
    noise_rms_v     (N,) sigma of the added noise (0 if none)
    snr_db          (N,) SNR per docs/conventions.md (inf without noise)
    signal_power_v2 (N,) P_signal of that definition
    saturated       (N,) bool, some sample clipped at ADC full scale
    polarity        (N,) +1 touch, -1 release
    """

    samples_v: np.ndarray
    clean_v: np.ndarray
    sample_rate_hz: float
    onset_index: np.ndarray
    points_m: np.ndarray
    delays_s: np.ndarray
    twist_s: np.ndarray
    arrival_times_s: np.ndarray
    emission_time_s: np.ndarray
    noise_rms_v: np.ndarray
    snr_db: np.ndarray
    signal_power_v2: np.ndarray
    saturated: np.ndarray
    polarity: np.ndarray

    def __len__(self):
        return int(self.samples_v.shape[0])


def validate_surface_points(points_m, geometry, rel_tol=1e-6) -> np.ndarray:
    """(N, 3) float array of points on the upper hemisphere, else a ValueError naming the
    first offending point."""
    p = np.asarray(points_m, dtype=float)
    if p.ndim == 1 and p.shape == (3,):
        p = p[None, :]
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points_m must have shape (N, 3), got {np.shape(points_m)}")
    bad = ~np.all(np.isfinite(p), axis=1)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise ValueError(f"point {i} is not finite: {p[i].tolist()}")
    r = np.linalg.norm(p, axis=1)
    off = np.abs(r - geometry.radius_m) > rel_tol * geometry.radius_m
    if np.any(off):
        i = int(np.argmax(off))
        raise ValueError(f"point {i} = {p[i].tolist()} m is off the sensing surface:"
                         f" |s| = {r[i]:.6g} m, expected R = {geometry.radius_m} m"
                         " (use geometry.surface_point_from_xy)")
    below = p[:, 2] < -rel_tol * geometry.radius_m
    if np.any(below):
        i = int(np.argmax(below))
        raise ValueError(f"point {i} = {p[i].tolist()} m is below the sensing hemisphere (z < 0)")
    return p


def _per_packet(name, value, n, positive=True):
    v = np.asarray(value, dtype=float)
    if v.ndim == 0:
        v = np.full(n, float(v))
    if v.shape != (n,):
        raise ValueError(f"{name} must be a scalar or have shape ({n},), got {v.shape}")
    if not np.all(np.isfinite(v)) or (positive and np.any(v <= 0)):
        raise ValueError(f"{name} must be {'positive and ' if positive else ''}finite")
    return v


def _window_samples(cfg, pretrigger_s, window_s, snr_db, noise_rms_v) -> tuple[int, float]:
    """(M, pretrigger [s]) of a triggered window, checked: the window exceeds the pretrigger
    by a sample, and holds the SNR window after the onset when ``snr_db`` is given."""
    fs = float(cfg.sample_rate_hz)
    m_len = int(round(float(window_s) * fs))
    pre = float(pretrigger_s)
    if not (math.isfinite(pre) and pre >= 0):
        raise ValueError(f"pretrigger_s must be >= 0, got {pretrigger_s!r}")
    if m_len < 2 or pre * fs + 1 >= m_len:
        raise ValueError(f"window_s={window_s} must exceed pretrigger_s={pretrigger_s}"
                         " by at least a sample")
    if snr_db is not None and noise_rms_v is not None:
        raise ValueError("give snr_db or noise_rms_v, not both")
    if snr_db is not None and (m_len - (pre * fs + 1)) < round(SNR_WINDOW_S * fs):
        raise ValueError(f"snr_db needs the {SNR_WINDOW_S * 1e6:g} us SNR window after the"
                         " onset inside the packet: window_s - pretrigger_s must be >="
                         f" {SNR_WINDOW_S * 1e6:g} us + 1 sample")
    return m_len, pre


def _subsample_offsets(subsample_offset, n, gen) -> np.ndarray:
    """u (n,) in [0, 1): drawn from ``gen`` for 'random', else the given value(s)."""
    if isinstance(subsample_offset, str):
        if subsample_offset != "random":
            raise ValueError("subsample_offset must be 'random' or a number in [0, 1)")
        return gen.random(n)
    u = _per_packet("subsample_offset", subsample_offset, n, positive=False)
    if np.any((u < 0) | (u >= 1)):
        raise ValueError("subsample_offset must lie in [0, 1)")
    return u


def _render_clean(pts, strength, alpha, t_first, direct_t, cfg, m_len) -> np.ndarray:
    """Noise-free windows (N, 4, M) [V] whose earliest direct arrival is at ``t_first`` [s]
    after the first sample, in batches of _BATCH emissions. With the power loss law each
    path is rendered on a window padded by `_LOSS_PAD_S` on both sides, filtered by its
    loss (`propagation.apply_power_law`) and cropped."""
    n = pts.shape[0]
    power = cfg.attenuation_db_per_m > 0.0 and cfg.attenuation_law == "power"
    pad = int(math.ceil(_LOSS_PAD_S * cfg.sample_rate_hz)) if power else 0
    m_ext = m_len + 2 * pad
    clean = np.zeros((n, 4, m_len))
    for b0 in range(0, n, _BATCH):
        sl = slice(b0, min(n, b0 + _BATCH))
        nb = sl.stop - sl.start
        arr = compute_arrivals(pts[sl], strength[sl], alpha[sl], cfg)
        # offset from the window start = t_first + (delay - min direct delay) >= 0
        off = (t_first[sl] - direct_t[sl].min(axis=1))[arr.emission] + arr.delay_s
        if pad:
            off = off + pad * cfg.dt_s
        co = arrival_coefficients(arr.amplitude_pa, arr.alpha_1_s, arr.att_pole_rad_s,
                                  np.zeros(len(arr), np.int64), off, cfg)
        y = evaluate(co, cfg, n_samples=m_ext)                # (n_arr, M)
        # shift row a right by n0_a samples: window M - n0_a of [zeros(M) | y]
        padded = np.concatenate([np.zeros_like(y), y], axis=1)
        view = np.lib.stride_tricks.sliding_window_view(padded, m_ext, axis=1)
        placed = view[np.arange(len(co)), np.clip(m_ext - co.n0, 0, m_ext)]
        n_paths = len(arr) // (4 * nb)
        placed = placed.reshape(nb, n_paths, 4, m_ext)
        if pad:
            placed = apply_power_law(placed, path_lengths(pts[sl], cfg), cfg)[..., pad:pad + m_len]
        clean[sl] = placed.sum(axis=1)
    return clean


def _add_noise(samples, sigma, cfg, gen) -> None:
    """Add the noise of sigma [V] (N,) per packet in place: white, and the config's
    ``amplifier_noise_share`` of the variance as amplifier noise through the chain."""
    share = float(cfg.amplifier_noise_share)
    samples += (sigma * math.sqrt(1.0 - share))[:, None, None] * gen.standard_normal(samples.shape)
    if share > 0.0:
        coloured = cfg.frontend.amplifier_noise.draw(samples.shape, gen)
        samples += (sigma * math.sqrt(share))[:, None, None] * coloured


def _noise_levels(clean, onset, fs, snr_db, noise_rms_v):
    """(sigma [V], SNR [dB], P_signal [V^2]) per packet, from ``snr_db`` or ``noise_rms_v``
    (neither: no noise, SNR inf); P_signal is NaN when the SNR window does not fit."""
    n, _, m_len = clean.shape
    if snr_db is not None:
        snr = _per_packet("snr_db", snr_db, n, positive=False)
        p_sig = signal_power_v2(clean, onset, fs)
        return noise_rms_for_snr(p_sig, snr), snr, p_sig
    p_sig = (signal_power_v2(clean, onset, fs)
             if m_len - onset.max() >= round(SNR_WINDOW_S * fs) else np.full(n, np.nan))
    if noise_rms_v is not None:
        sigma = _per_packet("noise_rms_v", noise_rms_v, n, positive=False)
        if np.any(sigma < 0):
            raise ValueError("noise_rms_v must be >= 0")
    else:
        sigma = np.zeros(n)
    with np.errstate(divide="ignore"):
        snr = 10.0 * np.log10(p_sig / sigma ** 2)
    return sigma, snr, p_sig


def render_triggered(points_m, config: SimConfig | None = None, *, snr_db=None, noise_rms_v=None,
                     polarity=COMPRESSION, speed_m_s=DEFAULT_SPEED_M_S,
                     curvature_1_m=DEFAULT_CURVATURE_1_M, alpha_1_s=None,
                     pretrigger_s=8e-6, window_s=40e-6, subsample_offset="random",
                     rng=None) -> TriggeredPackets:
    """Render one triggered window per emission on the sphere, as a hardware trigger would
    capture it.

    The window holds M = round(window_s fs) samples; the earliest direct arrival lies at
    pretrigger_s + u / fs after its first sample. The defaults (8 us + 32 us) leave the
    30 us SNR window after the onset inside the packet.

    Parameters
    ----------
    points_m : array_like
        (N, 3) contact points on the upper hemisphere [m]
        (``config.geometry.surface_point_from_xy`` builds them).
    config : SimConfig, optional
        The simulated sensor (default ``SimConfig()``, the paper's water-skin tip).
    snr_db, noise_rms_v : float or array_like, optional
        Noise level per packet, not both: SNR [dB] (docs/conventions.md) or sigma [V];
        neither gives noise-free packets. Scalar or (N,).
    polarity : int or array_like
        +1 compression (touch), -1 rarefaction (release); scalar or (N,).
    speed_m_s, curvature_1_m, alpha_1_s : float or array_like
        Eq. 10 event parameters (emission.py) [m/s], [1/m], [1/s]; scalar or (N,);
        ``alpha_1_s`` None: the config's ``emission_alpha_1_s``.
    pretrigger_s, window_s : float
        Window start before the earliest direct arrival, and window length [s].
    subsample_offset : 'random' or float or array_like
        u in [0, 1): the arrival's fraction of a sample after the pretrigger; 'random'
        (default) draws it, as real triggers are not sample-aligned.
    rng : int, numpy.random.Generator or None
        Seed or generator of the offsets and the noise.

    Returns
    -------
    TriggeredPackets
        Samples, noise-free signal and ground truth of each window.
    """
    cfg = SimConfig() if config is None else config
    if not isinstance(cfg, SimConfig):
        raise TypeError(f"config must be a SimConfig, got {type(cfg).__name__}")
    pts = validate_surface_points(points_m, cfg.geometry)
    n = pts.shape[0]
    fs = float(cfg.sample_rate_hz)
    m_len, pre = _window_samples(cfg, pretrigger_s, window_s, snr_db, noise_rms_v)
    pol = _per_packet("polarity", polarity, n, positive=False)
    if not np.all(np.isin(pol, (-1.0, 1.0))):
        raise ValueError("polarity must be +1 (touch) or -1 (release)")
    speed = _per_packet("speed_m_s", speed_m_s, n)
    curv = _per_packet("curvature_1_m", curvature_1_m, n)
    alpha = _per_packet("alpha_1_s", cfg.emission_alpha_1_s if alpha_1_s is None else alpha_1_s, n)
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    u = _subsample_offsets(subsample_offset, n, gen)

    geo = cfg.geometry
    direct_t = geo.arrival_times_s(pts)                       # (N, 4) travel times [s]
    t_first = pre + u * cfg.dt_s                              # earliest direct arrival [s]
    t_emit = t_first - direct_t.min(axis=1)
    onset = np.ceil(t_first * fs - 1e-9).astype(np.int64)
    strength = source_strength_pa_m(speed, curv, cfg.density, pol)
    clean = _render_clean(pts, strength, alpha, t_first, direct_t, cfg, m_len)

    sigma, snr, p_sig = _noise_levels(clean, onset, fs, snr_db, noise_rms_v)
    samples = clean.copy()
    if np.any(sigma > 0):
        _add_noise(samples, sigma, cfg, gen)
    if cfg.quantization:
        samples, clipped = quantize(samples, cfg, out=samples)
        saturated = clipped.any(axis=(1, 2))
    else:
        saturated = (np.abs(samples) >= cfg.adc_full_scale_v).any(axis=(1, 2))
    d = geo.delays_from_arrival_times(direct_t)
    return TriggeredPackets(samples_v=samples, clean_v=clean, sample_rate_hz=fs, onset_index=onset,
                            points_m=pts, delays_s=d[:, :2], twist_s=d[:, 2],
                            arrival_times_s=t_emit[:, None] + direct_t, emission_time_s=t_emit,
                            noise_rms_v=sigma, snr_db=np.asarray(snr, float),
                            signal_power_v2=p_sig,
                            saturated=saturated, polarity=pol)
