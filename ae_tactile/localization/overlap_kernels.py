# SPDX-License-Identifier: Apache-2.0
# size: the overlap fit's numba kernels, one compiled unit (numpy twins: overlap/model, search)
"""Compiled joint fit of overlapping emissions: the Levenberg-Marquardt runs and the
matched-filter grid of `ae_tactile.localization.overlap`, one window at a time.

Same equations as the numpy path of `overlap` (``model._Model.evaluate`` / ``jacobian``,
``model._lstsq_amplitudes``, ``model._lm``, the inner loop of ``search._grid_search``),
without the per-call overhead of ~60 small numpy calls per model evaluation (a
two-emission window fits in about a millisecond). The pulse of an arrival at t_a on the
segment grid t_n = t_0 + n / f_s is

    h(t_n - t_a) = Re sum_p c_p E_p[n],  c_p = r_p e^{p (t_0 - t_a)},  E_p[n] = e^{p n / f_s}

for n >= n_0 (first sample at/after the arrival), 0 before; h' the same with c_p p. Lossless
media only (a lossy medium's per-path attenuation pole stays on the numpy path). Used
when numba is present (`ae_tactile.jit`); the tests check that both paths agree.
"""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.jit import NUMBA_AVAILABLE, njit
from ae_tactile.localization.fast import _adc_noise, prepare_packet

__all__ = [
    "NUMBA_AVAILABLE",
    "lm_fit",
    "model_residual",
    "grid_profile",
    "matched_filter",
    "quick_search",
    "prepare_window",
    "segment",
    "suspect_rss",
]

#: no fast-math: the same input gives the same bits in every process (the dot products
#: keep four fixed partial sums for speed instead of letting the compiler reorder them)
_FAST = False
#: reassociation only in sums of products (`_dot`): the compiler keeps the sum in vector
#: lanes (a fixed split for a given machine code, so still the same bits in every process
#: on one machine), several times faster than one scalar chain
_SUM = {"reassoc"}
#: Levenberg-Marquardt stops once an accepted step lowers the residual sum of squares by
#: less than this fraction of it. With rss ~ N sigma^2 (N ~ 1000 samples) that is ~1e-3
#: sigma^2: what is left moves the point by well under 1 % of its standard deviation.
LM_REL_TOL = 1e-6
#: ... when that step was damped by at most this lambda (the start is 1e-3): a short step
#: after rejected ones is no sign of convergence
LM_STOP_LAMBDA = 1e-2


@njit(cache=True, nogil=True, fastmath=_FAST)
def _solve(a, b, out):
    """Solve a x = b (n x n, partial pivoting; a, b overwritten). False if singular."""
    n = b.shape[0]
    for col in range(n):
        piv = col
        best = abs(a[col, col])
        for r in range(col + 1, n):
            v = abs(a[r, col])
            if v > best:
                best, piv = v, r
        if best == 0.0 or best != best:
            return False
        if piv != col:
            for q in range(n):
                a[col, q], a[piv, q] = a[piv, q], a[col, q]
            b[col], b[piv] = b[piv], b[col]
        inv = 1.0 / a[col, col]
        for r in range(col + 1, n):
            f = a[r, col] * inv
            if f != 0.0:
                for q in range(col, n):
                    a[r, q] -= f * a[col, q]
                b[r] -= f * b[col]
    for r in range(n - 1, -1, -1):
        s = b[r]
        for q in range(r + 1, n):
            s -= a[r, q] * out[q]
        out[r] = s / a[r, r]
    return True


@njit(cache=True, nogil=True, fastmath=_SUM)
def _dot(a, b):
    """sum a * b (the compiler may split the sum into vector lanes: `_SUM`)."""
    s = 0.0
    for q in range(a.shape[0]):
        s += a[q] * b[q]
    return s


@njit(cache=True, nogil=True, fastmath=_FAST)
def _gram(rows, m, g):
    """g = rows[:m] rows[:m]^T (symmetric)."""
    for i in range(m):
        for j in range(i + 1):
            s = _dot(rows[i], rows[j])
            g[i, j] = s
            g[j, i] = s


