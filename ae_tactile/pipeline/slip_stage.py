# SPDX-License-Identifier: Apache-2.0
"""Slip: localized emissions -> what the hand receives, in time order.

`SlipStage` feeds the localizer's records to the `SlipDetector`, which interprets them:
each emission comes back as an `EmissionRecord` with its reading (touch, release,
micro-slip, slip, texture, unknown) and its contact's id, and the detector's events as
ContactRecords: TOUCH when a contact begins, DETOUCH when it ends, SLIP_PRECURSOR / SLIP /
TEXTURE of a contact. `SlipOrder` decides when: at once for a new emission (a TOUCH is
decided there, so nothing puts the step off), except that emissions later than a window
with the overlap resolver are held until its answer (at most ``OVERLAP_HOLD_MAX_S``), so
that the detector sees every emission in time order, as offline.

Locks: `SlipOrder.lock` (re-entrant; the step lock) guards the held events and
the windows waited for, and makes one slip step at a time; inside it `SlipStage.lock`
guards the detector (a timer's `tick` takes it too).
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from typing import Callable, Sequence

import numpy as np

from ae_tactile.pipeline.config import OVERLAP_HOLD_MAX_S
from ae_tactile.records import (
    ContactRecord,
    EventType,
    contact_snapshot,
    emission_record,
    slip_record,
)
from ae_tactile.slip import LocalizedEvent, SlipConfig, SlipDetector


def _time_ns(r) -> int:
    return r.time_ns


#: the detector's events that go to the hand's ``contacts`` (a contact's begin and end)
CONTACT_EVENTS = (int(EventType.TOUCH), int(EventType.DETOUCH))


class SlipStage:
    """Localized emissions -> contact and slip events, readings and the finger's state.

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
    model : bool, optional
        The detector's fingertip model (`SlipDetector`'s ``model``); None: its default.

    Returns
    -------
    SlipStage
    """

    def __init__(self, config: SlipConfig | None = None, *, lag_s: float = 0.02,
                 model: bool | None = None):
        kw = {} if model is None else {"model": bool(model)}
        self.detector = SlipDetector(config or SlipConfig(), contact_events=True, **kw)
        self.lag_ns = int(lag_s * 1e9)
        self.lock = threading.Lock()
        self.counts: Counter = Counter()

    def process(
        self, contacts: Sequence[ContactRecord], emissions: list | None = None
    ) -> list[ContactRecord]:
        """The detector's events decided by these localized emissions.

        Parameters
        ----------
        contacts : sequence of ContactRecord
            The localizer's records (TOUCH: compression, DETOUCH: rarefaction), in time
            order.
        emissions : list, optional
            Gets one `EmissionRecord` per record, with its reading and contact id (a
            record the detector rejects: UNKNOWN, no contact).

        Returns
        -------
        list of ContactRecord
            In the order decided (`slip_record`, with the contact's id): TOUCH when a
            contact begins, DETOUCH when one ends, SLIP_PRECURSOR / SLIP / TEXTURE.
        """
        out: list[ContactRecord] = []
        det = self.detector
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
                for s in det.process(ev):
                    out.append(slip_record(s))
                if emissions is not None:
                    reading, cid = det.last_reading
                    emissions.append(emission_record(c, reading, cid))
        self.counts["slip_events"] += len(out)
        return out

    def pop_events(self) -> list[ContactRecord]:
        """The detector's events decided while time passed (`tick`: a contact's DETOUCH
        once its release is confirmed), each returned once.

        Returns
        -------
        list of ContactRecord
            Oldest first (often none).
        """
        with self.lock:
            return [slip_record(s) for s in self.detector.pop_events()]

    def contacts_key(self) -> tuple:
        """(id, state) of each current contact: cheap (no snapshot), for telling whether
        `contacts` changed."""
        with self.lock:
            return tuple((c.id, int(c.state)) for c in self.detector.contacts if c.confirmed)

    @property
    def contacts(self) -> list:
        """The current contacts (`ContactSnapshot`, oldest first): those begun (their
        TOUCH sent) and not ended."""
        with self.lock:
            infos = self.detector.contact_infos()
        return [contact_snapshot(i) for i in infos if i.confirmed]

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
    """When the slip step of localized emissions runs (at once, in time order, held for
    windows) and where its outputs go (``on_contacts``, ``on_slip``, ``on_emissions``).

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
        #: where the outputs go (the latest `ContactPipeline.process` call's): a contact's
        #: TOUCH / DETOUCH, its SLIP_PRECURSOR / SLIP / TEXTURE, every emission's record
        self.on_contacts: Callable[[list], None] | None = None
        self.on_slip: Callable[[list], None] | None = None
        self.on_emissions: Callable[[list], None] | None = None
        self.lock = threading.RLock()
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
        """The slip step of these localized emissions, in time order with those held back:
        held while a window is with the overlap resolver (at most ``hold_max_s``); its
        outputs handed out. Without a slip stage, each emission goes out at once with the
        reading UNKNOWN."""
        if self.slip is None:
            on_emissions = self.on_emissions
            if contacts and on_emissions is not None:
                on_emissions([emission_record(c) for c in contacts])
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
            emissions: list = []
            for c in batch:  # each emission's TOUCH / slip events out before the next's step
                events = self.slip.process((c,), emissions)
                if events:
                    self._hand_out(events, [])
            self._hand_out([], emissions)

    def _hand_out(self, events: list, emissions: list) -> None:
        """The slip step's outputs to their callbacks: the contacts' begin / end first (the
        reflex), then the slip events, then the emissions with their readings."""
        if events:
            contact = [r for r in events if r.event_type in CONTACT_EVENTS]
            if contact and self.on_contacts is not None:
                self.on_contacts(contact)
            slips = [r for r in events if r.event_type not in CONTACT_EVENTS] if contact \
                else events
            if slips and self.on_slip is not None:
                self.on_slip(slips)
        if emissions and self.on_emissions is not None:
            self.on_emissions(emissions)

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

    def step_before(self, contacts: list, horizon_ns: int) -> None:
        """Before overlapping windows are fitted in this thread (about a millisecond each):
        the slip step of the batch's other emissions older than ``horizon_ns`` (the
        windows' earliest possible emission), so that a TOUCH or slip precursor they
        decide does not wait for the fits; the rest are held until a later step (time
        order, as offline)."""
        with self.lock:
            self._inline_horizon_ns = horizon_ns
            try:
                self.step(contacts)
            finally:
                self._inline_horizon_ns = None

    def after_batch(self, contacts: list, more_waiting: Callable[[], bool] | None = None
                    ) -> None:
        """A batch's emissions are localized: their slip step now (``more_waiting`` is not
        asked: the step decides the batch's TOUCHes, nothing may wait for it)."""
        self.step(contacts)

    @property
    def pending(self) -> bool:
        """Emissions whose slip step was put off: never (the step runs at once)."""
        return False

    def run_pending(self) -> None:
        """Nothing: the slip step runs at once (kept for callers of the idle work)."""

    def release_held(self) -> None:
        """Run the slip step of held events whose wait has expired (a timer calls this)."""
        if self._held:
            self.step([])

    def busy(self) -> bool:
        """A window waited for, or events held or put off."""
        with self.lock:
            return bool(self._windows_out or self._held)

    def tick(self, now_ns: int, hand_limit_ns: Callable[[], int | None]):
        """Let time pass in the slip stage (`SlipStage.tick`), never past a held event nor
        (``hand_limit_ns()``, under this lock) an event the hand still holds; the contacts
        ended meanwhile go to ``on_contacts`` (their DETOUCH); returns the finger state."""
        with self.lock:
            if self._held:
                now_ns = min(int(now_ns), min(r.time_ns for r in self._held) + self.slip.lag_ns)
            limit = hand_limit_ns()
            if limit is not None:
                now_ns = min(int(now_ns), limit + self.slip.lag_ns)
            state = self.slip.tick(now_ns)
            events = self.slip.pop_events()
            if events:
                self._hand_out(events, [])
            return state
