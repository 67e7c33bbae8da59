# SPDX-License-Identifier: Apache-2.0
"""Scoring detected events against the simulator's ground truth (pure Python): the demo's
monitor (`ae_tactile.ros.monitor_node`) reports its own truth score with it.

Matching is one-to-one in time: each detected event is paired with the nearest unpaired
ground-truth emission within ``tolerance_ns`` (greedy over all candidate pairs, closest
first), which is exact for well-separated emissions and conservative for dense ones.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def match_by_time(truth_ns, event_ns, tolerance_ns: int, truth_points_m=None, event_points_m=None,
                  position_scale_m: float = 1e-3) -> list[tuple[int, int]]:
    """Pair detected events with truth emissions, one-to-one, cheapest pair first.

    A pair needs |t_truth - t_event| <= ``tolerance_ns``; its cost is
    (dt / tolerance)^2, plus (distance / ``position_scale_m``)^2 when points are given
    (which separates dense emissions that are close in time but not in space).

    Parameters
    ----------
    truth_ns, event_ns : array_like of int
        Truth emission times and detected event times [ns].
    tolerance_ns : int
        Largest time difference of a pair [ns].
    truth_points_m, event_points_m : array_like, optional
        (n, 3) points of each [m]; both or neither.
    position_scale_m : float
        Distance that costs as much as a time difference of ``tolerance_ns`` [m].

    Returns
    -------
    list of tuple of int
        (truth index, event index) pairs, sorted.
    """
    t = np.asarray(truth_ns, dtype=np.int64)
    e = np.asarray(event_ns, dtype=np.int64)
    if t.size == 0 or e.size == 0:
        return []
    tp = None if truth_points_m is None else np.asarray(truth_points_m, float).reshape(-1, 3)
    ep = None if event_points_m is None else np.asarray(event_points_m, float).reshape(-1, 3)
    order = np.argsort(t, kind="stable")
    ts = t[order]
    lo = np.searchsorted(ts, e - tolerance_ns, side="left")
    hi = np.searchsorted(ts, e + tolerance_ns, side="right")
    cand = []
    for j in range(e.size):
        for k in range(lo[j], hi[j]):
            i = int(order[k])
            cost = ((int(ts[k]) - int(e[j])) / tolerance_ns) ** 2
            if tp is not None and ep is not None:
                cost += float(np.sum((tp[i] - ep[j]) ** 2)) / position_scale_m ** 2
            cand.append((cost, i, j))
    cand.sort()
    used_t, used_e, pairs = set(), set(), []
    for _, i, j in cand:
        if i not in used_t and j not in used_e:
            used_t.add(i)
            used_e.add(j)
            pairs.append((i, j))
    return sorted(pairs)


@dataclass
class Score:
    """Detection and localization figures of one run.

    ``n_truth``, ``n_events``, ``n_matched``: truth emissions, detected events and pairs;
    ``position_errors_m``: (n_matched,) distance of each pair [m]; ``type_correct`` of
    ``type_checked`` pairs have the truth's polarity sign. ``recall``, ``precision``,
    ``rms_error_m`` [m] and ``type_accuracy`` derive from them.
    """

    n_truth: int
    n_events: int
    n_matched: int
    position_errors_m: np.ndarray = field(repr=False)
    type_correct: int = 0
    type_checked: int = 0

    @property
    def recall(self) -> float:
        return self.n_matched / self.n_truth if self.n_truth else 1.0

    @property
    def precision(self) -> float:
        return self.n_matched / self.n_events if self.n_events else 1.0

    @property
    def rms_error_m(self) -> float:
        e = self.position_errors_m
        return float(np.sqrt(np.mean(e * e))) if e.size else float("nan")

    @property
    def type_accuracy(self) -> float:
        return self.type_correct / self.type_checked if self.type_checked else 1.0

    def as_dict(self) -> dict:
        return {"truth": self.n_truth, "events": self.n_events, "matched": self.n_matched,
                "recall": self.recall, "precision": self.precision,
                "rms_position_error_mm": self.rms_error_m * 1e3,
                "type_accuracy": self.type_accuracy}


def score(truth_ns, truth_points_m, truth_polarity, event_ns, event_points_m, event_polarity,
          tolerance_ns: int = 1_000_000) -> Score:
    """Score localized events against truth emissions (`match_by_time` with points).

    Parameters
    ----------
    truth_ns, event_ns : array_like of int
        Times [ns].
    truth_points_m, event_points_m : array_like
        (n, 3) points [m].
    truth_polarity, event_polarity : array_like
        Polarity of each, +1 (touch) or -1 (release); compared by sign.
    tolerance_ns : int
        Largest time difference of a pair [ns].

    Returns
    -------
    Score
        Counts, position errors of the pairs and polarity agreement.
    """
    pairs = match_by_time(truth_ns, event_ns, tolerance_ns, truth_points_m, event_points_m)
    tp = np.asarray(truth_points_m, float).reshape(-1, 3)
    ep = np.asarray(event_points_m, float).reshape(-1, 3)
    tpol = np.asarray(truth_polarity)
    epol = np.asarray(event_polarity)
    if pairs:
        i, j = np.array(pairs).T
        err = np.linalg.norm(tp[i] - ep[j], axis=1)
        correct = int(np.sum(np.sign(tpol[i]) == np.sign(epol[j])))
    else:
        err, correct = np.zeros(0), 0
    return Score(n_truth=len(tp), n_events=len(ep), n_matched=len(pairs), position_errors_m=err,
                 type_correct=correct, type_checked=len(pairs))
