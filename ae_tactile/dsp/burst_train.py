# SPDX-License-Identifier: Apache-2.0
"""The timing of crystal-timed interference (`BurstTrain`): bursts at multiples of one
period, which touches never keep (`ae_tactile.dsp.interference` judges single packets)."""

from __future__ import annotations

import numpy as np

#: Periodic interference (`BurstTrain`): the apex packets remembered, and how closely (s; at
#: least TRAIN_TOL_SAMPLES sample periods) a new interval must equal an earlier one.
TRAIN_KEEP = 8
TRAIN_TOL_S = 1e-6
TRAIN_TOL_SAMPLES = 3
#: pairs (new interval, earlier interval) that must agree: 2 lets a train's 3rd burst pass
#: and catches the 4th, where one would let chance matches among dense random bursts drop
#: apex packets
TRAIN_MIN_MATCHES = 2
#: intervals shorter than this (s) are no period (packets closer than a packet's length;
#: stamps that do not advance)
TRAIN_MIN_PERIOD_S = 20e-6


class BurstTrain:
    """Timing of a crystal-timed interference source (a switching regulator, a motor
    driver's PWM): its bursts come at multiples of one period, to a fraction of a
    microsecond, where touches never do (a hand's or a robot's timing jitters by
    milliseconds). Remember the times of the last TRAIN_KEEP packets localized at the apex;
    a new one whose intervals to them equal intervals between two of them (within
    ``tol_s``, TRAIN_MIN_MATCHES distinct relations t = h_j + h_k - h_i) belongs to a
    train. The first three bursts of a train are not caught; an apex touch that falls on
    a train's period by chance is taken for a burst, more often the faster the train and
    below 2 MS/s, where the tolerance is 3 samples (rates: bench/bench_slip.py)."""

    def __init__(self, keep: int = TRAIN_KEEP):
        self._t: list[float] = []
        self.keep = int(keep)

    def is_member(self, t_s: float, tol_s: float) -> bool:
        n = len(self._t)
        if n < 2:
            return False  # (one earlier interval: one pair at most)
        # t - h_j = h_k - h_i (i < k, j != i: with j = i it only says t is near h_k), all
        # three intervals at least TRAIN_MIN_PERIOD_S (no near-duplicates, no still stamps)
        h = np.sort(np.asarray(self._t))
        i, k = np.triu_indices(n, 1)
        d_old = h[k] - h[i]
        d_new = t_s - h
        ok_old = (d_old >= TRAIN_MIN_PERIOD_S) & (t_s - h[k] >= TRAIN_MIN_PERIOD_S)
        ok_new = d_new >= TRAIN_MIN_PERIOD_S
        hit = np.abs(d_new[:, None] - d_old[None, :]) <= tol_s
        hit &= ok_new[:, None] & ok_old[None, :]
        j = np.arange(n)[:, None]
        # t - h_j = h_k - h_i and t - h_k = h_j - h_i are one relation: counted once (j >=
        # k); j = i only says t is near h_k
        hit &= (j != i[None, :]) & (j >= k[None, :])
        return int(np.count_nonzero(hit)) >= TRAIN_MIN_MATCHES

    def add(self, t_s: float) -> None:
        self._t.append(float(t_s))
        del self._t[: -self.keep]

    def reset(self) -> None:
        self._t.clear()