@njit(cache=True, nogil=True)
def _model_buffers(J, N, L):
    """Work arrays of `_evaluate` for J emissions on N = 4L samples: phi (2J, N); h, dh
    (J, 2, 4, L); gain (J, 2, 4); dgain, dtds (J, 2, 4, 2)."""
    return (
        np.empty((2 * J, N)),
        np.empty((J, 2, 4, L)),
        np.empty((J, 2, 4, L)),
        np.empty((J, 2, 4)),
        np.empty((J, 2, 4, 2)),
        np.empty((J, 2, 4, 2)),
    )


@njit(cache=True, nogil=True, fastmath=_FAST)
def _evaluate(theta, J, elem, c, R, echo, t0_s, fs, L, poles, res, tab_re, tab_im, mask,
              phi, h, dh, gain, dgain, dtds):
    """Basis phi (2J, 4L) and the parts of the Jacobian for theta (J, 3) = (s_x, s_y, T):
    h, dh (J, 2, 4, L); gain (J, 2, 4); dgain, dtds (J, 2, 4, 2)."""
    P = poles.shape[0]
    R2 = R * R
    floor = (1e-3 * R) ** 2
    cre = np.empty(P)
    cim = np.empty(P)
    dre = np.empty(P)
    dim = np.empty(P)
    for j in range(J):
        sx, sy, T = theta[j, 0], theta[j, 1], theta[j, 2]
        sz = math.sqrt(max(R2 - sx * sx - sy * sy, floor))
        for path in range(2):
            sign = -1.0 if path == 0 else 1.0
            base = 0.0 if path == 0 else 2.0 * R
            for k in range(4):
                vx = sx + sign * elem[k, 0]
                vy = sy + sign * elem[k, 1]
                vz = sz + sign * elem[k, 2]
                dist = math.sqrt(vx * vx + vy * vy + vz * vz)
                gx = (vx - vz * (sx / sz)) / dist
                gy = (vy - vz * (sy / sz)) / dist
                d = dist + base
                dtds[j, path, k, 0] = gx / c
                dtds[j, path, k, 1] = gy / c
                if path == 0:
                    gain[j, path, k] = R / d
                    dgain[j, path, k, 0] = -(R / (d * d)) * gx
                    dgain[j, path, k, 1] = -(R / (d * d)) * gy
                else:
                    gain[j, path, k] = 1.0 if echo else 0.0
                    dgain[j, path, k, 0] = 0.0
                    dgain[j, path, k, 1] = 0.0
                off = t0_s - (T + d / c)
                n0f = math.ceil(-off * fs - 1e-9)
                n0 = 0 if n0f < 0 else (L if n0f > L else int(n0f))
                for p in range(P):
                    cp = res[p] * np.exp(poles[p] * off)
                    cdp = cp * poles[p]
                    cre[p] = cp.real
                    cim[p] = cp.imag
                    dre[p] = cdp.real
                    dim[p] = cdp.imag
                hv = h[j, path, k]
                dv = dh[j, path, k]
                hv[:] = 0.0
                dv[:] = 0.0
                for p in range(P):
                    a, b, e, f = cre[p], cim[p], dre[p], dim[p]
                    er = tab_re[p]
                    ei = tab_im[p]
                    for n in range(n0, L):
                        hv[n] += a * er[n] - b * ei[n]
                        dv[n] += e * er[n] - f * ei[n]
                g = gain[j, path, k]
                row = phi[2 * j + path]
                for n in range(L):
                    row[k * L + n] = g * hv[n] * mask[k * L + n]


@njit(cache=True, nogil=True, fastmath=_FAST)
def _amplitudes(phi, m, y, amp, g, b, work, ridge):
    """LS amplitudes of y on the first m rows of phi (Jacobi scaled, relative ridge)."""
    _gram(phi, m, g)
    gmax = 0.0
    for i in range(m):
        b[i] = _dot(phi[i], y)
        gmax = max(gmax, g[i, i])
    sc = np.empty(m)
    for i in range(m):
        sc[i] = 1.0 / math.sqrt(max(g[i, i], 1e-300 + 1e-30 * gmax))
    a = np.empty((m, m))
    rhs = np.empty(m)
    for i in range(m):
        for j in range(m):
            a[i, j] = g[i, j] * sc[i] * sc[j]
        a[i, i] += ridge
        rhs[i] = b[i] * sc[i]
    if not _solve(a, rhs, work):
        for i in range(m):
            amp[i] = np.nan
        return
    for i in range(m):
        amp[i] = work[i] * sc[i]


