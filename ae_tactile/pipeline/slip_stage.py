# SPDX-License-Identifier: Apache-2.0
"""Slip: contact records -> slip records and the finger's state, in time order.

`SlipStage` feeds the records to the `SlipDetector`; `SlipOrder` decides when: the slip
step of contact events already out is put off while more packets wait on the port (at most
``SLIP_MAX_DEFER_S``), and held while a window that may hold an earlier emission is with
the overlap resolver (at most ``OVERLAP_HOLD_MAX_S``), so that the detector sees every
emission in time order, as offline.

Locks: `SlipOrder.lock` (re-entrant; the step lock) guards the held and put-off events and
the windows waited for, and makes one slip step at a time; inside it `SlipStage.lock`
guards the detector (a timer's `tick` takes it too).
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from typing import Callable, Sequence

import numpy as np

from ae_tactile.pipeline.config import OVERLAP_HOLD_MAX_S, SLIP_MAX_DEFER_S
from ae_tactile.records import ContactRecord, EventType, slip_record
from ae_tactile.slip import LocalizedEvent, SlipConfig, SlipDetector


def _time_ns(r) -> int:
    return r.time_ns


class SlipStage:
    """Contact events -> slip events and the finger's contact state.

    Events are fed in the order they come; the detector processes an event up to
    ``SlipConfig.reorder_tolerance_s`` older than the newest one it has seen with its own
    time stamp, and counts older ones (``counts['rejected_out_of_order']``). `tick` lets
    time pass without events (quiet slip states fall back to STICK): it never advances the
    detector's clock past ``now - lag_s``, so events still in flight are not overtaken.
    Thread-safe: the reader thread feeds events, a timer thread ticks.

    Parameters
    ----------
    config : SlipConfig, optional
        The detector's settings (default: `SlipConfig()`).
    lag_s : float
        How far behind now [s] `tick` keeps the detector's clock (events in flight).

    Returns
    -------
    SlipStage
    """

    def __init__(self, config: SlipConfig | None = None, *, lag_s: float = 0.02):
        self.detector = SlipDetector(config or SlipConfig())
        self.lag_ns = int(lag_s * 1e9)
        self.lock = threading.Lock()
        self.counts: Counter = Counter()

    def process(self, contacts: Sequence[ContactRecord]) -> list[ContactRecord]:
        """Slip events produced by these contact events.

        Parameters
        ----------
        contacts : sequence of ContactRecord
            TOUCH / DETOUCH records, in time order.

        Returns
        -------
        list of ContactRecord
            SLIP_PRECURSOR / SLIP / TEXTURE records (`slip_record`).
        """
        out: list[ContactRecord] = []
        with self.lock:
            for c in contacts:
                self.counts["contacts_in"] += 1
                pol = -1 if c.event_type == EventType.DETOUCH else 1
                cov = c.covariance_m2
                # the localizer's records have the stored types: the detector's cheap path
                # (it still rejects and counts non-finite values)
                ev = LocalizedEvent.trusted(
                    int(c.time_ns),
                    np.asarray(c.point_m, dtype=np.float64),
                    0.5 * (cov + cov.T),
                    pol,
                    float(c.amplitude_v),
                    min(max(float(c.confidence), 0.0), 1.0)
                    if c.confidence == c.confidence
                    else 0.0,
                    int(c.packet_ids[0]) if c.packet_ids else -1,
                )
                for s in self.detector.process(ev):
                    out.append(slip_record(s))
        self.counts["slip_events"] += len(out)
        return out

    def tick(self, now_ns: int):
        """Advance the detector to ``now_ns`` - lag [host ns].

        Parameters
        ----------
        now_ns : int
            Host time now [ns].

        Returns
        -------
        FingerState
            The finger's contact state.
        """
        with self.lock:
            return self.detector.advance(int(now_ns) - self.lag_ns)

    @property
    def state(self):
        """The finger's contact state (`FingerState`)."""
        with self.lock:
            return self.detector.state

    def all_counts(self) -> dict:
        """The stage's counters and the detector's (``slip_*``)."""
        with self.lock:
            d = {f"slip_{k}": v for k, v in self.detector.counts.items()}
        d.update(self.counts)
        return d


