# SPDX-License-Identifier: Apache-2.0
"""The paper's gradient method (its ref. [8]), iterated with re-alignment (method ``"gradient"``).

With p_{xi,eta}(t) = f(t + xi tau_x + eta tau_y), the channel mean m = (1/4) sum p and the
spatial differences d_x = (1/4) sum xi p, d_y = (1/4) sum eta p satisfy, to first order
in the delays, d_x = tau_x m', d_y = tau_y m'. Least squares gives

    tau_x = <d_x, m'> / <m', m'>,   tau_y = <d_y, m'> / <m', m'>,

(and the twist from d_xy = (1/4) sum xi eta p). This one-shot estimate only holds while
w tau << 1; here 2 pi f a / c ~ 6 at 1 MHz, so it is iterated: each channel is re-aligned
by the current estimate (integer cut + fractional FFT phase shift), the LS step is
applied to what is left, and the estimate is updated. The derivative is band-limited
(j w inside the signal band only), the inner products are sums over the band bins.

Start: band-limited cross-correlation of the 6 channel pairs (integer lag + parabola).
The fixed point is the stationary point of the steered response over (tau_x, tau_y,
twist), i.e. the "four delays against a common template" ML fit; the point then follows
from the exact inversion `FingertipGeometry.point_from_delays`.
"""

from __future__ import annotations

import numpy as np

from ae_tactile.localization.common import CONTRASTS, Plan
from ae_tactile.localization.covariance import arrival_fisher, delay_covariance_from_fisher
from ae_tactile.localization.pairs import (
    aligned_spectra,
    delays_from_pairs,
    pair_delays,
    relative_arrivals,
)
from ae_tactile.localization.segments import Prepared, subset

_SIGNS = CONTRASTS * 4.0  # rows: -xi, -eta, xi eta


def _iterate(Yb, w, theta, c0, iterations, lim, fs):
    """LS steps with re-alignment; a packet stops once its step is below 1e-4 sample."""
    theta = theta.copy()
    act = np.arange(theta.shape[0])
    for _ in range(iterations):
        if act.size == 0:
            break
        eps = relative_arrivals(theta[act]) - c0[act]
        z = Yb[act] * np.exp(1j * w * eps[..., None])
        dm = 1j * w * z.mean(axis=1)  # band-limited m'
        den = np.maximum((np.abs(dm) ** 2).sum(axis=1), 1e-300)
        diffs = np.einsum("ck,kbf->bcf", _SIGNS, np.moveaxis(z, 0, 1)) / 4.0  # (K, 3, nb)
        num = (diffs * np.conj(dm)[:, None, :]).real.sum(axis=2) / den[:, None]
        # diffs ~ j w M (estimate - truth) projected on each contrast: step back by it.
        step = np.clip(-num, -lim, lim)
        theta[act] += step
        act = act[np.abs(step).max(axis=1) >= 1e-4 / fs]
    return theta


def estimate(prep: Prepared, plan: Plan, *, iterations: int = 4, start: str = "xcorr"):
    """``start='xcorr'`` (default) or ``'zero'``: with ``start='zero', iterations=1`` this is
    the paper's one-shot estimate on the unaligned channels (valid only near the pole)."""
    geo = plan.geometry
    fs = plan.fs
    w = plan.w_al
    if start == "xcorr":
        d, _, edge = pair_delays(prep.X, plan)
        theta, pair_res = delays_from_pairs(d)
        lim = 0.5 / fs
    elif start == "zero":
        theta = np.zeros((prep.x.shape[0], 3))
        pair_res = np.zeros(prep.x.shape[0])
        edge = np.zeros(prep.x.shape[0], bool)
        lim = np.inf
    else:
        raise ValueError(f"start must be 'xcorr' or 'zero', got {start!r}")
    if (
        isinstance(iterations, bool)
        or not isinstance(iterations, (int, np.integer))
        or iterations < 1
    ):
        raise ValueError(f"iterations must be a positive integer, got {iterations!r}")
    raw0 = theta[:, :2].copy()
    al = aligned_spectra(prep, plan, relative_arrivals(theta))
    c0 = al.ref[:, None] + al.shift / fs
    theta = _iterate(al.Yb, w, theta, c0, iterations, lim, fs)
    # Re-cut (once) the packets whose estimate drifted more than 3/4 sample from the cut.
    eps = relative_arrivals(theta) - c0
    drift = np.abs(eps - eps.mean(axis=1, keepdims=True)).max(axis=1) * fs >= 0.75
    if drift.any():
        ids = np.nonzero(drift)[0]
        al2 = aligned_spectra(subset(prep, ids), plan, relative_arrivals(theta[ids]))
        c2 = al2.ref[:, None] + al2.shift / fs
        theta[ids] = _iterate(al2.Yb, w, theta[ids], c2, iterations, lim, fs)
        al.Y[ids], al.Yb[ids], al.shift[ids], al.ref[ids], al.count[ids] = (
            al2.Y,
            al2.Yb,
            al2.shift,
            al2.ref,
            al2.count,
        )
        c0[ids] = c2
    eps = relative_arrivals(theta) - c0
    zb = al.Yb * np.exp(1j * w * eps[..., None])
    z = al.Y * np.exp(1j * plan.w_full_al * eps[..., None])
    point, clamped = geo.point_from_delays(theta[:, 0], theta[:, 1], exact=True)

    def covariance(sigma2):
        F = arrival_fisher(zb, w, sigma2, al.count, plan.n_fft_al)
        return delay_covariance_from_fisher(F), np.ones(len(sigma2), bool)

    return dict(
        theta=theta,
        point=point,
        clamped=clamped,
        zb=zb,
        z=z,
        count=al.count,
        raw_delays=theta[:, :2],
        covariance=covariance,
        pair_residual_s=pair_res,
        start_delays=raw0,
        at_edge=edge,
    )
