# SPDX-License-Identifier: Apache-2.0
"""Bounds where issue 38's targets meet (numbers for the detector's design, not scores):

* `slide_decision_bound`: the share of slides from the start whose m-th kept emission
  (the landing one at t0 counted) comes within a deadline, for a SLIP decided at the m-th;
* `slide_touch_confusion`: the share of slides whose first m emissions could be a touch
  sequence (all compressions, pairwise at least d_min apart);
* `stick_zone_bound`: gross-slip emissions needed before one lands inside the stick zone
  of q = 0.9 (the position evidence that no micro-slip before q = 0.9 gives);
* `q_at_kth_micro_slip`: the load fraction at the k-th of N Cattaneo-Mindlin micro-slips.
"""

from __future__ import annotations

import math

import numpy as np


def slide_decision_bound(m, process="poisson", rates=(50.0, 200.0), deadline_s=0.1,
                         drop=0.02, n=100_000, seed=0):
    """P(the m-th kept emission of a slide comes within ``deadline_s`` [s] of its start),
    rates log-uniform in ``rates`` [Hz], a share ``drop`` lost, periodic with 5 % jitter
    or Poisson."""
    rng = np.random.default_rng(seed)
    lo, hi = rates
    r = np.exp(rng.uniform(math.log(lo), math.log(hi), n))[:, None]
    k = m + 8
    if process == "poisson":
        iv = rng.exponential(1.0 / r, (n, k))
    else:
        iv = np.maximum(rng.normal(1.0, 0.05, (n, k)), 0.05) / r
    t = np.concatenate([np.zeros((n, 1)), np.cumsum(iv, 1)], 1)
    t = np.sort(np.where(rng.uniform(size=t.shape) >= drop, t, np.inf), 1)
    return float(np.mean(t[:, m - 1] <= deadline_s))


def slide_touch_confusion(m, d_min_m=1.5e-3, a_m=(0.5e-3, 1.5e-3), n=100_000, seed=0):
    """P(a slide's first m emissions, uniform over a disc of radius a (uniform in a_m
    [m]) with random polarity, are all compressions pairwise >= d_min_m apart)."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(*a_m, n)[:, None]
    r = a * np.sqrt(rng.uniform(size=(n, m)))
    th = rng.uniform(0.0, 2.0 * math.pi, (n, m))
    x, y = r * np.cos(th), r * np.sin(th)
    d = np.hypot(x[:, :, None] - x[:, None, :], y[:, :, None] - y[:, None, :])
    iu = np.triu_indices(m, 1)
    far = d[:, iu[0], iu[1]].min(1) >= d_min_m if m > 1 else np.ones(n, bool)
    return float(0.5**m * np.mean(far))


def stick_zone_bound(q=0.9, confidence=0.95):
    """(c / a, P(a gross-slip emission, uniform over the disc, lands inside c), emissions
    needed for one inside with ``confidence``), c = a (1 - q)^(1/3)."""
    c = (1.0 - q) ** (1.0 / 3.0)
    p = c * c
    return c, p, math.log(1.0 - confidence) / math.log(1.0 - p)


def q_at_kth_micro_slip(k, n):
    """q at which the k-th of n micro-slips comes when their count grows as n f(q),
    f(q) = 1 - (1 - q)^(2/3)."""
    return 1.0 - (1.0 - min(k / n, 1.0)) ** 1.5


if __name__ == "__main__":
    for m in range(2, 8):
        print(m, [round(slide_decision_bound(m, p), 3) for p in ("poisson", "periodic")],
              round(slide_decision_bound(m, rates=(50.0, 50.0)), 3),
              round(slide_touch_confusion(m), 5), round(slide_touch_confusion(m, 2e-3), 5))
    print(stick_zone_bound(), stick_zone_bound(confidence=0.99))
