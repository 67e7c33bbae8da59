# SPDX-License-Identifier: Apache-2.0
"""Overlaps: windows holding several emissions, localized emission by emission.

`OverlapResolver` (`resolver.py`) answers windows in its own thread (quick search) and
worker process (exhaustive search). `OverlapStage` is the pipeline's side of it: which
windows are answered in the reader (the first ``inline_max`` of a batch), which go to the
resolver (the others, the second window of a pair, hard ones), and the duplicate check
that keeps one emission from being handed out twice (by the reader and the resolver's
thread).

Locks: `OverlapStage.lock` guards the duplicate check's memory (``_recent``,
``_pending_ns``, ``_resolved_newest_ns``); it is taken alone or inside the slip order's
lock, never around another. The late check (`late_check.py`) looks at single emissions
again in the resolver's thread.
"""

from __future__ import annotations

import threading
from collections import Counter, deque
from typing import Callable

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization.overlap import PulseLearner
from ae_tactile.pipeline.config import (
    COVERED_TOL_S,
    DUPLICATE_DISTANCE_M,
    DUPLICATE_TIME_S,
    ECHO_LEARN_CONFIDENCE,
    OVERLAP_INLINE_MAX,
    RECENT_MARGIN_NS,
)
from ae_tactile.pipeline.late_check import LateCheck
from ae_tactile.pipeline.resolver import OverlapResolver
from ae_tactile.records import earliest_emission_ns, onset_ns


def _not_in(records: list, recent) -> list:
    """The records with no row of recent (N, 4: t ns, x, y, z) within DUPLICATE_TIME_S and
    DUPLICATE_DISTANCE_M."""
    d2_max = DUPLICATE_DISTANCE_M**2
    keep = []
    for r in records:
        near = np.abs(recent[:, 0] - r.time_ns) <= DUPLICATE_TIME_S * 1e9
        if near.any():
            dp = recent[near, 1:] - np.asarray(r.point_m, dtype=float)
            if (np.einsum("ij,ij->i", dp, dp) <= d2_max).any():
                continue
        keep.append(r)
    return keep


