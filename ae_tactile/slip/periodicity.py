# SPDX-License-Identifier: Apache-2.0
"""Periodicity test for texture emissions (pure numpy, no state).

Sliding at speed v over a texture of spatial period lambda gives emissions at the rate
v / lambda (anchors: "Sliding over a texture of period lambda at speed v gives emissions
at v/lambda"). Micro-slip and gross-slip emissions are closer to a Poisson process. The
test takes the latest n + 1 emission times of a contact:

1. m = median interval; each interval dt_i counts k_i = max(1, round(dt_i / m)) periods
   (k > 1: packets the localizer rejected or the detector missed);
2. least squares t_j = t_0 + K_j T over the cumulative counts K_j: the period T and the
   residuals e_j;
3. periodic when at least ``min_fraction`` of the emissions have |e_j| <= tol T, at least
   ``min_fraction`` - 0.15 of the intervals are single (k = 1), no interval exceeds
   ``max_multiple`` periods, and the RMS residual of the regular emissions is <= tol T / 2.

For a Poisson process the residuals of step 2 spread over +-T/2 (RMS ~ 0.29 T), so the
test fails; for a texture with timing jitter sigma (fraction of T) the residual RMS is
~sigma.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Periodicity:
    """Result of `periodicity`: the verdict, the period [s] and rate [1/s], the fractions
    of regular emissions and single intervals, the regular emissions' RMS residual."""

    periodic: bool
    period_s: float
    rate_hz: float
    regular_fraction: float
    single_fraction: float
    residual_rms: float  # of the regular emissions, as a fraction of the period


def periodicity(
    times_ns, *, tolerance: float = 0.2, min_fraction: float = 0.75, max_multiple: int = 3
) -> Periodicity:
    """Test emission times for a common period (see the module docstring).

    Parameters
    ----------
    times_ns : array_like of int
        Emission times, increasing [ns].
    tolerance : float
        Largest residual of a regular emission, as a fraction of the period.
    min_fraction : float
        Smallest fraction of regular emissions (and, less 0.15, of single intervals).
    max_multiple : int
        Largest number of periods in one interval (missed emissions).

    Returns
    -------
    Periodicity
        Not periodic, with NaN period, for fewer than 4 times or no positive interval.
    """
    t = (np.asarray(times_ns, dtype=np.int64) - int(np.asarray(times_ns)[0])).astype(float) * 1e-9
    nan = Periodicity(False, np.nan, np.nan, 0.0, 0.0, np.nan)
    if t.size < 4:
        return nan
    dt = np.diff(t)
    if np.any(dt <= 0):
        dt = np.maximum(dt, 0.0)
    m = float(np.median(dt))
    if not m > 0:
        return nan
    k = np.maximum(1.0, np.round(dt / m))
    K = np.concatenate([[0.0], np.cumsum(k)])
    Kc = K - K.mean()
    T = float((Kc * (t - t.mean())).sum() / (Kc * Kc).sum())
    if not T > 0:
        return nan
    e = (t - t.mean()) - Kc * T
    reg = np.abs(e) <= tolerance * T
    reg_frac = float(reg.mean())
    single = float((k == 1).mean())
    rms = float(np.sqrt(np.mean((e[reg] / T) ** 2))) if reg.any() else np.inf
    ok = (
        reg_frac >= min_fraction
        and single >= min_fraction - 0.15
        and k.max() <= max_multiple
        and rms <= 0.5 * tolerance
    )
    return Periodicity(bool(ok), T, 1.0 / T, reg_frac, single, rms)
