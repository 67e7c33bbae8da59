# SPDX-License-Identifier: Apache-2.0
"""The pulse learnt from the device's own single-emission packets: `fit_pulse`, one fit
over a set of packets (`learner.PulseLearner` runs it online).

Model: one emission per packet, y_k(t) = A (R / d_k) h(t - T - d_k / c) + B h(t - T - e_k / c)
+ noise (the overlap model with J = 1), with the pulse h the response of the device's
chain to the emission, a sum of damped exponentials h(t) = Re sum_p r_p e^{p t} (t >= 0):
the emission's two real poles -alpha, -2 alpha (paper Eq. 9), one second-order section for
the high-pass and ``lowpass_sections`` second-order sections plus one real pole for the
anti-alias filter and the amplifier. Every section is s^2 + a_1 s + a_0 with a_0, a_1 > 0
(a complex pair or two real poles, so RC stages, Butterworth, Bessel and Chebyshev chains
are all inside the family); the residues are free but h(0) = h'(0) = 0 (a chain of
relative degree >= 3 starts smoothly). Fit by variable projection: the residues by linear
least squares inside a nonlinear least-squares fit of the log section coefficients, with
the packets' (s_x, s_y, T, A, B) refitted by the overlap model's own Levenberg-Marquardt
between rounds. The learnt pulse is trusted (``converged``) when at least ``min_packets``
packets pass the overlap model's residual test with it (chi^2 per degree of freedom
below the resolver's limit) and they are at least ``min_inlier_share`` of the candidates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import butter

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization.common import adc_noise, make_plan, validate_windows
from ae_tactile.localization.estimators import localize
from ae_tactile.localization.overlap.decide import _chi2_limit, _misfit_share, _trusted
from ae_tactile.localization.overlap.loss import (
    LEARN_LOSS,
    _keep_loss,
    _learnt,
    _loss_of,
    _lossy,
    _with_loss,
)
from ae_tactile.localization.overlap.model import _lm, _Model
from ae_tactile.localization.overlap.pulse import PulseModel, _given, shift_channels
from ae_tactile.localization.overlap.search import _segments
from ae_tactile.localization.segments import prepare

__all__ = ["PulseFit", "fit_pulse", "pulse_inliers"]

#: [rad] candidates for learning lie at least this polar angle from the apex: an apex
#: packet is the one an identical-channel burst imitates
MIN_LEARN_POLAR_RAD = math.radians(5.0)
#: [dB] candidates for learning have at least this SNR (the pulse is learnt, not the noise)
MIN_LEARN_SNR_DB = 20.0
#: [rad/s] fastest decay of a learnt pole: e^{|Re p| t} over a 30 us segment stays finite
MAX_DECAY_RAD_S = 1.5e7
#: [s] samples this close to a modelled arrival (before, after) are left out of the
#: first pole fit (`_Modes`): the emission time is not known to better than this yet
MODES_GUARD_S = (-1.0e-6, 2.0e-6)
#: rounds of the channels' gain and delay estimate (`_channels`)
CHANNEL_ROUNDS = 4
#: [1], [s] channel gains and delays within these of alike are not corrected (a 0.3 %
#: gain and 1 ns, 1.5 um of path, are below what a pair's residual test can see)
MIN_CHANNEL_GAIN = 3e-3
MIN_CHANNEL_DELAY_S = 1e-9
#: packets in the pole fit (the rest are checked against its pulse: 16 packets of 4
#: channels hold some 2e4 samples, far more than the ~10 pole parameters need)
POLE_FIT_PACKETS = 12
#: packets in the first pole fit (`_Modes`: residues of their own, some 5e3 samples each)
MODES_PACKETS = 8
#: residual evaluations per pole fit round (each ~10 ms at 10 MS/s)
POLE_FIT_NFEV = 40


@dataclass
class PulseFit:
    """The outcome of one `fit_pulse`.

    pulse            PulseModel (explicit poles and residues), or the initial model when
                     nothing could be fitted
    converged        the pulse explains ``n_inliers`` >= min_packets packets to the noise
    n_candidates     packets accepted as single emissions and offered to the fit
    n_inliers        packets whose one-emission residual passes the resolver's test
    chi2_median      median chi^2 per degree of freedom of the inliers (nan when none)
    chi2_ratio (N,)  per candidate, with the learnt pulse
    """

    pulse: PulseModel
    converged: bool
    n_candidates: int
    n_inliers: int
    chi2_median: float
    chi2_ratio: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _section_roots(w0, zeta):
    """Roots of s^2 + 2 zeta w0 s + w0^2: a conjugate pair (zeta < 1) or two distinct reals
    (a double root, zeta = 1, is split by 1e-3 of its size: the residues stay finite)."""
    if zeta >= 1.0:
        q = max(math.sqrt(zeta * zeta - 1.0), 1e-3)
        return [complex(-w0 * (zeta - q), 0.0), complex(-w0 * (zeta + q), 0.0)]
    w = w0 * math.sqrt(1.0 - zeta * zeta)
    return [complex(-zeta * w0, w), complex(-zeta * w0, -w)]


def _initial_vector(init: PulseModel, fs: float, lowpass_sections: int):
    """Log parameters [ln alpha, ln w0, ln zeta (high-pass), (ln w0, ln zeta) x sections,
    ln w_amp] of the start and their bounds (lower, upper): ``init``'s alpha and
    high-pass corner, a Butterworth low-pass of 2 x ``lowpass_sections`` poles at
    ``init``'s corner (0.3 fs without one). Bounds: alpha 1e2 .. 3e6 /s, the high-pass
    section 5 .. 500 kHz, the low-pass sections and the real pole 100 kHz .. fs (a
    chain's fast poles sit near Nyquist; their decay saturates, `_poles_of`), every zeta
    0.05 .. 5."""
    two_pi = 2 * math.pi
    w_hp = two_pi * (init.highpass_hz if not init.learnt else 100e3)
    alpha = init.alpha_1_s if not init.learnt else 3e3
    lz = (math.log(0.05), math.log(5.0))
    v = [math.log(alpha), math.log(w_hp), math.log(math.sqrt(0.5))]
    lo = [math.log(1e2), math.log(two_pi * 5e3), lz[0]]
    hi = [math.log(3e6), math.log(two_pi * 500e3), lz[1]]
    lp = init.lowpass_hz if (not init.learnt and init.lowpass_hz) else 0.3 * fs
    w_lp = two_pi * min(lp, 0.45 * fs)
    _, p, _ = butter(2 * lowpass_sections, w_lp, analog=True, output="zpk")
    up = sorted([q for q in p if q.imag > 0], key=lambda q: q.real)
    for q in up:
        v += [math.log(abs(q)), math.log(-q.real / abs(q))]
        lo += [math.log(two_pi * 100e3), lz[0]]
        hi += [math.log(two_pi * fs), lz[1]]
    v.append(math.log(min(3.0 * w_lp, 0.9 * two_pi * fs)))
    lo.append(math.log(two_pi * 100e3))
    hi.append(math.log(two_pi * fs))
    return np.clip(v, np.array(lo) + 1e-6, np.array(hi) - 1e-6), (np.array(lo), np.array(hi))


#: [1/s] starts of the emission's decay in the first round (its range in real devices;
#: from a wrong decade the fit does not find it: the two poles are nearly collinear)
ALPHA_STARTS_1_S = (3e3, 1e5, 1e6)


def _alpha_starts(v, bounds):
    """Copies of the start v with each of ALPHA_STARTS_1_S as the decay."""
    out = []
    for a in ALPHA_STARTS_1_S:
        w = v.copy()
        w[0] = min(max(math.log(a), bounds[0][0] + 1e-6), bounds[1][0] - 1e-6)
        out.append(w)
    return out


def _poles_of(v):
    """Poles (P,) of the log parameter vector (`_initial_vector`'s layout), the conjugate
    pairs adjacent."""
    alpha = math.exp(v[0])
    poles = [complex(-alpha, 0.0), complex(-2.0 * alpha * 1.0001, 0.0)]
    for i in range(1, len(v) - 1, 2):
        poles += _section_roots(math.exp(v[i]), math.exp(v[i + 1]))
    poles.append(complex(-math.exp(v[-1]), 0.0))
    p = np.array(poles)
    # decay rates saturate smoothly at MAX_DECAY_RAD_S: the model evaluates e^{-p t} over
    # a segment (overflow past ~700), and a faster pole is within a sample anyway
    re = -MAX_DECAY_RAD_S * np.tanh(-p.real / MAX_DECAY_RAD_S)
    return re * (1.0 + 1e-6 * np.arange(p.size)) + 1j * p.imag


def _basis(poles, tau, fs):
    """Real basis functions of h on the times tau (..., L) [s], uniform in steps of 1/fs
    along the last axis, zero before 0: (..., L, P): for a real pole e^{p tau}; for a
    conjugate pair (adjacent) Re and Im of e^{p tau}. e^{p tau_n} = e^{p tau_n0} z_p^(n-n0)
    from one table of powers z_p^m (no exponential per sample). Returns (values, kinds)
    with kinds[j] = (pole index, 0 re / 1 im)."""
    L = tau.shape[-1]
    zpow = np.exp(poles[None, :] * (np.arange(L) / fs)[:, None])  # (L, P)
    n0 = np.clip(np.ceil(-tau[..., 0] * fs - 1e-9), 0, L).astype(np.int64)  # (...)
    t_first = tau[..., 0] + n0 / fs
    lead = np.exp(poles * t_first[..., None])  # (..., P)
    m = np.arange(L) - n0[..., None]  # (..., L)
    e = lead[..., None, :] * zpow[np.clip(m, 0, L - 1)]
    e *= (m >= 0)[..., None]
    out = np.empty(e.shape)
    kinds = []
    j = 0
    while j < poles.size:
        if poles[j].imag > 0:
            out[..., j] = e[..., j].real
            out[..., j + 1] = e[..., j].imag
            kinds += [(j, 0), (j, 1)]
            j += 2
        else:
            out[..., j] = e[..., j].real
            kinds.append((j, 0))
            j += 1
    return out, kinds


def _constraint_null(poles, kinds):
    """(P, P - 2) basis of the coefficients with h(0) = 0 and h'(0) = 0."""
    c = np.zeros((2, len(kinds)))
    for j, (i, part) in enumerate(kinds):
        p = poles[i]
        c[0, j] = 1.0 if part == 0 else 0.0
        c[1, j] = p.real if part == 0 else p.imag
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    _, _, vt = np.linalg.svd(c)
    return vt[2:].T


def _residues_of(poles, kinds, coef):
    """Complex residues (P,) of the real coefficients (h = sum_j coef_j basis_j)."""
    r = np.zeros(poles.size, complex)
    for j, (i, part) in enumerate(kinds):
        if poles[i].imag > 0:
            # c1 Re(e) + c2 Im(e) = Re((c1 - i c2) e) = 2 Re(r e), r = (c1 - i c2) / 2
            r[i] += coef[j] / 2.0 if part == 0 else -1j * coef[j] / 2.0
        else:
            r[i] += coef[j]
    for i in range(poles.size):
        if poles[i].imag < 0:
            r[i] = np.conj(r[i - 1])
    return r


class _Problem:
    """The data of the pole fit: per packet its segment, mask, arrival times of the direct
    wave and the echo, and the amplitudes (held fixed while the poles move)."""

    def __init__(self, model: _Model, y, theta, amp, weight, with_loss=False):
        K, L = len(model.start), model.L
        #: the parameter vector ends with the medium's loss (`loss._with_loss`)
        self.with_loss = bool(with_loss)
        self.fs = model.fs
        d, _ = model._paths(theta[:, :, :2])  # (K, 1, 2, 4)
        t_arr = theta[:, 0, 2][:, None, None] + d[:, 0] / model.c  # (K, 2, 4)
        tn = (model.start[:, None] + np.arange(L)[None, :]) / model.fs  # (K, L)
        self.tau_d = tn[:, None, :] - t_arr[:, 0, :, None]  # (K, 4, L)
        self.tau_e = tn[:, None, :] - t_arr[:, 1, :, None]
        gain = model.R / d[:, 0, 0]  # (K, 4)
        #: [m] direct and echo path lengths (K, 4): the loss of each arrival's path
        self.path_d, self.path_e = d[:, 0, 0], d[:, 0, 1]
        a = amp.reshape(K, 2)
        self.w_d = (a[:, 0:1] * gain)[..., None] * weight[:, None, None]  # (K, 4, 1)
        self.w_e = (a[:, 1:2] * np.ones((1, 4)))[..., None] * weight[:, None, None]
        if not model.echo:
            self.w_e = self.w_e * 0.0
        mask = np.ones((K, 4 * L)) if model.mask is None else model.mask
        self.mask = mask.reshape(K, 4, L)
        self.y = y.reshape(K, 4, L) * weight[:, None, None] * self.mask

    def design(self, poles, loss: PulseModel | None = None):
        """Design matrix (rows: samples, columns: the real basis of the poles) and its
        kinds; ``loss``: a PulseModel whose power-law loss filters each path's basis."""
        bd, kinds = _basis(poles, self.tau_d, self.fs)
        be, _ = _basis(poles, self.tau_e, self.fs)
        if loss is not None and loss.attenuation_db_per_m_at_1mhz > 0:
            bd = _lossy(bd, self.path_d, self.fs, loss)
            be = _lossy(be, self.path_e, self.fs, loss)
        a = (self.w_d[..., None] * bd + self.w_e[..., None] * be) * self.mask[..., None]
        return a.reshape(-1, poles.size), kinds

    def residual(self, v):
        """The residual vector at v (non-finite values, from a degenerate basis, as a
        large finite misfit)."""
        r = self.solve(v)[0]
        return np.where(np.isfinite(r), r, 1e6)

    def solve(self, v):
        """(residual vector, poles, complex residues) at the parameters v (the pole log
        parameters, then, with ``with_loss``, the medium's loss: `_with_loss`)."""
        poles = _poles_of(v[:-2] if self.with_loss else v)
        a, kinds = self.design(poles, _loss_of(v) if self.with_loss else None)
        null = _constraint_null(poles, kinds)
        an = a @ null
        # normal equations, Jacobi-scaled, with a relative ridge (columns of very
        # different sizes; a pole with nothing to explain gets a residue of ~0)
        g = an.T @ an
        sc = 1.0 / np.sqrt(np.maximum(np.diag(g), 1e-300))
        g = g * sc[:, None] * sc[None, :] + 1e-10 * np.eye(g.shape[0])
        z = np.linalg.solve(g, (an.T @ self.y.ravel()) * sc) * sc
        coef = null @ z
        return self.y.ravel() - a @ coef, poles, _residues_of(poles, kinds, coef)


def _prepare(x, on, fs, geo, noise_rms_v, single, echo):
    """Segments, noise and start of the one-emission fits of the packets ``single``
    accepted (away from the apex, SNR >= MIN_LEARN_SNR_DB)."""
    plan = make_plan(fs, geo, x.shape[2], (100e3, 1e6))
    acc = np.asarray(single.accepted, bool)
    polar = np.asarray(single.polar_rad, float)
    snr = np.asarray(single.snr_db_est, float)
    ids = np.nonzero(acc & (polar >= MIN_LEARN_POLAR_RAD) & (snr >= MIN_LEARN_SNR_DB))[0]
    if ids.size == 0:
        return ids, None
    nr = None if noise_rms_v is None else np.broadcast_to(
        np.asarray(noise_rms_v, float), (len(on),))[ids]
    prep = prepare(x[ids], on[ids], plan, noise_rms_v=nr, spectra=False)
    sigma2 = adc_noise(prep.sigma2, prep.quant2, _given(prep))
    seg, start, length, inside = _segments(prep, plan, geo, plan.fs, None)
    n_noise = np.maximum(4 * (prep.onset - plan.pre), 4).astype(float)
    if noise_rms_v is not None:
        n_noise[:] = np.inf
    pts = np.asarray(single.point_m, float)[ids, :2]
    t0 = np.asarray(single.emission_offset_s, float)[ids]
    a0 = np.asarray(single.amplitude_v, float)[ids] / prep.scale
    return ids, (plan, seg, start, length, inside, sigma2, n_noise, pts, t0, a0)


def _chi2(model, y, theta, sigma2, n_noise):
    """One-emission LM from theta: (theta, amplitudes, chi^2 ratio, limit) per packet."""
    th, amp, rss, _ = _lm(model, y, theta)
    dof = np.maximum(model.mask.sum(axis=1) - 5, 1)
    return th, amp, rss / (sigma2 * dof), _chi2_limit(n_noise, dof, None)


def fit_pulse(windows, sample_rate_hz, onset_index, *, geometry=None, single=None,
              initial=None, noise_rms_v=None, echo=True, max_packets=32, min_packets=12,
              min_inlier_share=0.6, lowpass_sections=None, rounds=2) -> PulseFit:
    """Learn the pulse (the emission through the device's own front end) from packets
    holding one emission each.

    Parameters
    ----------
    windows : array_like, (K, 4, M)
        Packets [V]; those `localize` accepts (``single``) away from the apex and with
        SNR >= MIN_LEARN_SNR_DB are the candidates, the first ``max_packets`` used.
    sample_rate_hz : float
        Sample rate [Hz].
    onset_index : array_like of int, (K,)
        Packet onsets [samples].
    geometry : FingertipGeometry, optional
        The fingertip (default tip).
    single : LocalizationResult, optional
        `localize`'s answer for the windows (computed when not given).
    initial : PulseModel, optional
        Start of the fit (default `PulseModel.for_sample_rate`).
    noise_rms_v : float or array_like (K,), optional
        Known noise sigma [V]; default measured before the onset.
    echo : bool
        Model the first wall echo.
    max_packets, min_packets : int
        Packets used at most; inliers needed to trust the pulse.
    min_inlier_share : float
        Share of the candidates that must pass the residual test with the learnt pulse.
    lowpass_sections : int, optional
        Second-order sections of the low-pass and amplifier (default 4: an 8th-order
        anti-alias filter is inside the family).
    rounds : int
        Alternations of the pole fit and the packets' refit.

    Returns
    -------
    PulseFit
    """
    geo = FingertipGeometry() if geometry is None else geometry
    fs = float(sample_rate_hz)
    init = PulseModel.for_sample_rate(fs) if initial is None else initial
    x, on = validate_windows(windows, onset_index)
    with np.errstate(all="ignore"):
        if single is None:
            single = localize(x, fs, on, geometry=geo, noise_rms_v=noise_rms_v)
        ids, data = _prepare(x, on, fs, geo, noise_rms_v, single, echo)
        if data is None:
            return PulseFit(init, False, 0, 0, float("nan"))
        ids = ids[: int(max_packets)]
        data = tuple(d[: ids.size] if isinstance(d, np.ndarray) and d.ndim else d
                     for d in data)
        return _fit(init, fs, geo, echo, data, ids.size, min_packets, min_inlier_share,
                    lowpass_sections, rounds)


def pulse_inliers(windows, sample_rate_hz, onset_index, pulse, *, geometry=None,
                  noise_rms_v=None, echo=True) -> tuple[int, int]:
    """How many packets a given pulse explains: the candidates `fit_pulse` would take
    (accepted by `localize` away from the apex, SNR >= MIN_LEARN_SNR_DB), each one's
    one-emission Levenberg-Marquardt fit with ``pulse`` (its channel corrections
    applied), judged by the residual test that makes a fit converge.

    Parameters
    ----------
    windows : array_like, (K, 4, M)
        Packets [V].
    sample_rate_hz : float
        Sample rate [Hz].
    onset_index : array_like of int, (K,)
        Onsets [samples].
    pulse : PulseModel
        The pulse to check (e.g. one loaded from the device's calibration file).
    geometry : FingertipGeometry, optional
        The fingertip (default tip).
    noise_rms_v : float or array_like (K,), optional
        Known noise sigma [V]; default measured before the onset.
    echo : bool
        Model the first wall echo.

    Returns
    -------
    (int, int)
        (candidates, inliers).
    """
    geo = FingertipGeometry() if geometry is None else geometry
    fs = float(sample_rate_hz)
    x, on = validate_windows(windows, onset_index)
    x, nr = pulse.correct_channels(x, fs, noise_rms_v, on)
    bare = replace(pulse, channel_gain=(), channel_delay_s=())
    with np.errstate(all="ignore"):
        single = localize(x, fs, on, geometry=geo, noise_rms_v=nr)
        ids, data = _prepare(x, on, fs, geo, nr, single, echo)
        if data is None:
            return 0, 0
        plan, seg, start, length, inside, sigma2, n_noise, pts, t0, _ = data
        model = _Model(geo, plan.fs, start, length, bare, echo, inside)
        theta = np.concatenate([pts, t0[:, None]], axis=1)[:, None, :]
        _, _, ratio, limit = _chi2(model, seg.reshape(ids.size, -1), theta, sigma2, n_noise)
    return int(ids.size), int(np.sum(ratio <= limit))


def _fit(init, fs, geo, echo, data, n, min_packets, min_inlier_share, lowpass_sections,
         rounds):
    """`fit_pulse` on prepared candidates: the modes (poles, `_Modes`), then from them the
    lossless pulse (`_refine`); where it is not trusted, also the pulse with the medium's
    loss, kept only where it clearly explains the packets better (`_keep_loss`); the
    initial pulse where it explains them at least as well."""
    plan, seg, start, length, inside, sigma2, n_noise, pts, t0, a0 = data
    y = seg.reshape(n, -1)
    sections = 4 if lowpass_sections is None else int(lowpass_sections)
    v, bounds = _initial_vector(init, fs, sections)
    theta0 = np.concatenate([pts, t0[:, None]], axis=1)[:, None, :]
    weight = 1.0 / np.sqrt(sigma2)
    first = np.arange(min(n, MODES_PACKETS))
    sub = _Model(geo, plan.fs, start[first], length, init, echo, inside[first])
    modes = _Modes(sub, y[first], theta0[first], weight[first])
    short = [least_squares(modes.residual, v0, method="trf", bounds=bounds, diff_step=1e-4,
                           max_nfev=POLE_FIT_NFEV // 3) for v0 in _alpha_starts(v, bounds)]
    v = min(short, key=lambda f: f.cost).x
    v = least_squares(modes.residual, v, method="trf", bounds=bounds, diff_step=1e-4,
                      max_nfev=POLE_FIT_NFEV).x
    args = (init, geo, echo, data, n, weight, rounds)
    pulse, ratio, limit = _refine(*args, v, bounds, False)
    if LEARN_LOSS and not _trusted(ratio, limit, n, min_packets, min_inlier_share):
        lossy = _refine(*args, *_with_loss(v, bounds, init), True)
        if _keep_loss(ratio, limit, lossy[1], lossy[2]):
            pulse, ratio, limit = lossy
    # model selection: the initial pulse where it explains the packets at least as well
    # (the learnt family holds it, but a local optimum may not)
    model0 = _Model(geo, plan.fs, start, length, init, echo, inside)
    _, _, ratio0, limit0 = _chi2(model0, y, theta0, sigma2, n_noise)
    if not np.median(ratio) < np.median(ratio0):
        p0, r0 = init.poles_residues()
        pulse, ratio, limit = PulseModel.from_poles(p0, r0), ratio0, limit0
    ok = ratio <= limit
    n_in = int(ok.sum())
    pulse = replace(pulse, misfit_share=_misfit_share(ratio[ok], y[ok], sigma2[ok],
                                                      inside[ok]))
    converged = bool(pulse.learnt and _trusted(ratio, limit, n, min_packets, min_inlier_share))
    med = float(np.median(ratio[ok])) if n_in else float("nan")
    return PulseFit(pulse, converged, n, n_in, med, ratio)


def _refine(init, geo, echo, data, n, weight, rounds, v, bounds, with_loss):
    """From the modes' poles v (``with_loss``: then the medium's loss): shared residues
    and the packets' refit alternated, the channels' gain and delay, the poles polished
    (`_Problem`), on the inliers once more. Returns (pulse, chi^2 ratios, limits)."""
    plan, seg, start, length, inside, sigma2, n_noise, pts, t0, a0 = data
    y = seg.reshape(n, -1)
    theta = np.concatenate([pts, t0[:, None]], axis=1)[:, None, :]
    amp = np.stack([a0, np.zeros(n)], axis=1)
    pulse, ratio, limit = init, np.full(n, np.inf), np.ones(n)
    for _ in range(3):  # shared residues at these poles <-> the packets' refit
        got = _shared(geo, plan.fs, start, length, echo, inside, y, theta, amp, weight, v,
                      with_loss)
        if got is None:
            break
        pulse, model = got
        theta, amp, ratio, limit = _chi2(model, y, theta, sigma2, n_noise)
    if pulse.learnt:
        y, theta, amp, ratio, limit, gain, delay = _channels(
            model, seg, y, theta, amp, ratio, limit, weight, sigma2, n_noise)
    else:
        gain, delay = np.ones(4), np.zeros(4)
    keep = np.ones(n, bool)
    for rnd in range(int(rounds) + 1):
        if rnd == int(rounds):  # the last round: the inliers only
            keep = ratio <= limit
            if keep.sum() < 3 or keep.all():
                break
        ids = np.nonzero(keep)[0][:POLE_FIT_PACKETS]
        sub = _Model(geo, plan.fs, start[ids], length, pulse, echo, inside[ids])
        prob = _Problem(sub, y[ids], theta[ids], amp[ids], weight[ids], with_loss)
        v_new = least_squares(prob.residual, v, method="trf", bounds=bounds,
                              diff_step=1e-4, max_nfev=POLE_FIT_NFEV).x
        _, poles, res = prob.solve(v_new)
        try:
            cand = _learnt(poles, res, v_new, with_loss)
        except ValueError:
            break
        model = _Model(geo, plan.fs, start, length, cand, echo, inside)
        th2, amp2, ratio2, limit2 = _chi2(model, y, theta, sigma2, n_noise)
        if not np.nanmedian(ratio2) <= np.nanmedian(ratio):
            break
        v, pulse, theta, amp, ratio, limit = v_new, cand, th2, amp2, ratio2, limit2
    if pulse.learnt and (np.any(gain != 1.0) or np.any(delay != 0.0)):
        pulse = replace(pulse, channel_gain=tuple(float(g) for g in gain),
                        channel_delay_s=tuple(float(d) for d in delay))
    return pulse, ratio, limit


def _channels(model, seg, y, theta, amp, ratio, limit, weight, sigma2, n_noise):
    """The channels' own gain and delay: y_k = g_k m_k(t - d_k) ~ m_k + dg_k m_k - d_k m_k'
    about the fitted model m; each packet's residual and these columns are projected off
    what the packet's own parameters absorb (its (s_x, s_y, T) Jacobian and amplitude
    columns), then one least squares over all packets; the windows corrected and the
    packets refitted, CHANNEL_ROUNDS times, kept where the median chi^2 ratio falls.
    Returns (y, theta, amp, ratio, limit, gain (4,), delay (4,) [s])."""
    n, _, L = seg.shape
    gain, delay = np.ones(4), np.zeros(4)
    best = first = (y, theta, amp, ratio, limit, gain.copy(), delay.copy())
    mask = model.mask.reshape(n, 4, L)
    eye = np.eye(4)[None, :, :, None]
    for _ in range(CHANNEL_ROUNDS):
        phi, parts = model.evaluate(theta)
        h, dh, g_path = parts[0], parts[1], parts[2]  # (n, 1, 2, 4, L), (n, 1, 2, 4)
        a = amp.reshape(n, 1, 2)[..., None, None] * g_path[..., None]
        m = (a * h).sum(axis=(1, 2)) * mask  # (n, 4, L)
        md = (a * dh).sum(axis=(1, 2)) * mask
        cols = np.concatenate([(eye * m[:, None]), -(eye * md[:, None])], axis=1)
        cols = cols.reshape(n, 8, 4 * L)  # (dg_k, d_k) columns, channel k's rows only
        own = np.concatenate([model.jacobian(parts, amp), phi], axis=1)  # (n, 5, 4L)
        res = y - m.reshape(n, -1)
        w = weight[:, None, None]
        q = own * w
        g = q @ q.transpose(0, 2, 1) + 1e-12 * np.eye(q.shape[1])
        rhs = np.concatenate([cols * w, (res * weight[:, None])[:, None]], axis=1)
        coef = np.linalg.solve(g, q @ rhs.transpose(0, 2, 1))  # (n, 5, 9)
        proj = rhs - (coef.transpose(0, 2, 1) @ q)  # (n, 9, 4L)
        big = proj[:, :8].transpose(0, 2, 1).reshape(-1, 8)
        beta, *_ = np.linalg.lstsq(big, proj[:, 8].ravel(), rcond=1e-8)
        if not np.all(np.isfinite(beta)):
            return best
        gain *= 1.0 + beta[:4]
        delay += beta[4:]
        gain /= np.mean(gain)
        delay -= np.mean(delay)
        y = (shift_channels(seg, model.fs, gain, delay) * mask).reshape(n, -1)
        theta, amp, ratio, limit = _chi2(model, y, theta, sigma2, n_noise)
        if np.median(ratio) < np.median(best[3]):
            best = (y, theta, amp, ratio, limit, gain.copy(), delay.copy())
    g, d = best[5], best[6]
    if np.max(np.abs(g - 1.0)) < MIN_CHANNEL_GAIN and np.max(np.abs(d)) < MIN_CHANNEL_DELAY_S:
        return first  # alike channels: the windows are used as they are
    return best


def _shared(geo, fs, start, length, echo, inside, y, theta, amp, weight, v, with_loss):
    """(pulse, model) with the residues shared by all packets at the poles of v (and the
    loss, ``with_loss``; the packets' parameters held), or None when they give no valid
    pulse."""
    model = _Model(geo, fs, start, length, PulseModel(), echo, inside)
    _, poles, res = _Problem(model, y, theta, amp, weight, with_loss).solve(v)
    try:
        pulse = _learnt(poles, res, v, with_loss)
    except ValueError:
        return None
    return pulse, _Model(geo, fs, start, length, pulse, echo, inside)


class _Modes:
    """The pole fit that needs no pulse yet: every packet's direct wave and echo are sums
    of the same damped exponentials with residues of their own (linear, per packet), so an
    error of the packet's emission time or amplitude is absorbed by its residues; the
    samples within MODES_GUARD_S of a modelled arrival (where a time error would show)
    are left out."""

    def __init__(self, model: _Model, y, theta, weight):
        base = _Problem(model, y, theta, np.ones((len(y), 2)), weight)
        self.fs, self.tau_d, self.tau_e = base.fs, base.tau_d, base.tau_e
        self.g_d = base.w_d  # (K, 4, 1): R / d times the weight
        self.g_e = base.w_e
        lo, hi = MODES_GUARD_S
        near = ((self.tau_d > lo) & (self.tau_d < hi)) | ((self.tau_e > lo) & (self.tau_e < hi))
        self.mask = base.mask * ~near
        self.y = base.y * self.mask

    def residual(self, v):
        poles = _poles_of(v)
        bd, _ = _basis(poles, self.tau_d, self.fs)  # (K, 4, L, P)
        be, _ = _basis(poles, self.tau_e, self.fs)
        m = self.mask[..., None]
        K = bd.shape[0]
        a = np.concatenate([self.g_d[..., None] * bd * m, self.g_e[..., None] * be * m],
                           axis=-1).reshape(K, -1, 2 * poles.size)
        at = a.transpose(0, 2, 1)
        g = at @ a
        b = (at @ self.y.reshape(K, -1, 1))[..., 0]
        d = np.sqrt(np.maximum(np.einsum("kii->ki", g), 1e-300))
        g = g / d[:, :, None] / d[:, None, :] + 1e-9 * np.eye(g.shape[1])
        z = np.linalg.solve(g, (b / d)[..., None])[..., 0] / d
        r = self.y.reshape(K, -1) - (a @ z[..., None])[..., 0]
        return np.where(np.isfinite(r), r, 1e6).ravel()
