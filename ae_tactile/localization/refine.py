# SPDX-License-Identifier: Apache-2.0
"""Refine single-emission points with the device's pulse: the one-emission fit of the
overlap model (J = 1) started from `localize`'s answer.

`localize` (``ml``) aligns the four channels by band-limited interpolation of their
samples. Behind an anti-alias filter that lets the pulse through above f_s / 2 the
samples are aliased, the interpolation is not the waveform, and the delays lock towards
whole samples: on a 1st-order 50 kHz high-pass with a 2nd-order 800 kHz low-pass at 2 MS/s
the error is 12x the Cramer-Rao bound at 40 dB. The fit here models the samples as the
continuous pulse h(t) of the device's front end (`PulseModel`, evaluated exactly at each
sample instant) at the four arrival times of a surface point,

    y_k(n / f_s) = A (R / d_k) h(n / f_s - T - d_k / c) + B h(n / f_s - T - e_k / c) + noise,

so aliasing is part of the model; with the device's pulse it reaches the bound (see
docs/front_end.md).

Parameters (s_x, s_y, T) by Levenberg-Marquardt from the ml point, (A, B) by linear least
squares; the fit window, the first wall echo and the residual test are the overlap
resolver's. The covariance is that of this fit under the noise's colour measured before
the onset (`_sandwich`: the inverse Fisher matrix where the noise is white), inflated by
the chi^2 ratio above 1. A packet whose fit fails the residual test (a wrong pulse, a
second emission) keeps its ml answer (``refined`` False): refinement never makes a packet
worse than the model it can check.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy import fft as sfft

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization.common import adc_noise, make_plan, validate_windows
from ae_tactile.localization.noise_model import pre_onset_autocov
from ae_tactile.localization.overlap.decide import _chi2_limit, surface_covariance
from ae_tactile.localization.overlap.model import _lm, _Model, _sub
from ae_tactile.localization.overlap.pulse import PulseModel, _given, shift_channels
from ae_tactile.localization.overlap.search import _segments
from ae_tactile.localization.segments import prepare

__all__ = ["Refined", "refine_points", "refine_result", "REFINE_ITERATIONS"]

#: Levenberg-Marquardt iterations from the ml point (it starts within a few sigma)
REFINE_ITERATIONS = 10


@dataclass
class Refined:
    """The refined packets (K rows): point_m (K, 3), covariance_m2 (K, 3, 3),
    emission_offset_s (K,) [s] (emission instant after the window's first sample),
    chi2_ratio (K,) (residual per degree of freedom over sigma^2) and refined (K,) bool
    (the fit passed the residual test; where False the other fields are NaN)."""

    point_m: np.ndarray
    covariance_m2: np.ndarray
    emission_offset_s: np.ndarray
    chi2_ratio: np.ndarray
    refined: np.ndarray


def refine_points(windows, sample_rate_hz, onset_index, point_m, emission_offset_s, pulse, *,
                  geometry=None, noise_rms_v=None, channel_delays_s=None, echo=True,
                  iterations=REFINE_ITERATIONS) -> Refined:
    """One-emission fits with a known pulse from given starting points.

    Parameters
    ----------
    windows : array_like, (K, 4, M) or (4, M)
        Packet windows [V].
    sample_rate_hz : float
        Sample rate [Hz].
    onset_index : array_like of int, (K,)
        First sample at/after the earliest arrival.
    point_m : array_like, (K, 3) or (K, 2)
        Starting points (e.g. `localize`'s ``point_m``) [m]; rows with NaN are skipped.
    emission_offset_s : array_like, (K,)
        Starting emission instants after each window's first sample [s].
    pulse : PulseModel
        The device's pulse (`PulseModel.from_config`, a stated front end, or one learnt);
        its channel gains and delays, if any, are taken out of the windows first.
    geometry : FingertipGeometry, optional
        The fingertip (default tip).
    noise_rms_v : float or array_like (K,), optional
        Known noise sigma [V]; default measured before the onset.
    channel_delays_s : array_like (4,), optional
        The channels' own delays [s] (as `localize`'s), taken out of the windows.
    echo : bool
        Model the first wall echo.
    iterations : int
        Levenberg-Marquardt iterations.

    Returns
    -------
    Refined
    """
    if not isinstance(pulse, PulseModel):
        raise TypeError(f"pulse must be a PulseModel, got {type(pulse).__name__}")
    geo = FingertipGeometry() if geometry is None else geometry
    fs = float(sample_rate_hz)
    x, on = validate_windows(windows, onset_index)
    K = x.shape[0]
    p0 = np.asarray(point_m, float).reshape(K, -1)[:, :2]
    t0 = np.asarray(emission_offset_s, float).reshape(K)
    out = Refined(np.full((K, 3), np.nan), np.full((K, 3, 3), np.nan), np.full(K, np.nan),
                  np.full(K, np.nan), np.zeros(K, bool))
    ids = np.nonzero(np.isfinite(p0).all(axis=1) & np.isfinite(t0))[0]
    if ids.size == 0:
        return out
    plan = make_plan(fs, geo, x.shape[2], (100e3, 1e6))
    x, nr, noise_v2, raw = _corrected(x[ids], on[ids], fs, plan, pulse, channel_delays_s,
                                      _rows(noise_rms_v, K, ids))
    bare = replace(pulse, channel_gain=(), channel_delay_s=())
    with np.errstate(all="ignore"):
        prep = prepare(x, on[ids], plan, noise_rms_v=nr, spectra=False)
        sigma2 = adc_noise(prep.sigma2, prep.quant2, _given(prep))
        if noise_v2 is not None:
            sigma2 = noise_v2 / prep.scale**2
        seg, start, length, inside = _segments(prep, plan, geo, plan.fs, None)
        model = _Model(geo, plan.fs, start, length, bare, echo, inside)
        theta = np.concatenate([p0[ids], t0[ids, None]], axis=1)[:, None, :]
        th, amp, rss, gram = _lm(model, seg.reshape(ids.size, -1), theta, int(iterations))
        rho = _noise_correlation(prep if raw is None else raw, plan)  # before any shift
        cov5 = _sandwich(model, th, amp, gram, rho, sigma2)
    dof = np.maximum(model.mask.sum(axis=1) - 5, 1)
    ratio = rss / (sigma2 * dof)
    n_noise = np.maximum(4 * (prep.onset - plan.pre), 4).astype(float)
    if nr is not None:
        n_noise[:] = np.inf
    ok = np.isfinite(ratio) & (ratio <= _chi2_limit(n_noise, dof, None))
    _fill(out, ids, th[:, 0], ratio, ok, cov5, geo.radius_m)
    return out


def refine_result(result, windows, sample_rate_hz, onset_index, pulse, **kw):
    """`localize`'s result with its accepted packets refined by `refine_points` (points,
    covariances, directions, delays and emission instants; a packet whose fit fails the
    residual test keeps its own). Returns (LocalizationResult, Refined); keywords as
    `refine_points`'s."""
    acc = np.asarray(result.accepted, bool)
    pts = np.where(acc[:, None], result.point_m, np.nan)
    got = refine_points(windows, sample_rate_hz, onset_index, pts, result.emission_offset_s,
                        pulse, **kw)
    m = got.refined
    if not m.any():
        return replace(result, refined=m), got
    geo = kw.get("geometry") or FingertipGeometry()
    point = result.point_m.copy()
    point[m] = got.point_m[m]
    cov = result.covariance_m2.copy()
    cov[m] = got.covariance_m2[m]
    offs = np.array(result.emission_offset_s, float)
    offs[m] = got.emission_offset_s[m]
    polar, azimuth = geo.angles_from_points(point)
    tau = geo.exact_delays_s(point[m])
    tx, ty = np.array(result.tau_x_s, float), np.array(result.tau_y_s, float)
    tx[m], ty[m] = tau[:, 0], tau[:, 1]
    return replace(result, point_m=point, covariance_m2=cov, emission_offset_s=offs,
                   polar_rad=np.where(m, polar, result.polar_rad),
                   azimuth_rad=np.where(m, azimuth, result.azimuth_rad),
                   tau_x_s=tx, tau_y_s=ty, refined=m), got


