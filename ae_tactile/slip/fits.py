# SPDX-License-Identifier: Apache-2.0
"""The slip detector's small least-squares fits (pure numpy, no state): the circle through
a contact's micro-slips, the 90th percentile of their distances, the period of a
texture's emission times and the drift of emission points along the surface."""

from __future__ import annotations

import math

import numpy as np


def circle_centre(P):
    """Centre (3,) of the circle best fitting points P (n, 3) on the sphere (algebraic Kasa
    fit u^2 + v^2 = 2 cu u + 2 cv v + k in the tangent plane at their centroid, projected
    back on the sphere); None when the points are nearly collinear or the centre lands
    more than 3 spreads from the centroid."""
    k = len(P)
    m = P.sum(axis=0) / k  # P.mean(axis=0), bit for bit, without its Python wrapper
    rn = float(np.sqrt((P * P).sum(axis=1)).sum() / k)
    n = m / math.sqrt(float(m @ m))
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref @ n) * n
    e1 /= math.sqrt(float(e1 @ e1))
    n0, n1, n2 = n.tolist()
    a0, a1, a2 = e1.tolist()
    e2 = np.array([n1 * a2 - n2 * a1, n2 * a0 - n0 * a2, n0 * a1 - n1 * a0])  # n x e1
    D = P - m
    u, v = D @ e1, D @ e2
    suu, svv, suv = float(u @ u), float(v @ v), float(u @ v)
    tr, det = (suu + svv) / k, (suu * svv - suv * suv) / (k * k)
    disc = math.sqrt(max(tr * tr / 4 - det, 0.0))
    lo, hi = tr / 2 - disc, tr / 2 + disc
    if hi <= 0.0 or lo < 0.01 * hi:
        return None
    b = u * u + v * v
    r1, r2 = 2 * float(u @ b), 2 * float(v @ b)
    a11, a12, a22 = 4 * suu, 4 * suv, 4 * svv
    dd = a11 * a22 - a12 * a12
    cu, cv = (a22 * r1 - a12 * r2) / dd, (a11 * r2 - a12 * r1) / dd
    if math.hypot(cu, cv) > 3.0 * math.sqrt(hi):
        return None
    c = m + cu * e1 + cv * e2
    return c * (rn / math.sqrt(float(c @ c)))


def percentile90(d):
    """np.percentile(d, 90) (linear interpolation, numpy's rounding) of a short list of
    floats, without numpy's per-call overhead."""
    s = sorted(d)
    n = len(s)
    v = (n - 1) * 0.9
    lo = math.floor(v)
    hi = min(lo + 1, n - 1)
    g = v - lo
    a, b = s[lo], s[hi]
    diff = b - a
    return a + diff * g if g < 0.5 else b - diff * (1 - g)


def multiples(dt, unit):
    """Periods in each interval ``dt`` of ``unit`` (same time unit): 1, unless clearly
    more (>= 1.7 units: a missed packet, since timing jitter rarely stretches one interval
    by 0.7 of a period)."""
    r = dt / unit
    return np.where(r < 1.7, 1.0, np.round(r))


_MISS_PENALTY = 2.0 * math.log(9.0)
#: ambiguous intervals whose period counts `period_fit_best` tries both ways: at most
#: 2^8 fits, and at most this many times (counts) in all (2^6 fits of a run of 64)
_MAX_AMBIGUOUS = 8
_MAX_FIT_TIMES = 4096


