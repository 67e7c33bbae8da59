# SPDX-License-Identifier: Apache-2.0
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
the arrival and on n - n0, from tables shared by the config (e^{pole dt k}): that is
what makes windowed / chunked rendering equal to a full render, bit for bit (`accumulate`
and kernels.py: an elementwise formula, no matrix products).

Truncation (streaming only; `evaluate`, used for triggered windows, is not truncated):
the response of arrival a is zero from k = L_a on. L_a = max(L_fast, L_att, L_slow,a):
L_fast and L_att are per-config constants, the samples after which a bound on the fast
part (resp. the attenuation-pole term) stays below ``support_rel_tol`` |A| G for any
alpha (G the in-band gain); L_slow,a is the same bound for the arrival's own event poles
(-2 alpha, -alpha). All are capped at ``max_support_s``. With the defaults (order-2
high-pass) the slow part starts at ~2e-4 of the peak ((alpha/omega_0)^2 times small
factors) and decays at 2 alpha, so it runs to the 200 us cap, where < 5e-5 of the peak
is dropped (~0.01 LSB for the nominal 9 Pa touch).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ae_tactile.sim.emission import event_partial_fractions, event_transfer
from ae_tactile.sim.kernels import HAVE_NUMBA, accumulate_windows, compute_arrival_inputs
from ae_tactile.sim.propagation import attenuation_pole_rad_s


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
    slow_poles: np.ndarray    # (n, m) real, negative: -2 alpha, -alpha[, -omega_a]
    slow_c: np.ndarray        # (n, m) real
    fast_re: np.ndarray       # (n, n_fast) Re C_aj
    fast_im: np.ndarray       # (n, n_fast) Im C_aj
    length: np.ndarray        # (n,) int64 truncated support L_a (streaming)

    def __len__(self):
        return int(self.n0.shape[0])

    def take(self, idx) -> "ResponseCoefs":
        return ResponseCoefs(*(getattr(self, f)[idx] for f in self.__dataclass_fields__))


