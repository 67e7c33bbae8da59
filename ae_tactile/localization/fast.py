# SPDX-License-Identifier: Apache-2.0
# size: the ml hot path's numba kernel and helpers, one compiled unit (numpy twin: ml.py)
"""Compiled `ml` localization: one numba kernel per packet (the driver's hot path).

The kernel runs, per packet and with the same equations as the numpy path
(segments.prepare, ml.estimate, estimators._finish):

  prepare   non-finite samples, window, saturation (flag / full scale / flat top), channel
            gains, per-packet scale, pre-onset noise and baselines, SNR window power, ADC
            quantum;
  start     the coarse segment's band bins by a direct DFT (x[n] e^{-j 2 pi k n / N} from
            tables of the plan), the 6 pair cross-correlations r(d) = sum_f W_f Re(G_f
            e^{j w_f d}) at the physically possible integer lags only, parabola, pair LS,
            exact inversion (FingertipGeometry.point_from_delays);
  fit       the aligned segments' band bins (direct DFT), damped Newton on the steered
            response power with the analytic gradient / Hessian, line search, projection,
            one re-cut;
  finish    misfit, SNR, noise, Fisher covariance, horizon check, polarity / amplitude,
            confidence, reason, emission offset.

A direct DFT over the ~15-40 band bins costs 4 L nb multiply-adds per transform (L ~ 110
samples at 10 MS/s): ~20 k per packet, far less than the Python call overhead it
replaces. numba is optional: without it (or with AE_TACTILE_NO_NUMBA=1 in the
environment, or ``engine="numpy"``) the numpy path runs; the two agree to rounding.
"""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.jit import NUMBA_AVAILABLE, njit  # noqa: F401 (NUMBA_AVAILABLE: re-exported)
from ae_tactile.localization.common import (
    ALIAS_GUARD_DB,
    BAND_EDGE_POWER_RATIO,
    PAIR_PINV,
    PAIRS,
    QUANT_SIGMA2_Q2,
    QUANT_V_Q2,
)
from ae_tactile.localization.noise_model import MIN_PRE_SAMPLES, PSD_FLOOR, WHITE_TEST
from ae_tactile.localization.pairs import segment_taper

_XI = np.array([1.0, 1.0, -1.0, -1.0])
_ETA = np.array([1.0, -1.0, 1.0, -1.0])
_PAIR_I = PAIRS[:, 0].astype(np.int64).copy()
_PAIR_J = PAIRS[:, 1].astype(np.int64).copy()
_PINV = np.ascontiguousarray(PAIR_PINV)  # (3, 6)
_ALPHAS = np.array([0.5, 0.25, 0.125, 0.0])
ALIAS_GUARD = 10 ** (ALIAS_GUARD_DB / 10)

# Reason bits (common.Reason).
_NONFINITE, _NO_SIGNAL, _WINDOW, _SATURATED, _LOW_SNR, _OVERLAP, _OUT_OF_RANGE = (
    1,
    2,
    3,
    4,
    5,
    6,
    7,
)

#: Number of outputs per packet of the kernel, for the result builders.
N_SCALAR_OUT = 16


class Tables:
    """Per-plan constants of the kernel (DFT tables over the band bins, lag tables)."""

    def __init__(self, plan):
        n, n_al, L = plan.n_fft, plan.n_fft_al, plan.seg_len
        kc = np.nonzero(plan.band)[0]
        ka = np.nonzero(plan.band_al)[0]
        nn = np.arange(L)
        ph = 2 * np.pi * np.outer(kc, nn) / n
        self.cc, self.sc = np.cos(ph), np.sin(ph)  # (nbc, L)
        ph = 2 * np.pi * np.outer(ka, nn) / n_al
        win = segment_taper(L)  # the aligned segments' taper (pairs.aligned_spectra)
        self.ca, self.sa = np.cos(ph) * win, np.sin(ph) * win  # (nba, L)
        self.wa = 2 * np.pi * ka * plan.fs / n_al
        # band bin frequencies exactly as the numpy path computes them (band edge tests)
        self.fc = plan.w / (2 * np.pi)
        self.fa = plan.w_al / (2 * np.pi)
        self.auto = np.array([plan.auto_fallback_hz, 1.0 if self.fc[-1] >= 0.4 * plan.fs else 0.0])
        lmax = int(plan.max_lag.max())
        lags = np.arange(-lmax - 1, lmax + 2)  # +-1 beyond for the parabola
        ph = 2 * np.pi * np.outer(lags, kc) / n
        wt = np.where(2 * kc == n, 1.0, 2.0) / n  # irfft weights of the bins
        self.lc, self.ls = np.cos(ph) * wt, np.sin(ph) * wt  # (n_lags, nbc)
        self.lag0 = lmax + 1  # row of lag 0
        self.max_lag = plan.max_lag.astype(np.int64)
        g = plan.geometry
        self.geo = np.array([g.radius_m, g.element_offset_m, g.sound_speed_m_s])
        ints = [
            plan.pre,
            L,
            plan.snr_len,
            plan.flat_run,
            int(plan.max_lag.max()) + 2,
            int(math.ceil(3e-6 * plan.fs)),
            int(math.ceil(1.5e-6 * plan.fs)) + 1,
            n_al,
        ]
        self.ints = np.array(ints, dtype=np.int64)
        self.fs = float(plan.fs)
        # One Newton step is worth about one sample of delay at most (ml.estimate).
        self.max_step = g.radius_m * g.sound_speed_m_s / (g.element_offset_m * plan.fs)
        self.packed = (
            self.cc,
            self.sc,
            self.ca,
            self.sa,
            self.wa,
            self.lc,
            self.ls,
            self.max_lag,
            self.geo,
            self.ints,
            self.fc,
            self.fa,
            self.auto,
            np.array([self.fs, self.max_step, float(self.lag0), float(win @ win / L)]),
        )


_TABLES: dict = {}


def tables_for(plan) -> Tables:
    """Cached `Tables` of a plan (plans are themselves cached by `make_plan`)."""
    key = id(plan)
    hit = _TABLES.get(key)
    if hit is not None and hit[0] is plan:
        return hit[1]
    if len(_TABLES) > 64:
        _TABLES.clear()
    t = Tables(plan)
    _TABLES[key] = (plan, t)
    return t