class SlipOrder:
    """When the slip step of contact events runs (time order, put off, held for windows).

    Parameters
    ----------
    slip : SlipStage or None
        The slip stage (None: no slip step).
    counts : collections.Counter
        The pipeline's counters (``slip_hold_expired``).
    hold_max_s : float
        Longest wait for the overlap resolver [s].

    Returns
    -------
    SlipOrder
    """

    def __init__(self, slip: SlipStage | None, counts: Counter,
                 hold_max_s: float = OVERLAP_HOLD_MAX_S):
        self.slip = slip
        self.counts = counts
        self.hold_max_s = hold_max_s
        #: where the slip events go (the latest `ContactPipeline.process` call's on_slip)
        self.on_slip: Callable[[list], None] | None = None
        self.lock = threading.RLock()
        self._pending: list = []  # contacts handed out, slip step due (put off)
        self._pending_since = 0.0  # time.monotonic() of the oldest of them [s]
        #: windows with the overlap resolver: id -> (time.monotonic() handed over [s],
        #: earliest possible emission stamp of theirs [ns])
        self._windows_out: dict = {}
        self._held: list = []  # contacts whose slip step waits for a window
        #: earliest possible emission [ns] of the windows about to be fitted in the reader:
        #: `before` goes on with what is older
        self._inline_horizon_ns: int | None = None

    # ------------------------------------------------------------ windows waited for
    def hold_windows(self, items: list) -> None:
        """The slip step waits for these windows: [(id, earliest emission ns)]."""
        if self.slip is None:
            return
        with self.lock:
            now = time.monotonic()
            self._windows_out.update((k, (now, e)) for k, e in items)

    def unhold_windows(self, ids: list) -> None:
        """These windows will not be answered (lost): nothing waits for them."""
        with self.lock:
            for k in ids:
                self._windows_out.pop(k, None)

    def window_done(self, window_id: int) -> None:
        """The resolver answered a window: the slip step of what waited for it runs."""
        with self.lock:
            self._windows_out.pop(window_id, None)
            self.step([])

    # ------------------------------------------------------------ the step
    def step(self, contacts: list) -> None:
        """The slip step of these contact events, in time order with those held back: held
        while a window is with the overlap resolver (at most ``hold_max_s``)."""
        if self.slip is None:
            return
        with self.lock:
            self._held.extend(contacts)
            horizon = self._horizon()
            if horizon is None:
                batch, self._held = self._held, []
            else:
                batch = [c for c in self._held if c.time_ns < horizon]
                if not batch:
                    return
                self._held = [c for c in self._held if c.time_ns >= horizon]
            if not batch:
                return
            if len(batch) > 1:
                batch.sort(key=_time_ns)  # stable: packet order where stamps tie
            slips = self.slip.process(batch)
            on_slip = self.on_slip
            if slips and on_slip is not None:
                on_slip(slips)

    def _horizon(self) -> int | None:
        """Stamp [ns] from which events wait (None: none waits); expires old windows."""
        horizon = self._inline_horizon_ns
        if self._windows_out:
            out = self._windows_out.values()
            if time.monotonic() - min(t for t, _ in out) < self.hold_max_s:
                oldest = min(e for _, e in out)  # nothing the windows hold is older
                horizon = oldest if horizon is None else min(horizon, oldest)
            else:
                self.counts["slip_hold_expired"] += len(self._windows_out)
                self._windows_out.clear()
        return horizon

    def before(self, horizon_ns: int) -> None:
        """Before overlapping windows are fitted in this thread (about a millisecond each):
        the slip step put off while they arrived (earlier packets' contact events), so that
        a slip precursor those decide does not wait for the fits. What is not older than
        ``horizon_ns`` (the windows' earliest possible emission) is held until a later slip
        step (time order, as offline)."""
        pending, self._pending = self._pending, []
        with self.lock:
            self._inline_horizon_ns = horizon_ns
            try:
                self.step(pending)
            finally:
                self._inline_horizon_ns = None

    def after_batch(self, contacts: list, more_waiting: Callable[[], bool] | None) -> None:
        """A batch's contact events are out: their slip step now, or put off (at most
        ``SLIP_MAX_DEFER_S``) while ``more_waiting()`` says more packets wait."""
        if more_waiting is None or self.slip is None:
            self.step(contacts)
            return
        if contacts:
            if not self._pending:
                self._pending_since = time.monotonic()
            self._pending.extend(contacts)
        if self._pending and (
            time.monotonic() - self._pending_since >= SLIP_MAX_DEFER_S or not more_waiting()
        ):
            self.run_pending()

    @property
    def pending(self) -> bool:
        """Contact events handed out whose slip step is still due."""
        return bool(self._pending)

    def run_pending(self) -> None:
        """The slip step of contact events handed out while more packets were waiting."""
        with self.lock:  # the reader's idle call and a hand-out from a timer
            pending, self._pending = self._pending, []
            if pending:
                self.step(pending)

    def release_held(self) -> None:
        """Run the slip step of held events whose wait has expired (a timer calls this)."""
        if self._held:
            self.step([])

    def busy(self) -> bool:
        """A window waited for, or events held or put off."""
        with self.lock:
            return bool(self._windows_out or self._held or self._pending)

    def tick(self, now_ns: int, hand_limit_ns: Callable[[], int | None]):
        """Let time pass in the slip stage (`SlipStage.tick`), never past a held event nor
        (``hand_limit_ns()``, under this lock) an event the hand still holds; returns the
        finger state."""
        with self.lock:
            if self._held:
                now_ns = min(int(now_ns), min(r.time_ns for r in self._held) + self.slip.lag_ns)
            limit = hand_limit_ns()
            if limit is not None:
                now_ns = min(int(now_ns), limit + self.slip.lag_ns)
            return self.slip.tick(now_ns)
