# SPDX-License-Identifier: Apache-2.0
"""Compiled accumulation of arrival responses into sample windows (the renderers' hot path).

Every sample value is defined elementwise, in one fixed order of IEEE operations, so the
numba kernel and the numpy reference (`response.accumulate` with ``engine='numpy'``) give
the same bits (no BLAS, whose rounding may depend on the matrix shape; numba compiles
without fast-math, so no fused multiply-add is formed). For arrival a and k = n - n0_a
(response.py notation):

    v = c0 T0[k] + c1 T1[k]                    event poles, T_i[k] = e^{rho_i dt k} (tables)
    v = v + F_j B_j[k]       for j = 0..2 n_fast-1, while k < L_fast   (filter poles)
    v = v + att[k]                             while k < L_att (attenuation pole, numpy exp)
    out[channel_a, n] += v                     for arrivals in their global order

Everything transcendental (tables, e^{rho eps}, the attenuation term) is computed by numpy
outside the kernel and shared by both paths; the kernel does only products and sums.
numba is optional: without it, or with AE_TACTILE_NO_NUMBA=1, `HAVE_NUMBA` is False and
the callers use the numpy path (same bits, slower).
"""
from __future__ import annotations

import math

import numpy as np

from ae_tactile.jit import NUMBA_AVAILABLE as HAVE_NUMBA
from ae_tactile.jit import njit


@njit(cache=True, nogil=True)
def accumulate_windows(out, w0, a_lo, a_hi, n0, length, channel, key, cs, tabs, fcoef, basis,
                       k_fast, att, k_att):  # pragma: no cover - compiled
    """Add arrivals a_lo[w] <= a < a_hi[w] (global order) into window w of ``out``
    (n_win, 4, width), whose column 0 is absolute sample w0[w]; only the columns inside
    the window are evaluated. Inputs per arrival: n0, length (truncated support),
    channel, key (index into ``tabs`` (n_keys, 2, L)), cs (n, 2) = c e^{rho eps},
    fcoef (n, 2 n_fast) = [Re C, -Im C] against ``basis`` (2 n_fast, >= k_fast),
    att (n, k_att) the attenuation-pole term."""
    n_win = out.shape[0]
    width = out.shape[2]
    n_f = fcoef.shape[1]
    for w in range(n_win):
        for a in range(a_lo[w], a_hi[w]):
            s = n0[a] - w0[w]
            k0 = max(0, -s)
            k1 = min(length[a], width - s)
            if k1 <= k0:
                continue
            ch = channel[a]
            g = key[a]
            c0 = cs[a, 0]
            c1 = cs[a, 1]
            for k in range(k0, k1):
                v = c0 * tabs[g, 0, k] + c1 * tabs[g, 1, k]
                if k < k_fast:
                    for j in range(n_f):
                        v = v + fcoef[a, j] * basis[j, k]
                if k < k_att:
                    v = v + att[a, k]
                out[w, ch, s + k] += v