@njit(cache=True, nogil=True, fastmath=_FAST)
def _residual(phi, m, y, amp, r):
    """r = y - amp phi[:m]; returns sum r^2."""
    n = y.shape[0]
    for q in range(n):
        r[q] = y[q]
    for i in range(m):
        a = amp[i]
        row = phi[i]
        for q in range(n):
            r[q] -= a * row[q]
    return _dot(r, r)


@njit(cache=True, nogil=True, fastmath=_FAST)
def _jacobian_rows(J, L, amp, h, dh, gain, dgain, dtds, mask, jac):
    """Rows 0..3J-1 of jac: d model / d (s_x, s_y, T) of each emission."""
    for j in range(J):
        for q in range(3):
            jac[3 * j + q, :] = 0.0
        for path in range(2):
            a = amp[2 * j + path]
            for k in range(4):
                ag = a * gain[j, path, k]
                ax = a * dgain[j, path, k, 0]
                ay = a * dgain[j, path, k, 1]
                tx = ag * dtds[j, path, k, 0]
                ty = ag * dtds[j, path, k, 1]
                hv = h[j, path, k]
                dv = dh[j, path, k]
                rx = jac[3 * j]
                ry = jac[3 * j + 1]
                rt = jac[3 * j + 2]
                for n in range(L):
                    i = k * L + n
                    rx[i] += ax * hv[n] - tx * dv[n]
                    ry[i] += ay * hv[n] - ty * dv[n]
                    rt[i] -= ag * dv[n]
    for r in range(3 * J):
        row = jac[r]
        for i in range(row.shape[0]):
            row[i] *= mask[i]


@njit(cache=True, nogil=True, fastmath=_FAST)
def _clip(theta, J, max_rho):
    for j in range(J):
        rho = math.hypot(theta[j, 0], theta[j, 1])
        if rho > max_rho:
            f = max_rho / max(rho, 1e-300)
            theta[j, 0] *= f
            theta[j, 1] *= f


