# SPDX-License-Identifier: Apache-2.0
"""Results (`OverlapReason`, `OverlapSource`, `OverlapPacket`) and the J-emission model of a
window: its basis, Jacobian, amplitudes by least squares and the Levenberg-Marquardt fit
(numpy, or the compiled kernels of `overlap_kernels`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import overlap_kernels as _kernels
from ae_tactile.localization.common import Reason
from ae_tactile.localization.overlap.pulse import PulseModel, _tables, power_law_filter


class OverlapReason(IntEnum):
    """Why `resolve_overlaps` rejected a packet (0 = accepted). Codes 1-5 are those of
    `Reason` (input problems), 8-11 are specific to the overlap fit."""

    OK = 0
    NONFINITE = int(Reason.NONFINITE)
    NO_SIGNAL = int(Reason.NO_SIGNAL)
    WINDOW = int(Reason.WINDOW)
    SATURATED = int(Reason.SATURATED)
    LOW_SNR = int(Reason.LOW_SNR)
    UNRESOLVED = 8  # residual inconsistent with noise even with max_sources emissions
    UNCERTAIN = 9  # no emission could be localized with in-plane sigma <= max_sigma_m
    DEFERRED = 10  # exhaustive=False: the first joint fit left more than noise (not an answer)
    #: the window is not explained and the pulse is not trusted for this device (neither
    #: given, nor learnt, nor consistent with the batch's single emissions): it may hold a
    #: second emission that was not resolved; `localize_with_overlaps` keeps the
    #: single-source point of such a suspect (its OVERLAP flag set) and counts it here
    UNMODELLED = 11


@dataclass
class OverlapSource:
    """One localized emission (SI units).

    point_m (3,)            contact point on the upper hemisphere
    covariance_m2 (3, 3)    its covariance (joint-model Fisher information, see module doc)
    sigma_m                 in-plane 1-sigma, sqrt(C_xx + C_yy)
    confidence              in [0, 1]
    polarity                +1 touch, -1 release
    amplitude_v             signed direct-wave peak amplitude at distance R (V)
    emission_time_s         emission instant relative to the window's first sample (s)
    arrival_times_s (4,)    direct arrival at each element, same reference (s)
    snr_db                  SNR of this emission alone (docs/conventions.md definition)
    """

    point_m: np.ndarray
    covariance_m2: np.ndarray
    sigma_m: float
    confidence: float
    polarity: int
    amplitude_v: float
    emission_time_s: float
    arrival_times_s: np.ndarray
    snr_db: float


@dataclass
class OverlapPacket:
    """Result for one window: ``sources`` (accepted emissions, earliest first) or a rejection.

    accepted      bool, True when at least one emission was localized
    reason        `OverlapReason` code (0 when accepted)
    n_fitted      emissions in the selected model (0 when not fitted)
    n_dropped     fitted emissions not reported (in-plane sigma > max_sigma_m)
    chi2_ratio    residual energy / (sigma^2 x degrees of freedom) of the selected model
    noise_rms_v   noise sigma used (V)
    n_refused     emissions the model order refused: one carried more energy than the
                  window (emissions cancelling each other, not a touch), or the residual
                  drop was within the pulse's own misfit (`PulseModel.misfit_share`)
    """

    accepted: bool
    reason: int
    sources: list = field(default_factory=list)
    n_fitted: int = 0
    n_dropped: int = 0
    chi2_ratio: float = float("nan")
    noise_rms_v: float = float("nan")
    n_refused: int = 0

    @property
    def reason_name(self) -> str:
        return OverlapReason(self.reason).name


class _Model:
    """Batched evaluation of the J-emission model on K analysis segments."""

    def __init__(
        self,
        geo: FingertipGeometry,
        fs: float,
        start: np.ndarray,
        length: int,
        pulse: PulseModel,
        echo: bool,
        inside=None,
        engine: str = "auto",
    ):
        #: (K, 4L) 1 where the segment's sample lies inside the window, else 0
        self.mask = (
            None
            if inside is None
            else np.repeat(inside[:, None, :], 4, axis=1).reshape(len(start), -1).astype(float)
        )
        self.geo = geo
        self.fs = fs
        self.start = start.astype(float)  # (K,) first sample of each segment
        self.L = int(length)
        self.tab = _tables(pulse, fs, self.L)
        self.pulse = pulse
        self.echo = echo
        self.e = geo.element_positions_m  # (4, 3)
        self.c = geo.sound_speed_m_s
        self.R = geo.radius_m
        #: "auto": the compiled kernels where they apply (`_compiled`); "numpy": never
        self.engine = engine

    def _paths(self, s):
        """Path lengths and their (s_x, s_y) gradients. s (K, J, 2).

        Returns d (K, J, P, 4) with P = 2 paths (direct, echo) and dd (K, J, P, 4, 2)."""
        sx, sy = s[..., 0], s[..., 1]
        sz = np.sqrt(np.maximum(self.R**2 - sx * sx - sy * sy, (1e-3 * self.R) ** 2))
        pt = np.stack([sx, sy, sz], axis=-1)  # (K, J, 3)
        out_d, out_g = [], []
        for sign, base in ((-1.0, 0.0), (1.0, 2.0 * self.R)):
            v = pt[..., None, :] + sign * self.e  # (K, J, 4, 3)
            d = np.sqrt((v * v).sum(axis=-1))
            # d d/d s_x = (v_x + v_z d s_z/d s_x) / d, d s_z/d s_x = -s_x / s_z
            gx = (v[..., 0] - v[..., 2] * (sx / sz)[..., None]) / d
            gy = (v[..., 1] - v[..., 2] * (sy / sz)[..., None]) / d
            out_d.append(d + base)
            out_g.append(np.stack([gx, gy], axis=-1))
        return np.stack(out_d, axis=2), np.stack(out_g, axis=2)

    def pulses(self, t_arr, path_m=None):
        """h and h' on the segment grid for arrivals t_arr (K, A) (s, window time).

        h(t_n - t_a) = Re sum_p [r_p e^{p (t_0 - t_a)}] e^{p n dt} for n >= n0 (first sample
        at/after the arrival), 0 before: one real matrix product with the exponential
        table, no per-sample exponentials. In a lossy medium (``path_m`` (K, A) given) each
        residue is multiplied by W(p) = w_a / (p + w_a) and the term w_a H(-w_a) e^{-w_a t}
        of the attenuation pole is added. Returns (h, dh) (K, A, L)."""
        K, A = t_arr.shape
        fs, L = self.fs, self.L
        p, r = self.tab.poles, self.tab.res
        off = self.start[:, None] / fs - t_arr  # t_0 - t_a
        n0 = np.ceil(-off * fs - 1e-9)
        lossy = path_m is not None and self.pulse.attenuation_db_per_m_at_1mhz > 0
        power = lossy and self.pulse.attenuation_exponent != 2.0
        lossy = lossy and not power
        if lossy:
            wa = self.pulse.attenuation_pole_rad_s(path_m)  # (K, A)
            wa = np.where(np.isfinite(wa), wa, 1e15)
            c = r * (wa[..., None] / (p + wa[..., None])) * np.exp(p * off[..., None])
        else:
            c = r * np.exp(p * off[..., None])  # (K, A, P)
        cd = c * p
        coef = np.stack(
            [np.concatenate([c.real, -c.imag], -1), np.concatenate([cd.real, -cd.imag], -1)],
            axis=2,
        )  # (K, A, 2, 2P)
        vals = (coef.reshape(K * A * 2, -1) @ self.tab.table).reshape(K, A, 2, L)
        if lossy:
            # residue of H(s) W(s) at s = -w_a: w_a H(-w_a), H(s) = sum_p r_p / (s - p)
            ca = wa * (r / (-wa[..., None] - p)).sum(axis=-1).real  # (K, A)
            tau = np.arange(L) / fs + off[..., None]  # t_n - t_a (K, A, L)
            e = ca[..., None] * np.exp(-wa[..., None] * np.maximum(tau, 0.0))
            vals[:, :, 0] += e
            vals[:, :, 1] -= wa[..., None] * e
        vals *= (np.arange(L) >= n0[..., None])[:, :, None, :]
        if power:  # the causal power-law loss of each path, by FFT
            vals = power_law_filter(vals, path_m[:, :, None], fs, self.pulse)
        return vals[:, :, 0], vals[:, :, 1]

    def evaluate(self, theta):
        """Basis Phi (K, 2J, N) (columns: direct, echo of each emission; N = 4L, channel-major)
        and the parts the Jacobian needs, for theta (K, J, 3) = (s_x, s_y, T)."""
        K, J, _ = theta.shape
        L = self.L
        d, dd = self._paths(theta[..., :2])  # (K,J,2,4), (K,J,2,4,2)
        t_arr = theta[..., 2][..., None, None] + d / self.c  # (K, J, 2, 4)
        h, dh = self.pulses(t_arr.reshape(K, -1), d.reshape(K, -1))
        h = h.reshape(K, J, 2, 4, L)
        dh = dh.reshape(K, J, 2, 4, L)
        gain = np.ones((K, J, 2, 4))
        gain[:, :, 0] = self.R / d[:, :, 0]
        dgain = np.zeros((K, J, 2, 4, 2))
        dgain[:, :, 0] = -(self.R / d[:, :, 0] ** 2)[..., None] * dd[:, :, 0]
        if not self.echo:
            gain[:, :, 1] = 0.0
        phi = (gain[..., None] * h).reshape(K, 2 * J, 4 * L)
        if self.mask is not None:
            phi *= self.mask[:, None, :]
        return phi, (h, dh, gain, dgain, dd / self.c)

    def jacobian(self, parts, amp):
        """d model / d theta (K, 3J, N) for amplitudes amp (K, 2J):
        d/d s_i = sum_paths a (dgain_i h - gain h' dt_i),  d/d T = -sum_paths a gain h'."""
        h, dh, gain, dgain, dtds = parts
        K, J = h.shape[:2]
        a = amp.reshape(K, J, 2)
        ag = a[..., None] * gain  # (K, J, 2, 4)
        ads = a[..., None, None] * dgain  # (K, J, 2, 4, 2)
        agt = ag[..., None] * dtds  # (K, J, 2, 4, 2)
        dsx = np.einsum("kjec,kjecl->kjcl", ads[..., 0], h) - np.einsum(
            "kjec,kjecl->kjcl", agt[..., 0], dh
        )
        dsy = np.einsum("kjec,kjecl->kjcl", ads[..., 1], h) - np.einsum(
            "kjec,kjecl->kjcl", agt[..., 1], dh
        )
        dT = -np.einsum("kjec,kjecl->kjcl", ag, dh)
        jac = np.stack([dsx, dsy, dT], axis=2).reshape(K, 3 * J, -1)
        if self.mask is not None:
            jac *= self.mask[:, None, :]
        return jac


def _lstsq_amplitudes(phi, y, ridge=1e-9):
    """LS amplitudes a (K, 2J) of y (K, N) on columns phi (K, 2J, N) (ridge for empty ones)."""
    g = phi @ phi.transpose(0, 2, 1)
    b = (phi @ y[..., None])[..., 0]
    # Jacobi scaling (columns of very different units), then a relative ridge
    dg = np.einsum("kii->ki", g)
    sc = 1.0 / np.sqrt(np.maximum(dg, 1e-300 + 1e-30 * dg.max(axis=1, keepdims=True)))
    g = g * sc[:, :, None] * sc[:, None, :] + ridge * np.eye(g.shape[1])
    return np.linalg.solve(g, (b * sc)[..., None])[..., 0] * sc


def _model_values(phi, amp):
    return (amp[:, None, :] @ phi)[:, 0]


def _residual(model: "_Model", y, theta, amp):
    """y - model(theta, amp): (K, 4L) for theta (K, J, 3), amp (K, 2J)."""
    if not _compiled(model):
        phi, _ = model.evaluate(theta)
        return y - _model_values(phi, amp)
    out = np.empty(y.shape)
    args = _kernel_args(model)
    mask = np.ones(y.shape[1]) if model.mask is None else model.mask
    for k in range(y.shape[0]):
        _kernels.model_residual(
            np.ascontiguousarray(y[k], dtype=np.float64),
            np.ascontiguousarray(mask if mask.ndim == 1 else mask[k], dtype=np.float64),
            float(model.start[k]) / model.fs,
            np.ascontiguousarray(theta[k], dtype=np.float64),
            np.ascontiguousarray(amp[k], dtype=np.float64),
            *args,
            out[k],
        )
    return out


def _clip_theta(theta, geo, max_rho):
    s = theta[..., :2]
    rho = np.hypot(s[..., 0], s[..., 1])
    f = np.where(rho > max_rho, max_rho / np.maximum(rho, 1e-300), 1.0)
    out = theta.copy()
    out[..., :2] = s * f[..., None]
    return out


#: Levenberg-Marquardt steps per fit, and the fit's bound on the polar angle of a point
LM_ITERATIONS = 12


MAX_FIT_POLAR_DEG = 85.0


def _max_rho(geo) -> float:
    """Largest in-plane radius of a fitted point (m): R sin(MAX_FIT_POLAR_DEG)."""
    return geo.radius_m * math.sin(math.radians(MAX_FIT_POLAR_DEG))


def _lm(model: "_Model", y, theta, iterations=LM_ITERATIONS, max_rho=None):
    """Levenberg-Marquardt over all 5J parameters (K packets in parallel); after each step
    the linear amplitudes are re-solved by LS (variable projection). Returns theta,
    amplitudes (K, 2J), rss (K,), and the Gram matrix of the final Jacobian (K, 5J, 5J)
    (parameter order: (s_x, s_y, T) per emission, then (direct, echo) amplitudes)."""
    K, J, _ = theta.shape
    geo = model.geo
    max_rho = _max_rho(geo) if max_rho is None else max_rho
    if _compiled(model):
        return _lm_compiled(model, y, theta, iterations, max_rho)
    theta = _clip_theta(theta, geo, max_rho)
    phi, parts = model.evaluate(theta)
    amp = _lstsq_amplitudes(phi, y)
    res = y - _model_values(phi, amp)
    rss = (res * res).sum(axis=1)
    lam = np.full(K, 1e-3)
    active = np.ones(K, bool)
    parts = list(parts)
    for _ in range(iterations):
        ids = np.nonzero(active)[0]
        if ids.size == 0:
            break
        K_ = ids.size
        pa = tuple(q[ids] for q in parts)
        sub = _sub(model, ids)
        jac = np.concatenate([sub.jacobian(pa, amp[ids]), phi[ids]], axis=1)  # (K_, 5J, N)
        jtj = jac @ jac.transpose(0, 2, 1)
        jtr = (jac @ res[ids][..., None])[..., 0]
        dg = np.einsum("kii->ki", jtj)
        dg = np.maximum(dg, 1e-12 * dg.max(axis=1, keepdims=True) + 1e-300)
        a = jtj + (lam[ids][:, None] * dg)[:, :, None] * np.eye(jtj.shape[1])
        try:
            step = np.linalg.solve(a, jtr[..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = np.zeros_like(jtr)
        step = np.where(np.isfinite(step), step, 0.0)
        new = _clip_theta(theta[ids] + step[:, : 3 * J].reshape(K_, J, 3), geo, max_rho)
        ph2, pa2 = sub.evaluate(new)
        amp2 = _lstsq_amplitudes(ph2, y[ids])
        res2 = y[ids] - _model_values(ph2, amp2)
        rss2 = (res2 * res2).sum(axis=1)
        better = rss2 < rss[ids]
        gi = ids[better]
        theta[gi], amp[gi], res[gi], phi[gi] = new[better], amp2[better], res2[better], ph2[better]
        for q, q2 in zip(parts, pa2):
            q[gi] = q2[better]
        rel = (rss[gi] - rss2[better]) / np.maximum(rss[gi], 1e-300)
        converged = (rel < _kernels.LM_REL_TOL) & (lam[gi] <= _kernels.LM_STOP_LAMBDA)
        rss[gi] = rss2[better]
        lam[gi] = np.maximum(lam[gi] / 4.0, 1e-7)
        bi = ids[~better]
        lam[bi] = lam[bi] * 8.0
        done = np.zeros(K, bool)
        done[gi[converged]] = True
        done[bi[lam[bi] > 1e6]] = True
        active &= ~done
    jac = np.concatenate([model.jacobian(tuple(parts), amp), phi], axis=1)
    return theta, amp, rss, jac @ jac.transpose(0, 2, 1)


def _compiled_medium(pulse: PulseModel) -> bool:
    """The compiled kernels can fit this pulse: numba present, a lossless medium."""
    return _kernels.NUMBA_AVAILABLE and not pulse.attenuation_db_per_m_at_1mhz > 0


def _compiled(model: "_Model") -> bool:
    """The compiled kernels apply: not refused (engine "numpy"), `_compiled_medium`."""
    return model.engine != "numpy" and _compiled_medium(model.pulse)


def _kernel_args(model: "_Model") -> tuple:
    """The model's constants in the order of the kernels' arguments (elem .. tab_im)."""
    P = model.tab.half_poles.size
    tab = model.tab.half_table
    return (
        np.ascontiguousarray(model.e, dtype=np.float64),
        float(model.c),
        float(model.R),
        bool(model.echo),
        float(model.fs),
        model.tab.half_poles,
        model.tab.half_res,
        tab[:P],
        tab[P:],
    )


def _lm_compiled(model: "_Model", y, theta, iterations, max_rho):
    """`_lm` by `overlap_kernels.lm_fit`, one window at a time (same outputs)."""
    K, J, _ = theta.shape
    mask = np.ones(y.shape[1]) if model.mask is None else model.mask
    th = np.empty((K, J, 3))
    amp = np.empty((K, 2 * J))
    rss = np.empty(K)
    gram = np.empty((K, 5 * J, 5 * J))
    args = _kernel_args(model)
    for k in range(K):
        rss[k] = _kernels.lm_fit(
            np.ascontiguousarray(y[k], dtype=np.float64),
            np.ascontiguousarray(mask if mask.ndim == 1 else mask[k], dtype=np.float64),
            float(model.start[k]) / model.fs,
            np.ascontiguousarray(theta[k], dtype=np.float64),
            *args,
            int(iterations),
            float(max_rho),
            th[k],
            amp[k],
            gram[k],
        )
    return th, amp, rss, gram


def _sub(model: _Model, ids) -> _Model:
    sub = _Model.__new__(_Model)
    sub.__dict__.update(model.__dict__)
    sub.start = model.start[ids]
    if model.mask is not None:
        sub.mask = model.mask[ids]
    return sub


def _positive(name, v):
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {v!r}") from None
    if not (math.isfinite(f) and f > 0):
        raise ValueError(f"{name} must be a positive finite number, got {v!r}")
    return f
