# SPDX-License-Identifier: Apache-2.0
"""Overlaps: windows holding several emissions, localized emission by emission.

`OverlapResolver` answers windows in its own thread (quick search) and worker process
(exhaustive search, `ae_tactile.localization.overlap_worker`). `OverlapStage` is the
pipeline's side of it: which windows are answered in the reader (the first
``inline_max`` of a batch), which go to the resolver (the others, the second window of a
pair, hard ones), and the duplicate check that keeps one emission from being handed out
twice (by the reader and the resolver's thread).

Locks: `OverlapStage.lock` guards the duplicate check's memory (``_recent``,
``_pending_ns``, ``_resolved_newest_ns``); it is taken alone or inside the slip order's
lock, never around another. `OverlapResolver._count_lock` guards its counts (a leaf).
"""

from __future__ import annotations

import math
import pickle
import queue
import subprocess
import sys
import threading
from collections import Counter, deque
from typing import Callable, Sequence

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import overlap, overlap_worker
from ae_tactile.localization.overlap import OverlapReason, PulseLearner
from ae_tactile.pipeline.config import (
    COVERED_TOL_S,
    DUPLICATE_DISTANCE_M,
    DUPLICATE_TIME_S,
    ECHO_LEARN_CONFIDENCE,
    OVERLAP_INLINE_MAX,
    OVERLAP_MAX_PENDING,
    RECENT_MARGIN_NS,
)
from ae_tactile.records import onset_ns, source_record


