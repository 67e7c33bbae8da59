# SPDX-License-Identifier: Apache-2.0
"""Pairwise delays and aligned spectra shared by the estimators: GCC / cross-spectrum pair
delays (`pair_delays`), their least-squares arrivals, the channels' spectra aligned on
given arrivals (`aligned_spectra`) and the misfit of one shifted waveform (`misfit`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.fft as sfft

from ae_tactile.localization.common import CHANNEL_ROWS, PAIR_DESIGN, PAIR_PINV, PAIRS, Plan
from ae_tactile.localization.noise_model import whitening_gains
from ae_tactile.localization.segments import Prepared, gather


def pair_delays(X, plan: Plan, *, phat=False, refine=0):
    """Delays t_i - t_j (s) of the 6 channel pairs from the peak of their cross-correlation.

    ``X`` (K, 4, F) coarse spectra. The cross-spectrum X_i X_j^* is restricted to the
    signal band; with ``phat`` each band bin is divided by |X_i X_j^*| (PHAT inside the
    band only, zero outside). Integer peak within the physically possible lags, parabolic
    interpolation, then ``refine`` Newton steps on the band-limited correlation
    r(d) = sum_f W Re(G e^{j w d}).

    Returns (delays (K, 6) s, peak (K, 6) normalised correlation in [-1, 1], at_edge (K,)
    True when some pair peaked at the edge of its lag range, i.e. its delay is probably
    beyond what the geometry allows).
    """
    n = plan.n_fft
    fs = plan.fs
    band = plan.band
    Xi = X[:, PAIRS[:, 0]][..., band]
    Xj = X[:, PAIRS[:, 1]][..., band]
    G = Xi * np.conj(Xj)  # (K, 6, nb)
    ei = (np.abs(Xi) ** 2).sum(axis=2)
    ej = (np.abs(Xj) ** 2).sum(axis=2)
    if phat:
        mag = np.abs(G)
        floor = 1e-6 * mag.max(axis=2, keepdims=True) + 1e-300
        Wt = 1.0 / np.maximum(mag, floor)
    else:
        Wt = None
    Gw = G * Wt if phat else G
    full = np.zeros(G.shape[:2] + (n // 2 + 1,), complex)
    full[..., band] = Gw
    r = sfft.irfft(full, n=n, axis=2)  # (K, 6, n)
    lags = np.arange(n)
    lags = np.where(lags > n // 2, lags - n, lags)
    allowed = np.abs(lags)[None, :] <= plan.max_lag[:, None]  # (6, n)
    rm = np.where(allowed[None], r, -np.inf)
    i0 = np.argmax(rm, axis=2)
    at_edge = (np.abs(lags[i0]) >= plan.max_lag[None, :]).any(axis=1)
    kk = np.arange(r.shape[0])[:, None]
    pp = np.arange(6)[None, :]
    y0 = r[kk, pp, i0]
    ym = r[kk, pp, (i0 - 1) % n]
    yp = r[kk, pp, (i0 + 1) % n]
    den = ym - 2 * y0 + yp
    frac = np.where(den < 0, 0.5 * (ym - yp) / np.where(den < 0, den, -1.0), 0.0)
    frac = np.clip(frac, -0.5, 0.5)
    d = (lags[i0] + frac) / fs
    w = (2 * np.pi * np.fft.rfftfreq(n, 1.0 / fs))[band]
    for _ in range(refine):
        ph = np.exp(1j * w * d[..., None])
        z = Gw * ph
        g1 = -(w * z.imag).sum(axis=2)  # r'(d)
        g2 = -(w * w * z.real).sum(axis=2)  # r''(d) (< 0 at a peak)
        step = np.where(g2 < 0, -g1 / np.where(g2 < 0, g2, -1.0), 0.0)
        step = np.clip(step, -0.5 / fs, 0.5 / fs)
        d = d + step
    ph = np.exp(1j * w * d[..., None])
    peak_plain = (G * ph).real.sum(axis=2) / np.sqrt(np.maximum(ei * ej, 1e-300))
    return d, np.clip(peak_plain, -1.0, 1.0), at_edge


def delays_from_pairs(d):
    """LS (tau_x, tau_y, twist) (K, 3) from the 6 pair delays, and the rms LS residual (s)."""
    theta = d @ PAIR_PINV.T
    res = d - theta @ PAIR_DESIGN.T
    return theta, np.sqrt((res * res).mean(axis=1))


def relative_arrivals(theta):
    """Arrival times t_k - T0 (K, 4) of the model
    t_k = T0 - xi tau_x - eta tau_y + xi eta twist."""
    return theta @ CHANNEL_ROWS.T


@dataclass
class Aligned:
    """Aligned segments' spectra: Y (K, 4, F_al) full rfft, band part Yb, residual shifts eps."""

    Y: np.ndarray
    Yb: np.ndarray
    shift: np.ndarray  # (K, 4) integer sample shift of each channel's segment
    ref: np.ndarray  # (K,) common time reference (s) subtracted from arrivals
    count: np.ndarray  # (K, 4) samples inside the window
    seg: np.ndarray = None  # (K, 4, L) the aligned segments themselves (time domain)