def _bound_length(coef_abs, rate, ref, tol, lmax, dt):
    """First k with sum_terms |c| e^{-rate k dt} <= tol ref (conservative: m max terms)."""
    m = coef_abs.shape[-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.log(m * coef_abs / (tol * ref)) / (rate * dt)
    k = np.nan_to_num(k, nan=0.0, posinf=float(lmax), neginf=0.0)
    return np.clip(np.ceil(k.max(axis=-1)) + 1, 0, lmax).astype(np.int64)


def fast_support_samples(config, fe) -> int:
    """Config constant L_fast: bound on the filter-pole part for any alpha >= 0 and any
    attenuation pole, relative to the jump |A| G (sup of |P1(q) W(q)| over a grid, x2).
    ``fe`` is the config's FrontEnd."""
    q = fe.fast_poles
    al = np.concatenate([[0.0], np.geomspace(1.0, 1e8, 161)])[:, None]
    p1 = np.abs(2.0 / (q + 2 * al) - 1.0 / (q + al)).max(axis=0)
    w = np.concatenate([[np.inf], np.geomspace(1e4, 1e10, 121)])[:, None]
    inf = np.isinf(w)
    wq = np.where(inf, 1.0, np.abs(np.where(inf, 1.0, w) / (q + np.where(inf, 0.0, w))))
    bound = 2.0 * fe.fast_weights * np.abs(fe.fast_residues) * p1 * wq.max(axis=0)
    return int(_bound_length(bound[None, :], -q.real, config.sensitivity_v_per_pa,
                             config.support_rel_tol, config.max_support_samples, config.dt_s)[0])


def att_support_samples(config, max_path_m) -> int:
    """Config constant L_att for the attenuation-pole term: |c_att| <= 4 |A| G (conservative)
    and the slowest pole belongs to the longest path."""
    if config.attenuation_db_per_m <= 0 or config.attenuation_law != "pole":
        return 0
    w = float(attenuation_pole_rad_s(max_path_m, config.attenuation_db_per_m))
    if not np.isfinite(w):
        return 0
    return int(_bound_length(np.array([[4.0]]), np.array([w]), 1.0, config.support_rel_tol,
                             config.max_support_samples, config.dt_s)[0])


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

    ref = np.abs(A) * config.sensitivity_v_per_pa
    len_slow = _bound_length(np.abs(slow_c[:, :2]), -rho[:, :2], ref[:, None],
                             config.support_rel_tol,
                             config.max_support_samples, dt)
    length = np.maximum(len_slow, fe.support_fast)
    length = np.maximum(length, fe.support_att)
    length[ref == 0] = 0
    return ResponseCoefs(n0=n0, eps_s=eps, slow_poles=rho, slow_c=slow_c,
                         fast_re=np.ascontiguousarray(C.real),
                         fast_im=np.ascontiguousarray(C.imag),
                         length=length)


def evaluate(coefs: ResponseCoefs, config, n_samples: int) -> np.ndarray:
    """Untruncated response values y_a[k], k = 0..n_samples-1, shape (n, n_samples).

    For short windows (triggered packets): the fast part is one BLAS product, the slow
    part direct exponentials; nothing is truncated inside the window.
    """
    n = len(coefs)
    K = int(n_samples)
    if n == 0 or K == 0:
        return np.zeros((n, K))
    ere, eim = config.frontend.exp_table(K)
    out = np.hstack([coefs.fast_re, -coefs.fast_im]) @ np.vstack([ere, eim])
    tau = config.dt_s * np.arange(K)[None, :] + coefs.eps_s[:, None]
    tmp = np.empty_like(out)
    for i in range(coefs.slow_poles.shape[1]):
        np.multiply(coefs.slow_poles[:, i:i + 1], tau, out=tmp)
        np.exp(tmp, out=tmp)
        tmp *= coefs.slow_c[:, i:i + 1]
        out += tmp
    return out


class SlowTables:
    """Cache of e^{rho dt k}, k = 0..length-1, for the event-pole pair (-2 alpha, -alpha) of
    each distinct alpha (scenes usually use one or a few alphas)."""

    def __init__(self, config, length: int, max_entries: int = 256):
        self.dt = config.dt_s
        self.length = int(length)
        self.max_entries = max_entries
        self._cache: dict[tuple, np.ndarray] = {}
        self._work: list[np.ndarray] = []

    def work(self, i: int, n: int, k: int) -> np.ndarray:
        """Reusable scratch array i of shape (n, k) (avoids page-faulting fresh memory)."""
        while len(self._work) <= i:
            self._work.append(np.empty(0))
        buf = self._work[i]
        if buf.size < n * k:
            buf = np.empty(n * k)
            self._work[i] = buf
        return buf[:n * k].reshape(n, k)

    def stacked(self, alphas) -> np.ndarray:
        """(len(alphas), 2, length) tables of the pole pairs (-2 alpha, -alpha) (the last
        stack is kept: scenes mostly use one alpha)."""
        key = tuple(alphas)
        last = getattr(self, "_stacked", None)
        if last is not None and last[0] == key:
            return last[1]
        t = (np.stack([self.get((-2.0 * a, -a)) for a in key]) if key
             else np.zeros((0, 2, self.length)))
        self._stacked = (key, t)
        return t

    def get(self, rho_pair) -> np.ndarray:
        """(2, length) table for the pole pair (rho_0, rho_1)."""
        key = (float(rho_pair[0]), float(rho_pair[1]))
        t = self._cache.get(key)
        if t is None:
            k = np.arange(self.length, dtype=float) * self.dt
            t = np.exp(np.asarray(key)[:, None] * k[None, :])
            if len(self._cache) >= self.max_entries:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = t
        return t


class KernelInputs:
    """Per-arrival inputs of the elementwise sample formula (kernels.py), shared by the
    numpy and numba paths so that both see the same bits."""

    __slots__ = ("n0", "length", "channel", "key", "cs", "tabs", "fcoef", "basis",
                 "k_fast", "att", "k_att")

    def __init__(self, coefs: ResponseCoefs, channel, config, tables: SlowTables):
        fe = config.frontend
        n = len(coefs)
        self.n0 = np.ascontiguousarray(coefs.n0, dtype=np.int64)
        self.length = np.ascontiguousarray(coefs.length, dtype=np.int64)
        self.channel = np.ascontiguousarray(channel, dtype=np.int64)
        # event poles (-2 alpha, -alpha): (c e^{rho eps}) x table e^{rho dt k}, per alpha
        rho = coefs.slow_poles[:, :2]
        self.cs = coefs.slow_c[:, :2] * np.exp(rho * coefs.eps_s[:, None])
        if n:
            keys, inverse = np.unique(rho, axis=0, return_inverse=True)
        else:
            keys, inverse = np.zeros((0, 2)), np.zeros(0, np.int64)
        self.key = np.ascontiguousarray(inverse.reshape(-1), dtype=np.int64)
        self.tabs = (np.stack([tables.get(k) for k in keys]) if len(keys)
                     else np.zeros((0, 2, tables.length)))
        # filter poles: Re sum_j C_j E_j[k] = sum_j [Re C, -Im C]_j [Re E; Im E]_j[k]
        self.fcoef = np.ascontiguousarray(np.hstack([coefs.fast_re, -coefs.fast_im]))
        self.basis = fe.fast_basis
        self.k_fast = int(fe.support_fast)
        # attenuation pole (per arrival): c e^{w (eps + dt k)}, k < L_att, numpy exp
        ka = int(fe.support_att) if coefs.slow_poles.shape[1] > 2 else 0
        att = np.empty((n, ka))
        if ka:
            np.multiply(config.dt_s, np.arange(ka)[None, :], out=att)
            att += coefs.eps_s[:, None]
            att *= coefs.slow_poles[:, 2:3]
            np.exp(att, out=att)
            att *= coefs.slow_c[:, 2:3]
        self.att = att
        self.k_att = ka

    @classmethod
    def compiled(cls, points_m, strength_pa_m, alpha_1_s, n_e, frac_s, config,
                 tables: SlowTables) -> "KernelInputs":
        """The numba engine: inputs of emissions at absolute sample n_e + frac_s fs computed
        by `kernels.arrival_inputs` in one compiled call (arrivals ordered emission, path,
        channel, as `propagation.compute_arrivals`)."""
        fe = config.frontend
        geo = config.geometry
        real = fe.fast_poles.real[np.abs(fe.fast_poles.imag) == 0]
        n_paths = 1 + (config.n_reflections if config.reflections else 0)
        n0, length, channel, al, cs, fcoef, att = compute_arrival_inputs(
            points_m, strength_pa_m, alpha_1_s, n_e, frac_s, geo.element_positions_m,
            geo.radius_m, geo.sound_speed_m_s, n_paths, config.reflection_coefficient,
            config.attenuation_db_per_m, np.concatenate([-real, -real / 2.0]), -real, fe.zeros,
            fe.poles, fe.gain, fe.fast_poles, fe.fast_weights * fe.fast_residues,
            fe.support_fast, fe.support_att, config.max_support_samples,
            config.support_rel_tol, config.sensitivity_v_per_pa, config.sample_rate_hz,
            config.dt_s)
        self = cls.__new__(cls)
        self.n0, self.length, self.channel, self.cs, self.fcoef = n0, length, channel, cs, fcoef
        per = 4 * n_paths
        if al.shape[0] and np.all(al == al[0]):
            keys = al[:1]
            self.key = np.zeros(n0.shape[0], np.int64)
        else:
            keys, inv = np.unique(al, return_inverse=True)
            self.key = np.repeat(inv.reshape(-1).astype(np.int64), per)
        self.tabs = tables.stacked(keys.tolist())
        self.basis = fe.fast_basis
        self.k_fast = int(fe.support_fast)
        self.att = att
        self.k_att = att.shape[1]
        return self

    def call_kernel(self, out, w0, a_lo, a_hi):
        """The compiled kernel over windows ``out`` (n_win, 4, width) at ``w0``."""
        accumulate_windows(out, np.asarray(w0, np.int64), np.asarray(a_lo, np.int64),
                           np.asarray(a_hi, np.int64), self.n0, self.length, self.channel,
                           self.key, self.cs, self.tabs, self.fcoef, self.basis, self.k_fast,
                           self.att, self.k_att)


def default_engine(engine=None) -> str:
    """'numba' when the compiled kernel is available (kernels.HAVE_NUMBA), else 'numpy';
    an explicit 'numba' / 'numpy' is checked and returned."""
    if engine in (None, "auto"):
        return "numba" if HAVE_NUMBA else "numpy"
    if engine not in ("numba", "numpy"):
        raise ValueError(f"engine must be 'numba', 'numpy' or None, got {engine!r}")
    if engine == "numba" and not HAVE_NUMBA:
        raise ValueError("engine='numba' needs numba (not importable, or AE_TACTILE_NO_NUMBA set)")
    return engine


def accumulate(coefs: ResponseCoefs, channel, config, tables: SlowTables, out: np.ndarray,
               w0: int, engine=None) -> None:
    """Add the truncated responses of arrivals (in the given order) into ``out`` (4, W),
    whose column 0 is absolute sample ``w0``.

    Sample values follow the elementwise formula of kernels.py (event-pole tables from
    ``tables``, filter poles from ``config.frontend.fast_basis``, the attenuation pole by
    numpy exponentials); arrival a contributes on [n0_a, n0_a + L_a), added in arrival
    order, so every output sample sums the same terms in the same order whatever the
    window, and the numba kernel (``engine='numba'``, the default when available) and
    this numpy code (``engine='numpy'``, the reference) give the same bits.
    """
    n = len(coefs)
    if n == 0:
        return
    width = out.shape[1]
    length = coefs.length
    start = coefs.n0 - w0
    keep = (start < width) & (start + length > 0) & (length > 0)
    if not np.any(keep):
        return
    if not np.all(keep):
        coefs = coefs.take(keep)
        channel = np.asarray(channel)[keep]
        start, length = start[keep], length[keep]
        n = len(coefs)
    ki = KernelInputs(coefs, channel, config, tables)
    if default_engine(engine) == "numba":
        if not (out.flags.c_contiguous and out.dtype == np.float64):
            raise ValueError("out must be a C-contiguous float64 array")
        ki.call_kernel(out[None], [w0], [0], [n])
        return
    K = int(length.max())
    vals = tables.work(0, n, K)
    tmp = tables.work(1, n, K)
    for g in range(ki.tabs.shape[0]):
        tab = ki.tabs[g]
        rows = np.nonzero(ki.key == g)[0]
        if rows.shape[0] == n:
            np.multiply(ki.cs[:, 0:1], tab[0:1, :K], out=vals)
            np.multiply(ki.cs[:, 1:2], tab[1:2, :K], out=tmp)
            vals += tmp
        else:
            vals[rows] = ki.cs[rows, 0:1] * tab[0:1, :K] + ki.cs[rows, 1:2] * tab[1:2, :K]
    kf = min(K, ki.k_fast)
    for j in range(ki.fcoef.shape[1]):
        np.multiply(ki.fcoef[:, j:j + 1], ki.basis[j:j + 1, :kf], out=tmp[:, :kf])
        vals[:, :kf] += tmp[:, :kf]
    ka = min(K, ki.k_att)
    if ka > 0:
        vals[:, :ka] += ki.att[:, :ka]
    flat = out.reshape(-1)
    lo = np.maximum(0, -start)
    hi = np.minimum(length, width - start)
    base = ki.channel * width + start
    # sequential in arrival order (fixed summation order per output sample)
    for row, l0, h0, b in zip(vals, lo.tolist(), hi.tolist(), (base + lo).tolist()):
        flat[b:b + h0 - l0] += row[l0:h0]
