# SPDX-License-Identifier: Apache-2.0
"""Acoustic emission at a contact: the paper's collision model (Eqs. 6-11).

A rigid convex surface z = a_c (x^2 + y^2)/2 meets the flat skin at speed v0; the
indentation grows as u0 (1 - e^{-alpha t}) with v0 = alpha u0. At distance l the
pressure is (Eq. 10)

    p(t) = rho v0^2 / (a_c l) * (2 e^{-2 alpha (t - l/c)} - e^{-alpha (t - l/c)}),  t > l/c

i.e. a step of height rho v0^2/(a_c l) at the arrival followed by a zero-mean recovery
(the pulse integrates to zero). Laplace transform (Eq. 9), with A = rho v0^2/(a_c l):

    P(s) = A (2/(s + 2 alpha) - 1/(s + alpha)) = A s / ((s + alpha)(s + 2 alpha)),

so well above 2 alpha it is a step (1/s) and a high-pass with cut-off omega_0 >> alpha
turns it into a pulse of height A (Eq. 11) lasting ~ 1/omega_0.

A release (detouch) emits the same shape with the opposite sign (polarity RAREFACTION = -1,
a touch COMPRESSION = +1).
The signed source strength ``S = polarity rho v0^2 / a_c`` (Pa m) is what the
simulator carries per emission; the pressure jump at distance l is S / l.

Default event parameters (the paper's example, Eq. 11): v0 = 0.3 m/s,
a_c = 1/mm = 1000 1/m, and alpha = 3000 1/s (indentation u0 = v0/alpha = 0.1 mm,
contact radius sqrt(2 u0 / a_c) ~ 0.45 mm). With the 100 kHz high-pass,
omega_0 / alpha ~ 200, the paper's omega_0 >> alpha regime; the spectrum of the
emission is ~1/f from 2 alpha / 2 pi ~ 1 kHz upward, so the band the sensor sees
(0.1 - 1 MHz) is set by the front-end filters, not by alpha.
"""
from __future__ import annotations

import numpy as np

DEFAULT_SPEED_M_S = 0.30          # [m/s] contact speed v0
DEFAULT_CURVATURE_1_M = 1000.0    # [1/m] object curvature a_c (1/mm)
DEFAULT_ALPHA_1_S = 3000.0        # [1/s] indentation rate alpha

#: Polarity of an emission: the sign of its pressure jump (of the source strength S). A
#: touch compresses the medium, a release (detouch) rarefies it. A polarity, not an event
#: type (event types: `ae_tactile.records.EventType`).
COMPRESSION = 1
RAREFACTION = -1


def source_strength_pa_m(speed_m_s, curvature_1_m, density_kg_m3, polarity=COMPRESSION):
    """Signed source strength S = polarity rho v0^2 / a_c; the pressure jump at distance l
    is S / l.

    Parameters
    ----------
    speed_m_s, curvature_1_m : float or array_like
        Contact speed v0 [m/s] and object curvature a_c [1/m].
    density_kg_m3 : float
        Density rho of the medium [kg/m^3].
    polarity : int or array_like
        `COMPRESSION` (+1, touch) or `RAREFACTION` (-1, release).

    Returns
    -------
    numpy.ndarray
        S [Pa m], broadcast over the arguments.
    """
    v = np.asarray(speed_m_s, dtype=float)
    a = np.asarray(curvature_1_m, dtype=float)
    return np.asarray(polarity, dtype=float) * float(density_kg_m3) * v * v / a


def peak_pressure_pa(speed_m_s, curvature_1_m, distance_m, density_kg_m3):
    """Eq. (11): the high-passed pressure just after the arrival, rho v0^2 / (a_c l).

    Parameters
    ----------
    speed_m_s, curvature_1_m : float or array_like
        Contact speed v0 [m/s] and object curvature a_c [1/m].
    distance_m : float or array_like
        Path length l [m].
    density_kg_m3 : float
        Density rho [kg/m^3].

    Returns
    -------
    numpy.ndarray
        Peak pressure [Pa] (9 Pa for the paper's numbers at l = 1 cm in water).
    """
    s = source_strength_pa_m(speed_m_s, curvature_1_m, density_kg_m3)
    return s / np.asarray(distance_m, float)