class OverlapStage:
    """The pipeline's overlap bookkeeping: inline answers, hand-off to the resolver, and the
    duplicate check.

    Parameters
    ----------
    counts : collections.Counter
        The pipeline's counters (``overlap_covered``, ``overlap_duplicates``).
    on_late : callable
        ``on_late(records)``: the resolver's emissions, from its thread.
    on_window_done : callable
        ``on_window_done(window_id)``: the resolver answered a window.
    on_hold, on_unhold : callable
        ``on_hold([(window_id, earliest_ns)])``: windows the slip step waits for;
        ``on_unhold(window_ids)``: windows lost (backlog) it must not wait for.
    inline_max : int
        Overlapping windows per batch answered in the reader.
    covered_tol_s : float
        `covered` tolerance [s]; 0 answers every window on its own.
    idle : bool
        The resolver's thread and worker as SCHED_IDLE.
    """

    def __init__(
        self,
        counts: Counter,
        on_late: Callable[[list], None],
        on_window_done: Callable[[int], None],
        on_hold: Callable[[list], None],
        on_unhold: Callable[[list], None],
        *,
        inline_max: int = OVERLAP_INLINE_MAX,
        covered_tol_s: float = COVERED_TOL_S,
        idle: bool = False,
        resolver: OverlapResolver | None = None,
    ):
        self.counts = counts
        self.inline_max = inline_max
        self.covered_tol_s = covered_tol_s
        self.idle = idle
        self.resolver = resolver
        #: () -> the channel delays [s] the driver's localizer applies, or None: handed to
        #: the resolver (`OverlapResolver.channel_delays`)
        self.channel_delays: Callable[[], object] | None = None
        #: () -> the localizer's delay noise or None (`OverlapResolver.delay_noise`)
        self.delay_noise: Callable[[], object] | None = None
        self._on_late, self._on_window_done = on_late, on_window_done
        self._on_hold, self._on_unhold = on_hold, on_unhold
        self.lock = threading.Lock()
        #: the pulse learnt from the accepted single emissions (`offer_singles`), fitted in
        #: a process of its own from the first window with overlaps on (`register`); the
        #: resolver uses it once trusted
        self.pulse_learner = PulseLearner(background="process", on_demand=True)
        #: single emissions handed out, to be looked at again for a late second one
        self.late = LateCheck(counts)
        #: the late check runs only while the reader is idle: not inside `process`
        #: (``reader_active``) and, where set, no bytes waiting on its port
        #: (``reader_backlog()``, e.g. the link's ``unread_bytes``: safe from any thread)
        self.reader_active = False
        self.reader_backlog: Callable[[], int] | None = None
        #: sequence id -> point [m] handed out, of the late-checked windows with the resolver
        self._late_out: dict = {}
        self._late_busy = 0  # 1 while the resolver's thread checks (`pending`)
        #: (stamp ns, x, y, z) of the contact events handed out that a window still with the
        #: resolver could hold again (duplicate check), oldest first
        self._recent: deque = deque()
        #: windows with the resolver: id -> earliest possible emission stamp [ns]
        self._pending_ns: dict = {}
        self._resolved_newest_ns: int = -(1 << 62)  # newest stamp the resolver handed out
        #: (host ns, gave events) of the first arrivals of emissions resolved in the reader
        #: lately, and of the triggers of windows answered there (`covered`)
        self._arrivals_ns: deque = deque(maxlen=16)

    def start(self, geometry: FingertipGeometry, wait_s: float = 0.0) -> None:
        """Start the resolver (and its worker process) unless running; wait up to wait_s [s]
        for the worker to be warm."""
        self._body(geometry)
        if self.resolver is None:
            self.resolver = OverlapResolver(
                geometry, self._on_late, on_done=self._window_done, idle=self.idle,
                learner=self.pulse_learner, on_idle=self._late_turn,
            )
        self.resolver.channel_delays = self.channel_delays
        self.resolver.delay_noise = self.delay_noise
        if wait_s > 0:
            self.resolver.ready.wait(wait_s)

    def _body(self, geometry: FingertipGeometry) -> None:
        """Another body than the pulse learner's: it starts again on this one (an equal
        body is taken as it is)."""
        if self.pulse_learner.geometry != geometry:
            self.pulse_learner.reset()
        self.pulse_learner.geometry = geometry

    def offer_singles(self, packets, contacts: list, geometry: FingertipGeometry) -> int:
        """Queue the batch's single emissions the pipeline kept (suspects and interference
        withdrawn) for the pulse learner (`PulseLearner.enqueue_records`, confidence >=
        ECHO_LEARN_CONFIDENCE as for the screens' learners; another body resets it); the
        fit runs in a process of its own. Cheap: the reader calls it per batch. Returns
        the candidates queued."""
        if self.pulse_learner.geometry is not geometry:
            self._body(geometry)
        return self.pulse_learner.enqueue_records(packets, contacts, ECHO_LEARN_CONFIDENCE)

    def check_later(self, packets, contacts: list) -> None:
        """Queue the batch's single emissions for the late check (`LateCheck.offer`; only
        while the resolver runs), remembered by the duplicate check until checked."""
        if self.resolver is None or not contacts:
            return
        learner = self.pulse_learner
        taken, dropped = self.late.offer(
            packets, contacts, lambda fs: learner.pulse_at(fs) is not None)
        if taken or dropped:
            g = self.resolver.geometry
            with self.lock:
                self._pending_ns.update((id(p), earliest_emission_ns(p, g)) for p in taken)
                for p in dropped:
                    self._pending_ns.pop(id(p), None)

    def _late_turn(self) -> None:
        """The resolver's thread, no window to answer and the reader idle: check waiting
        single emissions; a packet found to hold a second emission goes to the resolver as
        a window (the reflex path never waits for a check: while the reader is busy they
        wait, and beyond LATE_CHECK_MAX the oldest are counted unchecked)."""
        if not len(self.late) or self.reader_active:
            return
        backlog = self.reader_backlog
        if backlog is not None and backlog() > 0:
            return
        self._late_busy = 1  # `pending` counts the packets being checked till handed on
        try:
            found, clean = self.late.run(self.resolver.geometry, self.resolver.learnt_pulse_at)
            if found:  # the emission each handed out already: its answer's nearest source
                with self.lock:
                    self._late_out.update((p.sequence_id, pt) for p, pt in found)
            queued = self.resolver.submit([p for p, _ in found]) if found else []
        finally:
            self._late_busy = 0
        gone = clean + [p for p, _ in found if all(p is not q for q in queued)]
        if gone:
            with self.lock:
                for p in gone:
                    self._pending_ns.pop(id(p), None)

    def _window_done(self, p) -> None:
        """The resolver answered a window: the slip step of what waited for it runs."""
        with self.lock:
            self._pending_ns.pop(id(p), None)
            self._late_out.pop(p.sequence_id, None)
        self._on_window_done(id(p))

    def register(self, windows: list, geometry: FingertipGeometry) -> None:
        """Windows for the resolver: their earliest possible emission stamps keep the
        duplicate check's memory until they are answered. The pulse learner fits from
        now on."""
        with self.lock:
            self._pending_ns.update((id(p), earliest_emission_ns(p, geometry)) for p in windows)
        self.pulse_learner.want()

    def claim(self, records: list, *, resolved: bool) -> list:
        """The records whose emission was not handed out already (none earlier within
        DUPLICATE_TIME_S and DUPLICATE_DISTANCE_M: |dt| <= T and |dp| <= D), remembered
        for as long as a window with the resolver could hold their emissions; the others
        are counted (``overlap_duplicates``). One step under the lock: the reader and the
        resolver's thread can never both hand out one emission. ``resolved``: the
        resolver's answers (checked always; the hot path's events only when the resolver
        already handed out emissions that recent, i.e. the reader fell behind)."""
        if not records:
            return records
        with self.lock:
            rec = self._recent
            fresh = self._drop_late_first(records) if self._late_out else records
            if rec and fresh and (
                resolved
                or min(r.time_ns for r in fresh)
                <= self._resolved_newest_ns + DUPLICATE_TIME_S * 1e9
            ):
                n = len(fresh)
                fresh = _not_in(fresh, np.array(rec, dtype=float))
                if len(fresh) < n:
                    self.counts["overlap_duplicates"] += n - len(fresh)
            if not fresh:
                return fresh
            if resolved:
                newest = max(r.time_ns for r in fresh)
                self._resolved_newest_ns = max(self._resolved_newest_ns, newest)
            rec.extend((r.time_ns, *r.point_m) for r in fresh)
            pending = self._pending_ns
            keep_from = (min(pending.values()) if pending else rec[-1][0]) - RECENT_MARGIN_NS
            # (stamps may go back, e.g. after a device reset: never more than all of them)
            while rec and rec[0][0] < keep_from:
                rec.popleft()
        return fresh

    def _drop_late_first(self, records: list) -> list:
        """(under the lock) A late-checked window's answer: the source nearest the point
        handed out for it already is that emission (counted ``overlap_duplicates``)."""
        out, by_packet = [], {}
        for r in records:
            if r.packet_ids and r.packet_ids[0] in self._late_out:
                by_packet.setdefault(r.packet_ids[0], []).append(r)
            else:
                out.append(r)
        for pid, rs in by_packet.items():
            point = self._late_out.pop(pid)
            first = min(rs, key=lambda r: float(np.sum((np.asarray(r.point_m) - point) ** 2)))
            self.counts["overlap_duplicates"] += 1
            out += [r for r in rs if r is not first]
        return out

    def overlapping(self, windows: list, on_contacts, geometry: FingertipGeometry) -> list:
        """Windows holding several emissions (registered): the first ``inline_max`` of the
        batch get the quick answer here, in the reader's thread (their emissions reach the
        hand soonest, in time for the slip step); the others, those whose quick answer is
        DEFERRED, and a window triggered by an emission (or whose trigger matches a window)
        just answered here, the second window of a pair, go to the resolver. Returns the
        contact events handed out here."""
        self.start(geometry)
        self.resolver.geometry = geometry
        found: list = []
        later: list = []  # (window, quick_first, slip step waits for it, hard)
        inline = 0
        for p in windows:
            covered = self.covered(p)
            if covered is not None:
                # the second window of a pair; hard when the first one gave no events here
                # (DEFERRED): the worker process gives both its answers
                self.counts["overlap_covered"] += 1
                later.append((p, True, covered, covered))
                continue
            if inline >= self.inline_max:
                later.append((p, True, True, False))
                continue
            inline += 1
            records = self.resolver.resolve_now(p)
            self._arrivals_ns.append((onset_ns(p), bool(records)))
            if records is None:  # DEFERRED (or failed here): the worker's exhaustive search
                later.append((p, False, False, True))
                continue
            self._arrivals_ns.extend((t, True) for t in self.resolver.arrivals_ns)
            fresh = self.claim(records, resolved=True)
            with self.lock:
                self._pending_ns.pop(id(p), None)
            if fresh:
                on_contacts(fresh)
                found.extend(fresh)
        if later:
            self._to_worker(later, geometry)
        return found

    def covered(self, p) -> bool | None:
        """None, unless the window's trigger (within ``covered_tol_s``) is the first arrival
        of an emission resolved in the reader or the trigger of a window answered there;
        then whether the slip step must wait for it (that window gave no events)."""
        if not self._arrivals_ns or self.covered_tol_s <= 0:
            return None
        t_ns = onset_ns(p)
        tol = self.covered_tol_s * 1e9
        match = [produced for t, produced in self._arrivals_ns if abs(t_ns - t) <= tol]
        return None if not match else not any(match)

    def _to_worker(self, later: list, geometry: FingertipGeometry) -> None:
        """Hand (window, quick_first, hold, hard) to the resolver (registered already for
        the duplicate check); the slip step waits for the ``hold`` ones, registered before
        the resolver can answer."""
        windows = [p for p, _, _, _ in later]
        held = [p for p, _, hold, _ in later if hold]
        if held:
            self._on_hold([(id(p), earliest_emission_ns(p, geometry)) for p in held])
        queued = []
        # quick answers first: the slip step may wait for them (a pair's hard second
        # window too); exhaustive searches of windows DEFERRED here (nothing waits) last
        for quick_first, hard in ((True, False), (True, True), (False, True)):
            ws = [p for p, q, _, h in later if q == quick_first and h == hard]
            if ws:
                queued += self.resolver.submit(ws, quick_first=quick_first, hard=hard)
        if len(queued) < len(windows):
            lost = {id(p) for p in windows} - {id(p) for p in queued}
            with self.lock:
                for k in lost:
                    self._pending_ns.pop(k, None)
            self._on_unhold(list(lost))

    def pending(self) -> int:
        """Windows with the resolver (queued or being answered) and single emissions
        waiting for the late check."""
        if self.resolver is None:
            return 0
        return self.resolver.pending() + len(self.late) + self._late_busy

    def close(self) -> None:
        """Stop the resolver's thread and worker, and the pulse learner's fit."""
        self.pulse_learner.close()
        if self.resolver is not None:
            self.resolver.close()
