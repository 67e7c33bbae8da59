"""Overlapping emissions: localize two or three emissions that share one packet window.

Several touches within microseconds (three pins, a plate landing, slip bursts) put two or
three emissions from different points into one window. The single-source estimators
(`localize`) reject them (OVERLAP) or, when the second emission arrives late in the
echo-free segment, accept a wrong point. This module fits them jointly.

Model (white Gaussian noise sigma^2 per sample, per channel): J emissions, source j at
the surface point s_j = (s_x, s_y, sqrt(R^2 - s_x^2 - s_y^2)), emission time T_j, direct
amplitude A_j (signed: touch > 0) and first-echo amplitude B_j:

    y_k(t) = sum_j [ A_j (R / d_jk) h(t - T_j - d_jk / c) + B_j h(t - T_j - e_jk / c) ] + n_k(t)

    d_jk = |s_j - e_k| (direct path),  e_jk = 2R + |s_j + e_k| (first wall echo: the
    hemisphere on its base acts, by the mirror image in the base plane, as a full sphere;
    the concave wall refocuses the echo, so its amplitude is the same on all elements).

h(t) is the *known pulse shape*: the response of the front end (Butterworth high-pass and
anti-alias low-pass, `PulseModel`) to the collision pressure of the paper's Eq. 9,
P1(s) = 2/(s + 2 alpha) - 1/(s + alpha) (a step for omega >> alpha), evaluated in closed
form at any sub-sample time (partial fractions) and normalised to a unit peak. Unknowns
per emission: (s_x, s_y, T_j) nonlinear, (A_j, B_j) linear: 5 per emission.

Fit over the window from 1 us before the onset to before the *second* wall echo of the
earliest emission (4R/c - 2 sqrt(2) a / c after it: 24 us in water), so that an emission
arriving up to ~10 us after the first is still seen whole; the first echoes of every
emission are part of the model. Search (RELAX, cyclic superimposed-signal estimation):

  1. matched-filter grid: per channel correlation with h, summed over channels along the
     travel times of a 1 mm grid of surface points; the three best points at distinct
     times are kept, the best starts the Levenberg-Marquardt fit of one emission;
  2. emission 2 is searched only when the one-emission residual is not noise: joint LM
     from (emission 1, best grid point of the residual); where that still leaves more
     than noise, also from each pair of the three time peaks of step 1, from emission 1
     re-searched on the data minus emission 2 (RELAX), and with the points swapped; the
     best residual wins. A third emission likewise;
  3. model order: J + 1 emissions only if the residual energy falls by more than
     ``add_threshold`` sigma^2 (a generalised likelihood-ratio test; single-source packets
     stay single, measured in docs/localization.md);
  4. the final residual must be consistent with noise (chi^2 per degree of freedom below
     ``max_chi2_ratio``) and no two emissions closer than ``min_separation_s``, else the
     packet is rejected (a wrong or missing emission leaves its energy in the residual);
  5. covariance of each point: the (s_x, s_y) block of the inverse Fisher matrix of the
     joint model, F = J^T J / sigma^2 (all 5J parameters), inflated by the chi^2 ratio
     when it exceeds 1; an emission whose in-plane 1-sigma exceeds ``max_sigma_m`` is not
     reported (counted in ``n_dropped``).

`suspect_overlap` is the cheap test for packets `localize` accepted as single: the
emission time by the matched filter along the accepted point's travel times, one linear
LS on [h, h'] (direct wave and echo), chi^2 per degree of freedom against the same limit.
`localize_with_overlaps` chains the fast path, the test and the overlap fit.
`calibrate_pulse` fits the front-end corners of `PulseModel` to single touches. The LM
fits and the grid run as compiled kernels where numba is present (`overlap_kernels`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
import scipy.fft as sfft
from scipy import signal

from ae_tactile.geometry import FingertipGeometry, front_end_lowpass
from ae_tactile.localization import overlap_kernels as _kernels
from ae_tactile.localization.common import (
    Reason,
    adc_noise,
    make_plan,
    per_packet,
    prepare,
    subset,
    validate_windows,
)

__all__ = [
    "PulseModel",
    "OverlapReason",
    "OverlapSource",
    "OverlapPacket",
    "resolve_overlaps",
    "suspect_overlap",
    "calibrate_pulse",
    "localize_with_overlaps",
    "warm_up",
]


class OverlapReason(IntEnum):
    """Why `resolve_overlaps` rejected a packet (0 = accepted). Codes 1-5 are those of
    `Reason` (input problems), 8 and 9 are specific to the overlap fit."""

    OK = 0
    NONFINITE = int(Reason.NONFINITE)
    NO_SIGNAL = int(Reason.NO_SIGNAL)
    WINDOW = int(Reason.WINDOW)
    SATURATED = int(Reason.SATURATED)
    LOW_SNR = int(Reason.LOW_SNR)
    UNRESOLVED = 8  # residual inconsistent with noise even with max_sources emissions
    UNCERTAIN = 9  # no emission could be localized with in-plane sigma <= max_sigma_m
    DEFERRED = 10  # exhaustive=False: the first joint fit left more than noise (not an answer)


# --------------------------------------------------------------------------- pulse model
@dataclass(frozen=True)
class PulseModel:
    """Known pulse shape h(t): front-end response to the collision pressure (paper Eq. 9).

    H(s) = P1(s) HP_n(s) LP_m(s), P1(s) = s / ((s + alpha)(s + 2 alpha)) (= 2/(s + 2 alpha)
    - 1/(s + alpha)), Butterworth HP (``highpass_hz``, order ``highpass_order``) and LP
    (``lowpass_hz``, order ``lowpass_order``; None: no low-pass). h(t) = sum_p r_p e^{p t}
    for t >= 0 (simple poles), 0 before, scaled to a peak of +1 (a touch starts positive).
    Parameters of the product's front end, not of any simulator.

    ``attenuation_db_per_m_at_1mhz`` > 0: a lossy medium, loss att l (f / 1 MHz)^2 dB over
    a path of length l, realised as one real pole per path, W_l(s) = w_a / (s + w_a) with
    10 log10(1 + (1 MHz / f_a)^2) = att l (the causal viscous law of docs/simulator.md):
    every arrival's pulse then depends on its path length.
    """

    highpass_hz: float = 100e3
    highpass_order: int = 2
    lowpass_hz: float | None = 1e6
    lowpass_order: int = 4
    alpha_1_s: float = 3000.0
    attenuation_db_per_m_at_1mhz: float = 0.0

    @classmethod
    def from_config(cls, config) -> "PulseModel":
        """From any object with the front-end attributes of ``ae_tactile.sim.SimConfig``
        (and its medium loss when its ``attenuation`` is on)."""
        att = float(getattr(config, "attenuation_db_per_m", 0.0) or 0.0)
        return cls(
            float(config.highpass_hz),
            int(config.highpass_order),
            None if config.lowpass_hz is None else float(config.lowpass_hz),
            int(config.lowpass_order),
            attenuation_db_per_m_at_1mhz=att,
        )

    @classmethod
    def for_sample_rate(cls, sample_rate_hz: float) -> "PulseModel":
        """The product's default front end at this ADC rate: its low-pass is
        `ae_tactile.geometry.front_end_lowpass` (1 MHz, order 4; below 3.33 MS/s the
        anti-alias filter, 0.3 fs, order 8). The default wherever ``pulse`` is None."""
        lp_hz, lp_order = front_end_lowpass(float(sample_rate_hz))
        return cls(lowpass_hz=lp_hz, lowpass_order=lp_order)

    def attenuation_pole_rad_s(self, path_m):
        """w_a (rad/s) of paths of length ``path_m`` (inf when lossless)."""
        loss_db = np.asarray(path_m, float) * float(self.attenuation_db_per_m_at_1mhz)
        x = np.expm1(loss_db * (math.log(10.0) / 10.0))
        return np.where(x > 0, 2.0 * math.pi * 1e6 / np.sqrt(np.where(x > 0, x, 1.0)), np.inf)

    def poles_residues(self):
        """(poles (P,) complex, residues (P,) complex) of h, peak-normalised (cached)."""
        cache = _PR_CACHE.get(self)
        if cache is not None:
            return cache
        zs, ps, k = (
            [np.zeros(1, complex)],
            [np.array([-self.alpha_1_s, -2.0 * self.alpha_1_s], complex)],
            1.0,
        )
        z, p, kk = signal.butter(
            self.highpass_order,
            2 * math.pi * self.highpass_hz,
            btype="highpass",
            analog=True,
            output="zpk",
        )
        zs.append(z)
        ps.append(p)
        k *= kk
        if self.lowpass_hz is not None:
            z, p, kk = signal.butter(
                self.lowpass_order,
                2 * math.pi * self.lowpass_hz,
                btype="lowpass",
                analog=True,
                output="zpk",
            )
            zs.append(z)
            ps.append(p)
            k *= kk
        zeros = np.concatenate(zs).astype(complex)
        poles = np.concatenate(ps).astype(complex)
        res = np.array(
            [
                k * np.prod(q - zeros) / np.prod(q - np.delete(poles, i))
                for i, q in enumerate(poles)
            ]
        )
        t = np.linspace(0.0, 20.0 / (2 * math.pi * self.highpass_hz), 20001)
        h = (res[None, :] * np.exp(poles[None, :] * t[:, None])).sum(axis=1).real
        res = res / h[np.argmax(np.abs(h))]
        _PR_CACHE[self] = (poles, res)
        return poles, res

    def waveform(self, t_s):
        """h(t) (unit peak) at times t_s (s, any shape)."""
        p, r = self.poles_residues()
        t = np.asarray(t_s, float)
        v = (r * np.exp(p * np.maximum(t, 0.0)[..., None])).sum(axis=-1).real
        return np.where(t >= 0, v, 0.0)


_PR_CACHE: dict = {}


@dataclass(frozen=True)
class _Tables:
    """Exponential tables E_p[m] = e^{p m dt} stacked [Re; Im] (2P, L) for h and h'."""

    poles: np.ndarray
    res: np.ndarray
    table: np.ndarray
    h_samples: np.ndarray  # h(m dt), m = 0..L-1 (matched filter)
    #: one pole of each conjugate pair (residue doubled: Re(c e^{pt}) + Re(c* e^{p* t}) =
    #: 2 Re(c e^{pt})) and the real poles; their tables [Re; Im]: the compiled kernels'
    half_poles: np.ndarray
    half_res: np.ndarray
    half_table: np.ndarray
    #: z_p = e^{p / f_s} of the half poles: h[m] = Re sum_p half_res_p z_p^m (the compiled
    #: matched filter's recursion)
    half_z: np.ndarray


