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
`DeviceClockMapper` (the lower envelope of the transport latency). Two links' mapped
stamps of one event differ by a constant of their own, the difference of their latency
floors (hundreds of microseconds between two simulated fingertips' ptys, tens on one USB
host), more than the window. The common events themselves measure it: each apex packet
of this fingertip is paired with the nearest report of each other fingertip within
``search_s`` (2 ms) once its wait is over, and the median of a fingertip's last 32
differences is its offset d_k = t_k - t once 8 pairs agree (median absolute deviation
<= window / 2; pairs by chance spread over +-search and do not). Until then d_k = 0.
When a link's offset moves (another latency floor: re-plugged on another port or hub; a
device reset on the same port re-learns the same floor), the newest 8
pairs agreeing on an offset more than ``window_s`` from the learnt one replace it
(counted as ``offsets_moved``): at most 7 bursts pass, not the 16 a median of 32 would
let by.
The test for an onset t: a report t_k of fingertip k with |t_k - d_k - t| <= window_s.

Cost to touches: with apex packets on the other fingertips at rate lambda (1/s, random
times), an apex touch is taken for interference with probability

    p = 1 - exp(-2 window_s lambda),

0.06 % at 1/s and 6 % at 100/s for ``window_s`` 0.3 ms. Periodic trains are caught by
their own timing (`BurstTrain`) from their fourth burst, on one fingertip.
"""

from __future__ import annotations

from collections import Counter, deque

import numpy as np

#: half-width of the coincidence window (s) about a fingertip's learnt clock offset
COINCIDENCE_WINDOW_S = 3e-4
#: how long an apex packet waits for the other fingertips' reports (s, host time): their
#: transport latency, processing and the hand topic's delivery
COINCIDENCE_WAIT_S = 5e-3
#: how long the other fingertips' reports are remembered (s; at least twice the wait)
COINCIDENCE_KEEP_S = 1.0
#: pairs (this fingertip's apex packet, another's nearest report) within this (s) measure
#: the other fingertip's clock offset
OFFSET_SEARCH_S = 2e-3
OFFSET_PAIRS = 32  # the differences an offset is the median of
OFFSET_MIN_PAIRS = 8  # ... at least, and agreeing to window / 2 (median absolute deviation)


class HandCoincidence:
    """One fingertip's view of the hand's apex packets.

    ``add_own(onsets_ns)``: this fingertip's apex packet onsets (host ns; every one, kept
    or rejected by its tests: they pair with the others' reports to learn the clock
    offsets). ``add_others(onsets_ns, source)``: fingertip ``source``'s apex packet onsets.
    ``hold(onset_ns, item)``: an apex packet of this fingertip the per-packet tests kept.
    ``due(now_ns)`` -> (kept, rejected): the held items whose wait is over at host time
    ``now_ns`` (onset + ``wait_s`` <= now), in onset order; rejected when a report of
    another fingertip lies within ``window_s`` of the onset (less that fingertip's
    offset). Counts: ``held``, ``kept``, ``rejected_coincidence``, ``rejected_nonfinite``
    (stamps that are not finite numbers), ``reports_late`` (a report within ``window_s`` of
    one of the last 64 packets decided before it came: it does not change that decision),
    ``offsets_learnt`` (fingertips whose offset is known), ``offsets_moved`` (learnt offsets
    replaced by the newest pairs')."""

    def __init__(
        self,
        window_s: float = COINCIDENCE_WINDOW_S,
        wait_s: float = COINCIDENCE_WAIT_S,
        keep_s: float | None = None,
    ):
        window_s, wait_s = float(window_s), float(wait_s)
        keep_s = max(COINCIDENCE_KEEP_S, 2.0 * wait_s) if keep_s is None else float(keep_s)
        if not (np.isfinite(window_s) and 0.0 < window_s <= 0.01):
            raise ValueError(f"window_s must be in (0, 0.01] s, got {window_s!r}")
        if not (np.isfinite(wait_s) and window_s <= wait_s <= 1.0):
            raise ValueError(f"wait_s must be in [window_s, 1] s, got {wait_s!r}")
        if not (np.isfinite(keep_s) and keep_s >= 2.0 * wait_s):
            raise ValueError(f"keep_s must be >= 2 wait_s, got {keep_s!r}")
        self.window_ns = int(round(window_s * 1e9))
        self.wait_ns = int(round(wait_s * 1e9))
        self.keep_ns = int(round(keep_s * 1e9))
        self.search_ns = int(round(OFFSET_SEARCH_S * 1e9))
        self._others: dict[str, np.ndarray] = {}  # source -> sorted onsets
        self._diffs: dict[str, deque] = {}  # source -> recent t_k - t
        self.offsets_ns: dict[str, int] = {}  # source -> learnt offset d_k
        self._own: list[int] = []  # own onsets not yet paired (their wait not over)
        self._held: list[tuple[int, object]] = []  # (onset ns, item), onset order
        self._decided: deque[int] = deque(maxlen=64)  # onsets decided, newest last
        self.counts: Counter = Counter()

    def with_settings(self, window_s: float, wait_s: float) -> HandCoincidence:
        """A copy with another window and wait that keeps the reports, the learnt offsets,
        the held packets and the counts (ValueError on bad settings)."""
        new = HandCoincidence(window_s, wait_s)
        new._others = {k: v.copy() for k, v in self._others.items()}
        new._diffs = {k: deque(v, maxlen=OFFSET_PAIRS) for k, v in self._diffs.items()}
        new._own = list(self._own)
        new._held = list(self._held)
        new._decided = deque(self._decided, maxlen=self._decided.maxlen)
        new.counts = self.counts.copy()
        for k in new._diffs:
            new._learn(k)
        return new

    def _finite(self, onsets_ns) -> np.ndarray:
        t = np.asarray(onsets_ns, dtype=np.float64).ravel()
        ok = np.isfinite(t) & (np.abs(t) < 2.0**62)
        if not ok.all():
            self.counts["rejected_nonfinite"] += int(np.count_nonzero(~ok))
        return t[ok].astype(np.int64)

    def add_own(self, onsets_ns) -> None:
        """This fingertip's apex packet onsets (host ns), for learning the offsets."""
        t = self._finite(onsets_ns)
        if t.size:
            self._own.extend(int(x) for x in t)
            del self._own[:-1024]  # a flood: the newest

    def add_others(self, onsets_ns, source: str = "") -> None:
        """Remember another fingertip's apex packet onsets (host ns)."""
        t = self._finite(onsets_ns)
        if t.size == 0:
            return
        source = str(source)
        off = self.offsets_ns.get(source, 0)
        if self._decided and int(t.min()) - off <= self._decided[-1] + self.window_ns:
            d = np.fromiter(self._decided, np.int64, len(self._decided))
            late = np.abs((t - off)[:, None] - d[None, :]).min(axis=1) <= self.window_ns
            self.counts["reports_late"] += int(np.count_nonzero(late))
        old = self._others.get(source, np.zeros(0, np.int64))
        newest = max(int(t.max()), int(old[-1]) if old.size else -(2**62))
        both = np.concatenate([old, t])
        both.sort(kind="stable")
        self._others[source] = both[both >= newest - self.keep_ns]

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
        """(kept, rejected) items of the held packets whose wait is over at ``now_ns``; the
        own onsets whose wait is over are paired with the reports first (offsets)."""
        limit = int(now_ns) - self.wait_ns
        if self._own and self._others:
            ripe = [t for t in self._own if t <= limit]
            if ripe:
                self._own = [t for t in self._own if t > limit]
                self._pair(np.asarray(ripe, np.int64))
        n = 0
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

    def _pair(self, own: np.ndarray) -> None:
        """Each own onset with each fingertip's nearest report within the search range."""
        for source, rep in self._others.items():
            if rep.size == 0:
                continue
            j = np.searchsorted(rep, own)
            lo = rep[np.clip(j - 1, 0, rep.size - 1)] - own
            hi = rep[np.clip(j, 0, rep.size - 1)] - own
            d = np.where(np.abs(lo) <= np.abs(hi), lo, hi)
            d = d[np.abs(d) <= self.search_ns]
            if d.size:
                self._diffs.setdefault(source, deque(maxlen=OFFSET_PAIRS)).extend(
                    int(x) for x in d
                )
                self._learn(source)

    def _learn(self, source: str) -> None:
        """The offset: the median of the last 32 pairs once 8 agree; or, when the newest 8
        agree on an offset more than ``window_s`` from the learnt one (the link's clock
        moved: another latency floor), theirs, the older pairs dropped."""
        q = self._diffs[source]
        d = np.fromiter(q, np.int64, len(q))
        if d.size < OFFSET_MIN_PAIRS:
            return
        half = 0.5 * self.window_ns
        old = self.offsets_ns.get(source)
        if old is not None:
            r = d[-OFFSET_MIN_PAIRS:]
            med = float(np.median(r))
            if abs(med - old) > self.window_ns and float(np.median(np.abs(r - med))) <= half:
                q.clear()
                q.extend(int(x) for x in r)
                self.offsets_ns[source] = int(round(med))
                self.counts["offsets_moved"] += 1
                return
        med = float(np.median(d))
        if float(np.median(np.abs(d - med))) <= half:
            if old is None:
                self.counts["offsets_learnt"] += 1
            self.offsets_ns[source] = int(round(med))

    def coincident(self, onsets_ns) -> np.ndarray:
        """Mask: another fingertip's report lies within ``window_s`` of each onset (ns),
        that fingertip's offset removed."""
        t = np.asarray(onsets_ns, dtype=np.int64)
        hit = np.zeros(t.shape, bool)
        for source, rep in self._others.items():
            if rep.size == 0:
                continue
            c = t + self.offsets_ns.get(source, 0)
            lo = np.searchsorted(rep, c - self.window_ns, side="left")
            hi = np.searchsorted(rep, c + self.window_ns, side="right")
            hit |= hi > lo
        return hit