@njit(cache=True, nogil=True)
def arrival_inputs(points, strength, alpha, n_e, frac, elem, radius_m, sound_speed_m_s,
                   n_paths, refl_coef, att_db_per_m, sep_alpha, sep_w, fe_zeros, fe_poles,
                   fe_gain, q, q_wres, support_fast, support_att, max_support, tol, sens, fs,
                   dt):  # pragma: no cover - compiled
    """Per-arrival kernel inputs (the numba engine's equivalent of propagation.py's
    `compute_arrivals` + response.py's `arrival_coefficients` + `KernelInputs`), for
    emissions at absolute sample n_e + frac fs. Same equations, compiled: its transcendental
    functions (exp, log, complex division) come from LLVM/libm, not numpy's SIMD loops,
    so it agrees with the numpy engine to rounding (~1e-16 relative), not bit for bit.
    Arrival order: emission, path, channel. Returns (n0, length, channel, al_sep, cs,
    fcoef, att)."""
    n = points.shape[0]
    n_arr = n * n_paths * 4
    n_f = q.shape[0]
    ka = support_att if att_db_per_m > 0.0 else 0
    n0 = np.empty(n_arr, np.int64)
    length = np.empty(n_arr, np.int64)
    channel = np.empty(n_arr, np.int64)
    al_out = np.empty(n, np.float64)
    cs = np.empty((n_arr, 2), np.float64)
    fcoef = np.empty((n_arr, 2 * n_f), np.float64)
    att = np.zeros((n_arr, ka), np.float64)
    ln10_10 = math.log(10.0) / 10.0
    a_idx = 0
    for e in range(n):
        al = alpha[e]
        for f in sep_alpha:
            if abs(al - f) <= 1e-7 * abs(f):
                al *= 1.0 + 10.0 * 1e-7
        al_out[e] = al
        S = strength[e]
        for m in range(n_paths):
            sign = -1.0 if m % 2 else 1.0
            for k in range(4):
                dx = sign * points[e, 0] - elem[k, 0]
                dy = sign * points[e, 1] - elem[k, 1]
                dz = sign * points[e, 2] - elem[k, 2]
                d = math.sqrt(dx * dx + dy * dy + dz * dz)
                if m == 0:
                    L = d
                    A = S / L
                else:
                    L = 2.0 * m * radius_m + d
                    A = S * (refl_coef ** m) / radius_m
                off = frac[e] + L / sound_speed_m_s
                j0 = math.ceil(off * fs)
                eps = max(j0 * dt - off, 0.0)
                n0[a_idx] = n_e[e] + np.int64(j0)
                channel[a_idx] = k
                w = math.inf
                if att_db_per_m > 0.0:
                    x = math.expm1(L * att_db_per_m * ln10_10)
                    if x > 0:
                        w = 2.0 * math.pi * 1e6 / math.sqrt(x)
                        for f in sep_w:
                            if abs(w - f) <= 1e-7 * abs(f):
                                w *= 1.0 + 10.0 * 1e-7
                        for kk in (1.0, 2.0):
                            if abs(w - kk * al) <= 1e-7 * w:
                                w = w * (1.0 + 1e-6)
                has_w = math.isfinite(w)
                # slow part: residues of R at (-2 al, -al[, -w]) times F(pole)
                if has_w:
                    r0 = 2.0 * A * w / (w - 2.0 * al)
                    r1 = -A * w / (w - al)
                    r2 = A * w * (2.0 / (2.0 * al - w) - 1.0 / (al - w))
                else:
                    r0 = 2.0 * A
                    r1 = -A
                    r2 = 0.0
                c_s0 = r0 * _transfer(-2.0 * al, fe_zeros, fe_poles, fe_gain)
                c_s1 = r1 * _transfer(-al, fe_zeros, fe_poles, fe_gain)
                cs[a_idx, 0] = c_s0 * math.exp(-2.0 * al * eps)
                cs[a_idx, 1] = c_s1 * math.exp(-al * eps)
                # fast part: C_j = w_j f_j R(q_j) e^{q_j eps}
                for j in range(n_f):
                    qj = q[j]
                    R = A * (2.0 / (qj + 2.0 * al) - 1.0 / (qj + al))
                    if has_w:
                        R = R * (w / (qj + w))
                    C = q_wres[j] * R * np.exp(qj * eps)
                    fcoef[a_idx, j] = C.real
                    fcoef[a_idx, n_f + j] = -C.imag
                # truncated support (response.py `_bound_length` with 2 terms)
                ref = abs(A) * sens
                if ref == 0.0:
                    length[a_idx] = 0
                else:
                    kmax = -math.inf
                    for c_abs, rate in ((abs(c_s0), 2.0 * al), (abs(c_s1), al)):
                        if c_abs == 0.0:
                            kk2 = 0.0
                        else:
                            kk2 = math.log(2.0 * c_abs / (tol * ref)) / (rate * dt)
                            if math.isnan(kk2):
                                kk2 = 0.0
                            elif kk2 == math.inf:
                                kk2 = float(max_support)
                        kmax = max(kmax, kk2)
                    ls = min(max(math.ceil(kmax) + 1.0, 0.0), float(max_support))
                    length[a_idx] = max(np.int64(ls), support_fast, support_att)
                if has_w and ka > 0:
                    c_att = r2 * _transfer(-w, fe_zeros, fe_poles, fe_gain)
                    for kk3 in range(ka):
                        att[a_idx, kk3] = c_att * math.exp((dt * kk3 + eps) * -w)
                a_idx += 1
    return n0, length, channel, al_out, cs, fcoef, att


@njit(cache=True, nogil=True)
def _transfer(s, zeros, poles, gain):  # pragma: no cover - compiled
    """Re F(s) at real s: gain prod (s - z) / prod (s - p) (frontend.FrontEnd.transfer)."""
    num = 1.0 + 0.0j
    for z in zeros:
        num = num * (s - z)
    den = 1.0 + 0.0j
    for p in poles:
        den = den * (s - p)
    return (gain * num / den).real


