# SPDX-License-Identifier: Apache-2.0
"""Propagation from a contact point on the sphere to the four PVDF elements.

Direct path (exact geometry, `ae_tactile.geometry`): straight ray from the contact point
s (|s| = R, upper hemisphere) to element k at e_k = (xi a, eta a, 0),

    l_k = |s - e_k|,   t_k = l_k / c,   pressure jump at element k: S / l_k  (1/l spreading)

with S the signed source strength of the emission (Pa m). The paper's far-field Eq. (2)
is kept in ``FingertipGeometry.far_field_delays_s``; the two agree to first order in a/R.

Wall echoes (``reflections`` switch): the body is a hemisphere on a flat base; by the
mirror image in the base plane (the elements lie in it) it acts as a full sphere of
radius R centred on the array. A ray that leaves s and comes back to the centre after
m specular bounces on the wall runs along the diameter, so the m-th echo reaches element
k over the path

    L_mk = 2 m R + |(-1)^m s - e_k|

(exact for an element at the centre; for an element off-centre the true specular path is
stationary around this one by Fermat's principle, so the error is second order in a/R).
Odd echoes thus arrive from the antipode, with the delay pattern of the direct wave
mirrored; the first one arrives ~2R/c (13.5 us in water) after the direct wave. The
concave wall refocuses the echo toward the centre, so instead of 1/L spreading each
bounce multiplies the pressure at the array centre, S/R, by ``reflection_coefficient``
(default -0.5: a nearly pressure-release skin/air wall with losses in skin and base).

Channel mismatch: every arrival at element k is scaled by ``channel_gain[k]`` and delayed
by ``channel_delay_s[k]`` (the electronics of that channel).

Power-law attenuation (``attenuation_law='power'``, `power_law_transfer`): loss
att_1MHz l (f / 1 MHz)^y with its Kramers-Kronig dispersion, applied per path by FFT in
`render_triggered`.

Attenuation (``attenuation`` switch, ``attenuation_law='pole'``): loss
L_dB(f) = att_1MHz * l * (f / 1 MHz)^2 at low frequency (viscous / Kelvin-Voigt law),
realised causally as one real pole per path,
|W(f)|^2 = 1 / (1 + (f/f_a)^2), with f_a chosen so that the loss at 1 MHz is exactly
att_1MHz * l. A causal loss is dispersive: W adds a group delay 1/(2 pi f_a) that grows
with l (~0.1 us over 1 cm of the silicone preset), so in a lossy body the four channels
are no longer exact delayed copies; the geometric delays stay the ground truth.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def attenuation_pole_rad_s(path_m, att_db_per_m_at_1mhz):
    """omega_a = 2 pi f_a with 10 log10(1 + (1 MHz / f_a)^2) = att * l; inf when lossless."""
    loss_db = np.asarray(path_m, dtype=float) * float(att_db_per_m_at_1mhz)
    with np.errstate(divide="ignore"):
        x = np.expm1(loss_db * (math.log(10.0) / 10.0))
        return np.where(x > 0, 2.0 * math.pi * 1e6 / np.sqrt(np.where(x > 0, x, 1.0)), np.inf)


def power_law_transfer(f_hz, path_m, att_db_per_m_at_1mhz, exponent, ref_hz):
    """Transfer of a path in a power-law lossy medium, relative to the lossless delay l/c.

    H(f) = exp(-a(f) l) exp(-j b(f) l) with a(f) = a1 (f / 1 MHz)^y [Np/m] and the
    Kramers-Kronig (Szabo's time-causal) dispersion
    b(f) = a1 tan(pi y / 2) [(f / 1 MHz)^y - (f / 1 MHz) (f_ref / 1 MHz)^(y-1)] [rad/m],
    which makes c the phase velocity at f_ref.

    Parameters
    ----------
    f_hz : array_like
        Frequencies >= 0 [Hz].
    path_m : array_like
        Path lengths [m], broadcast against ``f_hz``.
    att_db_per_m_at_1mhz, exponent, ref_hz : float
        Loss at 1 MHz [dB/m], y, f_ref [Hz].

    Returns
    -------
    ndarray
        Complex H.
    """
    a1 = float(att_db_per_m_at_1mhz) * math.log(10.0) / 20.0          # [Np/m]
    y = float(exponent)
    x = np.asarray(f_hz, dtype=float) / 1e6
    xr = float(ref_hz) / 1e6
    b = a1 * math.tan(math.pi * y / 2.0) * (x ** y - x * xr ** (y - 1.0))
    return np.exp(-(a1 * x ** y + 1j * b) * np.asarray(path_m, dtype=float))


def apply_power_law(x, path_m, config) -> np.ndarray:
    """Filter windows ``x`` (..., M) [V] by the power-law loss of their paths ``path_m``
    (...) (config's ``attenuation_law='power'``), by FFT: the caller pads the windows so
    that the circular wrap of the loss's short impulse response stays in the padding.

    Parameters
    ----------
    x : ndarray
    path_m : ndarray
    config : SimConfig

    Returns
    -------
    ndarray
    """
    m_len = x.shape[-1]
    f = np.fft.rfftfreq(m_len, config.dt_s)
    h = power_law_transfer(f, np.asarray(path_m)[..., None], config.attenuation_db_per_m,
                           config.attenuation_exponent, config.attenuation_ref_hz)
    return np.fft.irfft(np.fft.rfft(x, axis=-1) * h, n=m_len, axis=-1)


@dataclass(frozen=True)
class Arrivals:
    """All wave arrivals of a batch of emissions at the elements (flat arrays, length n).

    emission   index of the emission in the batch
    channel    element k (0..3)
    path       0 = direct, m >= 1 = m-th wall echo
    delay_s    travel time from the emission instant (s)
    amplitude_pa  signed pressure jump at the element (Pa)
    alpha_1_s  the emission's alpha
    att_pole_rad_s  attenuation pole omega_a, or None when attenuation is off
    """

    emission: np.ndarray
    channel: np.ndarray
    path: np.ndarray
    delay_s: np.ndarray
    amplitude_pa: np.ndarray
    alpha_1_s: np.ndarray
    att_pole_rad_s: np.ndarray | None

    def __len__(self):
        return int(self.emission.shape[0])


def path_lengths(points_m, config) -> np.ndarray:
    """Path lengths (N, n_paths, 4): direct, then the wall echoes if switched on."""
    geo = config.geometry
    p = np.asarray(points_m, dtype=float).reshape(-1, 3)
    direct = geo.path_lengths_m(p)
    if not config.reflections or config.n_reflections == 0:
        return direct[:, None, :]
    out = [direct]
    r = geo.radius_m
    for m in range(1, config.n_reflections + 1):
        sign = -1.0 if m % 2 else 1.0
        out.append(2.0 * m * r + geo.path_lengths_m(sign * p))
    return np.stack(out, axis=1)


def compute_arrivals(points_m, strength_pa_m, alpha_1_s, config) -> Arrivals:
    """Arrivals of N emissions at points (N, 3) with signed strengths S (N,) and alpha (N,).

    Ordered emission-major, then path, then channel.
    """
    p = np.asarray(points_m, dtype=float).reshape(-1, 3)
    n = p.shape[0]
    S = np.broadcast_to(np.asarray(strength_pa_m, dtype=float), (n,))
    al = np.broadcast_to(np.asarray(alpha_1_s, dtype=float), (n,))
    lengths = path_lengths(p, config)                         # (n, P, 4)
    n_paths = lengths.shape[1]
    amp = np.empty_like(lengths)
    amp[:, 0, :] = S[:, None] / lengths[:, 0, :]
    if n_paths > 1:
        r = config.reflection_coefficient
        for m in range(1, n_paths):
            amp[:, m, :] = (S * (r ** m) / config.geometry.radius_m)[:, None]
    # channel gain and delay mismatch of the electronics (1.0 and 0.0: exact no-ops)
    amp *= np.asarray(config.channel_gain, dtype=float)
    delay = lengths / config.geometry.sound_speed_m_s + np.asarray(config.channel_delay_s, float)
    att = None
    if config.attenuation_db_per_m > 0.0 and config.attenuation_law == "pole":
        att = attenuation_pole_rad_s(lengths, config.attenuation_db_per_m).reshape(-1)
        if not np.all(np.isfinite(att)):
            att = None
    emission = np.repeat(np.arange(n), n_paths * 4)
    path = np.tile(np.repeat(np.arange(n_paths), 4), n)
    channel = np.tile(np.arange(4), n * n_paths)
    return Arrivals(emission=emission, channel=channel, path=path,
                    delay_s=delay.reshape(-1), amplitude_pa=amp.reshape(-1),
                    alpha_1_s=np.repeat(al, n_paths * 4), att_pole_rad_s=att)