@njit(cache=True, nogil=True, fastmath=_FAST)
def lm_fit(y, mask, t0_s, theta0, elem, c, R, echo, fs, poles, res, tab_re, tab_im,
           iterations, max_rho, theta_out, amp_out, gram_out):
    """Levenberg-Marquardt over the 5J parameters of one window (variable projection: the
    amplitudes are re-solved by LS after each step), as ``overlap._lm`` for K = 1.
    y, mask (4L,); theta0 (J, 3). Writes theta_out (J, 3), amp_out (2J,), gram_out
    (5J, 5J) (Gram matrix of the final Jacobian); returns the residual sum of squares."""
    J = theta0.shape[0]
    N = y.shape[0]
    L = N // 4
    M = 5 * J
    theta = theta0.copy()
    _clip(theta, J, max_rho)
    phi, h, dh, gain, dgain, dtds = _model_buffers(J, N, L)
    phi2, h2, dh2, gain2, dgain2, dtds2 = _model_buffers(J, N, L)
    g2 = np.empty((2 * J, 2 * J))
    b2 = np.empty(2 * J)
    w2 = np.empty(2 * J)
    amp = np.empty(2 * J)
    amp2 = np.empty(2 * J)
    r = np.empty(N)
    r2 = np.empty(N)
    jac = np.empty((M, N))
    jtj = np.empty((M, M))
    jtr = np.empty(M)
    a = np.empty((M, M))
    rhs = np.empty(M)
    step = np.empty(M)
    new = np.empty((J, 3))
    _evaluate(theta, J, elem, c, R, echo, t0_s, fs, L, poles, res, tab_re, tab_im, mask,
              phi, h, dh, gain, dgain, dtds)
    _amplitudes(phi, 2 * J, y, amp, g2, b2, w2, 1e-9)
    rss = _residual(phi, 2 * J, y, amp, r)
    lam = 1e-3
    stale = True  # jtj / jtr to be rebuilt (after an accepted step)
    for _ in range(iterations):
        if stale:
            _jacobian_rows(J, L, amp, h, dh, gain, dgain, dtds, mask, jac)
            for i in range(2 * J):
                jac[3 * J + i, :] = phi[i]
            _gram(jac, M, jtj)
            for i in range(M):
                jtr[i] = _dot(jac[i], r)
            stale = False
        dmax = 0.0
        for i in range(M):
            dmax = max(dmax, jtj[i, i])
        for i in range(M):
            for j in range(M):
                a[i, j] = jtj[i, j]
            a[i, i] += lam * max(jtj[i, i], 1e-12 * dmax + 1e-300)
            rhs[i] = jtr[i]
        if not _solve(a, rhs, step):
            step[:] = 0.0
        for i in range(M):
            if not math.isfinite(step[i]):
                step[i] = 0.0
        for j in range(J):
            for q in range(3):
                new[j, q] = theta[j, q] + step[3 * j + q]
        _clip(new, J, max_rho)
        _evaluate(new, J, elem, c, R, echo, t0_s, fs, L, poles, res, tab_re, tab_im, mask,
                  phi2, h2, dh2, gain2, dgain2, dtds2)
        _amplitudes(phi2, 2 * J, y, amp2, g2, b2, w2, 1e-9)
        rss2 = _residual(phi2, 2 * J, y, amp2, r2)
        if rss2 < rss:
            theta, new = new, theta
            amp, amp2 = amp2, amp
            r, r2 = r2, r
            phi, phi2 = phi2, phi
            h, h2 = h2, h
            dh, dh2 = dh2, dh
            gain, gain2 = gain2, gain
            dgain, dgain2 = dgain2, dgain
            dtds, dtds2 = dtds2, dtds
            rel = (rss - rss2) / max(rss, 1e-300)
            rss = rss2
            converged = rel < LM_REL_TOL and lam <= LM_STOP_LAMBDA
            lam = max(lam / 4.0, 1e-7)
            stale = True
            if converged:
                break
        else:
            lam *= 8.0
            if lam > 1e6:
                break
    _jacobian_rows(J, L, amp, h, dh, gain, dgain, dtds, mask, jac)
    for i in range(2 * J):
        jac[3 * J + i, :] = phi[i]
    _gram(jac, M, gram_out)
    theta_out[:, :] = theta
    amp_out[:] = amp
    return rss


@njit(cache=True, nogil=True, fastmath=_FAST)
def model_residual(y, mask, t0_s, theta, amp, elem, c, R, echo, fs, poles, res, tab_re, tab_im,
                   r_out):
    """r_out = y - model(theta (J, 3), amp (2J,)) of one window (4L,)."""
    J = theta.shape[0]
    N = y.shape[0]
    L = N // 4
    phi, h, dh, gain, dgain, dtds = _model_buffers(J, N, L)
    _evaluate(theta, J, elem, c, R, echo, t0_s, fs, L, poles, res, tab_re, tab_im, mask,
              phi, h, dh, gain, dgain, dtds)
    _residual(phi, 2 * J, y, amp, r_out)