class OverlapResolver:
    """Localizes every emission of windows that hold several (`resolve_overlaps`) and hands
    the sources to ``on_records(list[ContactRecord])`` from its own thread: one contact
    event per source, naming the shared packet id, stamped at its own emission instant. At
    most ``max_pending`` windows wait; more are counted (``overlap_dropped_backlog``).

    The quick search (one compiled call, mostly without the interpreter lock) runs in this
    thread, beside the reader; the exhaustive search of a window whose quick answer is
    DEFERRED (tens of ms of numpy and Python, holding the lock) runs in a worker process
    (`ae_tactile.localization.overlap_worker`, warmed up before the first window), as does
    the quick search where it is not compiled (no numba, a lossy medium). Where the
    process cannot run (``use_process=False``, or it failed), this thread does it
    (``overlap_worker_unavailable``). The pulse is the learner's once trusted
    (`current_pulse`).

    ``idle`` (a driver on cores of its own): this thread and the worker run as SCHED_IDLE,
    so the reader on their core takes it the moment it wakes. Otherwise the worker is
    niced and this thread keeps its priority: on cores shared with busy processes an
    idle-class thread holding the interpreter lock or a pipeline lock could stall the
    reader indefinitely.
    """

    def __init__(
        self,
        geometry: FingertipGeometry,
        on_records: Callable[[list], None],
        *,
        max_pending: int = OVERLAP_MAX_PENDING,
        pulse=None,
        use_process: bool = True,
        on_done: Callable[[object], None] | None = None,
        idle: bool = False,
        learner: PulseLearner | None = None,
    ):
        self.geometry = geometry
        #: the pulse learnt from the device's single emissions: used once it is trusted
        self.learner = learner
        self.idle = bool(idle)
        #: what the thread's priority became ("idle", "nice" or "": as created)
        self.priority = ""
        self.on_records = on_records
        #: called with each window once it is answered (sources handed over, rejected or
        #: failed), after ``on_records``
        self.on_done = on_done
        self.pulse = pulse
        self.counts: Counter = Counter()  # written under _count_lock (two threads count)
        self._count_lock = threading.Lock()
        self._queue: queue.Queue = queue.Queue(maxsize=int(max_pending))
        self.ready = threading.Event()  # the worker has warmed up (or is not used)
        self._proc = self._start_worker() if use_process else None
        if not use_process:
            self._count("overlap_worker_unavailable")
        self._thread = threading.Thread(target=self._run, name="ae_tactile_overlaps", daemon=True)
        self._thread.start()

    def _start_worker(self):
        try:
            # its own session: a Ctrl-C at the terminal (sent to the foreground process
            # group) reaches the node, which ends the worker by closing its stdin, and
            # never interrupts the worker's imports with a traceback
            return subprocess.Popen(
                [sys.executable, "-m", "ae_tactile.localization.overlap_worker"]
                + ([overlap_worker.IDLE_FLAG] if self.idle else []),
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                start_new_session=True,
            )
        except OSError:
            self._count("overlap_worker_unavailable")
            return None

    def _count(self, key: str, n: int = 1) -> None:
        with self._count_lock:
            self.counts[key] += n

    def snapshot_counts(self) -> dict:
        """A consistent copy of the counts (the reader and the resolver's thread write them),
        with the pulse learner's state (``pulse_converged``, ``pulse_loaded``,
        ``pulse_inliers``, ``pulse_fits``, ``pulse_fit_errors``, ``pulse_candidates_kept``,
        ``pulse_candidates_offered``)."""
        with self._count_lock:
            out = dict(self.counts)
        if self.learner is not None:
            st = self.learner.state()
            out.update({k: int(v) for k, v in st.items() if k != "pulse_chi2_median"})
        return out

    def current_pulse(self, sample_rate_hz: float | None = None):
        """The pulse the fits of windows at ``sample_rate_hz`` [Hz] use: the learnt one
        once trusted (at that rate, when given), else the configured one (None: the
        default `PulseModel.for_sample_rate`, untrusted: a window it does not explain is
        rejected and counted, ``overlap_rejected_UNRESOLVED``)."""
        learner = self.learner
        if learner is None:
            return self.pulse
        learnt = learner.pulse if sample_rate_hz is None else learner.pulse_at(sample_rate_hz)
        return learnt if learnt is not None else self.pulse

    def submit(self, packets: Sequence, *, quick_first: bool = True, hard: bool = False) -> list:
        """Queue windows for the resolver (``quick_first=False``: windows whose quick
        answer was DEFERRED, for the exhaustive search only; ``hard``: the worker process
        gives the quick answer too, as for a window likely DEFERRED, so that this thread
        does no fitting beside the reader); returns those queued (the rest are counted)."""
        queued = []
        for p in packets:
            try:
                self._queue.put_nowait((p, bool(quick_first), bool(hard)))
                queued.append(p)
            except queue.Full:
                self._count("overlap_dropped_backlog")
        return queued

    #: first arrivals (host ns) of the emissions of the latest `resolve_now` answer
    arrivals_ns: list = []

    def resolve_now(self, p) -> list | None:
        """The quick answer to one window in the calling thread (the reader's; one compiled
        call, about 0.5-1 ms): its emissions' contact events ([] when it is rejected), or None
        when the worker has to answer it (DEFERRED, or the fit failed here: then `submit`
        it with ``quick_first=False``). Never raises."""
        self.arrivals_ns = []
        try:
            fs = float(p.sample_rate_hz)
            res = self._resolve(np.asarray(p.samples_v, dtype=np.float64), fs,
                                int(p.onset_index), bool(getattr(p, "saturated", False)),
                                self.current_pulse(fs), False)
            records = self._records(p, res)
            if records is not None:
                stamp = int(p.stamp_ns)
                self.arrivals_ns = [
                    stamp + float(np.min(src.arrival_times_s)) * 1e9 for src in res.sources
                ]
        except Exception:  # never let one window stop the reader: the worker tries it
            self._count("overlap_errors")
            return None
        if records is not None:
            self._count("overlap_answered_in_reader")
        return records

    def _resolve(self, samples, fs, onset, sat, pulse, exhaustive):
        """`resolve_overlaps` of one window (4, M) here: its OverlapPacket."""
        with np.errstate(all="ignore"):
            return overlap.resolve_overlaps(
                samples[None], fs, [onset], geometry=self.geometry, pulse=pulse,
                saturated=[sat], exhaustive=exhaustive)[0]

    def _records(self, p, res) -> list | None:
        """Contact events of one answer (counted), None when it is DEFERRED."""
        if res.reason == OverlapReason.DEFERRED:
            self._count("overlap_deferred")
            return None
        if not res.accepted:
            self._count("overlap_rejected_" + res.reason_name)
            return []
        records = [source_record(p, src) for src in res.sources]  # may raise: count after
        self._count("overlap_windows_resolved")
        self._count("overlap_sources", len(records))
        return records

    def pending(self) -> int:
        """Windows queued or being resolved: the queue's unfinished tasks (one per window
        put, done once its records are handed on), so that no moment between taking a
        window and working on it reads as idle."""
        with self._queue.mutex:
            return self._queue.unfinished_tasks

    def _quick_here(self, sample_rate_hz: float | None = None) -> bool:
        """The quick search runs in this thread: compiled (numba, a lossless medium), it
        spends most of its ~0.5 ms without the interpreter lock, so the reader goes on
        beside it, and the answer needs no trip to the worker process."""
        pulse = self.current_pulse(sample_rate_hz)
        lossless = pulse is None or not pulse.attenuation_db_per_m_at_1mhz > 0
        return overlap._kernels.NUMBA_AVAILABLE and lossless

    def _answers(self, p, quick_first: bool = True, hard: bool = False):
        """The OverlapPackets of one window: the quick answer (computed here when compiled,
        `_quick_here`, and the window not ``hard``; else by the worker process) and, when
        it is DEFERRED, the exhaustive search's from the worker process (only the latter
        when not ``quick_first``; computed here when the process is not available)."""
        samples = np.asarray(p.samples_v, dtype=np.float64)
        fs, onset = float(p.sample_rate_hz), int(p.onset_index)
        sat = bool(getattr(p, "saturated", False))
        pulse = self.current_pulse(fs)
        if quick_first and not hard and self._quick_here(fs):
            try:
                res = self._resolve(samples, fs, onset, sat, pulse, False)
            except Exception:  # counted; the worker process answers the window instead
                self._count("overlap_errors")
            else:
                self._count("overlap_quick_in_thread")
                yield res
                if res.reason != OverlapReason.DEFERRED:
                    return
                quick_first = False
        proc = self._proc
        if proc is not None:
            try:
                pickle.dump(
                    (samples, fs, onset, sat, self.geometry, pulse, quick_first),
                    proc.stdin,
                    protocol=pickle.HIGHEST_PROTOCOL,
                )
                proc.stdin.flush()
                res = pickle.load(proc.stdout)
                if isinstance(res, str):
                    raise RuntimeError(res)
                self._count("overlap_worker_answers")
                if quick_first and res.reason == OverlapReason.DEFERRED:
                    yield res
                    res = pickle.load(proc.stdout)
                    if isinstance(res, str):
                        raise RuntimeError(res)
                    self._count("overlap_worker_answers")
            except (OSError, EOFError, pickle.UnpicklingError):
                self._count("overlap_worker_unavailable")
                self._stop_worker()
            else:
                yield res
                return
        for exhaustive in (False, True) if quick_first else (True,):
            res = self._resolve(samples, fs, onset, sat, pulse, exhaustive)
            yield res
            if res.reason != OverlapReason.DEFERRED:
                return

    def _done(self, p) -> None:
        if self.on_done is not None:
            try:
                self.on_done(p)
            except Exception:
                self._count("overlap_errors")

    def _run(self) -> None:
        if self.idle:  # this thread only: the reader, on the same core, comes first
            self.priority = overlap_worker.background_priority(idle=True)
        if self._proc is not None:
            try:
                if pickle.load(self._proc.stdout) != "ready":
                    raise pickle.UnpicklingError("no ready message")
            except (OSError, EOFError, pickle.UnpicklingError):
                self._count("overlap_worker_unavailable")
                self._stop_worker()
        self.ready.set()
        while True:
            item = self._queue.get()
            if item is None:
                self._queue.task_done()
                self._stop_worker()
                return
            p, quick_first, hard = item
            told = False  # on_done called (the quick answer said DEFERRED)
            try:
                for res in self._answers(p, quick_first, hard):
                    records = self._records(p, res)
                    if records is None:
                        # a hard window: what waits for it goes on; its emissions, if
                        # any, come from the exhaustive search, late, with their stamps
                        self._done(p)
                        told = True
                        continue
                    if records:
                        self.on_records(records)
            except Exception:  # never let one window stop the resolver
                self._count("overlap_errors")
            finally:
                if not told:
                    self._done(p)
                self._queue.task_done()

    def _stop_worker(self) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        try:
            proc.stdin.close()  # EOF: the worker exits
            proc.wait(2.0)
        except (OSError, subprocess.TimeoutExpired):
            proc.kill()
            proc.wait()

    def close(self) -> None:
        """Stop the thread and the worker process (pending windows are given up)."""
        while True:
            try:
                self._queue.get_nowait()
            except queue.Empty:
                break
            self._queue.task_done()  # given up
        try:
            self._queue.put_nowait(None)
        except queue.Full:
            pass
        self._thread.join(3.0)