def period_fit_best(ts_ns, dt, units):
    """Period T (s), its standard error and the period count of each interval, the counts
    chosen by the whole fit: a wrong count shifts every later time by a period, a jitter
    of sd s T only one time by s T. For each trial ``unit`` (ns: the median interval, a
    period found before), every interval counts `multiples` units, except the ambiguous
    ones (1.25 .. 2.75 units, > 0.25 from a whole number: a jittered double interval or a
    long single one; the ``_MAX_AMBIGUOUS`` farthest from a whole number, fewer in a long
    run: at most ``_MAX_FIT_TIMES`` times in all), whose counts are tried both ways in one
    batch. Score n ln(RSS) (Gaussian jitter, its variance fitted) + 2 ln 9 per missed
    packet (one interval in ten spans two periods a priori); the least wins over every
    unit. (A unit that is itself wrong, e.g. a period that took four long singles for
    doubles, cannot reach the right counts alone: hence several units.)
    Least squares t_j = t_0 + K_j T on the cumulative counts K_j (c: less the mean):
    T = Kc.tc / Kc.Kc, RSS = tc.tc - (Kc.tc)^2 / Kc.Kc."""
    tc = (ts_ns - ts_ns[0]) * 1e-9
    tc -= tc.mean()
    stt = float(tc @ tc)
    n = ts_ns.size
    n_amb = max(0, min(_MAX_AMBIGUOUS, (_MAX_FIT_TIMES // n).bit_length() - 1))
    K = np.zeros((1, n))
    best = None
    tried = []
    for unit in units:
        if not unit > 0:
            continue
        r = dt / unit
        rr = np.rint(r)
        dev = np.abs(r - rr)
        kk = np.where(r < 1.7, 1.0, rr)
        amb = np.flatnonzero((dev > 0.25) & (r > 1.25) & (r < 2.75))
        if amb.size > n_amb:
            amb = amb[np.argsort(-dev[amb])[:n_amb]]
        key = (kk.tobytes(), amb.tobytes())
        if key in tried:  # the same counts to try as a unit before
            continue
        tried.append(key)
        if amb.size:
            bits = (np.arange(1 << amb.size)[:, None] >> np.arange(amb.size)) & 1
            k2 = np.repeat(kk[None, :], bits.shape[0], axis=0)
            k2[:, amb] = np.floor(r[amb]) + bits
        else:
            k2 = kk[None, :]
        if K.shape[0] != k2.shape[0]:
            K = np.zeros((k2.shape[0], n))
        np.cumsum(k2, axis=1, out=K[:, 1:])
        Kc = K - K.mean(axis=1, keepdims=True)
        skk = np.einsum("ij,ij->i", Kc, Kc)
        skt = Kc @ tc
        rss = np.maximum(stt - skt * skt / skk, 1e-30)
        score = n * np.log(rss) + _MISS_PENALTY * (k2.sum(axis=1) - k2.shape[1])
        j = int(np.argmin(score))
        if best is None or score[j] < best[0]:
            best = (float(score[j]), Kc[j].copy(), k2[j])
    if best is None:
        return math.nan, math.inf, None
    _, Kc, kk = best
    # the chosen fit's error from its residuals: tc.tc - (Kc.tc)^2 / Kc.Kc cancels when
    # the jitter is tiny (a near-perfect train), the residuals do not
    skk = float(Kc @ Kc)
    T = float(Kc @ tc) / skk
    res = tc - Kc * T
    se = math.sqrt(float(res @ res) / max(1.0, n - 2.0) / skk)
    return T, se, kk


def drift_fit(t_ns, P):
    """Drift of emission points along the surface, least squares p(t) = p_m + v (t - t_m)
    with v projected onto the tangent plane at p_m (one 4 x 4 moment matrix of (t, p)):
    (v (3,) m/s, p_m (3,) m, t_m s, s2 m^2, stt s^2), s2 = |p - p_m - v (t - t_m)|^2 summed
    / (2 (n - 2)) (residual variance per tangent axis), stt = sum (t - t_m)^2; None when
    the times have no spread."""
    n = len(P)
    Z = np.empty((n, 4))
    t_ref = int(t_ns[0])  # times from the first, in integer ns: exact for any clock origin
    Z[:, 0] = (t_ns - t_ref) * 1e-9
    Z[:, 1:] = P
    zm = Z.sum(axis=0) / n
    Zc = Z - zm
    M = (Zc.T @ Zc).tolist()
    stt = M[0][0]
    if not stt > 0:
        return None
    g = M[0][1:]  # sum (t - t_m)(p - p_m)
    tm, px, py, pz = zm.tolist()
    tm += t_ref * 1e-9
    pn = math.sqrt(px * px + py * py + pz * pz)
    nx, ny, nz = px / pn, py / pn, pz / pn
    vx, vy, vz = g[0] / stt, g[1] / stt, g[2] / stt
    d = vx * nx + vy * ny + vz * nz
    vx, vy, vz = vx - d * nx, vy - d * ny, vz - d * nz
    # sum |Pc - tc v|^2 = tr(Pc' Pc) - 2 v . g + stt |v|^2
    rss = M[1][1] + M[2][2] + M[3][3] - 2.0 * (vx * g[0] + vy * g[1] + vz * g[2])
    rss += stt * (vx * vx + vy * vy + vz * vz)
    s2 = max(rss, 0.0) / max(1, 2 * (n - 2))
    return np.array([vx, vy, vz]), zm[1:], tm, s2, stt