def compute_arrival_inputs(points_m, strength_pa_m, alpha_1_s, n_e, frac_s, elements_m, radius_m,
                           sound_speed_m_s, n_paths, reflection_coefficient, att_db_per_m,
                           sep_alpha_1_s, sep_att_rad_s, fe_zeros, fe_poles, fe_gain, fast_poles,
                           fast_weighted_residues, support_fast, support_att, max_support,
                           support_rel_tol, sensitivity_v_per_pa, sample_rate_hz, dt_s):
    """`arrival_inputs` with its arguments converted to the one signature it is compiled for
    (C-contiguous float64 / int64 / complex128 arrays, Python floats and ints), so that
    `warm_up` and the renderers use the same machine code.

    Parameters
    ----------
    points_m, strength_pa_m, alpha_1_s : array_like
        Emission points (n, 3) [m], signed source strengths (n,) [Pa m], alphas (n,) [1/s].
    n_e, frac_s : array_like
        Emission instants as absolute sample (n,) [samples] plus a fraction (n,) [s].
    elements_m, radius_m, sound_speed_m_s : array_like, float, float
        Element centres (4, 3) [m], sphere radius [m], sound speed [m/s].
    n_paths, reflection_coefficient, att_db_per_m : int, float, float
        Direct path plus echoes, echo ratio per bounce, loss at 1 MHz [dB/m] (0: lossless).
    sep_alpha_1_s, sep_att_rad_s : array_like
        Values an alpha [1/s] / an attenuation pole [rad/s] is nudged away from.
    fe_zeros, fe_poles, fe_gain : array_like, array_like, float
        Front-end zeros and poles [rad/s] and gain [V/Pa].
    fast_poles, fast_weighted_residues : array_like
        Filter poles kept (one per conjugate pair) [rad/s] and their weighted residues.
    support_fast, support_att, max_support : int
        Truncation lengths of the filter-pole and attenuation parts, and the cap [samples].
    support_rel_tol, sensitivity_v_per_pa, sample_rate_hz, dt_s : float
        Truncation tolerance, in-band gain [V/Pa], sample rate [Hz], period [s].

    Returns
    -------
    tuple
        (n0, length, channel, al_sep, cs, fcoef, att), see `arrival_inputs`.
    """
    f8 = np.float64
    return arrival_inputs(
        np.ascontiguousarray(points_m, f8), np.ascontiguousarray(strength_pa_m, f8),
        np.ascontiguousarray(alpha_1_s, f8), np.ascontiguousarray(n_e, np.int64),
        np.ascontiguousarray(frac_s, f8), np.ascontiguousarray(elements_m, f8),
        float(radius_m), float(sound_speed_m_s), int(n_paths), float(reflection_coefficient),
        float(att_db_per_m), np.ascontiguousarray(sep_alpha_1_s, f8),
        np.ascontiguousarray(sep_att_rad_s, f8), np.ascontiguousarray(fe_zeros, np.complex128),
        np.ascontiguousarray(fe_poles, np.complex128), float(fe_gain),
        np.ascontiguousarray(fast_poles, np.complex128),
        np.ascontiguousarray(fast_weighted_residues, np.complex128), int(support_fast),
        int(support_att), int(max_support), float(support_rel_tol), float(sensitivity_v_per_pa),
        float(sample_rate_hz), float(dt_s))


_WARM = False


def warm_up() -> bool:
    """Compile (or load from numba's cache) the kernels now, so that the first rendered
    packet is not delayed by compilation (seconds; a fraction of a second from the cache).
    Each kernel is called once on tiny inputs of the types the renderers pass. Idempotent;
    `load_scene` calls it.

    Returns
    -------
    bool
        `HAVE_NUMBA`: whether the compiled kernels exist (else the numpy path runs).
    """
    global _WARM
    if HAVE_NUMBA and not _WARM:
        _WARM = True
        i1 = np.zeros(1, np.int64)
        accumulate_windows(np.zeros((1, 4, 2)), i1, i1, i1 + 1, i1, i1 + 2, i1, i1,
                           np.zeros((1, 2)), np.zeros((1, 2, 2)), np.zeros((1, 6)),
                           np.zeros((6, 2)), 2, np.zeros((1, 0)), 0)
        w0 = 2e5 * math.pi                          # [rad/s] a 100 kHz high-pass pair
        pair = np.array([w0 * (-1 + 1j), w0 * (-1 - 1j)]) / math.sqrt(2.0)
        compute_arrival_inputs(
            [[0.0, 0.0, 0.01]], [1.0], [3000.0], [0], [0.0],
            np.array([[1.5e-3, 0.0, 0.0], [-1.5e-3, 0.0, 0.0], [0.0, 1.5e-3, 0.0],
                      [0.0, -1.5e-3, 0.0]]), 0.01, 1480.0, 1, -0.5, 100.0, [w0], [w0], [0, 0],
            pair, 0.01, pair[:1], [2.0], 4, 4, 2000, 1e-6, 0.01, 10e6, 1e-7)
    return HAVE_NUMBA