def earliest_emission_ns(p, geometry: FingertipGeometry) -> int:
    """Earliest possible emission stamp of a window [ns]: its emissions are at most one
    sphere diameter's travel time older than its first sample."""
    g = geometry
    return int(p.stamp_ns) - int(math.ceil(2.0 * g.radius_m / g.sound_speed_m_s * 1e9))


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

    Returns
    -------
    OverlapStage
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
        self._on_late, self._on_window_done = on_late, on_window_done
        self._on_hold, self._on_unhold = on_hold, on_unhold
        self.lock = threading.Lock()
        #: the pulse learnt from the accepted single emissions (`offer_singles`), fitted in
        #: a process of its own from the first window with overlaps on (`register`); the
        #: resolver uses it once trusted
        self.pulse_learner = PulseLearner(background="process", on_demand=True)
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
                learner=self.pulse_learner,
            )
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

    def _window_done(self, p) -> None:
        """The resolver answered a window: the slip step of what waited for it runs."""
        with self.lock:
            self._pending_ns.pop(id(p), None)
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
            fresh = records
            if rec and (
                resolved
                or min(r.time_ns for r in records)
                <= self._resolved_newest_ns + DUPLICATE_TIME_S * 1e9
            ):
                fresh = _not_in(records, np.array(rec, dtype=float))
                if len(fresh) < len(records):
                    self.counts["overlap_duplicates"] += len(records) - len(fresh)
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
        """Windows with the resolver (queued or being answered)."""
        return 0 if self.resolver is None else self.resolver.pending()

    def close(self) -> None:
        """Stop the resolver's thread and worker, and the pulse learner's fit."""
        self.pulse_learner.close()
        if self.resolver is not None:
            self.resolver.close()
