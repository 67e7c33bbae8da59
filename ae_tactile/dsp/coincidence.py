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
#: another fingertip's onsets remembered (10 kHz bursts over ``keep_s`` are 10,000); more,
#: in one report or in all: the newest, the rest counted (``reports_rejected_flood``)
REPORTS_MAX = 65536
#: fingertips remembered (a hand has five; more names: the silent ones are forgotten, and
#: while every one is active a new name's reports are counted, ``reports_rejected_sources``)
SOURCES_MAX = 16


def _median(x: list) -> float:
    """Median of a short list (plain Python: tens of values, no numpy call overhead)."""
    s = sorted(x)
    n = len(s)
    return 0.5 * (s[(n - 1) // 2] + s[n // 2])


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
    one of the last 64 packets kept before it came: that packet went out as a touch),
    ``offsets_learnt`` (fingertips whose offset is known), ``offsets_moved`` (learnt offsets
    replaced by the newest pairs'), and for reports that cannot be right:
    ``reports_rejected_stamp`` (more than ``keep_s`` from this fingertip's clock, when the
    receiver's time is given), ``reports_rejected_flood`` (beyond `REPORTS_MAX` of one
    fingertip), ``reports_rejected_sources`` (a name beyond `SOURCES_MAX` active ones).

    ``follow``: records that must not overtake the held packets (later events of the same
    fingertip: a release after its held touch); `due` hands them out in time order once no
    held packet older than them is left. ``key`` gives a record's time (ns), for the
    order.

    Parameters
    ----------
    window_s : float
        Coincidence window [s], in (0, 0.01]: another fingertip's report this close to an
        onset (less the learnt clock offset) rejects the packet.
    wait_s : float
        Wait [s] before a held packet is decided, in [window_s, 1]: the others' reports
        arrive within it.
    keep_s : float, optional
        How long the other fingertips' reports are remembered [s], >= 2 wait_s (default
        max(COINCIDENCE_KEEP_S, 2 wait_s)).

    Returns
    -------
    HandCoincidence
        ``due(now_ns)`` returns (kept, rejected) lists of the held items.

    Raises
    ------
    ValueError
        A duration out of its range.
    """

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
        self._follow: list = []  # records behind the held packets, arrival order
        self._decided: deque[int] = deque(maxlen=64)  # onsets kept, newest last
        self.counts: Counter = Counter()

    def with_settings(self, window_s: float, wait_s: float) -> HandCoincidence:
        """A copy with another window and wait that keeps the reports, the learnt offsets,
        the held packets and the counts (ValueError on bad settings)."""
        new = HandCoincidence(window_s, wait_s)
        new._others = {k: v.copy() for k, v in self._others.items()}
        new._diffs = {k: deque(v, maxlen=OFFSET_PAIRS) for k, v in self._diffs.items()}
        new._own = list(self._own)
        new._held = list(self._held)
        new._follow = list(self._follow)
        new._decided = deque(self._decided, maxlen=self._decided.maxlen)
        new.counts = self.counts.copy()
        for k in new._diffs:
            new._learn(k)
        return new

    def _finite(self, onsets_ns) -> np.ndarray:
        """The stamps as int64 ns (integers exactly: a float64 rounds today's epoch stamps
        to 256 ns); not finite or beyond +-2^62 ns: counted and dropped."""
        t = np.asarray(onsets_ns).ravel()
        if t.dtype.kind == "O":  # Python ints beyond int64 among good ones: one by one
            good = [int(x) for x in t.tolist()
                    if isinstance(x, (int, np.integer)) and not isinstance(x, bool)
                    and -(2**62) < int(x) < 2**62]
            if len(good) < t.size:
                self.counts["rejected_nonfinite"] += int(t.size - len(good))
            return np.asarray(good, np.int64)
        if t.dtype.kind not in "iuf":  # bools, strings: no stamps
            self.counts["rejected_nonfinite"] += int(t.size)
            return np.zeros(0, np.int64)
        if t.dtype.kind == "i":
            t = t.astype(np.int64, copy=False)
            ok = (t > -(2**62)) & (t < 2**62)
        elif t.dtype.kind == "u":
            ok = t < 2**62
            t = np.where(ok, t, 0).astype(np.int64)
        else:
            f = t.astype(np.float64)
            ok = np.isfinite(f) & (np.abs(f) < 2.0**62)
            t = np.where(ok, f, 0.0).astype(np.int64)
        if not ok.all():
            self.counts["rejected_nonfinite"] += int(np.count_nonzero(~ok))
            t = t[ok]
        return t

    def add_own(self, onsets_ns) -> None:
        """This fingertip's apex packet onsets (host ns), for learning the offsets."""
        t = self._finite(onsets_ns)
        if t.size:
            self._own.extend(int(x) for x in t)
            del self._own[:-1024]  # a flood: the newest

    def add_others(self, onsets_ns, source: str = "", now_ns: int | None = None) -> None:
        """Remember another fingertip's apex packet onsets (host ns). ``now_ns``: this
        fingertip's host time; stamps more than ``keep_s`` from it are counted and dropped
        (a clock that jumped, a node on another clock), and old reports are forgotten by
        it (else by the source's newest stamp)."""
        t = self._finite(onsets_ns)
        if now_ns is not None:
            now_ns = int(now_ns)
            if abs(now_ns) < 2**62:
                ok = np.abs(t - now_ns) <= self.keep_ns
            else:  # no clock of this machine reads that: nothing can be checked
                ok = np.zeros(t.size, bool)
            if not ok.all():
                self.counts["reports_rejected_stamp"] += int(np.count_nonzero(~ok))
                t = t[ok]
        if t.size > REPORTS_MAX:
            self.counts["reports_rejected_flood"] += int(t.size - REPORTS_MAX)
            t = np.sort(t)[-REPORTS_MAX:]
        if t.size == 0:
            return
        source = str(source)
        if source not in self._others and len(self._others) >= SOURCES_MAX:
            self._forget_silent(now_ns if now_ns is not None else int(t.max()))
            if len(self._others) >= SOURCES_MAX:
                self.counts["reports_rejected_sources"] += int(t.size)
                return
        off = self.offsets_ns.get(source, 0)
        if self._decided and int(t.min()) - off <= max(self._decided) + self.window_ns:
            d = np.sort(np.fromiter(self._decided, np.int64, len(self._decided)))
            c = t - off
            late = (np.searchsorted(d, c + self.window_ns, side="right")
                    > np.searchsorted(d, c - self.window_ns, side="left"))
            self.counts["reports_late"] += int(np.count_nonzero(late))
        old = self._others.get(source, np.zeros(0, np.int64))
        if now_ns is not None:
            oldest = now_ns - self.keep_ns
        else:
            oldest = max(int(t.max()), int(old[-1]) if old.size else -(2**62)) - self.keep_ns
        both = np.concatenate([old, t])
        both.sort(kind="stable")
        both = both[both >= oldest]
        if both.size > REPORTS_MAX:
            self.counts["reports_rejected_flood"] += int(both.size - REPORTS_MAX)
            both = both[-REPORTS_MAX:]
        self._others[source] = both

    def _forget_silent(self, now_ns: int) -> None:
        """Forget the reports of the fingertips with none within ``keep_s`` of ``now_ns``
        (their offsets stay, but for names beyond 4 `SOURCES_MAX`)."""
        for k in [k for k, v in self._others.items() if v.size == 0
                  or int(v[-1]) < now_ns - self.keep_ns]:
            del self._others[k]
        if len(self._diffs) > 4 * SOURCES_MAX:
            for k in [k for k in self._diffs if k not in self._others]:
                self._diffs.pop(k, None)
                self.offsets_ns.pop(k, None)

    def hold(self, onset_ns, item=None) -> bool:
        """Hold an apex packet of this fingertip until its wait is over; False (counted)
        if its stamp is not a finite number."""
        if isinstance(onset_ns, (bool, np.bool_, str, bytes)):
            ok, t_ns = False, 0
        elif isinstance(onset_ns, (int, np.integer)):
            t_ns = int(onset_ns)
            ok = abs(t_ns) < 2**62
        else:
            try:
                t = float(onset_ns)
            except (TypeError, ValueError):
                t = float("nan")
            ok = bool(np.isfinite(t) and abs(t) < 2.0**62)
            t_ns = int(t) if ok else 0
        if not ok:
            self.counts["rejected_nonfinite"] += 1
            return False
        self._held.append((t_ns, item))
        if len(self._held) > 1 and t_ns < self._held[-2][0]:
            self._held.sort(key=lambda h: h[0])
        self.counts["held"] += 1
        return True

    def follow(self, item) -> None:
        """A record that must wait behind the held packets older than it."""
        self._follow.append(item)

    def held_min(self, key):
        """The least ``key(item)`` of the held items (None: none held)."""
        held = self._held
        return min(key(h[1]) for h in held) if held else None

    @property
    def pending(self) -> int:
        """Held packets and records behind them."""
        return len(self._held) + len(self._follow)

    @property
    def unpaired(self) -> int:
        """This fingertip's onsets not yet paired with the others' reports."""
        return len(self._own)

    def next_due_ns(self) -> int | None:
        """Host time (ns) at which the oldest held packet is decided (None: none held)."""
        held = self._held  # one read: another thread may rebind it
        return held[0][0] + self.wait_ns if held else None

    def due(self, now_ns: int, key=None, flush: bool = False) -> tuple[list, list]:
        """(kept, rejected) items of the held packets whose wait is over at ``now_ns``
        (``flush``: every held packet, with the reports at hand), and after them the
        records behind them (`follow`) that no held packet older than them (by ``key``,
        a record's time in ns) holds back any more; the own onsets whose wait is over are
        paired with the reports first (offsets)."""
        limit = int(now_ns) - self.wait_ns
        if self._own and self._others:
            ripe = [t for t in self._own if t <= limit or flush]
            if ripe:
                self._own = [t for t in self._own if t > limit and not flush]
                self._pair(np.asarray(ripe, np.int64))
        n = len(self._held) if flush else 0
        while n < len(self._held) and self._held[n][0] <= limit:
            n += 1
        kept: list = []
        rejected: list = []
        if n:
            done, self._held = self._held[:n], self._held[n:]
            t = np.fromiter((h[0] for h in done), np.int64, n)
            hit = self.coincident(t)
            kept = [h[1] for h, m in zip(done, hit) if not m]
            rejected = [h[1] for h, m in zip(done, hit) if m]
            self.counts["kept"] += len(kept)
            self.counts["rejected_coincidence"] += len(rejected)
            self._decided.extend(int(x) for x in t[~hit][-64:])
        if self._follow and (n or not self._held):
            if not self._held:
                free, self._follow = self._follow, []
            elif key is None:
                free = []
            else:
                bar = self.held_min(key)
                free = [r for r in self._follow if key(r) < bar]
                self._follow = [r for r in self._follow if key(r) >= bar]
            if free:
                kept = kept + free
                if key is not None:
                    kept.sort(key=key)
        return kept, rejected

    def _pair(self, own: np.ndarray) -> None:
        """Each own onset with each fingertip's nearest report within the search range."""
        for source, rep in self._others.items():
            if rep.size == 0:
                continue
            j = rep.searchsorted(own)
            lo = rep[np.maximum(j - 1, 0)] - own
            hi = rep[np.minimum(j, rep.size - 1)] - own
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
        if len(q) < OFFSET_MIN_PAIRS:
            return
        d = list(q)
        half = 0.5 * self.window_ns
        old = self.offsets_ns.get(source)
        if old is not None:
            r = d[-OFFSET_MIN_PAIRS:]
            med = _median(r)
            if abs(med - old) > self.window_ns and _median([abs(x - med) for x in r]) <= half:
                q.clear()
                q.extend(r)
                self.offsets_ns[source] = int(round(med))
                self.counts["offsets_moved"] += 1
                return
        med = _median(d)
        if _median([abs(x - med) for x in d]) <= half:
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
