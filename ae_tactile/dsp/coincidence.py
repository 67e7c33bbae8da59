# SPDX-License-Identifier: Apache-2.0
"""Coincidence across the fingertips of one hand: interference every fingertip sees at once.

A motor driver's switching edge or an ESD event reaches the front ends of all the
fingertips of a hand within nanoseconds (their cables, a shared ground). A touch at one
fingertip's apex comes at a time of its own: another fingertip has an apex packet within
``window_s`` of it only by chance (or when both apexes are touched at once). An apex
packet the per-packet tests kept (interference coupled into the amplifier's input has an
acoustic packet's spectrum, and without a wall echo or a periodic train nothing in one
packet tells) is held for ``wait_s`` of host time; if another fingertip of the hand
reports an apex packet (kept or rejected by its own tests) whose onset lies within
``window_s`` of this one's, both came from one electrical event: interference. Otherwise
the packet goes on as a touch.

Times are host times (ns): each device's sample clock mapped by its link's
`DeviceClockMapper` (the lower envelope of the transport latency), so two fingertips'
stamps of one burst differ by the spread of their latency floors and the mappers' errors
(the hand benchmark in docs/slip.md measures it on its model of the links).

Cost to touches: with apex packets on the other fingertips at rate lambda (1/s, random
times), an apex touch is taken for interference with probability

    p = 1 - exp(-2 window_s lambda),

0.06 % at 1/s and 6 % at 100/s for ``window_s`` 0.3 ms. Periodic trains are caught by
their own timing (`BurstTrain`) from their fourth burst, on one fingertip.
"""

from __future__ import annotations

from collections import Counter, deque

import numpy as np

#: half-width of the coincidence window (s): the fingertips' stamps of one burst agree
#: to the spread of their links' latency floors
COINCIDENCE_WINDOW_S = 3e-4
#: how long an apex packet waits for the other fingertips' reports (s, host time): their
#: transport latency, processing and the hand topic's delivery
COINCIDENCE_WAIT_S = 5e-3
#: how long the other fingertips' reports are remembered (s)
COINCIDENCE_KEEP_S = 1.0


class HandCoincidence:
    """One fingertip's view of the hand's apex packets.

    ``add_others(onsets_ns)``: the other fingertips' apex packet onsets (host ns, any
    order). ``hold(onset_ns, item)``: an apex packet of this fingertip the per-packet tests
    kept. ``due(now_ns)`` -> (kept, rejected): the held items whose wait is over at host
    time ``now_ns`` (onset + ``wait_s`` <= now), in onset order; rejected when a report of
    another fingertip lies within ``window_s`` of the onset. Counts: ``held``, ``kept``,
    ``rejected_coincidence``, ``rejected_nonfinite`` (stamps that are not finite numbers),
    ``reports_late`` (a report within ``window_s`` of one of the last 64 packets decided
    before it came: it does not change that decision)."""

    def __init__(
        self,
        window_s: float = COINCIDENCE_WINDOW_S,
        wait_s: float = COINCIDENCE_WAIT_S,
        keep_s: float = COINCIDENCE_KEEP_S,
    ):
        window_s, wait_s, keep_s = float(window_s), float(wait_s), float(keep_s)
        if not (np.isfinite(window_s) and 0.0 < window_s <= 0.01):
            raise ValueError(f"window_s must be in (0, 0.01] s, got {window_s!r}")
        if not (np.isfinite(wait_s) and window_s <= wait_s <= 1.0):
            raise ValueError(f"wait_s must be in [window_s, 1] s, got {wait_s!r}")
        if not (np.isfinite(keep_s) and keep_s >= 2.0 * wait_s):
            raise ValueError(f"keep_s must be >= 2 wait_s, got {keep_s!r}")
        self.window_ns = int(round(window_s * 1e9))
        self.wait_ns = int(round(wait_s * 1e9))
        self.keep_ns = int(round(keep_s * 1e9))
        self._others = np.zeros(0, np.int64)  # sorted
        self._held: list[tuple[int, object]] = []  # (onset ns, item), onset order
        self._decided: deque[int] = deque(maxlen=64)  # onsets decided, newest last
        self.counts: Counter = Counter()

    def add_others(self, onsets_ns) -> None:
        """Remember other fingertips' apex packet onsets (host ns)."""
        t = np.asarray(onsets_ns, dtype=np.float64).ravel()
        ok = np.isfinite(t) & (np.abs(t) < 2.0**62)
        if not ok.all():
            self.counts["rejected_nonfinite"] += int(np.count_nonzero(~ok))
        if not ok.any():
            return
        t = t[ok].astype(np.int64)
        if self._decided and int(t.min()) <= self._decided[-1] + self.window_ns:
            d = np.fromiter(self._decided, np.int64, len(self._decided))
            late = np.abs(t[:, None] - d[None, :]).min(axis=1) <= self.window_ns
            self.counts["reports_late"] += int(np.count_nonzero(late))
        newest = max(int(t.max()), int(self._others[-1]) if self._others.size else -(2**62))
        both = np.concatenate([self._others, t])
        both.sort(kind="stable")
        self._others = both[both >= newest - self.keep_ns]

    def hold(self, onset_ns, item=None) -> bool:
        """Hold an apex packet of this fingertip until its wait is over; False (counted)
        if its stamp is not a finite number."""
        try:
            t = float(onset_ns)
        except (TypeError, ValueError):
            t = float("nan")
        if not (np.isfinite(t) and abs(t) < 2.0**62):
            self.counts["rejected_nonfinite"] += 1
            return False
        t_ns = int(t)
        self._held.append((t_ns, item))
        if len(self._held) > 1 and t_ns < self._held[-2][0]:
            self._held.sort(key=lambda h: h[0])
        self.counts["held"] += 1
        return True

    @property
    def pending(self) -> int:
        return len(self._held)

    def next_due_ns(self) -> int | None:
        """Host time (ns) at which the oldest held packet is decided (None: none held)."""
        return self._held[0][0] + self.wait_ns if self._held else None

    def due(self, now_ns: int) -> tuple[list, list]:
        """(kept, rejected) items of the held packets whose wait is over at ``now_ns``."""
        n = 0
        limit = int(now_ns) - self.wait_ns
        while n < len(self._held) and self._held[n][0] <= limit:
            n += 1
        if n == 0:
            return [], []
        done, self._held = self._held[:n], self._held[n:]
        t = np.fromiter((h[0] for h in done), np.int64, n)
        hit = self.coincident(t)
        kept = [h[1] for h, m in zip(done, hit) if not m]
        rejected = [h[1] for h, m in zip(done, hit) if m]
        self.counts["kept"] += len(kept)
        self.counts["rejected_coincidence"] += len(rejected)
        self._decided.extend(int(x) for x in t[-64:])
        return kept, rejected

    def coincident(self, onsets_ns) -> np.ndarray:
        """Mask: another fingertip's report lies within ``window_s`` of each onset (ns)."""
        t = np.asarray(onsets_ns, dtype=np.int64)
        if self._others.size == 0:
            return np.zeros(t.shape, bool)
        lo = np.searchsorted(self._others, t - self.window_ns, side="left")
        hi = np.searchsorted(self._others, t + self.window_ns, side="right")
        return hi > lo