def _noise_correlation(prep, plan) -> np.ndarray:
    """(K, P + 1) the noise's correlation at lags 0..P [1] from the pre-onset
    autocovariance of the prepared raw windows (a fractional shift's rounding would read
    as colour); white (1, 0, ...) where it is unknown."""
    n_pre = np.clip(prep.seg_start, 0, prep.x.shape[2])
    acov = pre_onset_autocov(prep.x, n_pre, prep.pre_mean, plan.seg_len)
    rho = acov / acov[:, :1]
    bad = ~np.all(np.isfinite(rho), axis=1)
    rho[bad] = 0.0
    rho[bad, 0] = 1.0
    return rho


def _sandwich(model, th, amp, gram, rho, sigma2) -> np.ndarray:
    """(n, 5, 5) covariance of the fit's (s_x, s_y, T, A, B). Where the noise is white
    (``rho`` has no lag beyond 0: the pre-onset estimate keeps only a significant colour)
    sigma2 G^-1 with G = J J^T, the fit's own ``gram``; where the front end colours it,
    G^-1 B G^-1 with B = J Sigma J^T, Sigma the noise's covariance along each channel
    (sigma2 times the Toeplitz matrix of ``rho``): the fit weighs the samples alike, and
    the white formula would be 2-3x too small under amplifier noise."""
    out = sigma2[:, None, None] * np.linalg.pinv(gram, rcond=1e-13, hermitian=True)
    col = np.nonzero(np.any(rho[:, 1:] != 0.0, axis=1))[0]
    if col.size == 0:
        return out
    sub = _sub(model, col)
    phi, parts = sub.evaluate(th[col])
    jac = np.concatenate([sub.jacobian(parts, amp[col]), phi], axis=1)  # (m, 5, 4L)
    m, q, _ = jac.shape
    j4 = jac.reshape(m, q, 4, model.L)
    r = rho[col]
    P = r.shape[1] - 1
    # J Sigma J^T by Parseval on a zero-padded length (>= L + P: the circular correlation
    # is the banded Toeplitz one): sum over bins of Jf S Jf^H, S the spectrum of rho
    nf = sfft.next_fast_len(model.L + P + 1, real=True)
    jf = sfft.rfft(j4, n=nf, axis=-1)  # (m, q, 4, F)
    kern = np.zeros((m, nf))
    kern[:, : P + 1] = r
    if P:
        kern[:, nf - P:] = r[:, :0:-1]
    wts = np.full(jf.shape[-1], 2.0)
    wts[0] = 1.0
    if nf % 2 == 0:
        wts[-1] = 1.0
    spec = sfft.rfft(kern, axis=-1).real * wts / nf  # (m, F)
    b = np.einsum("mqcf,mrcf,mf->mqr", jf, jf.conj(), spec).real
    g = np.einsum("mqcl,mrcl->mqr", j4, j4)
    gi = np.linalg.pinv(g, rcond=1e-13, hermitian=True)
    out[col] = sigma2[col, None, None] * (gi @ b @ gi)
    return out


