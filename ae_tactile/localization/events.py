# SPDX-License-Identifier: Apache-2.0
"""Event type (touch / release), amplitude and confidence of a localized packet.

Touch vs release: the paper's collision model (Eq. 10) starts with a compressive
pressure jump for a touch and the opposite sign for a release (detouch); after the
front end the first lobe of the packet keeps that sign (the simulator follows the same
convention). The four channels are aligned by the fitted delays and averaged (`ml`: the
aligned segments interpolated at the fit's residual shifts, 4-point Lagrange, the same
computation as the compiled kernel; the other methods: phase-shifted spectra); the first
sample of that mean at or after the start of the segment whose magnitude reaches half
the segment's peak magnitude marks the first significant lobe; its sign is the polarity
(+1 touch, -1 release) and the extreme of the mean over the following 1.5 us is the
signed amplitude (V).

Confidence in [0, 1], 0 for rejected packets, otherwise the product of
  c_snr  = clip((SNR_est - min_snr_db) / 20 dB, 0, 1) ** 0.5    (weak packets)
  c_fit  = clip(1 - max(excess, 0) / overlap_threshold, 0, 1)  (not shifted copies)
  c_pos  = 1 / (1 + sigma_pos^2 / (0.5 mm)^2)                  (predicted in-plane 1-sigma)
  c_clamp = 0.5 when the point was clamped onto the horizon, else 1.
"""
from __future__ import annotations

import math

import numpy as np
import scipy.fft as sfft


def polarity_amplitude(z, plan):
    """(polarity (K,) int8, amplitude (K,) V) from aligned full spectra z (K, 4, F)."""
    b = sfft.irfft(z.mean(axis=1), n=plan.n_fft_al, axis=1)[:, : plan.seg_len]
    return _first_lobe(b, plan)


def lagrange4(seg, e):
    """b[k, c, n] = seg[k, c](n + e[k, c]) by 4-point Lagrange interpolation (zeros outside
    the segment); seg (K, 4, L), e (K, 4) in samples."""
    k, nc, L = seg.shape
    p = np.arange(L)[None, None, :] + e[..., None]
    i = np.floor(p)
    u = p - i
    i = i.astype(np.int64)
    wts = (-u * (u - 1.0) * (u - 2.0) / 6.0, (u + 1.0) * (u - 1.0) * (u - 2.0) / 2.0,
           -(u + 1.0) * u * (u - 2.0) / 2.0, (u + 1.0) * u * (u - 1.0) / 6.0)
    out = np.zeros(seg.shape)
    for off, w in zip((-1, 0, 1, 2), wts):
        j = i + off
        ok = (j >= 0) & (j < L)
        out += np.where(ok, w * np.take_along_axis(seg, np.clip(j, 0, L - 1), axis=2), 0.0)
    return out


def polarity_amplitude_aligned(seg, eps_samples, plan):
    """(polarity (K,) int8, amplitude (K,)) from the aligned time-domain segments (K, 4, L)
    and the fit's residual shifts (K, 4) in samples: the channel mean b[n] = mean_k
    y_k(n + eps_k) (4-point Lagrange interpolation), then the first-lobe rule above."""
    b = lagrange4(seg, np.asarray(eps_samples, float)).mean(axis=1)
    return _first_lobe(b, plan)


def _first_lobe(b, plan):
    mag = np.abs(b)
    peak = mag.max(axis=1)
    stop = min(plan.seg_len, plan.pre + int(math.ceil(3e-6 * plan.fs)) + 1)
    hit = mag[:, :stop] >= 0.5 * peak[:, None]
    first = np.where(hit.any(axis=1), np.argmax(hit, axis=1), np.argmax(mag, axis=1))
    rows = np.arange(b.shape[0])
    pol = np.sign(b[rows, first])
    pol = np.where(peak > 0, pol, 0.0)
    span = int(math.ceil(1.5e-6 * plan.fs)) + 1
    idx = np.clip(first[:, None] + np.arange(span), 0, plan.seg_len - 1)
    seg = np.take_along_axis(b, idx, axis=1) * pol[:, None]
    amp = pol * seg.max(axis=1)
    return pol.astype(np.int8), amp


def confidence(accepted, snr_db, min_snr_db, excess, overlap_threshold, sigma_pos_m, clamped):
    c_snr = np.sqrt(np.clip((snr_db - min_snr_db) / 20.0, 0.0, 1.0))
    c_fit = np.clip(1.0 - np.maximum(excess, 0.0) / overlap_threshold, 0.0, 1.0)
    c_pos = 1.0 / (1.0 + (sigma_pos_m / 0.5e-3) ** 2)
    c_clamp = np.where(clamped, 0.5, 1.0)
    c = c_snr * c_fit * c_pos * c_clamp
    c = np.where(np.isfinite(c), c, 0.0)
    return np.where(accepted, np.clip(c, 0.0, 1.0), 0.0)