def collision_pressure_pa(t_s, distance_m, sound_speed_m_s, *, speed_m_s=DEFAULT_SPEED_M_S,
                          curvature_1_m=DEFAULT_CURVATURE_1_M, alpha_1_s=DEFAULT_ALPHA_1_S,
                          density_kg_m3=1000.0, polarity=COMPRESSION):
    """Eq. (10): the unfiltered pressure at distance l from a collision at t = 0.

    Parameters
    ----------
    t_s : float or array_like
        Times [s].
    distance_m : float or array_like
        Path length l [m].
    sound_speed_m_s : float
        Sound speed c [m/s].
    speed_m_s, curvature_1_m, alpha_1_s : float or array_like
        Event parameters v0 [m/s], a_c [1/m], alpha [1/s].
    density_kg_m3 : float
        Density rho [kg/m^3].
    polarity : int or array_like
        `COMPRESSION` (+1) or `RAREFACTION` (-1).

    Returns
    -------
    numpy.ndarray
        p(t) [Pa], zero for t <= l/c; broadcast over all arguments.
    """
    t = np.asarray(t_s, dtype=float)
    dist = np.asarray(distance_m, dtype=float)
    tau = t - dist / float(sound_speed_m_s)
    al = np.asarray(alpha_1_s, dtype=float)
    amp = source_strength_pa_m(speed_m_s, curvature_1_m, density_kg_m3, polarity) / dist
    pos = tau > 0
    taup = np.where(pos, tau, 0.0)
    return np.where(pos, amp * (2.0 * np.exp(-2.0 * al * taup) - np.exp(-al * taup)), 0.0)


def event_partial_fractions(amplitude_pa, alpha_1_s, att_pole_rad_s=None):
    """Poles and residues of the pressure at the element, R(s) = A P1(s) W(s).

    P1(s) = 2/(s + 2 alpha) - 1/(s + alpha) (Eq. 9 with unit jump) and
    W(s) = w/(s + w) the medium's attenuation pole (omitted when ``att_pole_rad_s`` is None).
    Poles must be distinct (the caller separates w from alpha, 2 alpha).

    Parameters
    ----------
    amplitude_pa : array_like
        Pressure jump A per arrival (n,) [Pa].
    alpha_1_s : array_like
        Indentation rate alpha (n,) [1/s].
    att_pole_rad_s : array_like, optional
        Attenuation pole w (n,) [rad/s]; None: lossless.

    Returns
    -------
    poles : numpy.ndarray
        (n, m) real [1/s], m = 2 (lossless) or 3.
    residues : numpy.ndarray
        (n, m) real [Pa/s].
    """
    A = np.asarray(amplitude_pa, dtype=float)
    al = np.broadcast_to(np.asarray(alpha_1_s, dtype=float), A.shape)
    if att_pole_rad_s is None:
        poles = np.stack([-2.0 * al, -al], axis=-1)
        res = np.stack([2.0 * A, -A], axis=-1)
        return poles, res
    w = np.broadcast_to(np.asarray(att_pole_rad_s, dtype=float), A.shape)
    poles = np.stack([-2.0 * al, -al, -w], axis=-1)
    res = np.stack([2.0 * A * w / (w - 2.0 * al),
                    -A * w / (w - al),
                    A * w * (2.0 / (2.0 * al - w) - 1.0 / (al - w))], axis=-1)
    return poles, res


def event_transfer(s, amplitude_pa, alpha_1_s, att_pole_rad_s=None):
    """R(s) = A (2/(s + 2 alpha) - 1/(s + alpha)) [w/(s + w)] at complex s.

    Parameters
    ----------
    s : array_like
        Complex frequencies (..., m) [1/s].
    amplitude_pa, alpha_1_s : array_like
        Pressure jump A [Pa] and alpha [1/s] per arrival, (..., 1).
    att_pole_rad_s : array_like, optional
        Attenuation pole w [rad/s] per arrival (..., 1); None: lossless.

    Returns
    -------
    numpy.ndarray
        R(s) [Pa s], complex, broadcast shape.
    """
    s = np.asarray(s)
    A = np.asarray(amplitude_pa, dtype=float)
    al = np.asarray(alpha_1_s, dtype=float)
    r = A * (2.0 / (s + 2.0 * al) - 1.0 / (s + al))
    if att_pole_rad_s is not None:
        w = np.asarray(att_pole_rad_s, dtype=float)
        r = r * (w / (s + w))
    return r
