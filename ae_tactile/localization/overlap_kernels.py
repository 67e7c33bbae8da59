# SPDX-License-Identifier: Apache-2.0
"""Compiled joint fit of overlapping emissions: the Levenberg-Marquardt runs and the
matched-filter grid of `ae_tactile.localization.overlap`, one window at a time.

Same equations as the numpy path of `overlap` (``_Model.evaluate`` / ``jacobian``,
``_lstsq_amplitudes``, ``_lm``, the inner loop of ``_grid_search``), without the per-call
overhead of ~60 small numpy calls per model evaluation: a two-emission window fits in
about a millisecond instead of tens. The pulse of an arrival at t_a on the segment grid
t_n = t_0 + n / f_s is

    h(t_n - t_a) = Re sum_p c_p E_p[n],  c_p = r_p e^{p (t_0 - t_a)},  E_p[n] = e^{p n / f_s}

for n >= n_0 (first sample at/after the arrival), 0 before; h' the same with c_p p. Lossless
media only (a lossy medium's per-path attenuation pole stays on the numpy path). Used
when numba is present (`ae_tactile.jit`); the tests check that both paths agree.
"""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.jit import NUMBA_AVAILABLE, njit

__all__ = ["NUMBA_AVAILABLE", "lm_fit", "model_residual", "grid_profile"]

#: no fast-math: the same input gives the same bits in every process (the dot products
#: keep four fixed partial sums for speed instead of letting the compiler reorder them)
_FAST = False


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


@njit(cache=True, nogil=True, fastmath=_FAST)
def _dot(a, b):
    """sum a * b with four partial sums in a fixed order (fast and reproducible)."""
    n = a.shape[0]
    m = n - n % 4
    s0 = s1 = s2 = s3 = 0.0
    for q in range(0, m, 4):
        s0 += a[q] * b[q]
        s1 += a[q + 1] * b[q + 1]
        s2 += a[q + 2] * b[q + 2]
        s3 += a[q + 3] * b[q + 3]
    for q in range(m, n):
        s0 += a[q] * b[q]
    return (s0 + s1) + (s2 + s3)


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
            lam = max(lam / 4.0, 1e-7)
            stale = True
            if rel < 1e-9:
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
def grid_profile(cp, gain, rel, norm, mm, prof, prof_g):
    """Matched-filter grid of one window: for each arrival sample mm[i] the best grid point
    g of stat = (sum_k gain[g, k] cp[k, rel[g, k] + mm[i]])^2 / ||phi_g||^2, in float32
    and in the numpy path's order of operations (the same values, the same ties).
    cp (4, L + pad), gain (G, 4), norm (G,) float32; writes prof (M,) float32, prof_g (M,)."""
    G = gain.shape[0]
    M = mm.shape[0]
    for i in range(M):
        prof[i] = -np.inf
        prof_g[i] = 0
    zero = np.float32(0.0)
    for g in range(G):
        g0, g1, g2, g3 = gain[g, 0], gain[g, 1], gain[g, 2], gain[g, 3]
        r0, r1, r2, r3 = rel[g, 0], rel[g, 1], rel[g, 2], rel[g, 3]
        w = norm[g]
        for i in range(M):
            m = mm[i]
            v = zero + g0 * cp[0, r0 + m]
            v = v + g1 * cp[1, r1 + m]
            v = v + g2 * cp[2, r2 + m]
            v = v + g3 * cp[3, r3 + m]
            s = (v * v) / w
            if s > prof[i]:
                prof[i] = s
                prof_g[i] = g