# --------------------------------------------------------------------------- geometry
@njit(cache=True, nogil=True)
def _times(geo, sx, sy, t):
    r, a, c = geo[0], geo[1], geo[2]
    base = r * r + 2.0 * a * a
    t[0] = math.sqrt(base - 2.0 * a * (sx + sy)) / c
    t[1] = math.sqrt(base - 2.0 * a * (sx - sy)) / c
    t[2] = math.sqrt(base - 2.0 * a * (-sx + sy)) / c
    t[3] = math.sqrt(base - 2.0 * a * (-sx - sy)) / c


@njit(cache=True, nogil=True)
def _project(r, sx, sy):
    rho = math.hypot(sx, sy)
    lim = r * (1.0 - 1e-9)
    if rho > lim:
        f = lim / rho if rho > 0 else 1.0
        return sx * f, sy * f, True
    return sx, sy, False


@njit(cache=True, nogil=True)
def _jacobian(geo, sx, sy):
    """d(tau_x, tau_y)/d(s_x, s_y): (diag, off) (geometry.delay_jacobian)."""
    t = np.empty(4)
    _times(geo, sx, sy, t)
    k = geo[1] / (4.0 * geo[2])
    c = geo[2]
    diag = 0.0
    off = 0.0
    for i in range(4):
        inv = 1.0 / (t[i] * c)
        diag += inv
        off += _XI[i] * _ETA[i] * inv
    return k * diag, k * off


@njit(cache=True, nogil=True)
def _point_from_delays(geo, tx, ty):
    """Exact inversion, clamped onto the horizon (geometry.point_from_delays)."""
    r, a, c = geo[0], geo[1], geo[2]
    scale = c * r / a
    sx, sy, over = _project(r, tx * scale, ty * scale)
    t = np.empty(4)
    for _ in range(8):
        _times(geo, sx, sy, t)
        px = -(t[0] + t[1] - t[2] - t[3]) / 4.0
        py = -(t[0] - t[1] + t[2] - t[3]) / 4.0
        jd, jo = _jacobian(geo, sx, sy)
        rx, ry = tx - px, ty - py
        det = jd * jd - jo * jo
        dx = (jd * rx - jo * ry) / det
        dy = (jd * ry - jo * rx) / det
        sx, sy, over = _project(r, sx + dx, sy + dy)
        if not (abs(dx) + abs(dy) > 1e-13 * r):
            break
    if not (math.isfinite(sx) and math.isfinite(sy)):
        return 0.0, 0.0, True
    return sx, sy, over


# --------------------------------------------------------------------------- spectra


@njit(cache=True, nogil=True)
def _adc_noise(var, quant2, given):
    """common.adc_noise for one packet: sigma^2 + q^2/12 (quant2 = q^2/12), a measured
    quantized variance inverted through the mid-tread table."""
    if given:
        return var + quant2
    if quant2 <= 0.0:
        return var
    q2 = 12.0 * quant2
    v = var / q2
    if v <= QUANT_V_Q2[-1]:
        s2 = np.interp(v, QUANT_V_Q2, QUANT_SIGMA2_Q2)
    else:
        s2 = v - 1.0 / 12.0
    return (s2 + 1.0 / 12.0) * q2


