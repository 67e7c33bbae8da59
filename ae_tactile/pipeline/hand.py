# SPDX-License-Identifier: Apache-2.0
"""Hand: the coincidence test of the fingertips of one hand (`ae_tactile.dsp.coincidence`).

An apex packet the packet tests kept where no echo test runs is held for
``hand_coincidence_wait_s``; one another fingertip saw at once is interference
(``rejected_INTERFERENCE_HAND``); every later event of the fingertip waits behind a held
packet (a release never overtakes its touch).

Locks: `HandStage.release_lock` makes one thread at a time hand out events while the hand
holds some (the reader's `ContactPipeline.process`, `release_coincidence` from the reader or
a timer); it is the outermost lock. `HandStage.lock` guards the `HandCoincidence`, its
reports and the apex onsets to report; it is innermost (nothing is taken inside it).
"""

from __future__ import annotations

import threading
from collections import Counter

from ae_tactile.dsp.coincidence import HandCoincidence
from ae_tactile.pipeline.config import APEX_OUT_MAX


def _time_ns(r) -> int:
    return r.time_ns


class HandStage:
    """The fingertip's part in the hand's coincidence test.

    Parameters
    ----------
    counts : collections.Counter
        The pipeline's counters (``rejected_INTERFERENCE_HAND``).
    hand : HandCoincidence, optional
        The test (None: off until `enable`).

    Returns
    -------
    HandStage
    """

    def __init__(self, counts: Counter, hand: HandCoincidence | None = None):
        self.counts = counts
        #: the coincidence test of the fingertips of one hand; None: off
        self.hand = hand
        self.lock = threading.Lock()
        self.release_lock = threading.Lock()
        self._apex_out: list = []  # apex onsets [ns] to report to the hand

    def enable(self, window_s: float | None = None, wait_s: float | None = None) -> None:
        """Switch the test on or change its settings [s] (ValueError on bad settings: nothing
        changed then); the reports, held packets and counts stay."""
        kw = {k: v for k, v in (("window_s", window_s), ("wait_s", wait_s)) if v is not None}
        hand = HandCoincidence(**kw)  # checks the settings
        # never in the middle of a hand-out (the same lock order as `process`)
        with self.release_lock, self.lock:
            if self.hand is not None:
                hand = self.hand.with_settings(hand.window_ns * 1e-9, hand.wait_ns * 1e-9)
            self.hand = hand

    def hold_apex(self, contacts: list, apex_onsets_ns: list, apex_held: list) -> list:
        """Report this call's apex onsets; hold the events of apex packets the localizer
        left to the hand (``apex_held`` [(onset ns, record)]), and behind them every later
        event of this fingertip; returns the rest."""
        if apex_onsets_ns:
            with self.lock:
                if self.hand is not None:
                    self.hand.add_own(apex_onsets_ns)
                self._apex_out.extend(apex_onsets_ns)
                if len(self._apex_out) > APEX_OUT_MAX:  # nobody takes them: the newest
                    del self._apex_out[:-APEX_OUT_MAX]
        if self.hand is None or not (apex_held or self.hand.pending):
            return contacts
        held = {id(rec): t for t, rec in apex_held}
        keep = []
        with self.lock:
            hand = self.hand
            for rec in contacts:
                t = held.get(id(rec))
                if t is not None and hand.hold(t, rec):
                    held[id(rec)] = None  # held
            bar = hand.held_min(_time_ns)  # the earliest held event
            for rec in contacts:
                if held.get(id(rec), 0) is None:
                    continue
                if bar is not None and rec.time_ns >= bar:
                    hand.follow(rec)
                else:
                    keep.append(rec)
        return keep

    def take_apex_onsets(self) -> list:
        """This fingertip's apex packet onsets [host ns] not reported yet."""
        if not self._apex_out:
            return []
        with self.lock:
            out, self._apex_out = self._apex_out, []
        return out

    def reports(self, onsets_ns, source: str = "", now_ns: int | None = None) -> None:
        """Another fingertip's (``source``) apex packet onsets [host ns]; ``now_ns``: this
        fingertip's host time (stamps far from it are counted and dropped)."""
        with self.lock:
            if self.hand is not None:
                self.hand.add_others(onsets_ns, source, now_ns)

    def waiting(self) -> bool:
        """Held packets or unpaired reports to decide."""
        hand = self.hand
        return hand is not None and bool(hand.pending or hand.unpaired)

    def pending(self) -> bool:
        """Events held."""
        return self.hand is not None and bool(self.hand.pending)

    def decide(self, now_ns: int, flush: bool) -> list:
        """The held events whose wait is over at ``now_ns`` [host ns] (``flush``: all) that
        no other fingertip saw (to hand out, with the events behind them, in time order);
        those another saw are counted as interference."""
        with self.lock:
            kept, rejected = self.hand.due(int(now_ns), _time_ns, flush)
        if rejected:
            self.counts["rejected_INTERFERENCE_HAND"] += len(rejected)
        return kept

    def limit_ns(self) -> int | None:
        """Host time [ns] the slip stage's clock must not pass (the earliest held event's
        onset); None when nothing is held."""
        hand = self.hand
        due = hand.next_due_ns() if hand is not None else None
        return None if due is None else due - hand.wait_ns

    def all_counts(self) -> dict:
        """The test's counters as ``hand_*``."""
        hand = self.hand
        if hand is None:
            return {}
        return {f"hand_{k}": v for k, v in dict.copy(hand.counts).items()}