#: Share of the aligned segment's end under a raised-cosine taper: a front end that rings
#: past the echo-free segment leaves the pulse cut at a sample-grid edge that does not move
#: with a channel's fractional delay (not a shifted copy: a bias growing with the SNR); the
#: taper brings the segment smoothly to zero, so that what is kept is what the shifted-copy
#: model describes, at the cost of the information in the tapered tail.
TAPER_FRACTION = 0.25


@lru_cache(maxsize=64)
def _taper(seg_len: int) -> np.ndarray:
    nr = max(1, int(round(TAPER_FRACTION * seg_len)))
    win = np.ones(seg_len)
    win[seg_len - nr:] = 0.5 * (1.0 + np.cos(np.pi * (np.arange(nr) + 1) / (nr + 1)))
    win.flags.writeable = False
    return win


def segment_taper(seg_len: int) -> np.ndarray:
    """The aligned segments' window (seg_len,): 1, then a raised cosine to 0 over the last
    `TAPER_FRACTION` of the segment.

    Parameters
    ----------
    seg_len : int
        Samples per aligned segment.

    Returns
    -------
    ndarray (seg_len,), read-only
    """
    return _taper(int(seg_len))


def aligned_spectra(prep: Prepared, plan: Plan, arrivals_rel) -> Aligned:
    """Re-cut each channel's segment at its own arrival (integer samples), taper its end
    (`segment_taper`), transform, and whiten the band bins by the noise colour of the
    pre-onset samples (`noise_model.whitening_gains`; ``count`` then holds the tapered
    segment's noise energy in samples, sum of w^2 over the samples inside the window).

    ``arrivals_rel`` (K, 4): arrival times relative to any per-packet constant (s).
    The residual (fractional) shifts are eps_k = arrivals_rel_k - ref - shift_k / fs.
    """
    fs = plan.fs
    t = np.asarray(arrivals_rel, float)
    ref = t.min(axis=1)
    shift = np.rint((t - ref[:, None]) * fs).astype(np.int64)
    max_shift = int(plan.max_lag.max()) + 2
    shift = np.clip(shift, 0, max_shift)
    start = prep.seg_start[:, None] + shift
    seg, count = gather(prep.x, start, plan.seg_len, prep.pre_mean)
    win = segment_taper(plan.seg_len)
    # noise energy per bin of a tapered segment: sigma^2 sum w^2 (count: its sample share)
    count = count * (win @ win / plan.seg_len)
    Y = sfft.rfft(seg * win, n=plan.n_fft_al, axis=2)
    Yb = Y[..., plan.band_al]
    if prep.noise_acov is not None:
        Yb = Yb * whitening_gains(prep.noise_acov, plan.w_al, fs)[:, None, :]
    return Aligned(Y=Y, Yb=Yb, shift=shift, ref=ref, count=count, seg=seg)


def misfit(Zb):
    """Fraction of in-band energy not explained by one common waveform, and its parts.

    Zb (K, 4, nb) aligned band spectra. Returns (misfit in [0, 1], residual energy,
    total energy).
    """
    B = Zb.mean(axis=1, keepdims=True)
    res = (np.abs(Zb - B) ** 2).sum(axis=(1, 2))
    tot = (np.abs(Zb) ** 2).sum(axis=(1, 2))
    return np.clip(res / np.maximum(tot, 1e-300), 0.0, 1.0), res, tot