def _given(prep):
    """(K,) bool: the noise sigma was given (analog: + q^2/12), not measured."""
    if prep.noise_given is None:
        return np.zeros(len(prep.sigma2), bool)
    return np.asarray(prep.noise_given, bool)


def _tables(pulse: PulseModel, fs: float, n: int) -> _Tables:
    key = (pulse, fs, n)
    t = _TAB_CACHE.get(key)
    if t is None:
        p, r = pulse.poles_residues()
        e = np.exp(p[:, None] * (np.arange(n) / fs)[None, :])
        tab = np.ascontiguousarray(np.vstack([e.real, e.imag]))
        h = (r[:, None] * e).sum(axis=0).real
        tiny = 1e-9 * np.abs(p)
        upper, real = p.imag > tiny, np.abs(p.imag) <= tiny
        if upper.sum() == (p.imag < -tiny).sum():  # every complex pole has its conjugate
            keep = upper | real
        else:
            keep = np.ones(p.size, bool)
        hp, hr, eh = p[keep], (np.where(upper, 2.0, 1.0) * r)[keep], e[keep]
        htab = np.ascontiguousarray(np.vstack([eh.real, eh.imag]))
        t = _TAB_CACHE[key] = _Tables(
            p, r, tab, h, hp.copy(), hr.copy(), htab, np.exp(hp / fs)
        )
    return t


_TAB_CACHE: dict = {}


