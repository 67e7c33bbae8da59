# SPDX-License-Identifier: Apache-2.0
"""The noise's colour from the pre-trigger samples: its autocovariance and the per-bin
whitening gains the estimators apply to their band spectra.

Model: stationary Gaussian noise with autocovariance r(l), the same on the four channels
(one amplifier design, one ADC). White ADC noise gives r(l) = 0 for l > 0; amplifier noise
that passes through the front end has the front end's colour. The power spectrum per
sample is estimated by the lag-windowed correlogram (Bartlett window over P lags)

    N(f) = r(0) + 2 sum_{l=1}^{P} (1 - l / (P + 1)) r(l) cos(2 pi f l / fs),

r(l) the biased autocovariance of the samples before the onset (pooled over the four
channels; each channel minus its own pre-onset mean). Dividing each band bin of a DFT by
sqrt(N(f) / r(0)) whitens the noise: every bin then carries r(0) L per L samples, what the
white-noise equations of the estimators and their covariance (`covariance`) assume; for an
unknown waveform in Gaussian noise of spectrum N(f) the likelihood of the delays is the
steered response power with each bin weighted by 1 / N(f) (the generalised matched
filter), which this weighting gives.

Few pre-trigger samples (P lags need about 3 P samples per channel): the lags are limited
to a third of the pre-onset samples; each lag is shrunk towards 0 by rho^2 / (rho^2 +
1 / (4 n)) (rho = r / r(0), whose sampling variance is 1 / (4 n) for white noise over 4 n
products) and the colour as a whole by the test `WHITE_TEST`; fewer than
`MIN_PRE_SAMPLES` samples per channel give no estimate (white). N(f) is floored at
`PSD_FLOOR` r(0) (a correlogram can dip below zero).
"""

from __future__ import annotations

import numpy as np

#: Pre-onset samples per channel below which the colour is not estimated [samples].
MIN_PRE_SAMPLES = 12
#: Colour test: Q = 4 n sum_l rho_l^2 is chi^2 with P degrees of freedom for white noise
#: (mean P, sd sqrt(2 P)); the colour is used only where Q > P + WHITE_TEST sqrt(2 P), so
#: that a white device is not given the colour of its estimation noise [sd].
WHITE_TEST = 4.0
#: Lower bound of N(f) / r(0): a lag-windowed correlogram from few samples can dip to or
#: below zero where the true spectrum is small, which would give a bin an unbounded weight.
PSD_FLOOR = 0.05


def n_lags_for(n_pre: int, seg_len: int) -> int:
    """Lags P of the correlogram [samples]: a third of the pre-onset samples (enough
    products per lag), at most half the analysis segment (the resolution it can use).

    Parameters
    ----------
    n_pre : int
        Pre-onset samples per channel.
    seg_len : int
        Analysis segment length [samples].

    Returns
    -------
    int
        0 when the colour cannot be estimated (fewer than `MIN_PRE_SAMPLES`).
    """
    if n_pre < MIN_PRE_SAMPLES:
        return 0
    return int(max(1, min(n_pre // 3, seg_len // 2)))


def pre_onset_autocov(x, n_pre, pre_mean, seg_len):
    """Lag-windowed autocovariance (1 - l / (P + 1)) r(l), l = 0..P_max (K, P_max + 1) of
    the pre-onset samples, pooled over the four channels, r the biased estimate; each
    packet's own P = `n_lags_for` (n_pre, seg_len), zeros beyond it; NaN rows where a
    packet has fewer than `MIN_PRE_SAMPLES` of them.

    Parameters
    ----------
    x : ndarray (K, 4, M)
        Windows (any common scale).
    n_pre : ndarray (K,) of int
        Pre-onset samples of each packet [samples].
    pre_mean : ndarray (K, 4)
        Channel baselines (their pre-onset means).
    seg_len : int
        Analysis segment length [samples].

    Returns
    -------
    ndarray (K, P_max + 1)
    """
    k = x.shape[0]
    n_pre = np.asarray(n_pre, np.int64)
    lags = np.array([n_lags_for(int(n), seg_len) for n in n_pre], np.int64)
    p_max = int(lags.max(initial=0))
    out = np.full((k, p_max + 1), np.nan)
    if p_max < 1:
        return out
    m_max = int(n_pre.max())
    xp = x[:, :, :m_max] - pre_mean[:, :, None]
    xp = xp * (np.arange(m_max)[None, :] < n_pre[:, None])[:, None, :]
    n = np.maximum(n_pre, 1).astype(float)
    r0 = np.einsum("kcm,kcm->k", xp, xp) / (4.0 * n)
    out[:, 0] = r0
    q = np.zeros(k)
    for lag in range(1, p_max + 1):
        r = np.einsum("kcm,kcm->k", xp[:, :, lag:], xp[:, :, : m_max - lag]) / (4.0 * n)
        rho2 = np.where(lag <= lags, r * r / np.maximum(r0 * r0, 1e-300), 0.0)
        q += 4.0 * n * rho2
        # per lag: Wiener shrinkage towards white, rho^2 / (rho^2 + 1 / (4 n))
        shrink = rho2 / (rho2 + 1.0 / (4.0 * n))
        out[:, lag] = np.where(lag <= lags, r * shrink * (1.0 - lag / (lags + 1.0)), 0.0)
    # as a whole: white unless the colour is significant (`WHITE_TEST`)
    out[:, 1:] *= (q > lags + WHITE_TEST * np.sqrt(2.0 * lags))[:, None]
    out[lags < 1] = np.nan
    return out


def whitening_gains(acov, w, fs):
    """Per-bin gains sqrt(r(0) / N(f)) (K, nb) at the angular frequencies ``w`` [rad/s]
    (module docstring); 1 where the autocovariance is unknown (NaN) or zero.

    Parameters
    ----------
    acov : ndarray (K, P + 1)
        Lag-windowed r(0..P) (`pre_onset_autocov`).
    w : ndarray (nb,)
        Band bins [rad/s].
    fs : float
        Sample rate [Hz].

    Returns
    -------
    ndarray (K, nb)
    """
    acov = np.asarray(acov, float)
    p = acov.shape[1] - 1
    ok = np.isfinite(acov).all(axis=1) & (acov[:, 0] > 0)
    rho = np.where(ok[:, None], acov / np.where(ok, acov[:, 0], 1.0)[:, None], 0.0)
    cosm = np.cos(np.outer(np.arange(1, p + 1), w) / fs)  # (P, nb)
    shape = np.maximum(1.0 + 2.0 * rho[:, 1:] @ cosm, PSD_FLOOR)
    return np.where(ok[:, None], 1.0 / np.sqrt(shape), 1.0)
