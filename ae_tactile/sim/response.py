"""Exact sampled response of the front end to each wave arrival (the simulator's core).

Each arrival a (emission e, element k, path m) is a pressure R_a(s) = A_a P1(s) W_a(s)
(emission.py: unit-jump Eq. 9 pulse times the optional attenuation pole) starting at
time t_a. The front end F(s) (frontend.py) is rational with simple poles q_j, so the
output voltage is, exactly, for tau = t - t_a >= 0,

    y_a(tau) = sum_i r_i F(rho_i) e^{rho_i tau}  +  sum_j f_j R_a(q_j) e^{q_j tau}

(partial fractions of R_a(s) F(s): residues r_i of R_a at its poles rho_i = -2 alpha,
-alpha, -omega_a, and f_j of F at q_j). The first sum is the "slow" part (event poles),
the second the "fast" part (filter poles; conjugate pairs give 2 Re(.)).

Sampling: with n0 the first sample index at or after t_a and eps = n0 dt - t_a in
[0, dt), sample n0 + k has tau = eps + k dt, so

    fast: Re sum_j C_aj E_j[k],  C_aj = w_j f_j R_a(q_j) e^{q_j eps},  E_j[k] = e^{q_j dt k}
    slow: sum_i c_ai exp(rho_i (eps + k dt)).

This is exact for any sub-sample arrival time (no rounding, no FFT wrap-around, no
Gibbs ringing from a sampled step), and the value at absolute sample n depends only on
the arrival and on n - n0, computed by the same elementwise operations whatever window
is rendered: that is what makes windowed / chunked rendering bit-identical to a full
render.

Truncation: the response of arrival a is set to zero from k = L_a on, where L_a is the
first k at which a bound on the remaining tail, sum |coef| e^{Re(pole) k dt}, falls
below ``support_rel_tol`` |A_a| G (G the in-band gain), capped at ``max_support_s``.
The fast and slow parts get their own lengths (the slow part is ~(alpha/omega_0)^n
smaller but decays ~100x more slowly).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ae_tactile.sim.emission import event_partial_fractions, event_transfer


def _separate(x, forbidden, rel=1e-7):
    """Nudge values of x (n,) lying within rel of any forbidden value, by 10 rel."""
    x = np.array(x, dtype=float, copy=True)
    for f in forbidden:
        close = np.abs(x - f) <= rel * np.abs(f)
        x[close] *= 1.0 + 10.0 * rel
    return x


@dataclass
class ResponseCoefs:
    """Per-arrival coefficients of the sampled response (see module docstring)."""

    n0: np.ndarray            # (n,) int64 first sample at/after the arrival
    eps_s: np.ndarray         # (n,) in [0, dt)
    slow_poles: np.ndarray    # (n, m) real, negative
    slow_c: np.ndarray        # (n, m) real
    fast_re: np.ndarray       # (n, n_fast) Re C_aj
    fast_im: np.ndarray       # (n, n_fast) Im C_aj
    len_fast: np.ndarray      # (n,) int64
    len_slow: np.ndarray      # (n,) int64

    def __len__(self):
        return int(self.n0.shape[0])

    @property
    def length(self) -> np.ndarray:
        return np.maximum(self.len_fast, self.len_slow)

    def take(self, idx) -> "ResponseCoefs":
        return ResponseCoefs(*(getattr(self, f)[idx] for f in self.__dataclass_fields__))


def arrival_coefficients(amplitude_pa, alpha_1_s, att_pole_rad_s, n_ref, offset_s, config
                         ) -> ResponseCoefs:
    """Coefficients for arrivals at time n_ref dt + offset_s (n_ref int64, offset_s >= 0).

    ``att_pole_rad_s`` is None (lossless) or (n,) omega_a.
    """
    fe = config.frontend
    fs = float(config.sample_rate_hz)
    dt = config.dt_s
    A = np.asarray(amplitude_pa, dtype=float).reshape(-1)
    n = A.shape[0]
    off = np.asarray(offset_s, dtype=float).reshape(-1)
    j0 = np.ceil(off * fs)
    eps = np.maximum(j0 * dt - off, 0.0)
    n0 = np.asarray(n_ref, dtype=np.int64).reshape(-1) + j0.astype(np.int64)

    real_filter_poles = fe.fast_poles.real[np.abs(fe.fast_poles.imag) == 0]
    al = np.broadcast_to(np.asarray(alpha_1_s, dtype=float), (n,))
    al = _separate(al, np.concatenate([-real_filter_poles, -real_filter_poles / 2.0]))
    w = None
    if att_pole_rad_s is not None:
        w = np.broadcast_to(np.asarray(att_pole_rad_s, dtype=float), (n,))
        w = _separate(w, -real_filter_poles)
        for k in (1.0, 2.0):   # keep omega_a off alpha and 2 alpha
            close = np.abs(w - k * al) <= 1e-7 * w
            w = np.where(close, w * (1.0 + 1e-6), w)

    # slow part: residues of R at its poles times F(pole)
    rho, r = event_partial_fractions(A, al, w)
    slow_c = (r * fe.transfer(rho).real)
    # fast part: residues of F at q_j times R(q_j), times e^{q eps}
    q = fe.fast_poles[None, :]
    Rq = event_transfer(q, A[:, None], al[:, None], None if w is None else w[:, None])
    C = (fe.fast_weights * fe.fast_residues)[None, :] * Rq * np.exp(q * eps[:, None])

    # support lengths from tail bounds
    ref = np.abs(A) * config.sensitivity_v_per_pa
    tol = config.support_rel_tol
    lmax = config.max_support_samples
    with np.errstate(divide="ignore", invalid="ignore"):
        nf = C.shape[1]
        kf = np.log(nf * np.abs(C) / (tol * ref[:, None])) / (-q.real * dt)
        ns = rho.shape[1]
        ks = np.log(ns * np.abs(slow_c) / (tol * ref[:, None])) / (-rho * dt)
    kf = np.nan_to_num(kf, nan=0.0, posinf=lmax, neginf=0.0)
    ks = np.nan_to_num(ks, nan=0.0, posinf=lmax, neginf=0.0)
    len_fast = np.clip(np.ceil(kf.max(axis=1)) + 1, 1, lmax).astype(np.int64)
    len_slow = np.clip(np.ceil(ks.max(axis=1)) + 1, 0, lmax).astype(np.int64)
    zero = ref == 0
    len_fast[zero] = 0
    len_slow[zero] = 0
    return ResponseCoefs(n0=n0, eps_s=eps, slow_poles=rho, slow_c=slow_c,
                         fast_re=np.ascontiguousarray(C.real), fast_im=np.ascontiguousarray(C.imag),
                         len_fast=len_fast, len_slow=len_slow)


def evaluate(coefs: ResponseCoefs, config, n_samples: int | None = None,
             deterministic: bool = True) -> np.ndarray:
    """Response values y_a[k], k = 0..K-1, shape (n, K) float64, zero beyond each L_a.

    K = ``n_samples`` or max L_a. With ``deterministic`` every element is computed by the
    same sequence of elementwise operations whatever the batch, so a sample's value does
    not depend on which window is rendered (bit-reproducible). ``deterministic=False``
    uses one BLAS matrix product for the fast part (faster; BLAS kernels may round a
    row differently depending on its position in the matrix, ~1e-16 relative).
    """
    n = len(coefs)
    K = int(coefs.length.max()) if n_samples is None else int(n_samples)
    out = np.zeros((n, K))
    if n == 0 or K == 0:
        return out
    dt = config.dt_s
    k = np.arange(K)
    kf = min(K, int(coefs.len_fast.max()))
    if kf > 0:
        ere, eim = config.frontend.exp_table(kf)
        acc = out[:, :kf]
        if deterministic:
            tmp = np.empty_like(acc)
            for j in range(ere.shape[0]):
                np.multiply(coefs.fast_re[:, j:j + 1], ere[j], out=tmp)
                acc += tmp
                np.multiply(coefs.fast_im[:, j:j + 1], eim[j], out=tmp)
                acc -= tmp
        else:
            acc[...] = np.hstack([coefs.fast_re, -coefs.fast_im]) @ np.vstack([ere, eim])
        short = coefs.len_fast < kf
        if np.any(short):
            acc[short] *= k[None, :kf] < coefs.len_fast[short, None]
    ks = min(K, int(coefs.len_slow.max()))
    if ks > 0:
        tau = dt * k[None, :ks] + coefs.eps_s[:, None]
        slow = np.zeros((n, ks))
        tmp = np.empty_like(slow)
        for i in range(coefs.slow_poles.shape[1]):
            np.multiply(coefs.slow_poles[:, i:i + 1], tau, out=tmp)
            np.exp(tmp, out=tmp)
            tmp *= coefs.slow_c[:, i:i + 1]
            slow += tmp
        short = coefs.len_slow < ks
        if np.any(short):
            slow[short] *= k[None, :ks] < coefs.len_slow[short, None]
        out[:, :ks] += slow
    return out