# --------------------------------------------------------------------------- results
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
    """

    accepted: bool
    reason: int
    sources: list = field(default_factory=list)
    n_fitted: int = 0
    n_dropped: int = 0
    chi2_ratio: float = float("nan")
    noise_rms_v: float = float("nan")

    @property
    def reason_name(self) -> str:
        return OverlapReason(self.reason).name


# --------------------------------------------------------------------------- model
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


# --------------------------------------------------------------------------- grid search
def _surface_grid(geo: FingertipGeometry, spacing_m, max_polar_deg=80.0):
    """(G, 2) square grid of (s_x, s_y) over the cap polar <= max_polar_deg (cached; do
    not modify the array)."""
    key = (geo, float(spacing_m), float(max_polar_deg))
    grid = _GRID_CACHE.get(key)
    if grid is None:
        rmax = geo.radius_m * math.sin(math.radians(max_polar_deg))
        n = int(math.ceil(rmax / spacing_m))
        g = np.arange(-n, n + 1) * spacing_m
        gx, gy = np.meshgrid(g, g, indexing="ij")
        keep = np.hypot(gx, gy) <= rmax
        grid = np.stack([gx[keep], gy[keep]], axis=1)
        grid.setflags(write=False)
        if len(_GRID_CACHE) > 16:
            _GRID_CACHE.clear()
        _GRID_CACHE[key] = grid
    return grid


_GRID_CACHE: dict = {}


@dataclass(frozen=True)
class _GridTables:
    """What the grid search needs of a grid, a geometry and a pulse (cached per segment
    length): distances d (G, 4), direct gains R / d, travel times tt, integer relative
    delays rel (G, 4), ||phi||^2 per point, float32 copies, the conjugate spectrum of h."""

    d: np.ndarray
    gain: np.ndarray
    tt: np.ndarray
    rel: np.ndarray
    pad: int
    norm: np.ndarray
    gain32: np.ndarray
    norm32: np.ndarray
    nfft: int
    h_conj_spectrum: np.ndarray


def _grid_tables(model: _Model, grid, L) -> _GridTables:
    key = (model.geo, model.fs, model.pulse, L, grid.shape, grid.tobytes())
    t = _GRID_TAB_CACHE.get(key)
    if t is None:
        fs = model.fs
        h = model.tab.h_samples
        nfft = sfft.next_fast_len(2 * L, real=True)
        d = model.geo._xy_distances(grid[:, 0], grid[:, 1])  # (G, 4)
        gain = model.R / d
        tt = d / model.c
        rel = np.rint((tt - tt.min(axis=1, keepdims=True)) * fs).astype(np.int64)  # (G, 4)
        # ||phi||^2 for an arrival inside the segment: sum_k gain^2 sum h^2
        norm = (gain**2).sum(axis=1) * float((h * h).sum())
        t = _GridTables(
            d, gain, tt, rel, int(rel.max()) + 1, norm, gain.astype(np.float32),
            norm.astype(np.float32), nfft, np.conj(sfft.rfft(h, n=nfft)),
        )
        if len(_GRID_TAB_CACHE) > 64:
            _GRID_TAB_CACHE.clear()
        _GRID_TAB_CACHE[key] = t
    return t


_GRID_TAB_CACHE: dict = {}


def _grid_step(fs: float) -> int:
    """Arrival samples the grid tries first: every second one at >= 5 MS/s (the matched
    filter is smooth: the band ends at 1 MHz <= fs / 5), else every one."""
    return 2 if fs >= 5e6 else 1


def _grid_search(model: _Model, r, grid, chunk=64, n_peaks=1, min_sep_s=0.8e-6):
    """Best (s_x, s_y, T) (K, 3) of one emission in residual r (K, 4, L): matched filter per
    channel (correlation with h), summed over channels along each grid point's travel
    times (integer samples), maximising |C|^2 / ||phi||^2. With ``n_peaks`` > 1 it returns
    (K, n_peaks, 3): the best, then the best points at the next peaks in time of the
    profile max_g |C|^2 / ||phi||^2 (>= ``min_sep_s`` from earlier ones)."""
    K, _, L = r.shape
    fs = model.fs
    gt = _grid_tables(model, grid, L)
    gain, tt, rel, pad, norm, gain32 = gt.gain, gt.tt, gt.rel, gt.pad, gt.norm, gt.gain32
    cp = np.zeros((K, 4, L + pad + 2), np.float32)
    if _compiled(model):  # the same correlation by the pulse's poles (no FFT)
        rf = np.ascontiguousarray(r, dtype=np.float64).reshape(K, 4 * L)
        for k in range(K):
            _kernels.matched_filter(rf[k], L, model.tab.half_z, model.tab.half_res, cp[k])
    else:
        nfft, H = gt.nfft, gt.h_conj_spectrum
        corr = sfft.irfft(sfft.rfft(r, n=nfft, axis=2) * H, n=nfft, axis=2)
        cp[:, :, :L] = corr[..., :L]  # arrival at n
    # every second arrival sample first (`_grid_step`), then the best point's neighbours
    step = _grid_step(fs)
    mm = np.arange(0, L, step)
    min_sep = max(1, int(round(min_sep_s * fs)))
    prof = np.zeros((K, mm.size))
    prof_g = np.zeros((K, mm.size), np.int64)
    if _compiled(model):
        p32 = np.empty(mm.size, np.float32)
        for k in range(K):
            _kernels.grid_profile(cp[k], gain32, rel, gt.norm32, step, p32, prof_g[k])
            prof[k] = p32
    else:
        idx = rel[:, :, None] + mm[None, None, :]  # (G, 4, L/2)
    for k0 in range(0, K if not _compiled(model) else 0, chunk):
        sl = slice(k0, min(K, k0 + chunk))
        c = np.zeros((sl.stop - sl.start, grid.shape[0], mm.size), np.float32)
        for ch in range(4):
            c += gain32[None, :, ch, None] * cp[sl, ch][:, idx[:, ch]]
        stat = (c * c) / norm[None, :, None].astype(np.float32)
        gi = np.argmax(stat, axis=1)  # (k, L/2)
        prof_g[sl] = gi
        prof[sl] = np.take_along_axis(stat, gi[:, None, :], axis=1)[:, 0]
    i = np.argmax(prof, axis=1)
    best_g = prof_g[np.arange(K), i]
    best_m = mm[i]
    if n_peaks > 1:
        # further peaks of the time profile max_g stat(g, m), >= min_sep samples apart
        peaks = [np.stack([grid[best_g, 0], grid[best_g, 1], best_m.astype(float)], 1)]
        pr = prof.copy()
        rows_ = np.arange(K)
        last = i
        for _ in range(n_peaks - 1):
            lo = np.searchsorted(mm, mm[last] - min_sep)
            hi = np.searchsorted(mm, mm[last] + min_sep, side="right")
            mask = (np.arange(mm.size)[None, :] >= lo[:, None]) & (
                np.arange(mm.size)[None, :] < hi[:, None]
            )
            pr[mask] = -np.inf
            last = np.argmax(pr, axis=1)
            g2 = prof_g[rows_, last]
            peaks.append(np.stack([grid[g2, 0], grid[g2, 1], mm[last].astype(float)], 1))
        extra = []
        for pk in peaks[1:]:
            gidx = np.argmin(
                np.abs(grid[:, None, 0] - pk[None, :, 0])
                + np.abs(grid[:, None, 1] - pk[None, :, 1]),
                axis=0,
            )
            T2 = (model.start + pk[:, 2]) / fs - tt[gidx].min(axis=1)
            extra.append(np.stack([pk[:, 0], pk[:, 1], T2], 1))
    rows = np.arange(K)
    cand = np.clip(best_m[:, None] + np.array([-1, 0, 1]), 0, L - 1)  # (K, 3)
    ix = rel[best_g][:, :, None] + cand[:, None, :]  # (K, 4, 3)
    cv = (gain[best_g][:, :, None] * cp[rows[:, None, None], np.arange(4)[None, :, None], ix]).sum(
        axis=1
    )
    st = cv * cv / norm[best_g][:, None]
    pick = np.argmax(st, axis=1)
    best_m = cand[rows, pick]
    best_val = st[rows, pick]
    s = grid[best_g]
    t_first = (model.start + best_m) / fs
    T = t_first - tt[best_g].min(axis=1)
    best = np.concatenate([s, T[:, None]], axis=1)
    if n_peaks > 1:
        return np.stack([best] + extra, axis=1), best_val
    return best, best_val


# --------------------------------------------------------------------------- driver
@dataclass
class _Fit:
    theta: np.ndarray  # (K, J, 3)
    amp: np.ndarray  # (K, 2J)
    rss: np.ndarray  # (K,)
    gram: np.ndarray  # (K, 5J, 5J) Gram matrix of the Jacobian (Fisher x sigma^2)


def _analysis_s(geo, analysis_s) -> float:
    """Span of the fit after the onset (s): up to before the earliest emission's second
    wall echo, 4R/c - 2 sqrt(2) a / c - 0.3 us, unless given."""
    if analysis_s is not None:
        return analysis_s
    a = geo.element_offset_m
    return (4.0 * geo.radius_m - 2.0 * math.sqrt(2.0) * a) / geo.sound_speed_m_s - 0.3e-6


def _segments(prep, plan, geo, fs, analysis_s):
    m = prep.x.shape[2]
    start = np.clip(prep.onset - plan.pre, 0, m - 1)
    nominal = plan.pre + int(math.floor(_analysis_s(geo, analysis_s) * fs))
    length = max(int(np.max(np.minimum(m - start, nominal), initial=8)), 8)
    idx = start[:, None] + np.arange(length)[None, :]
    inside = idx < m  # samples past the window end are masked out of the fit
    seg = np.take_along_axis(prep.x, np.clip(idx, 0, m - 1)[:, None, :].repeat(4, axis=1), axis=2)
    seg = (seg - prep.pre_mean[..., None]) * inside[:, None, :]
    return seg, start, length, inside


def _search(
    model: _Model,
    seg,
    max_sources,
    grid,
    sigma2=None,
    add_threshold=None,
    search_limit=None,
    deferred=None,
):
    """RELAX search for 1..max_sources emissions. Returns the list of _Fit, one per J
    (packets that stop adding emissions keep their previous fit in later entries).

    With ``sigma2`` (K,), emission j + 1 is searched only where the j-emission residual is
    above ``search_limit`` (K,) x sigma^2 x dof (the data are not yet explained: a
    single-source packet costs one fit) and, for j >= 2, the j-th emission was significant
    (residual drop > ``add_threshold`` sigma^2). ``deferred`` (K,) bool: where given, a
    packet whose first joint fit still leaves more than noise is marked there and searched
    no further (the caller answers it later with the exhaustive search)."""
    K = seg.shape[0]
    y = seg.reshape(K, -1)
    cands, _ = _grid_search(model, seg, grid, n_peaks=3)
    theta, amp, rss, jac = _lm(model, y, cands[:, :1].copy())
    fits = [_Fit(theta, amp, rss, jac)]
    for j in range(2, max_sources + 1):
        prev = fits[-1]
        go = np.ones(K, bool)
        if sigma2 is not None:
            n_in = y.shape[1] if model.mask is None else model.mask.sum(axis=1)
            dof = np.maximum(n_in - 5 * (j - 1), 1)
            go = prev.rss > search_limit * sigma2 * dof
            if j > 2:
                go &= (fits[-2].rss - prev.rss) > add_threshold * sigma2
        if deferred is not None:
            go &= ~deferred
        ids = np.nonzero(go)[0]
        theta = np.concatenate([prev.theta, np.zeros((K, 1, 3))], axis=1)
        amp = np.concatenate([prev.amp, np.zeros((K, 2))], axis=1)
        rss = prev.rss.copy()
        jac = np.zeros((K, 5 * j, 5 * j))
        if ids.size:
            sub = _sub(model, ids)
            ys = y[ids]
            res = _residual(sub, ys, prev.theta[ids], prev.amp[ids])
            thn, _ = _grid_search(sub, res.reshape(len(ids), 4, -1), grid)
            start = np.concatenate([prev.theta[ids], thn[:, None, :]], axis=1)
            t1, a1, r1, j1 = _lm(sub, ys, start)
            # Other starting points, only where this fit leaves more than noise (a fit at
            # the noise level explains the data; the others guard against local optima).
            alt = np.arange(len(ids))
            if sigma2 is not None:
                n_in = y.shape[1] if sub.mask is None else sub.mask.sum(axis=1)
                dof = np.maximum(n_in - 5 * j, 1)
                alt = np.nonzero(r1 > search_limit[ids] * sigma2[ids] * dof)[0]
            if alt.size and deferred is not None:
                deferred[ids[alt]] = True
                alt = alt[:0]
            if alt.size:
                _alternatives(
                    _sub(sub, alt), ys[alt], j, cands[ids[alt]], grid, alt, t1, a1, r1, j1
                )
            # order emissions by emission time
            order = np.argsort(t1[..., 2], axis=1)
            t1 = np.take_along_axis(t1, order[..., None], axis=1)
            ao = np.stack([2 * order, 2 * order + 1], axis=2).reshape(len(ids), -1)
            a1 = np.take_along_axis(a1, ao, axis=1)
            jo = np.concatenate(
                [(3 * order[..., None] + np.arange(3)).reshape(len(ids), -1), 3 * j + ao], axis=1
            )
            j1 = np.take_along_axis(
                np.take_along_axis(j1, jo[:, None, :], axis=2), jo[:, :, None], axis=1
            )
            theta[ids], amp[ids], rss[ids], jac[ids] = t1, a1, r1, j1
        fits.append(_Fit(theta, amp, rss, jac))
    return fits


def _quick_search_compiled(model, ys, masks, max_sources, grid, sigma2, add_threshold,
                           search_limit, deferred):
    """`_search` with ``deferred`` by `overlap_kernels.quick_search`, one call per window
    (the same fits; the grid's further time peaks, which only the exhaustive search uses,
    are not computed). ys, masks (K, 4L)."""
    K, N = ys.shape
    L = N // 4
    gt = _grid_tables(model, grid, L)
    mm = np.arange(0, L, _grid_step(model.fs))
    J = max_sources
    theta = np.empty((K, J, J, 3))
    amp = np.empty((K, J, 2 * J))
    rss = np.empty((K, J))
    gram = np.empty((K, J, 5 * J, 5 * J))
    args = _kernel_args(model)
    for k in range(K):
        deferred[k] = _kernels.quick_search(
            ys[k],
            masks[k],
            float(model.start[k]),
            float(sigma2[k]),
            float(search_limit[k]),
            float(add_threshold),
            int(max_sources),
            *args,
            LM_ITERATIONS,
            _max_rho(model.geo),
            model.tab.half_z,
            model.tab.half_res,
            gt.gain32,
            gt.rel,
            gt.norm32,
            mm,
            gt.gain,
            gt.norm,
            gt.tt,
            grid,
            int(gt.pad),
            theta[k],
            amp[k],
            rss[k],
            gram[k],
        )
    return [
        _Fit(
            theta[:, j - 1, :j].copy(),
            amp[:, j - 1, : 2 * j].copy(),
            rss[:, j - 1].copy(),
            gram[:, j - 1, : 5 * j, : 5 * j].copy(),
        )
        for j in range(1, J + 1)
    ]


def _noise_sat_fs(noise_rms_v, saturated, full_scale_v, K):
    """The compiled preparation's per-window arguments: known noise sigma (NaN: measured,
    as for non-positive values in `common.prepare`), saturation flag (-1: unknown), full
    scale (NaN: unknown)."""
    if noise_rms_v is None:
        noise = np.full(K, np.nan)
    else:
        nr = per_packet("noise_rms_v", noise_rms_v, K)
        noise = np.where(np.isfinite(nr) & (nr > 0), nr, np.nan)
    sat = (
        np.full(K, -1, np.int64)
        if saturated is None
        else per_packet("saturated", saturated, K, dtype=bool).astype(np.int64)
    )
    fsv = np.nan if full_scale_v is None else _positive("full_scale_v", full_scale_v)
    return noise, sat, fsv


def _segments_compiled(preps, m, plan, geo, analysis_s):
    """`_segments` of windows prepared by `overlap_kernels.prepare_window` (list of its
    outputs): ys, masks (n, 4L), start (n,), L."""
    nominal = plan.pre + int(math.floor(_analysis_s(geo, analysis_s) * plan.fs))
    start = np.array([min(max(int(pr[3]) - plan.pre, 0), m - 1) for pr in preps], np.int64)
    L = max(int(np.max(np.minimum(m - start, nominal), initial=8)), 8)
    ys = np.empty((len(preps), 4 * L))
    masks = np.empty((len(preps), 4 * L))
    for i, pr in enumerate(preps):
        _kernels.segment(pr[0], int(start[i]), L, pr[1], ys[i], masks[i])
    return ys, masks, start, L


def _resolve_quick(x, on, plan, geo, pulse, noise_rms_v, saturated, full_scale_v, echo,
                   analysis_s, grid, decide_args) -> list:
    """`resolve_overlaps` with ``exhaustive=False`` by the compiled kernels: per window one
    call to prepare it (`overlap_kernels.prepare_window`, the equations of
    `common.prepare` and `common.adc_noise`), one to cut its segment and one for the whole
    quick search; then the same decisions (`_answers`)."""
    K, _, m = x.shape
    noise, sat, fsv = _noise_sat_fs(noise_rms_v, saturated, full_scale_v, K)
    out: list = [None] * K
    ok, preps = [], []
    for k in range(K):
        pr = _kernels.prepare_window(
            x[k], int(on[k]), float(noise[k]), int(sat[k]), fsv, plan.pre, plan.seg_len,
            plan.flat_run,
        )
        flags, scale, s2 = int(pr[2]), pr[4], pr[5]
        if not (math.isfinite(s2) and s2 > 0):
            flags |= 1 << Reason.WINDOW
        if flags:
            noise_v = math.sqrt(float(np.nan_to_num(s2))) * scale
            out[k] = OverlapPacket(False, _first_reason(flags), noise_rms_v=noise_v)
        else:
            ok.append(k)
            preps.append(pr)
    if not ok:
        return out
    fs = plan.fs
    ys, masks, start, L = _segments_compiled(preps, m, plan, geo, analysis_s)
    sigma2 = np.array([pr[5] for pr in preps])
    if noise_rms_v is None:
        n_noise = np.maximum(4 * (np.array([pr[3] for pr in preps]) - plan.pre), 4)
        n_noise = n_noise.astype(float)
    else:
        n_noise = np.full(len(ok), np.inf)
    N = masks.sum(axis=1)
    search_limit = _search_limit(n_noise, N)
    model = _Model(geo, fs, start, L, pulse, echo)
    max_sources, add_threshold = decide_args[0], decide_args[1]
    deferred = np.zeros(len(ok), bool)
    fits = _quick_search_compiled(
        model, ys, masks, max_sources, grid, sigma2, add_threshold, search_limit, deferred
    )
    res = _answers(
        fits, deferred, N, sigma2, n_noise, *decide_args,
        np.array([pr[4] for pr in preps]), geo, model.tab.h_samples, fs,
    )
    for k, r in zip(ok, res):
        out[k] = r
    return out


def _alternatives(sub, ys, j, cs, grid, rows, t1, a1, r1, j1) -> None:
    """Joint fits of j emissions from other starting points; where one ends with a smaller
    residual it replaces rows ``rows`` of (t1, a1, r1, j1) in place."""
    t1_, a1_, r1_, j1_ = t1[rows], a1[rows], r1[rows], j1[rows]

    def take(fit):
        t2, a2, r2, j2 = fit
        b = r2 < r1_
        t1_[b], a1_[b], r1_[b], j1_[b] = t2[b], a2[b], r2[b], j2[b]

    if j == 2:
        # pairs of the first search's peaks in time (two similar emissions a few us apart
        # make a spurious single-emission optimum between them)
        for q, p in ((0, 1), (0, 2), (1, 2)):
            take(_lm(sub, ys, cs[:, [q, p]].copy()))
    # RELAX: re-start each earlier emission from the data minus the others.
    for i in range(j - 1):
        keep = [q for q in range(j) if q != i]
        cols = np.concatenate([[2 * q, 2 * q + 1] for q in keep])
        res = _residual(sub, ys, np.ascontiguousarray(t1_[:, keep]), a1_[:, cols])
        thi, _ = _grid_search(sub, res.reshape(len(rows), 4, -1), grid)
        st = t1_.copy()
        st[:, i] = thi
        take(_lm(sub, ys, st))
    # Swapped points (same emission times): the local optimum of nearly simultaneous
    # emissions of similar strength.
    for q in range(j):
        for p in range(q + 1, j):
            st = t1_.copy()
            st[:, q, :2], st[:, p, :2] = t1_[:, p, :2], t1_[:, q, :2]
            take(_lm(sub, ys, st))
    t1[rows], a1[rows], r1[rows], j1[rows] = t1_, a1_, r1_, j1_


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


def resolve_overlaps(
    windows,
    sample_rate_hz,
    onset_index,
    *,
    geometry=None,
    pulse=None,
    noise_rms_v=None,
    saturated=None,
    full_scale_v=None,
    max_sources=3,
    band_hz=(100e3, 1e6),
    analysis_s=None,
    add_threshold=60.0,
    max_chi2_ratio=None,
    max_sigma_m=0.2e-3,
    min_snr_db=5.0,
    echo=True,
    grid_spacing_m=1.0e-3,
    min_separation_s=1.5e-6,
    engine="auto",
    exhaustive=True,
) -> list:
    """Localize every emission in each of K windows (two or three overlapping emissions).

    windows (K, 4, M) volts (a (4, M) window is accepted), sample_rate_hz, onset_index (K,)
    the first sample at/after the earliest arrival (detector or trigger). geometry:
    FingertipGeometry (default tip); pulse: `PulseModel` of the front end (default:
    `PulseModel.for_sample_rate`: 100 kHz 2nd-order high-pass, 1 MHz 4th-order low-pass,
    below 3.33 MS/s the 0.3 fs 8th-order anti-alias low-pass). noise_rms_v: known sigma (scalar or
    (K,)), default measured before the onset (the ADC's rounding by `common.adc_noise`).
    saturated, full_scale_v: as `localize`. max_sources: 1-3. add_threshold: residual-energy drop
    (in sigma^2) needed to add an emission. max_chi2_ratio: largest accepted residual /
    (sigma^2 dof) (default 1 + 5 sqrt(2/n_noise + 2/dof)). max_sigma_m: emissions with a
    larger in-plane 1-sigma are dropped. echo: model the first wall echo.
    min_separation_s: emissions fitted closer than this in time are not separated reliably
    (the joint likelihood has several nearly equal optima): such packets are rejected
    (UNRESOLVED). engine: "auto" fits with the compiled kernels (`overlap_kernels`) when
    numba is present and the medium lossless, "numpy" always with the numpy path.
    exhaustive=False: a window whose first joint fit still leaves more than noise is not
    searched further but answered DEFERRED (the quick answer of the driver's resolver,
    which then runs the exhaustive search on it).

    Returns a list of K `OverlapPacket` (``sources`` earliest first, or a rejection reason).
    Parameter and shape errors raise ValueError / TypeError; data problems are rejections.
    """
    geo = FingertipGeometry() if geometry is None else geometry
    if not isinstance(geo, FingertipGeometry):
        raise TypeError(f"geometry must be a FingertipGeometry, got {type(geo).__name__}")
    pulse = PulseModel.for_sample_rate(sample_rate_hz) if pulse is None else pulse
    if not isinstance(pulse, PulseModel):
        raise TypeError(f"pulse must be a PulseModel, got {type(pulse).__name__}")
    if (
        isinstance(max_sources, bool)
        or not isinstance(max_sources, (int, np.integer))
        or not 1 <= max_sources <= 3
    ):
        raise ValueError(f"max_sources must be 1, 2 or 3, got {max_sources!r}")
    add_threshold = _positive("add_threshold", add_threshold)
    max_sigma_m = _positive("max_sigma_m", max_sigma_m)
    if max_chi2_ratio is not None:
        max_chi2_ratio = _positive("max_chi2_ratio", max_chi2_ratio)
    min_snr_db = float(min_snr_db)
    if not math.isfinite(min_snr_db):
        raise ValueError(f"min_snr_db must be finite, got {min_snr_db!r}")
    if analysis_s is not None:
        analysis_s = _positive("analysis_s", analysis_s)
    grid_spacing_m = _positive("grid_spacing_m", grid_spacing_m)
    min_separation_s = float(min_separation_s)
    if not (math.isfinite(min_separation_s) and min_separation_s >= 0):
        raise ValueError(f"min_separation_s must be >= 0, got {min_separation_s!r}")
    if engine not in ("auto", "numpy"):
        raise ValueError(f"engine must be 'auto' or 'numpy', got {engine!r}")
    x, on = validate_windows(windows, onset_index)
    plan = make_plan(sample_rate_hz, geo, x.shape[2], band_hz)
    K = x.shape[0]
    if K == 0:
        return []
    grid = _surface_grid(geo, grid_spacing_m)
    if not exhaustive and engine == "auto" and _compiled_medium(pulse):
        decide_args = (
            max_sources, add_threshold, max_chi2_ratio, max_sigma_m, min_snr_db,
            min_separation_s,
        )
        with np.errstate(all="ignore"):
            return _resolve_quick(
                x, on, plan, geo, pulse, noise_rms_v, saturated, full_scale_v, echo,
                analysis_s, grid, decide_args,
            )
    with np.errstate(all="ignore"):
        prep = prepare(
            x,
            on,
            plan,
            noise_rms_v=noise_rms_v,
            saturated=saturated,
            full_scale_v=full_scale_v,
            spectra=False,
        )
        sigma2 = adc_noise(prep.sigma2, prep.quant2, _given(prep))
        n_noise = np.maximum(4 * (prep.onset - plan.pre), 4).astype(float)
        if noise_rms_v is not None:
            n_noise[:] = np.inf
        unknown = ~np.isfinite(sigma2) | (sigma2 <= 0)
        flags = prep.flags.copy()
        flags[unknown] |= 1 << Reason.WINDOW
        ok = flags == 0
        out: list = [None] * K
        ids = np.nonzero(ok)[0]
        if ids.size:
            seg, start, length, inside = _segments(
                subset(prep, ids), plan, geo, plan.fs, analysis_s
            )
            model = _Model(geo, plan.fs, start, length, pulse, echo, inside, engine)
            res = _decide(
                model,
                seg,
                sigma2[ids],
                n_noise[ids],
                max_sources,
                add_threshold,
                max_chi2_ratio,
                max_sigma_m,
                min_snr_db,
                prep.scale[ids],
                geo,
                grid,
                min_separation_s,
                exhaustive,
            )
            for i, r in zip(ids, res):
                out[i] = r
        for i in np.nonzero(~ok)[0]:
            code = _first_reason(int(flags[i]))
            out[i] = OverlapPacket(
                False, code, noise_rms_v=float(np.sqrt(np.nan_to_num(sigma2[i])) * prep.scale[i])
            )
    return out


def warm_up(geometry=None, sample_rate_hz=10e6, n_samples=400, pulse=None) -> OverlapPacket:
    """Resolve one synthetic two-emission window (4 us apart, opposite polarities, light
    noise) by the quick and by the exhaustive search: loads every table and compiled
    kernel the first real overlap would otherwise wait for (the driver's overlap worker
    does this before it says it is ready). Returns the exhaustive search's answer."""
    geo = FingertipGeometry() if geometry is None else geometry
    fs = float(sample_rate_hz)
    pulse = PulseModel.for_sample_rate(fs) if pulse is None else pulse
    n = max(int(n_samples), 64)
    on = n // 4
    pts = geo.surface_point_from_angles(np.array([0.35, 0.3]), np.array([0.4, 3.5]))
    tt = geo.arrival_times_s(pts)  # (2, 4)
    gain = geo.radius_m / (tt * geo.sound_speed_m_s)  # R / d
    t0 = on / fs - tt.min()
    t = np.arange(n) / fs
    x = np.random.default_rng(0).normal(0.0, 1e-4, (4, n))
    for j, (amp, delay) in enumerate(((1e-2, 0.0), (-0.7e-2, 4e-6))):
        x += amp * gain[j][:, None] * pulse.waveform(t[None, :] - t0 - delay - tt[j][:, None])
    with np.errstate(all="ignore"):
        resolve_overlaps(x[None], fs, [on], geometry=geo, pulse=pulse, exhaustive=False)
        return resolve_overlaps(x[None], fs, [on], geometry=geo, pulse=pulse)[0]


def _first_reason(flags: int) -> int:
    for r in Reason:
        if r != Reason.OK and flags & (1 << int(r)):
            return int(r)
    return int(OverlapReason.UNRESOLVED)


def _search_limit(n_noise, n_fit):
    """Residual per sample and sigma^2 above which another emission is searched: 1 + 2
    sqrt(2 / n_noise + 2 / n_fit) (two standard deviations of both variance estimates)."""
    return 1.0 + 2.0 * np.sqrt(2.0 / n_noise + 2.0 / n_fit)


def _chi2_limit(n_noise, dof, max_chi2_ratio):
    if max_chi2_ratio is not None:
        return np.full(np.shape(dof), max_chi2_ratio)
    return 1.0 + 5.0 * np.sqrt(2.0 / n_noise + 2.0 / dof)


def _decide(
    model,
    seg,
    sigma2,
    n_noise,
    max_sources,
    add_threshold,
    max_chi2_ratio,
    max_sigma_m,
    min_snr_db,
    scale,
    geo,
    grid,
    min_separation_s,
    exhaustive=True,
):
    K = seg.shape[0]
    deferred = None if exhaustive else np.zeros(K, bool)
    N = (
        model.mask.sum(axis=1)
        if model.mask is not None
        else np.full(K, seg.shape[1] * seg.shape[2])
    )
    search_limit = _search_limit(n_noise, N)
    fits = _search(
        model, seg, max_sources, grid, sigma2, add_threshold, search_limit, deferred
    )
    return _answers(
        fits, deferred, N, sigma2, n_noise, max_sources, add_threshold, max_chi2_ratio,
        max_sigma_m, min_snr_db, min_separation_s, scale, geo, model.tab.h_samples, model.fs,
    )


def _answers(
    fits,
    deferred,
    N,
    sigma2,
    n_noise,
    max_sources,
    add_threshold,
    max_chi2_ratio,
    max_sigma_m,
    min_snr_db,
    min_separation_s,
    scale,
    geo,
    h_samples,
    fs,
):
    """The `OverlapPacket` of each window from its fits (one per number of emissions):
    model order, residual test, separation, covariances, per-emission SNR and confidence.
    N (K,): samples in each window's fit."""
    K = len(sigma2)
    # Model order: add emission j+1 while the residual energy drops by > add_threshold sigma^2.
    J = np.ones(K, np.int64)
    going = np.ones(K, bool)
    for j in range(2, max_sources + 1):
        gain = (fits[j - 2].rss - fits[j - 1].rss) / sigma2
        step = going & (gain > add_threshold)
        J[step] = j
        going &= step
    out = []
    snr_len = int(round(30e-6 * fs))
    e_pulse = float((h_samples[:snr_len] ** 2).sum())  # the direct wave's energy in 30 us
    R = geo.radius_m
    for i in range(K):
        if deferred is not None and deferred[i]:
            out.append(
                OverlapPacket(
                    False,
                    int(OverlapReason.DEFERRED),
                    noise_rms_v=float(np.sqrt(sigma2[i]) * scale[i]),
                )
            )
            continue
        f = fits[J[i] - 1]
        j = int(J[i])
        theta, amp, rss, gram = f.theta[i, :j], f.amp[i, : 2 * j], f.rss[i], f.gram[i]
        dof = max(N[i] - 5 * j, 1)
        ratio = rss / (sigma2[i] * dof)
        noise_v = float(np.sqrt(sigma2[i]) * scale[i])
        limit = float(_chi2_limit(n_noise[i], dof, max_chi2_ratio))
        times = theta[:, 2].tolist()
        too_close = j > 1 and min(b - a for a, b in zip(times, times[1:])) < min_separation_s
        if not math.isfinite(ratio) or ratio > limit or too_close:
            out.append(
                OverlapPacket(
                    False,
                    int(OverlapReason.UNRESOLVED),
                    n_fitted=j,
                    chi2_ratio=float(ratio),
                    noise_rms_v=noise_v,
                )
            )
            continue
        s2 = sigma2[i] * max(ratio, 1.0)
        fis = gram / s2
        try:
            cov = np.linalg.pinv(fis, rcond=1e-13, hermitian=True)
        except np.linalg.LinAlgError:
            cov = np.full(fis.shape, np.nan)
        d_all = geo._xy_distances(theta[:, 0], theta[:, 1])  # (j, 4)
        gain2 = ((R / d_all) ** 2).sum(axis=1)
        sources = []
        dropped = 0
        for q in range(j):
            c_xy = cov[3 * q : 3 * q + 2, 3 * q : 3 * q + 2]
            sx, sy, T = (float(v) for v in theta[q])
            vxx, vxy, vyx, vyy = c_xy.ravel().tolist()
            finite = all(math.isfinite(v) for v in (vxx, vxy, vyx, vyy))
            sig = math.sqrt(max(vxx + vyy, 0.0)) if finite else math.inf
            a_dir = float(amp[2 * q])
            # SNR of this emission alone: power of its direct wave over the 30 us window
            p_sig = a_dir**2 * float(gain2[q]) * e_pulse / (4.0 * snr_len)
            snr = 10.0 * math.log10(max(p_sig, 1e-300) / sigma2[i])
            if not (sig <= max_sigma_m) or snr < min_snr_db:
                dropped += 1
                continue
            sz = math.sqrt(max(R**2 - sx * sx - sy * sy, 0.0))
            g = np.array(
                [
                    [1.0, 0.0],
                    [0.0, 1.0],
                    [-sx / max(sz, 1e-6 * R), -sy / max(sz, 1e-6 * R)],
                ]
            )
            c3 = g @ c_xy @ g.T
            c_snr = math.sqrt(min(max((snr - min_snr_db) / 20.0, 0.0), 1.0))
            c_pos = 1.0 / (1.0 + (sig / 0.5e-3) ** 2)
            c_fit = min(max(1.0 - max(ratio - 1.0, 0.0) / max(limit - 1.0, 1e-9), 0.0), 1.0)
            conf = min(max(c_snr * c_pos * c_fit, 0.0), 1.0)
            sources.append(
                OverlapSource(
                    point_m=np.array([sx, sy, sz]),
                    covariance_m2=c3,
                    sigma_m=sig,
                    confidence=conf,
                    polarity=(a_dir > 0) - (a_dir < 0),
                    amplitude_v=a_dir * float(scale[i]),
                    emission_time_s=T,
                    arrival_times_s=T + d_all[q] / geo.sound_speed_m_s,
                    snr_db=float(snr),
                )
            )
        if not sources:
            out.append(
                OverlapPacket(
                    False,
                    int(OverlapReason.UNCERTAIN),
                    n_fitted=j,
                    n_dropped=dropped,
                    chi2_ratio=float(ratio),
                    noise_rms_v=noise_v,
                )
            )
        else:
            out.append(
                OverlapPacket(
                    True,
                    0,
                    sources,
                    n_fitted=j,
                    n_dropped=dropped,
                    chi2_ratio=float(ratio),
                    noise_rms_v=noise_v,
                )
            )
    return out


def suspect_overlap(
    windows,
    sample_rate_hz,
    onset_index,
    single_source_result,
    *,
    geometry=None,
    pulse=None,
    noise_rms_v=None,
    band_hz=(100e3, 1e6),
    analysis_s=None,
    echo=True,
    max_chi2_ratio=None,
    engine="auto",
):
    """(K,) bool: packets that `localize` ACCEPTED as single-source but whose one-emission fit
    (known pulse, first echo, started at the accepted point) leaves a residual inconsistent
    with noise (chi^2 per degree of freedom above the limit of `resolve_overlaps`): hand
    those to `resolve_overlaps`. Rejected packets give False (they are not single-source
    answers to withdraw). Cost: a 1-D matched-filter search of the emission time and
    ``iterations`` LM steps per accepted packet. engine: "auto" one compiled call per
    packet (`overlap_kernels.suspect_rss`) where numba is present and the medium lossless,
    "numpy" always numpy."""
    geo = FingertipGeometry() if geometry is None else geometry
    pulse = PulseModel.for_sample_rate(sample_rate_hz) if pulse is None else pulse
    x, on = validate_windows(windows, onset_index)
    K = x.shape[0]
    acc = np.asarray(single_source_result.accepted, bool)
    pts = np.asarray(single_source_result.point_m, float)
    if acc.shape != (K,) or pts.shape != (K, 3):
        raise ValueError(f"single_source_result must hold {K} packets, got {acc.shape[0]}")
    if engine not in ("auto", "numpy"):
        raise ValueError(f"engine must be 'auto' or 'numpy', got {engine!r}")
    plan = make_plan(sample_rate_hz, geo, x.shape[2], band_hz)
    out = np.zeros(K, bool)
    ids = np.nonzero(acc)[0]
    if ids.size == 0:
        return out
    if engine == "auto" and _compiled_medium(pulse):
        with np.errstate(all="ignore"):
            out[ids] = _suspects_compiled(
                x[ids], on[ids], pts[ids, :2], plan, geo, pulse, noise_rms_v, K, ids,
                analysis_s, echo, max_chi2_ratio,
            )
        return out
    with np.errstate(all="ignore"):
        prep = prepare(
            x[ids],
            on[ids],
            plan,
            noise_rms_v=None
            if noise_rms_v is None
            else np.broadcast_to(np.asarray(noise_rms_v, float), (K,))[ids],
            spectra=False,
        )
        seg, start, length, inside = _segments(prep, plan, geo, plan.fs, analysis_s)
        sigma2 = adc_noise(prep.sigma2, prep.quant2, _given(prep))
        model = _Model(geo, plan.fs, start, length, pulse, echo, inside)
        # emission time: matched filter along the accepted point's travel times
        th0 = _time_search(model, seg, pts[ids, :2])
        y = seg.reshape(len(ids), -1)
        # Linearised in the emission time: LS on [h, h'] of the direct wave and the echo at
        # (ml point, matched-filter time +- half a sample); the ml point is good to ~20 um,
        # whose residual is negligible against the noise.
        phi, parts = model.evaluate(th0[:, None, :])
        dh, gain = parts[1], parts[2]
        dcol = (gain[..., None] * dh).reshape(phi.shape)
        if model.mask is not None:
            dcol = dcol * model.mask[:, None, :]
        cols = np.concatenate([phi, dcol], axis=1)
        a2 = _lstsq_amplitudes(cols, y)
        res = y - _model_values(cols, a2)
        rss = np.einsum("kn,kn->k", res, res)
        dof = np.maximum(model.mask.sum(axis=1) - 5, 1)
        n_noise = np.maximum(4 * start, 4).astype(float)
        if noise_rms_v is not None:
            n_noise[:] = np.inf
        limit = _chi2_limit(n_noise, dof, max_chi2_ratio)
        ratio = rss / (sigma2 * dof)
        out[ids] = ~(ratio <= limit)
    return out


def _suspects_compiled(x, on, s_xy, plan, geo, pulse, noise_rms_v, K, ids, analysis_s, echo,
                       max_chi2_ratio):
    """`suspect_overlap` of accepted windows x (n, 4, M) at their points s_xy (n, 2) by the
    compiled kernels (`overlap_kernels.prepare_window`, `segment`, `suspect_rss`)."""
    m = x.shape[2]
    noise = None if noise_rms_v is None else np.broadcast_to(
        np.asarray(noise_rms_v, float), (K,)
    )[ids]
    noise, _, _ = _noise_sat_fs(noise, None, None, len(x))
    preps = [
        _kernels.prepare_window(
            x[i], int(on[i]), float(noise[i]), -1, np.nan, plan.pre, plan.seg_len,
            plan.flat_run,
        )
        for i in range(len(x))
    ]
    ys, masks, start, L = _segments_compiled(preps, m, plan, geo, analysis_s)
    model = _Model(geo, plan.fs, start, L, pulse, echo)
    args = _kernel_args(model)
    rss = np.array(
        [
            _kernels.suspect_rss(
                ys[i], masks[i], float(start[i]), float(s_xy[i, 0]), float(s_xy[i, 1]),
                *args, model.tab.half_z, model.tab.half_res,
            )
            for i in range(len(x))
        ]
    )
    sigma2 = np.array([pr[5] for pr in preps])
    dof = np.maximum(masks.sum(axis=1) - 5, 1)
    n_noise = np.maximum(4 * start, 4).astype(float)
    if noise_rms_v is not None:
        n_noise[:] = np.inf
    limit = _chi2_limit(n_noise, dof, max_chi2_ratio)
    return ~(rss / (sigma2 * dof) <= limit)


def _time_search(model: _Model, seg, s_xy):
    """(s_x, s_y, T) (K, 3): the emission time maximising the channel-summed matched filter
    along the travel times of the given points (K, 2)."""
    K, _, L = seg.shape
    fs = model.fs
    h = model.tab.h_samples
    nfft = sfft.next_fast_len(2 * L, real=True)
    corr = sfft.irfft(
        sfft.rfft(seg, n=nfft, axis=2) * np.conj(sfft.rfft(h, n=nfft)), n=nfft, axis=2
    )[..., :L]
    d = model.geo._xy_distances(s_xy[:, 0], s_xy[:, 1])
    tt = d / model.c
    rel = np.rint((tt - tt.min(axis=1, keepdims=True)) * fs).astype(np.int64)
    idx = np.clip(rel[:, :, None] + np.arange(L), 0, L - 1)
    c = (np.take_along_axis(corr, idx, axis=2) * (model.R / d)[..., None]).sum(axis=1)
    m = np.argmax(c * c, axis=1)
    T = (model.start + m) / fs - tt.min(axis=1)
    return np.concatenate([s_xy, T[:, None]], axis=1)


def calibrate_pulse(
    windows,
    sample_rate_hz,
    onset_index,
    *,
    geometry=None,
    initial=None,
    noise_rms_v=None,
    max_packets=64,
    echo=True,
):
    """Fit the front end's corner frequencies (`PulseModel` high-pass and low-pass) to
    single-emission packets, e.g. a few dozen single touches recorded at start-up.

    The known-pulse model needs the pulse shape: a front end whose corners are off by 10 %
    makes every overlap fit fail the residual test (rejected, not wrong; docs/localization.md).
    Each packet is localized by `localize` (ml); the objective is the summed residual of
    the one-emission model (3 LM steps from that point) over the accepted packets,
    minimised over (log f_hp, log f_lp) by Nelder-Mead from ``initial``.
    Returns the fitted `PulseModel` (orders, alpha and medium loss as in ``initial``)."""
    from scipy.optimize import minimize

    from ae_tactile.localization import localize

    geo = FingertipGeometry() if geometry is None else geometry
    init = PulseModel.for_sample_rate(sample_rate_hz) if initial is None else initial
    x, on = validate_windows(windows, onset_index)
    ml = localize(x, sample_rate_hz, on, geometry=geo, noise_rms_v=noise_rms_v)
    ids = np.nonzero(ml.accepted)[0][: int(max_packets)]
    if ids.size == 0:
        raise ValueError("calibrate_pulse needs single-emission packets that localize accepts")
    plan = make_plan(sample_rate_hz, geo, x.shape[2], (100e3, 1e6))
    with np.errstate(all="ignore"):
        prep = prepare(x[ids], on[ids], plan)
        seg, start, length, inside = _segments(prep, plan, geo, plan.fs, None)
    y = seg.reshape(len(ids), -1)
    pts = ml.point_m[ids, :2]
    lp0 = init.lowpass_hz

    def model_of(v):
        return PulseModel(
            float(np.exp(v[0])),
            init.highpass_order,
            None if lp0 is None else float(np.exp(v[1])),
            init.lowpass_order,
            init.alpha_1_s,
            init.attenuation_db_per_m_at_1mhz,
        )

    def objective(v):
        pm = model_of(v)
        with np.errstate(all="ignore"):
            model = _Model(geo, plan.fs, start, length, pm, echo, inside)
            th0 = _time_search(model, seg, pts)
            _, _, rss, _ = _lm(model, y, th0[:, None, :], iterations=3)
        _TAB_CACHE.pop((pm, plan.fs, length), None)
        _PR_CACHE.pop(pm, None)
        return float(np.sum(rss))

    v0 = np.log([init.highpass_hz, lp0 if lp0 is not None else 1.0])
    r = minimize(
        objective,
        v0,
        method="Nelder-Mead",
        options=dict(
            xatol=2e-3, fatol=1e-9, initial_simplex=[v0, v0 + [0.15, 0], v0 + [0, 0.15]], maxfev=80
        ),
    )
    return model_of(r.x)


def localize_with_overlaps(
    windows,
    sample_rate_hz,
    onset_index,
    *,
    geometry=None,
    pulse=None,
    noise_rms_v=None,
    saturated=None,
    max_sources=3,
    overlap_kwargs=None,
    **localize_kwargs,
):
    """The fast single-source path plus the overlap path only where needed.

    1. ``localize`` (``method``, default ml) on every window;
    2. `suspect_overlap` on what it accepted;
    3. `resolve_overlaps` on the windows it rejected as OVERLAP and on the suspects.

    Returns (single, overlap): ``single`` the `LocalizationResult`, with ``accepted`` set to
    False for the suspects (their single-source point is withdrawn: publish the overlap
    result instead); ``overlap`` a dict {window index: `OverlapPacket`}.
    """
    from ae_tactile.localization import localize

    geo = FingertipGeometry() if geometry is None else geometry
    x, on = validate_windows(windows, onset_index)
    single = localize(
        x,
        sample_rate_hz,
        on,
        geometry=geo,
        noise_rms_v=noise_rms_v,
        saturated=saturated,
        **localize_kwargs,
    )
    sus = suspect_overlap(
        x, sample_rate_hz, on, single, geometry=geo, pulse=pulse, noise_rms_v=noise_rms_v
    )
    need = sus | (single.reason == int(Reason.OVERLAP))
    ids = np.nonzero(need)[0]
    overlap = {}
    if ids.size:
        nr = (
            None
            if noise_rms_v is None
            else np.broadcast_to(np.asarray(noise_rms_v, float), (len(on),))[ids]
        )
        sat = (
            None
            if saturated is None
            else np.broadcast_to(np.asarray(saturated, bool), (len(on),))[ids]
        )
        res = resolve_overlaps(
            x[ids],
            sample_rate_hz,
            on[ids],
            geometry=geo,
            pulse=pulse,
            noise_rms_v=nr,
            saturated=sat,
            max_sources=max_sources,
            **(overlap_kwargs or {}),
        )
        overlap = {int(i): r for i, r in zip(ids, res)}
    single.accepted = single.accepted & ~sus
    single.confidence = np.where(sus, 0.0, single.confidence)
    single.reason = np.where(sus, np.uint8(Reason.OVERLAP), single.reason).astype(np.uint8)
    single.reason_flags = (
        single.reason_flags | np.where(sus, 1 << int(Reason.OVERLAP), 0)
    ).astype(np.uint16)
    return single, overlap