def _fill(out, ids, th, ratio, ok, cov5, R) -> None:
    """``out``'s rows ``ids``: the fits (th (n, 3): s_x, s_y [m], T [s]) that passed the
    residual test (``ok``) and lie on the cap, with their covariance (``cov5`` (n, 5, 5),
    inflated by the chi^2 ratio above 1)."""
    for j, k in enumerate(ids):
        sx, sy, T = (float(v) for v in th[j])
        out.chi2_ratio[k] = ratio[j]
        if not ok[j] or sx * sx + sy * sy >= R * R:
            continue
        c3 = surface_covariance(sx, sy, cov5[j, :2, :2] * max(float(ratio[j]), 1.0), R)
        if not np.all(np.isfinite(c3)):
            continue
        out.point_m[k] = (sx, sy, math.sqrt(R * R - sx * sx - sy * sy))
        out.covariance_m2[k] = c3
        out.emission_offset_s[k] = T
        out.refined[k] = True


def _corrected(x, on, fs, plan, pulse, channel_delays_s, nr):
    """(windows with the pulse's channel corrections and the channels' own delays taken
    out, noise sigma [V] to give, noise variance [V^2] measured before the shift or None,
    the raw windows prepared or None when nothing was shifted). The noise is measured on
    the raw windows: a shift moves the samples off the ADC's grid, where its quantum (part
    of the noise) can no longer be seen and its rounding reads as colour."""
    delays = None if channel_delays_s is None or not np.any(channel_delays_s) else \
        tuple(float(d) for d in channel_delays_s)
    if delays is None and not (pulse.channel_gain or pulse.channel_delay_s):
        return x, nr, None, None
    with np.errstate(all="ignore"):
        raw = prepare(np.array(x, float), on, plan, spectra=False)  # it scales in place
    noise_v2 = adc_noise(raw.sigma2, raw.quant2, _given(raw)) * raw.scale**2 \
        if nr is None else None
    x, nr = pulse.correct_channels(x, fs, nr)
    if delays is not None:
        x = shift_channels(x, fs, (1.0,) * 4, delays)
    return x, nr, noise_v2, raw


def _rows(v, K, ids):
    """A per-packet argument (scalar or (K,)) for the rows ``ids``; None stays None."""
    if v is None:
        return None
    return np.broadcast_to(np.asarray(v, float), (K,))[ids]
