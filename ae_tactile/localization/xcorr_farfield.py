# SPDX-License-Identifier: Apache-2.0
"""The paper's baseline estimator (method ``"xcorr_farfield"``, what the paper did for
Fig. 7(d) and 8(e)): plain full-band cross-correlation of the sums p11 + p1-1 against
p-11 + p-1-1 (lag = -2 tau_x) and of p11 + p-11 against p1-1 + p-1-1 (lag = -2 tau_y),
parabolic peak, and the far-field inversion of Eq. 2-3, (s_x, s_y) = (c R / a)(tau_x, tau_y).
The covariance and the common post-processing are those of `gcc`.
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

from ae_tactile.localization.common import Plan
from ae_tactile.localization.gcc import _finish
from ae_tactile.localization.segments import Prepared


def _sum_pair_lag(U, V, plan, max_lag):
    """Lag (samples) of the plain full-band cross-correlation peak of U against V (K,), and
    whether it sits at the edge of the allowed lags (K,)."""
    n = plan.n_fft
    G = U * np.conj(V)
    G[:, 0] = 0.0
    r = sfft.irfft(G, n=n, axis=1)
    lags = np.arange(n)
    lags = np.where(lags > n // 2, lags - n, lags)
    rm = np.where(np.abs(lags)[None, :] <= max_lag, r, -np.inf)
    i0 = np.argmax(rm, axis=1)
    rows = np.arange(r.shape[0])
    y0, ym, yp = r[rows, i0], r[rows, (i0 - 1) % n], r[rows, (i0 + 1) % n]
    den = ym - 2 * y0 + yp
    frac = np.where(den < 0, 0.5 * (ym - yp) / np.where(den < 0, den, -1.0), 0.0)
    return lags[i0] + np.clip(frac, -0.5, 0.5), np.abs(lags[i0]) >= max_lag


def estimate_xcorr_farfield(prep: Prepared, plan: Plan):
    X = prep.X
    fs = plan.fs
    max_lag = int(plan.max_lag[0])  # elements 2a apart
    lx, ex = _sum_pair_lag(X[:, 0] + X[:, 1], X[:, 2] + X[:, 3], plan, max_lag)
    ly, ey = _sum_pair_lag(X[:, 0] + X[:, 2], X[:, 1] + X[:, 3], plan, max_lag)
    tx = -lx / (2.0 * fs)
    ty = -ly / (2.0 * fs)
    theta = np.stack([tx, ty, np.zeros_like(tx)], axis=1)
    point, clamped = plan.geometry.point_from_delays(tx, ty, exact=False)
    return _finish(
        prep, plan, theta, point, clamped, "plain", np.zeros_like(tx), theta[:, :2], ex | ey
    )