@njit(cache=True, nogil=True, fastmath=False)
def grid_profile(cp, gain, rel, norm, step, prof, prof_g):
    """Matched-filter grid of one window: for each arrival sample m_i = step i (i < M =
    prof.size) the best grid point g of stat = (sum_k gain[g, k] cp[k, rel[g, k] + m_i])^2 /
    ||phi_g||^2, in float32 and in the numpy path's order of operations (the same values,
    the same ties: the first g of the largest stat). cp (4, L + pad), gain (G, 4), norm (G,)
    float32; writes prof (M,) float32, prof_g (M,). Each channel is first split into its
    ``step`` phases (cp[k, q + step j]), so that the loop over i reads contiguous memory."""
    G = gain.shape[0]
    M = prof.shape[0]
    W = cp.shape[1]
    n_ph = (W + step - 1) // step
    dec = np.zeros((4, step, n_ph), np.float32)
    for k in range(4):
        for n in range(W):
            dec[k, n % step, n // step] = cp[k, n]
    best = np.full(M, -np.inf, np.float32)
    best_g = np.zeros(M, np.int32)
    zero = np.float32(0.0)
    for g in range(G):
        g0, g1, g2, g3 = gain[g, 0], gain[g, 1], gain[g, 2], gain[g, 3]
        r0, r1, r2, r3 = rel[g, 0], rel[g, 1], rel[g, 2], rel[g, 3]
        c0 = dec[0, r0 % step, r0 // step:]
        c1 = dec[1, r1 % step, r1 // step:]
        c2 = dec[2, r2 % step, r2 // step:]
        c3 = dec[3, r3 % step, r3 // step:]
        w = norm[g]
        gg = np.int32(g)
        for i in range(M):
            v = zero + g0 * c0[i]
            v = v + g1 * c1[i]
            v = v + g2 * c2[i]
            v = v + g3 * c3[i]
            st = (v * v) / w
            up = st > best[i]
            best[i] = st if up else best[i]
            best_g[i] = gg if up else best_g[i]
    for i in range(M):
        prof[i] = best[i]
        prof_g[i] = best_g[i]


@njit(cache=True, nogil=True, fastmath=_FAST)
def matched_filter(r, L, z, hr, cp):
    """Matched filter of a window's four channels r (4L,) with the pulse h, in cp's type:

        cp[k, n] = sum_{m=0}^{L-1-n} r_k[n + m] h[m],  h[m] = Re sum_p hr_p z_p^m,

    by the backward recursion u_p[n] = r_k[n] + z_p u_p[n + 1] (z_p = e^{p / f_s}: one
    complex multiply-add per pole and sample instead of an FFT pair). cp (4, >= L): the
    rest of each row is set to 0."""
    P = z.shape[0]
    acc = np.empty(L)
    for k in range(4):
        for n in range(L):
            acc[n] = 0.0
        for p in range(P):
            zp = z[p]
            hp = hr[p]
            u = 0j
            for n in range(L - 1, -1, -1):
                u = r[k * L + n] + zp * u
                acc[n] += (hp * u).real
        for n in range(L):
            cp[k, n] = acc[n]
        for n in range(L, cp.shape[1]):
            cp[k, n] = 0.0


@njit(cache=True, nogil=True, fastmath=_FAST)
def _grid_best(cp, L, gain32, rel, norm32, mm, gain, norm, tt, grid, start, fs, prof, prof_g,
               out):
    """The best grid point of one emission (``overlap._grid_search`` with n_peaks = 1):
    the profile's first maximum, refined to the best of its arrival sample +- 1 in float64;
    out (3,) = (s_x, s_y, T)."""
    grid_profile(cp, gain32, rel, norm32, mm[1] - mm[0] if mm.shape[0] > 1 else 1, prof,
                 prof_g)
    i = 0
    for q in range(1, mm.shape[0]):
        if prof[q] > prof[i]:
            i = q
    g = prof_g[i]
    m0 = mm[i]
    best_m = m0
    best = -np.inf
    for dm in range(-1, 2):
        m = min(max(m0 + dm, 0), L - 1)
        v = 0.0
        for k in range(4):
            v = v + gain[g, k] * np.float64(cp[k, rel[g, k] + m])
        st = v * v / norm[g]
        if st > best:
            best = st
            best_m = m
    t_min = tt[g, 0]
    for k in range(1, 4):
        t_min = min(t_min, tt[g, k])
    out[0] = grid[g, 0]
    out[1] = grid[g, 1]
    out[2] = (start + best_m) / fs - t_min


@njit(cache=True, nogil=True, fastmath=_FAST)
def quick_search(y, mask, start, sigma2, search_limit, add_threshold, max_sources,
                 elem, c, R, echo, fs, poles, res, tab_re, tab_im, iterations, max_rho,
                 z, hr, gain32, rel, norm32, mm, gain, norm, tt, grid, pad,
                 theta_out, amp_out, rss_out, gram_out):
    """The quick search of one window in one call (``overlap._search`` with ``deferred``):
    grid + LM of one emission; emission j = 2.. only while the (j-1)-emission residual
    is above search_limit sigma^2 dof (and, for j >= 3, emission j-1 lowered it by more
    than add_threshold sigma^2): grid point of the residual, joint LM from there. A joint
    fit that still leaves more than noise marks the window deferred (no further search).
    Emissions of each fit ordered by emission time. y, mask (4L,), start: first sample of
    the segment. Writes fit j into theta_out[j-1, :j], amp_out[j-1, :2j], rss_out[j-1],
    gram_out[j-1, :5j, :5j] (a fit not searched repeats fit j-1 with zeros); returns
    True when deferred."""
    N = y.shape[0]
    L = N // 4
    t0_s = start / fs
    n_in = 0.0
    for q in range(N):
        n_in += mask[q]
    cp = np.empty((4, L + pad + 2), np.float32)
    prof = np.empty(mm.shape[0], np.float32)
    prof_g = np.empty(mm.shape[0], np.int64)
    r = np.empty(N)
    best = np.empty(3)
    theta_out[:, :, :] = 0.0
    amp_out[:, :] = 0.0
    gram_out[:, :, :] = 0.0
    matched_filter(y, L, z, hr, cp)
    _grid_best(cp, L, gain32, rel, norm32, mm, gain, norm, tt, grid, start, fs, prof, prof_g,
               best)
    th = np.empty((1, 3))
    th[0, :] = best
    t1 = np.empty((1, 3))
    a1 = np.empty(2)
    g1 = np.empty((5, 5))
    rss_out[0] = lm_fit(y, mask, t0_s, th, elem, c, R, echo, fs, poles, res, tab_re, tab_im,
                        iterations, max_rho, t1, a1, g1)
    theta_out[0, :1] = t1
    amp_out[0, :2] = a1
    gram_out[0, :5, :5] = g1
    deferred = False
    for j in range(2, max_sources + 1):
        pj = j - 2  # the previous fit
        dof = max(n_in - 5 * (j - 1), 1.0)
        go = rss_out[pj] > search_limit * sigma2 * dof
        if j > 2:
            go = go and (rss_out[pj - 1] - rss_out[pj]) > add_threshold * sigma2
        if not go or deferred:
            theta_out[j - 1, : j - 1] = theta_out[pj, : j - 1]
            amp_out[j - 1, : 2 * (j - 1)] = amp_out[pj, : 2 * (j - 1)]
            rss_out[j - 1] = rss_out[pj]
            continue
        model_residual(y, mask, t0_s, theta_out[pj, : j - 1], amp_out[pj, : 2 * (j - 1)],
                       elem, c, R, echo, fs, poles, res, tab_re, tab_im, r)
        matched_filter(r, L, z, hr, cp)
        _grid_best(cp, L, gain32, rel, norm32, mm, gain, norm, tt, grid, start, fs, prof,
                   prof_g, best)
        th = np.empty((j, 3))
        th[: j - 1] = theta_out[pj, : j - 1]
        th[j - 1] = best
        t1 = np.empty((j, 3))
        a1 = np.empty(2 * j)
        g1 = np.empty((5 * j, 5 * j))
        rss_out[j - 1] = lm_fit(y, mask, t0_s, th, elem, c, R, echo, fs, poles, res, tab_re,
                                tab_im, iterations, max_rho, t1, a1, g1)
        if rss_out[j - 1] > search_limit * sigma2 * max(n_in - 5 * j, 1.0):
            deferred = True
        # order the emissions by emission time (parameters and Gram matrix alike)
        order = np.argsort(t1[:, 2])
        perm = np.empty(5 * j, np.int64)
        for q in range(j):
            o = order[q]
            theta_out[j - 1, q] = t1[o]
            amp_out[j - 1, 2 * q] = a1[2 * o]
            amp_out[j - 1, 2 * q + 1] = a1[2 * o + 1]
            for d in range(3):
                perm[3 * q + d] = 3 * o + d
            perm[3 * j + 2 * q] = 3 * j + 2 * o
            perm[3 * j + 2 * q + 1] = 3 * j + 2 * o + 1
        for a in range(5 * j):
            for b in range(5 * j):
                gram_out[j - 1, a, b] = g1[perm[a], perm[b]]
    return deferred


@njit(cache=True, nogil=True)
def prepare_window(xin, onset, noise_rms, sat_in, full_scale, pre, seg_len, flat_run):
    """`common.prepare` and `common.adc_noise` of one window (`fast.prepare_packet`, no
    channel gains). Returns (x (4, m) scaled, pre_mean (4,), flags, onset, scale, sigma2:
    the noise variance on the signal samples, units^2)."""
    x, raw, pre_mean, flags, on, seg_start, scale, sigma2, given, quant2 = prepare_packet(
        xin, onset, noise_rms, sat_in, full_scale, np.ones(4), False, 1.0, pre, seg_len,
        flat_run,
    )
    return x, pre_mean, flags, on, scale, _adc_noise(sigma2, quant2, given)


@njit(cache=True, nogil=True)
def segment(x, start, L, pre_mean, y, mask):
    """The analysis segment of one window (``overlap._segments``): y[kL + n] = x[k, start + n]
    - pre_mean[k] and mask[kL + n] = 1 inside the window, both 0 past its end."""
    m = x.shape[1]
    for k in range(4):
        for n in range(L):
            i = start + n
            inside = 1.0 if i < m else 0.0
            y[k * L + n] = (x[k, min(i, m - 1)] - pre_mean[k]) * inside
            mask[k * L + n] = inside


@njit(cache=True, nogil=True, fastmath=_FAST)
def suspect_rss(y, mask, start, sx, sy, elem, c, R, echo, fs, poles, res, tab_re, tab_im, z,
                hr):
    """Residual sum of squares of one emission at the surface point (sx, sy) in one window
    (``overlap.suspect_overlap``): emission time T by the channel-summed matched filter
    along the point's travel times, then LS on [h, h'] of the direct wave and the echo
    at (sx, sy, T) (linearised in T). y, mask (4L,); start: the segment's first sample."""
    N = y.shape[0]
    L = N // 4
    corr = np.empty((4, L))
    matched_filter(y, L, z, hr, corr)
    sz = math.sqrt(max(R * R - sx * sx - sy * sy, 0.0))
    d = np.empty(4)
    t_min = np.inf
    for k in range(4):
        vx = sx - elem[k, 0]
        vy = sy - elem[k, 1]
        vz = sz - elem[k, 2]
        d[k] = math.sqrt(vx * vx + vy * vy + vz * vz)
        t_min = min(t_min, d[k] / c)
    rel = np.empty(4, np.int64)
    for k in range(4):
        rel[k] = int(np.rint((d[k] / c - t_min) * fs))
    best = -1.0
    best_n = 0
    for n in range(L):
        v = 0.0
        for k in range(4):
            v = v + corr[k, min(rel[k] + n, L - 1)] * (R / d[k])
        if v * v > best:
            best = v * v
            best_n = n
    theta = np.empty((1, 3))
    theta[0, 0] = sx
    theta[0, 1] = sy
    theta[0, 2] = (start + best_n) / fs - t_min
    phi, h, dh, gain, dgain, dtds = _model_buffers(1, N, L)
    _evaluate(theta, 1, elem, c, R, echo, start / fs, fs, L, poles, res, tab_re, tab_im, mask,
              phi, h, dh, gain, dgain, dtds)
    cols = np.empty((4, N))
    for path in range(2):
        cols[path] = phi[path]
        for k in range(4):
            g = gain[0, path, k]
            for n in range(L):
                cols[2 + path, k * L + n] = g * dh[0, path, k, n] * mask[k * L + n]
    amp = np.empty(4)
    _amplitudes(cols, 4, y, amp, np.empty((4, 4)), np.empty(4), np.empty(4), 1e-9)
    return _residual(cols, 4, y, amp, np.empty(N))