@njit(cache=True, nogil=True)
def _noise_acov(x, n_pre, pre_mean, L):
    """noise_model.pre_onset_autocov of one packet: the lag-windowed, shrunk
    autocovariance (P + 1,) of its pre-onset samples; empty when it has too few."""
    if n_pre < MIN_PRE_SAMPLES:
        return np.empty(0)
    p = max(1, min(n_pre // 3, L // 2))
    out = np.zeros(p + 1)
    n = float(max(n_pre, 1))
    for lag in range(p + 1):
        r = 0.0
        for k in range(4):
            mu = pre_mean[k]
            for i in range(n_pre - lag):
                r += (x[k, i + lag] - mu) * (x[k, i] - mu)
        out[lag] = r / (4.0 * n)
    r0 = out[0]
    q = 0.0
    for lag in range(1, p + 1):
        r = out[lag]
        rho2 = r * r / max(r0 * r0, 1e-300)
        q += 4.0 * n * rho2
        out[lag] = r * (rho2 / (rho2 + 1.0 / (4.0 * n))) * (1.0 - lag / (p + 1.0))
    if not q > p + WHITE_TEST * math.sqrt(2.0 * p):
        for lag in range(1, p + 1):
            out[lag] = 0.0
    return out


@njit(cache=True, nogil=True)
def _noise_gains(acov, f_hz, fs, out):
    """noise_model.whitening_gains of one packet at the bins f_hz [Hz] into out."""
    p = acov.shape[0] - 1
    ok = p >= 1 and acov[0] > 0 and math.isfinite(acov[0])
    for j in range(f_hz.shape[0]):
        if not ok:
            out[j] = 1.0
            continue
        # cos(l th) by the Chebyshev recurrence: one cosine per bin
        c1 = math.cos(2.0 * math.pi * f_hz[j] / fs)
        cm, cl = 1.0, c1
        sh = 1.0
        for lag in range(1, p + 1):
            sh += 2.0 * (acov[lag] / acov[0]) * cl
            cm, cl = cl, 2.0 * c1 * cl - cm
        out[j] = 1.0 / math.sqrt(max(sh, PSD_FLOOR))


@njit(cache=True, nogil=True)
def _gather(x, m, start, L, base, seg, count, k):
    """seg[k] = x[k, start:start+L] - base, zero outside the window; returns inside count."""
    cnt = 0
    for n in range(L):
        i = start + n
        if 0 <= i < m:
            seg[k, n] = x[k, i] - base
            cnt += 1
        else:
            seg[k, n] = 0.0
    count[k] = cnt


_FM = {"reassoc", "contract"}  # vectorisable sums; NaN / inf semantics kept


@njit(cache=True, nogil=True, fastmath=_FM)
def _dft(seg, cos_t, sin_t, out):
    """out[k, f] = sum_n seg[k, n] e^{-j phase[f, n]} (band bins only); the four channels
    share each table row (one pass over the tables)."""
    nb, L = cos_t.shape
    for f in range(nb):
        r0 = r1 = r2 = r3 = 0.0
        i0 = i1 = i2 = i3 = 0.0
        for n in range(L):
            c = cos_t[f, n]
            s = sin_t[f, n]
            v0, v1, v2, v3 = seg[0, n], seg[1, n], seg[2, n], seg[3, n]
            r0 += v0 * c
            r1 += v1 * c
            r2 += v2 * c
            r3 += v3 * c
            i0 -= v0 * s
            i1 -= v1 * s
            i2 -= v2 * s
            i3 -= v3 * s
        out[0, f] = complex(r0, i0)
        out[1, f] = complex(r1, i1)
        out[2, f] = complex(r2, i2)
        out[3, f] = complex(r3, i3)


@njit(cache=True, nogil=True)
def _srp(yb, w, t, c0, z):
    """P = sum_f |sum_k Yb e^{j w (t_k - c_k)}|^2; z[k, f] receives the shifted spectra.

    The band bins are evenly spaced (w_f = w_0 + f dw): e^{j w_f e} by recurrence, two
    trigonometric calls per channel."""
    nb = w.shape[0]
    dw = w[1] - w[0] if nb > 1 else 0.0
    for k in range(4):
        e = t[k] - c0[k]
        ph = complex(math.cos(w[0] * e), math.sin(w[0] * e))
        st = complex(math.cos(dw * e), math.sin(dw * e))
        for f in range(nb):
            z[k, f] = yb[k, f] * ph
            ph *= st
    p = 0.0
    for f in range(nb):
        br = z[0, f].real + z[1, f].real + z[2, f].real + z[3, f].real
        bi = z[0, f].imag + z[1, f].imag + z[2, f].imag + z[3, f].imag
        p += br * br + bi * bi
    return p


@njit(cache=True, nogil=True)
def _newton(yb, w, geo, sx, sy, c0, iterations, max_step, tol):
    r, a, c = geo[0], geo[1], geo[2]
    nb = w.shape[0]
    t = np.empty(4)
    z = np.empty((4, nb), np.complex128)
    zt = np.empty((4, nb), np.complex128)
    ge = np.empty(4)
    he = np.empty((4, 4))
    dt = np.empty((4, 2))
    clamped = False
    for _ in range(iterations):
        _times(geo, sx, sy, t)
        p_old = _srp(yb, w, t, c0, z)
        for k in range(4):
            dk = t[k] * c
            dt[k, 0] = -a / c * _XI[k] / dk
            dt[k, 1] = -a / c * _ETA[k] / dk
        for k in range(4):
            g = 0.0
            hk = 0.0
            for f in range(nb):
                br = 0.0
                bi = 0.0
                for j in range(4):
                    br += z[j, f].real
                    bi += z[j, f].imag
                # conj(b) z_k
                cr = br * z[k, f].real + bi * z[k, f].imag
                ci = br * z[k, f].imag - bi * z[k, f].real
                g += w[f] * ci
                hk += w[f] * w[f] * cr
            ge[k] = -2.0 * g
            he[k, k] = -2.0 * hk
        for i in range(4):
            for j in range(i, 4):
                s = 0.0
                for f in range(nb):
                    s += w[f] * w[f] * (z[i, f].real * z[j, f].real + z[i, f].imag * z[j, f].imag)
                if i == j:
                    he[i, i] += 2.0 * s
                else:
                    he[i, j] = 2.0 * s
                    he[j, i] = 2.0 * s
        g0 = 0.0
        g1 = 0.0
        h00 = 0.0
        h01 = 0.0
        h11 = 0.0
        for i in range(4):
            g0 += dt[i, 0] * ge[i]
            g1 += dt[i, 1] * ge[i]
            for j in range(4):
                h00 += dt[i, 0] * he[i, j] * dt[j, 0]
                h01 += dt[i, 0] * he[i, j] * dt[j, 1]
                h11 += dt[i, 1] * he[i, j] * dt[j, 1]
            dk = t[i] * c
            f2 = ge[i] * (-a * a / c) / (dk * dk * dk)
            h00 += f2
            h01 += f2 * _XI[i] * _ETA[i]
            h11 += f2
        mid = 0.5 * (h00 + h11)
        rad = math.sqrt(0.25 * (h00 - h11) ** 2 + h01 * h01)
        lmax, lmin = mid + rad, mid - rad
        scale = abs(h00) + abs(h11) + 1e-300
        mu = lmax + 0.1 * abs(lmin) + 1e-3 * scale if lmax > -1e-6 * scale else 0.0
        h00 -= mu
        h11 -= mu
        det = h00 * h11 - h01 * h01
        if not abs(det) > 0:
            det = 1e-300
        stx = -(h11 * g0 - h01 * g1) / det
        sty = -(h00 * g1 - h01 * g0) / det
        norm = math.hypot(stx, sty)
        f = max_step / norm if norm > max_step else 1.0
        if math.isfinite(stx):
            stx *= f
        else:
            stx = 0.0
        if math.isfinite(sty):
            sty *= f
        else:
            sty = 0.0
        taken = norm * f if math.isfinite(norm) else 0.0
        nx, ny, over = _project(r, sx + stx, sy + sty)
        _times(geo, nx, ny, t)
        p_new = _srp(yb, w, t, c0, zt)
        if not (p_new >= p_old):
            best = -1.0
            bx, by, bo, ba = sx, sy, False, 0.0
            for ia in range(4):
                al = _ALPHAS[ia]
                cx, cy, ov = _project(r, sx + al * stx, sy + al * sty)
                _times(geo, cx, cy, t)
                pc = _srp(yb, w, t, c0, zt)
                if pc > best or ia == 0:
                    best = pc
                    bx, by, bo, ba = cx, cy, ov, al
            nx, ny, over = bx, by, bo
            taken *= ba
        sx, sy, clamped = nx, ny, over
        if not (taken >= tol):
            break
    return sx, sy, clamped


@njit(cache=True, nogil=True)
def _aligned(x, m, seg_start, t, fs, max_shift, L, pre_mean, ca, sa, seg, count, yb, c0,
             gains):
    """pairs.aligned_spectra of one packet: segments cut at the integer arrivals, the
    tapered DFT (the taper is in ca, sa), band bins whitened by ``gains``."""
    ref = min(min(t[0], t[1]), min(t[2], t[3]))
    for k in range(4):
        sh = np.rint((t[k] - ref) * fs)
        sh = min(max(sh, 0.0), float(max_shift))
        c0[k] = ref + sh / fs
        _gather(x, m, seg_start + int(sh), L, pre_mean[k], seg, count, k)
    _dft(seg, ca, sa, yb)
    for k in range(4):
        for f in range(yb.shape[1]):
            yb[k, f] *= gains[f]


@njit(cache=True, nogil=True)
def _cut_delayed(x, m, seg_start, t, fs, max_shift, L, pre_mean, ca, sa, seg, count, yb, c0,
                 gains, cdel):
    """`_aligned` at the arrivals t_k + cdel[k] (the channels' own delays [s]); c0 is
    returned less cdel, so that eps_k = t_k - c0[k] everywhere after (t unchanged)."""
    for k in range(4):
        t[k] += cdel[k]
    _aligned(x, m, seg_start, t, fs, max_shift, L, pre_mean, ca, sa, seg, count, yb, c0, gains)
    for k in range(4):
        t[k] -= cdel[k]
        c0[k] -= cdel[k]


@njit(cache=True, nogil=True)
def _polarity(seg, e, pre, stop_s, span, b):
    """Sign and signed amplitude of the first lobe of the aligned mean b[n] = mean_k
    y_k(n + e_k) (4-point Lagrange interpolation, e_k in samples); events.py."""
    L = seg.shape[1]
    b[:] = 0.0
    for k in range(4):
        i0 = int(math.floor(e[k]))
        u = e[k] - i0
        wt = (
            -u * (u - 1.0) * (u - 2.0) / 6.0,
            (u + 1.0) * (u - 1.0) * (u - 2.0) / 2.0,
            -(u + 1.0) * u * (u - 2.0) / 2.0,
            (u + 1.0) * u * (u - 1.0) / 6.0,
        )
        for o in range(4):
            sh = i0 + o - 1
            wo = wt[o]
            for n in range(max(0, -sh), min(L, L - sh)):
                b[n] += wo * seg[k, n + sh]
    peak = 0.0
    for n in range(L):
        b[n] *= 0.25
        if abs(b[n]) > peak:
            peak = abs(b[n])
    stop = min(L, pre + stop_s + 1)
    first = -1
    for n in range(stop):
        if abs(b[n]) >= 0.5 * peak:
            first = n
            break
    if first < 0:
        best = -1.0
        for n in range(L):
            if abs(b[n]) > best:
                best = abs(b[n])
                first = n
    if not (peak > 0):
        return 0.0, 0.0
    pol = 1.0 if b[first] > 0 else (-1.0 if b[first] < 0 else 0.0)
    amp = -np.inf
    for j in range(span):
        i = min(max(first + j, 0), L - 1)
        amp = max(amp, b[i] * pol)
    return pol, pol * amp


@njit(cache=True, nogil=True, fastmath=_FM)
def _corr_at(gr, gi, lc, ls, row):
    """r(d) = sum_f Re(G_f e^{j w_f d}) (irfft weights in the tables) at lag row ``row``;
    only the first len(gr) bins."""
    rr = 0.0
    for f in range(gr.shape[0]):
        rr += gr[f] * lc[row, f] - gi[f] * ls[row, f]
    return rr


@njit(cache=True, nogil=True)
def _peak_lag(gr, gi, lc, ls, lag0, ml_):
    """Integer lag of the largest r(d) within |d| <= ml_, numpy's order on ties (lags
    0..max, then -max..-1: the first maximum wins)."""
    best = -np.inf
    best_lag = 0
    for q_ in range(2 * ml_ + 1):
        lag = q_ if q_ <= ml_ else q_ - 2 * ml_ - 1
        rr = _corr_at(gr, gi, lc, ls, lag0 + lag)
        if rr > best:
            best = rr
            best_lag = lag
    return best, best_lag


# --------------------------------------------------------------------------- kernel
@njit(cache=True, nogil=True)
def prepare_packet(xin, onset, noise_rms, sat_in, full_scale, gains, has_gains, gain_rms, pre,
                   L, flat_run):
    """`common.prepare` of one packet (xin (4, m), any float dtype): non-finite samples,
    window, saturation (sat_in > 0 / == 0 flagged by the caller, < 0 unknown: full scale,
    else flat top), channel gains, per-packet scale, pre-onset noise and baselines, ADC
    quantum. noise_rms: the known sigma (V), NaN if measured. Returns (x (4, m) scaled,
    raw (4, L) coarse segment, pre_mean (4,), flags, onset, seg_start, scale, sigma2
    (units^2, before `_adc_noise`), given, quant2)."""
    m = xin.shape[1]
    x = np.empty((4, m))
    flags = 0
    bad = False
    for k in range(4):
        for i in range(m):
            v = float(xin[k, i])
            if not math.isfinite(v):
                v = 0.0
                bad = True
            x[k, i] = v
    if bad:
        flags |= 1 << _NONFINITE
    on = onset
    if on < 0 or on >= m:
        flags |= 1 << _WINDOW
    on = min(max(on, 0), m - 1)
    if (m - on) < max(4, (L - pre) // 4):
        flags |= 1 << _WINDOW
    seg_start = on - pre
    sat = sat_in > 0
    if math.isfinite(full_scale):
        lim = full_scale * (1.0 - 1e-3)
        for k in range(4):
            for n in range(L):
                i = min(max(seg_start + n, 0), m - 1)
                if abs(x[k, i]) >= lim:
                    sat = True
    if has_gains:
        for k in range(4):
            for i in range(m):
                x[k, i] /= gains[k]
    dev = 0.0
    for k in range(4):
        x0 = x[k, 0]
        for i in range(m):
            x[k, i] -= x0
            dev = max(dev, abs(x[k, i]))
    if not math.isfinite(dev):
        x[:, :] = 0.0
        flags |= 1 << _NONFINITE
        dev = 0.0
    scale = dev if dev > 0 else 1.0
    inv = 1.0 / scale
    for k in range(4):
        for i in range(m):
            x[k, i] *= inv
    # noise from the pre-onset samples [0, seg_start)
    n_pre = min(max(seg_start, 0), m)
    pre_mean = np.zeros(4)
    sigma2 = 0.0
    for k in range(4):
        s1 = 0.0
        s2 = 0.0
        for i in range(n_pre):
            s1 += x[k, i]
            s2 += x[k, i] * x[k, i]
        nn = max(n_pre, 1)
        mu = s1 / nn
        sigma2 += max(s2 - nn * mu * mu, 0.0) / max(nn - 1, 1)
        pre_mean[k] = mu
    sigma2 /= 4.0
    if n_pre < 4:
        sigma2 = np.nan
    given = math.isfinite(noise_rms)
    if given:
        nr = noise_rms
        if has_gains:
            nr /= gain_rms
        nr *= inv
        sigma2 = nr * nr
    # coarse segment: raw (edge-clipped) for the checks, baseline-removed for the spectra
    raw = np.empty((4, L))
    const = False
    q = np.inf
    for k in range(4):
        vmax = -np.inf
        vmin = np.inf
        for n in range(L):
            v = x[k, min(max(seg_start + n, 0), m - 1)]
            raw[k, n] = v
            vmax = max(vmax, v)
            vmin = min(vmin, v)
            if n > 0:
                d = abs(v - raw[k, n - 1])
                if d > 0 and d < q:
                    q = d
        if vmax == vmin:
            const = True
    if const:
        flags |= 1 << _NO_SIGNAL
    if sat_in < 0 and not math.isfinite(full_scale) and L >= flat_run:
        for k in range(4):
            vmax = -np.inf
            vmin = np.inf
            mean = 0.0
            for n in range(L):
                vmax = max(vmax, raw[k, n])
                vmin = min(vmin, raw[k, n])
                mean += raw[k, n]
            mean /= L
            if not (vmax > vmin):
                continue
            v = vmax if vmax - mean >= mean - vmin else vmin
            run = 0
            for n in range(L):
                run = run + 1 if raw[k, n] == v else 0
                if run >= flat_run:
                    sat = True
                    break
    if sat:
        flags |= 1 << _SATURATED
    if n_pre < 4:
        for k in range(4):
            s = 0.0
            for n in range(L):
                s += raw[k, n]
            pre_mean[k] = s / L
    quant2 = q * q / 12.0 if math.isfinite(q) else 0.0
    return x, raw, pre_mean, flags, on, seg_start, scale, sigma2, given, quant2


@njit(cache=True, nogil=True)
def _packet(
    xin,
    onset,
    noise_rms,
    sat_in,
    full_scale,
    gains,
    has_gains,
    gain_rms,
    tabs,
    iterations,
    min_snr_db,
    thr,
    out,
    pt,
    cov,
    ctau,
    cdel,
    cnoise,
):
    """One packet. out: 16 scalars (see estimators.PacketLocation); pt (3,), cov (3, 3),
    ctau (2, 2). tabs: `Tables.packed`. cdel (4,): the channels' own delays [s] (each
    arrival is modelled t_k(s) + cdel[k]; zeros: none). cnoise (2,): the device's delay
    noise, (scale of the model's tau covariance, variance [s^2] added to tau_x and tau_y;
    `channel_delays.fit_delay_noise`; (1, 0): the model's)."""
    cc, sc, ca, sa, wa, lc, ls, max_lag, geo, ints, fc, fa, auto, scal = tabs
    fs, max_step, lag0, win2 = scal[0], scal[1], int(scal[2]), scal[3]
    pre, L, snr_len, flat_run, max_shift, stop_s, span, n_al = (
        ints[0],
        ints[1],
        ints[2],
        ints[3],
        ints[4],
        ints[5],
        ints[6],
        ints[7],
    )
    r_sph, a_el, c_snd = geo[0], geo[1], geo[2]
    m = xin.shape[1]
    x, raw, pre_mean, flags, on, seg_start, scale, sigma2, given, quant2 = prepare_packet(
        xin, onset, noise_rms, sat_in, full_scale, gains, has_gains, gain_rms, pre, L, flat_run
    )
    seg = np.empty((4, L))
    count = np.empty(4, np.int64)
    for k in range(4):
        _gather(x, m, seg_start, L, pre_mean[k], seg, count, k)
    # SNR window power
    w_len = min(snr_len, m)
    s0 = min(on, m - w_len)
    p_total = 0.0
    for k in range(4):
        for i in range(s0, s0 + w_len):
            v = x[k, i] - pre_mean[k]
            p_total += v * v
    p_total /= 4.0 * w_len

    # ---- start: pair cross-correlations over the possible lags
    nbc = cc.shape[0]
    xb = np.empty((4, nbc), np.complex128)
    _dft(seg, cc, sc, xb)
    # the noise's colour from the pre-onset samples (noise_model): whitened band bins
    acov = _noise_acov(x, min(max(seg_start, 0), m), pre_mean, L)
    gc = np.empty(nbc)
    _noise_gains(acov, fc, fs, gc)
    for k in range(4):
        for f in range(nbc):
            xb[k, f] *= gc[f]
    # data-driven band (common.band_edge_hz): bins up to each packet's own edge
    nbc_u = nbc
    nba_u = wa.shape[0]
    if auto[0] > 0:
        edge = auto[0]
        s2e = sigma2
        if math.isfinite(s2e):
            s2e = _adc_noise(s2e, quant2, given)
            n0 = (count[0] + count[1] + count[2] + count[3]) * s2e
            last = 0
            sm_max = 0.0
            sm = 0.0
            for f in range(nbc):
                acc = 0.0
                nacc = 0
                for f2 in range(max(f - 1, 0), min(f + 2, nbc)):
                    for k in range(4):
                        acc += xb[k, f2].real ** 2 + xb[k, f2].imag ** 2
                    nacc += 1
                sm = acc / nacc
                sm_max = max(sm_max, sm)
                if sm > BAND_EDGE_POWER_RATIO * n0:
                    last = f
            last = max(last, min(3, nbc - 1))
            edge = fc[last]
            if auto[1] > 0 and last == nbc - 1 and sm > ALIAS_GUARD * sm_max:
                edge = min(edge, 0.25 * fs)
        # the pair start needs the integer lag only: bins up to min(edge, fallback edge)
        nbc_u = 0
        while nbc_u < nbc and fc[nbc_u] <= min(edge, auto[0]):
            nbc_u += 1
        nba_u = 0
        while nba_u < wa.shape[0] and fa[nba_u] <= edge:
            nba_u += 1
    d6 = np.empty(6)
    gr = np.empty(nbc_u)
    gi = np.empty(nbc_u)
    at_edge = False
    for p in range(6):
        i, j = _PAIR_I[p], _PAIR_J[p]
        for f in range(nbc_u):
            g = xb[i, f] * xb[j, f].conjugate()
            gr[f] = g.real
            gi[f] = g.imag
        ml_ = max_lag[p]
        best, best_lag = _peak_lag(gr, gi, lc, ls, lag0, ml_)
        if abs(best_lag) >= ml_:
            at_edge = True
        ym = _corr_at(gr, gi, lc, ls, lag0 + best_lag - 1)
        yp = _corr_at(gr, gi, lc, ls, lag0 + best_lag + 1)
        den = ym - 2 * best + yp
        frac = 0.5 * (ym - yp) / den if den < 0 else 0.0
        frac = min(max(frac, -0.5), 0.5)
        d6[p] = (best_lag + frac) / fs - (cdel[i] - cdel[j])  # the channels' own delays out
    th0 = np.zeros(3)
    for r_ in range(3):
        for p in range(6):
            th0[r_] += _PINV[r_, p] * d6[p]
    pres = 0.0
    for p in range(6):
        i, j = _PAIR_I[p], _PAIR_J[p]
        ri = -_XI[i] * th0[0] - _ETA[i] * th0[1] + _XI[i] * _ETA[i] * th0[2]
        rj = -_XI[j] * th0[0] - _ETA[j] * th0[1] + _XI[j] * _ETA[j] * th0[2]
        e = d6[p] - (ri - rj)
        pres += e * e
    pres = math.sqrt(pres / 6.0)
    sx, sy, _ = _point_from_delays(geo, th0[0], th0[1])

    # ---- fit
    t = np.empty(4)
    _times(geo, sx, sy, t)
    nba = nba_u
    ca = ca[:nba]
    sa = sa[:nba]
    wa = wa[:nba]
    yb = np.empty((4, nba), np.complex128)
    c0 = np.empty(4)
    cnt_al = np.empty(4, np.int64)
    ga = np.empty(nba)
    _noise_gains(acov, fa[:nba], fs, ga)
    _cut_delayed(x, m, seg_start, t, fs, max_shift, L, pre_mean, ca, sa, seg, cnt_al, yb, c0,
                 ga, cdel)
    tol = 1e-4 * max_step
    sx, sy, clamped = _newton(yb, wa, geo, sx, sy, c0, iterations, max_step, tol)
    _times(geo, sx, sy, t)
    em = 0.25 * (t[0] - c0[0] + t[1] - c0[1] + t[2] - c0[2] + t[3] - c0[3])
    drift = 0.0
    for k in range(4):
        drift = max(drift, abs(t[k] - c0[k] - em))
    if drift * fs >= 0.75:
        _cut_delayed(x, m, seg_start, t, fs, max_shift, L, pre_mean, ca, sa, seg, cnt_al, yb,
                     c0, ga, cdel)
        sx, sy, clamped = _newton(yb, wa, geo, sx, sy, c0, iterations, max_step, tol)
    _times(geo, sx, sy, t)
    zb = np.empty((4, nba), np.complex128)
    _srp(yb, wa, t, c0, zb)
    sz = math.sqrt(max(r_sph * r_sph - sx * sx - sy * sy, 0.0))
    tau_x = -(t[0] + t[1] - t[2] - t[3]) / 4.0
    tau_y = -(t[0] - t[1] + t[2] - t[3]) / 4.0
    twist = (t[0] - t[1] - t[2] + t[3]) / 4.0

    # ---- finish: misfit, noise, SNR
    res_e = 0.0
    tot_e = 0.0
    bb2 = np.empty(nba)
    for f in range(nba):
        bm = 0.25 * (zb[0, f] + zb[1, f] + zb[2, f] + zb[3, f])
        bb2[f] = bm.real * bm.real + bm.imag * bm.imag
        for k in range(4):
            dz = zb[k, f] - bm
            res_e += dz.real * dz.real + dz.imag * dz.imag
            tot_e += zb[k, f].real * zb[k, f].real + zb[k, f].imag * zb[k, f].imag
    mis = min(max(res_e / max(tot_e, 1e-300), 0.0), 1.0)
    # noise energy per bin of the tapered segments, in samples (pairs.aligned_spectra)
    Lm = 0.25 * (cnt_al[0] + cnt_al[1] + cnt_al[2] + cnt_al[3]) * win2
    if not math.isfinite(sigma2):
        sigma2 = res_e / max(3.0 * nba * Lm, 1.0)
    else:
        sigma2 = _adc_noise(sigma2, quant2, given)  # ADC rounding (common.adc_noise)
    sigma2 = max(sigma2, 1e-12 * max(p_total, 0.0) + 1e-300)
    p_sig = max(p_total - sigma2, 1e-300)
    snr = min(max(10.0 * math.log10(p_sig / sigma2), -100.0), 120.0)
    if snr < min_snr_db:
        flags |= 1 << _LOW_SNR
    excess = mis - 3.0 * nba * Lm * sigma2 / max(tot_e, 1e-300)
    if not math.isfinite(excess):
        excess = 1.0
    if excess > thr:
        flags |= 1 << _OVERLAP

    # ---- covariance (covariance.arrival_fisher, sphere_covariance)
    e = np.empty(4)
    emax = 0.0
    for k in range(4):
        s = 0.0
        for f in range(nba):
            s += zb[k, f].real * zb[k, f].real + zb[k, f].imag * zb[k, f].imag
        e[k] = s - nba * Lm * sigma2
        emax = max(emax, abs(e[k]))
    esum = 0.0
    for k in range(4):
        e[k] = max(e[k], 1e-12 * emax + 1e-300)
        esum += e[k]
    emean = max(esum / 4.0, 1e-300)
    e_mean = 0.0
    sw2 = 0.0
    for f in range(nba):
        e_mean += wa[f] * wa[f] * max(bb2[f] - Lm * sigma2 / 4.0, 0.0)
        sw2 += wa[f] * wa[f]
    kappa = 0.5 * Lm * sigma2 * sw2 / max(e_mean, 1e-300)  # noise-by-noise share
    e_mean *= 2.0 / n_al
    e_mean /= 1.0 + kappa
    ee = np.empty(4)
    esum = 0.0
    for k in range(4):
        ee[k] = min(max(e[k] / emean, 0.1), 10.0) * e_mean
        esum += ee[k]
    esum = max(esum, 1e-300)
    dt = np.empty((4, 2))
    for k in range(4):
        dk = t[k] * c_snd
        dt[k, 0] = -a_el / c_snd * _XI[k] / dk
        dt[k, 1] = -a_el / c_snd * _ETA[k] / dk
    f00 = 0.0
    f01 = 0.0
    f11 = 0.0
    for i in range(4):
        for j in range(4):
            fij = ((ee[i] if i == j else 0.0) - ee[i] * ee[j] / esum) / sigma2
            f00 += dt[i, 0] * fij * dt[j, 0]
            f01 += dt[i, 0] * fij * dt[j, 1]
            f11 += dt[i, 1] * fij * dt[j, 1]
    det = f00 * f11 - f01 * f01
    cov_ok = math.isfinite(det) and det > 1e-30 * max(f00 * f11, 1e-300) and f00 > 0 and f11 > 0
    jd, jo = _jacobian(geo, sx, sy)
    if cov_ok:
        c00, c01, c11 = f11 / det, -f01 / det, f00 / det
        # C_tau = J C_xy J^T, J = [[jd, jo], [jo, jd]]
        a0 = jd * c00 + jo * c01
        a1 = jd * c01 + jo * c11
        b0 = jo * c00 + jd * c01
        b1 = jo * c01 + jd * c11
        t00 = a0 * jd + a1 * jo
        t01 = a0 * jo + a1 * jd
        t11 = b0 * jo + b1 * jd
        cov_ok = math.isfinite(t00) and math.isfinite(t01) and math.isfinite(t11)
        t00 = cnoise[0] * t00 + cnoise[1]
        t01 = cnoise[0] * t01
        t11 = cnoise[0] * t11 + cnoise[1]
    else:
        t00 = t01 = t11 = 0.0
    # ---- horizon check on the start's delays
    sd = math.sqrt(max(t00 + t11, 0.0)) if cov_ok else 0.0
    phi = math.atan2(th0[1], th0[0])
    hx, hy, hz = r_sph * math.cos(phi), r_sph * math.sin(phi), r_sph * math.cos(math.pi / 2)
    th = np.empty(4)
    for k in range(4):
        dx = hx - _XI[k] * a_el
        dy = hy - _ETA[k] * a_el
        th[k] = math.sqrt(dx * dx + dy * dy + hz * hz) / c_snd
    htx = -(th[0] + th[1] - th[2] - th[3]) / 4.0
    hty = -(th[0] - th[1] + th[2] - th[3]) / 4.0
    over = math.hypot(th0[0], th0[1]) - math.hypot(htx, hty) > 4.0 * sd + 0.25 / fs
    if over or at_edge:
        flags |= 1 << _OUT_OF_RANGE
    finite_pt = math.isfinite(sx) and math.isfinite(sy) and math.isfinite(tau_x)
    if not finite_pt:
        sx, sy, sz = 0.0, 0.0, r_sph
        tau_x = tau_y = twist = 0.0
        if flags == 0:
            flags |= 1 << _OUT_OF_RANGE
    cov_fin = finite_pt and cov_ok
    if not cov_fin:
        md = a_el / c_snd
        t00, t01, t11 = md * md, 0.0, md * md
    ctau[0, 0], ctau[0, 1], ctau[1, 0], ctau[1, 1] = t00, t01, t01, t11
    # point covariance (geometry.point_covariance)
    jd, jo = _jacobian(geo, sx, sy)
    dj = jd * jd - jo * jo
    i00, i01 = jd / dj, -jo / dj
    a0 = i00 * t00 + i01 * t01
    a1 = i00 * t01 + i01 * t11
    b0 = i01 * t00 + i00 * t01
    b1 = i01 * t01 + i00 * t11
    x00 = a0 * i00 + a1 * i01
    x01 = a0 * i01 + a1 * i00
    x11 = b0 * i01 + b1 * i00
    szc = max(sz, 1e-6 * r_sph)
    g0, g1 = -sx / szc, -sy / szc
    cov[0, 0], cov[0, 1], cov[1, 1] = x00, x01, x11
    cov[0, 2] = x00 * g0 + x01 * g1
    cov[1, 2] = x01 * g0 + x11 * g1
    cov[2, 2] = g0 * (x00 * g0 + x01 * g1) + g1 * (x01 * g0 + x11 * g1)
    cov[1, 0], cov[2, 0], cov[2, 1] = cov[0, 1], cov[0, 2], cov[1, 2]
    good = cov_fin
    for i in range(3):
        for j in range(3):
            if not math.isfinite(cov[i, j]):
                good = False
    big = r_sph * r_sph
    for i in range(3):
        for j in range(3):
            v = cov[i, j] if good else (big if i == j else 0.0)
            cov[i, j] = min(max(v, -1e3 * big), 1e3 * big)
    # ---- polarity, amplitude
    eps = np.empty(4)
    for k in range(4):
        eps[k] = (t[k] - c0[k]) * fs
    bbuf = np.empty(L)
    pol, amp = _polarity(seg, eps, pre, stop_s, span, bbuf)
    if not math.isfinite(amp):
        amp = 0.0
    if flags & ((1 << _NONFINITE) | (1 << _NO_SIGNAL)):
        pol, amp = 0.0, 0.0
    # ---- reason, confidence
    reason = 0
    for rcode in range(1, 8):
        if flags & (1 << rcode):
            reason = rcode
            break
    accepted = reason == 0
    sig_pos = math.sqrt(max(cov[0, 0] + cov[1, 1], 0.0))
    conf = 0.0
    if accepted:
        c_snr = math.sqrt(min(max((snr - min_snr_db) / 20.0, 0.0), 1.0))
        c_fit = min(max(1.0 - max(excess, 0.0) / thr, 0.0), 1.0)
        c_pos = 1.0 / (1.0 + (sig_pos / 0.5e-3) ** 2)
        conf = c_snr * c_fit * c_pos * (0.5 if clamped else 1.0)
        conf = min(max(conf, 0.0), 1.0) if math.isfinite(conf) else 0.0
    pt[0], pt[1], pt[2] = sx, sy, sz
    if not finite_pt:
        _times(geo, sx, sy, t)
    tmin = min(min(t[0] + cdel[0], t[1] + cdel[1]), min(t[2] + cdel[2], t[3] + cdel[3]))
    out[0] = tau_x
    out[1] = tau_y
    out[2] = twist
    out[3] = mis if math.isfinite(mis) else 1.0
    out[4] = excess
    out[5] = pres if math.isfinite(pres) else 0.0
    out[6] = snr
    nre = math.sqrt(sigma2) * scale
    out[7] = nre if math.isfinite(nre) else 0.0
    out[8] = pol
    out[9] = amp * scale if math.isfinite(amp * scale) else 0.0
    out[10] = conf
    out[11] = 1.0 if clamped else 0.0
    out[12] = float(flags)
    out[13] = on / fs - tmin
    out[14] = math.atan2(math.hypot(sx, sy), sz)
    out[15] = math.atan2(sy, sx)


@njit(cache=True, nogil=True)
def _batch(
    x,
    onset,
    noise_rms,
    sat,
    full_scale,
    gains,
    has_gains,
    gain_rms,
    tabs,
    iterations,
    min_snr_db,
    thr,
    out,
    pt,
    cov,
    ctau,
    cdel,
    cnoise,
):
    for i in range(x.shape[0]):
        _packet(
            x[i],
            onset[i],
            noise_rms[i],
            sat[i],
            full_scale,
            gains,
            has_gains,
            gain_rms,
            tabs,
            iterations,
            min_snr_db,
            thr,
            out[i],
            pt[i],
            cov[i],
            ctau[i],
            cdel,
            cnoise,
        )


def run_batch(
    x, onset, tables: Tables, *, noise_rms, sat, full_scale, gains, iterations, min_snr_db, thr,
    channel_delays_s=None, delay_noise=None,
):
    """Localize K packets with the kernel. x (K, 4, M) float32/float64 C-contiguous,
    onset (K,) int64, noise_rms (K,) float (NaN: measure), sat (K,) int8 (-1 unknown),
    full_scale float (NaN: unknown), gains (4,) or None, channel_delays_s (4,) float64 [s]
    or None (the channels' own delays, taken out of the arrivals), delay_noise (scale,
    timing sd [s]) or None (`noise_args`). Returns (out (K, 16), point (K, 3), covariance
    (K, 3, 3), delay covariance (K, 2, 2))."""
    k = x.shape[0]
    out = np.empty((k, N_SCALAR_OUT))
    pt = np.empty((k, 3))
    cov = np.empty((k, 3, 3))
    ctau = np.empty((k, 2, 2))
    has_gains = gains is not None
    g = np.ones(4) if gains is None else np.asarray(gains, float)
    gain_rms = float(np.sqrt(np.mean(g * g)))
    _batch(
        x,
        onset,
        noise_rms,
        sat,
        float(full_scale),
        g,
        has_gains,
        gain_rms,
        tables.packed,
        int(iterations),
        float(min_snr_db),
        float(thr),
        out,
        pt,
        cov,
        ctau,
        _ZEROS if channel_delays_s is None else channel_delays_s,
        noise_args(delay_noise),
    )
    return out, pt, cov, ctau


_ONES = np.ones(4)
_ZEROS = np.zeros(4)
_MODEL_NOISE = np.array([1.0, 0.0])


def noise_args(delay_noise):
    """The kernel's cnoise (2,) of a delay noise (scale, per-channel timing sd [s]) or None
    (the model's): (scale, sd^2 / 4), what tau_x and tau_y each gain
    (`covariance.delay_noise_covariance`)."""
    if delay_noise is None:
        return _MODEL_NOISE
    scale, sd = delay_noise
    return np.array([float(scale), float(sd) ** 2 / 4.0])


def run_one(
    x,
    onset,
    noise_rms,
    sat,
    full_scale,
    gains,
    tables: Tables,
    iterations,
    min_snr_db,
    thr,
    out,
    pt,
    cov,
    ctau,
    channel_delays_s=None,
    cnoise=_MODEL_NOISE,
):
    """One (4, M) window into out (16,), pt (3,), cov (3, 3), ctau (2, 2) (see `_packet`);
    channel_delays_s: (4,) float64 [s] or None (the channels' own delays); cnoise: the
    delay noise as `noise_args` gives it."""
    if gains is None:
        g, has, grms = _ONES, False, 1.0
    else:
        g, has, grms = gains, True, float(np.sqrt(np.mean(gains * gains)))
    _packet(
        x,
        onset,
        noise_rms,
        sat,
        full_scale,
        g,
        has,
        grms,
        tables.packed,
        iterations,
        min_snr_db,
        thr,
        out,
        pt,
        cov,
        ctau,
        _ZEROS if channel_delays_s is None else channel_delays_s,
        cnoise,
    )
