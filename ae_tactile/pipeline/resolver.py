# SPDX-License-Identifier: Apache-2.0
"""`OverlapResolver`: windows holding several emissions, localized emission by emission in
a thread of its own (quick search) and a worker process (exhaustive search,
`ae_tactile.localization.overlap_worker`); `OverlapStage` (`overlaps.py`) decides which
windows reach it. `OverlapResolver._count_lock` guards its counts (a leaf).
"""

from __future__ import annotations

import contextlib
import logging
import pickle
import queue
import subprocess
import sys
import threading
from collections import Counter
from dataclasses import replace
from typing import Callable, Sequence

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import overlap, overlap_worker
from ae_tactile.localization.covariance import with_delay_noise
from ae_tactile.localization.overlap import OverlapReason, PulseLearner
from ae_tactile.pipeline import worker_share
from ae_tactile.pipeline.config import LATE_CHECK_POLL_S, OVERLAP_MAX_PENDING
from ae_tactile.records import source_record

_log = logging.getLogger(__name__)


class OverlapResolver:
    """Localizes every emission of windows that hold several (`resolve_overlaps`) and hands
    the sources to ``on_records(list[ContactRecord])`` from its own thread: one contact
    event per source, naming the shared packet id, stamped at its own emission instant. At
    most ``max_pending`` windows wait; more are counted (``overlap_dropped_backlog``). An
    emission the fit found but too uncertain to hand out (`OverlapPacket.n_dropped`) is
    counted (``overlap_dropped_uncertain``; the first one logged).

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
        on_idle: Callable[[], None] | None = None,
    ):
        self.geometry = geometry
        #: called from this thread when it has no window to answer (the late check)
        self.on_idle = on_idle
        #: () -> the front end's channel delays (4,) [s] the driver's channel-delay learner
        #: applies, or None (`ContactPipeline` sets it): they replace the learnt pulse's own
        self.channel_delays: Callable[[], object] | None = None
        #: () -> the localizer's delay noise (scale, timing sd [s]) or None
        #: (`Localizer.delay_noise`; `ContactPipeline` sets it): the resolved emissions'
        #: covariances carry it as the localizer's do
        self.delay_noise: Callable[[], object] | None = None
        self._delayed = (None, None, None)  # (learnt pulse, delays, the two combined)
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
        self._warned_uncertain = False  # the first dropped emission is logged, once
        self._count_lock = threading.Lock()
        self._queue: queue.Queue = queue.Queue(maxsize=int(max_pending))
        self.ready = threading.Event()  # the worker has warmed up (or is not used)
        #: the process's one worker, where fingertips share a process (`worker_share`)
        self._shared = None
        self._proc = self._start_worker() if use_process else None
        if not use_process:
            self._count("overlap_worker_unavailable")
        self._thread = threading.Thread(target=self._run, name="ae_tactile_overlaps", daemon=True)
        self._thread.start()

    def _start_worker(self):
        if worker_share.enabled():
            self._shared = worker_share.acquire(self.idle)
            if self._shared.proc is None:
                self._count("overlap_worker_unavailable")
            return self._shared.proc
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
        if self.learner is None:
            return self.pulse
        learnt = self.learnt_pulse_at(sample_rate_hz)
        return learnt if learnt is not None else self.pulse

    def learnt_pulse_at(self, sample_rate_hz: float | None = None):
        """The learnt pulse once trusted (at ``sample_rate_hz`` [Hz], when given), else None;
        with the channel delays the driver's channel-delay learner applies (`channel_delays`)
        in place of the pulse's own: from a few dozen single touches the pulse learner
        determines their xy (twist) contrast well, their x and y contrasts (a shift of every
        point, ~|beta| R c for d_k = beta . e_k) poorly; the channel-delay learner identifies
        those over many touches (docs/localization.md, Channel delays)."""
        learner = self.learner
        if learner is None:
            return None
        learnt = learner.pulse if sample_rate_hz is None else learner.pulse_at(sample_rate_hz)
        get = self.channel_delays
        d = get() if (learnt is not None and get is not None) else None
        if d is None:
            return learnt
        d = tuple(float(v) for v in d)
        pulse, delays, combined = self._delayed
        if pulse is not learnt or delays != d:  # one combined pulse per change (its tables)
            combined = replace(learnt, channel_delay_s=d)
            self._delayed = (learnt, d, combined)
        return combined

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
        if res.n_refused:  # emissions cancelling each other: not reported
            self._count("overlap_dropped_refused", res.n_refused)
        if not res.accepted:
            self._count("overlap_rejected_" + res.reason_name)
            return []
        records = [source_record(p, src) for src in res.sources]  # may raise: count after
        noise = self.delay_noise() if self.delay_noise is not None else None
        if noise is not None:
            for rec in records:
                rec.covariance_m2 = with_delay_noise(self.geometry, rec.point_m,
                                                     rec.covariance_m2, noise)
        self._count("overlap_windows_resolved")
        self._count("overlap_sources", len(records))
        if res.n_dropped:
            # fitted emissions not handed out (1-sigma over max_sigma_m or SNR under
            # min_snr_db): counted and logged, never a window's second emission lost unsaid
            self._count("overlap_dropped_uncertain", int(res.n_dropped))
            if not self._warned_uncertain:
                self._warned_uncertain = True
                _log.warning(
                    "the overlap resolver fitted %d emissions in a window and handed out %d: "
                    "the others were too uncertain (counted: overlap_dropped_uncertain)",
                    res.n_fitted, len(records))
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
        if self._proc is not None and (
                yield from self._from_worker(samples, fs, onset, sat, pulse, quick_first)):
            return
        for exhaustive in (False, True) if quick_first else (True,):
            res = self._resolve(samples, fs, onset, sat, pulse, exhaustive)
            yield res
            if res.reason != OverlapReason.DEFERRED:
                return

    def _from_worker(self, samples, fs, onset, sat, pulse, quick_first):
        """The worker process's answers to one window (yielded as `_answers` does); returns
        True when it gave the last one, False when it could not answer (then here)."""
        proc, shared = self._proc, self._shared
        # a shared worker: this window's request and its answers together (the lock stays
        # held across the yield of a DEFERRED quick answer)
        with shared.io_lock if shared is not None else contextlib.nullcontext():
            try:
                pickle.dump((samples, fs, onset, sat, self.geometry, pulse, quick_first),
                            proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
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
                if shared is not None:
                    shared.broken()
                self._count("overlap_worker_unavailable")
                self._stop_worker()
                return False
        yield res
        return True

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
                if self._shared is not None:
                    if not self._shared.wait_ready():
                        raise EOFError("the shared worker did not start")
                elif pickle.load(self._proc.stdout) != "ready":
                    raise pickle.UnpicklingError("no ready message")
            except (OSError, EOFError, pickle.UnpicklingError):
                self._count("overlap_worker_unavailable")
                self._stop_worker()
        self.ready.set()
        while True:
            try:
                item = self._queue.get(timeout=LATE_CHECK_POLL_S if self.on_idle else None)
            except queue.Empty:
                try:
                    self.on_idle()
                except Exception:  # never let the late check stop the resolver
                    self._count("overlap_errors")
                continue
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
        shared, self._shared = self._shared, None
        if shared is not None:
            worker_share.release(shared)
            return
        worker_share.end_worker(proc)

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
        shared = self._shared  # first: the thread clears _proc before _shared
        proc = self._proc
        if self._thread.is_alive() and proc is not None and shared is None:
            # the thread still waits on its own worker (loading its kernels, or busy on a
            # window): end the worker, and the thread ends by itself (EOF on its pipe)
            try:
                proc.kill()
            except OSError:
                pass
