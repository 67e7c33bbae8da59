# SPDX-License-Identifier: Apache-2.0
"""Coincidence across the fingertips of one hand (ae_tactile.dsp.coincidence): one
electrical event seen by several fingertips is interference, an apex touch at a time of its
own is kept, at the rate Poisson statistics give; and the hand trial that runs it behind
each fingertip's packet tests (ae_tactile.slip.evaluate.hand_interference_trial)."""

import math

import numpy as np
import pytest

from ae_tactile.dsp.coincidence import HandCoincidence
from ae_tactile.slip import evaluate as ev

MS = 1_000_000


def test_a_burst_seen_by_another_fingertip_is_rejected_a_lone_packet_kept():
    hc = HandCoincidence(window_s=3e-4, wait_s=5e-3)
    hc.add_others([100 * MS + 250_000])  # 0.25 ms after this fingertip's stamp
    assert hc.hold(100 * MS, "burst") and hc.hold(200 * MS, "touch")
    assert hc.due(104 * MS) == ([], [])  # the burst's wait is not over
    assert hc.next_due_ns() == 105 * MS
    assert hc.due(105 * MS) == ([], ["burst"])
    hc.add_others([200 * MS + 350_000])  # outside the window
    assert hc.due(205 * MS) == (["touch"], [])
    assert hc.counts["kept"] == 1 and hc.counts["rejected_coincidence"] == 1
    assert hc.pending == 0 and hc.next_due_ns() is None


def test_a_report_after_the_decision_does_not_change_it_and_is_counted_late():
    hc = HandCoincidence(window_s=3e-4, wait_s=5e-3)
    hc.hold(10 * MS, "a")
    assert hc.due(15 * MS) == (["a"], [])
    hc.add_others([10 * MS])
    assert hc.counts["reports_late"] == 1
    hc.hold(30 * MS, "b")  # held out of order: decided in onset order
    hc.hold(20 * MS, "c")
    hc.add_others([30 * MS + 100_000])
    assert hc.due(40 * MS) == (["c"], ["b"])


def test_apex_touches_are_kept_at_the_poisson_rate():
    """Reports of the other fingertips at random times, 200 / s: a touch at a time of its
    own is kept with probability exp(-2 window lambda) = 0.887 for a 0.3 ms window."""
    rng = np.random.default_rng(5)
    lam, dur_s, w = 200.0, 100.0, 3e-4
    hc = HandCoincidence(window_s=w, wait_s=5e-3, keep_s=2 * dur_s)
    hc.add_others(np.sort(rng.uniform(0, dur_s, rng.poisson(lam * dur_s))) * 1e9)
    n = 20_000
    for i, t in enumerate(np.sort(rng.uniform(0.01, dur_s - 0.01, n))):
        hc.hold(t * 1e9, i)
    kept, rejected = hc.due(int(2 * dur_s * 1e9))
    p = math.exp(-2 * w * lam)
    assert len(kept) + len(rejected) == n
    assert abs(len(kept) / n - p) <= 4 * math.sqrt(p * (1 - p) / n)


def test_bad_stamps_are_counted_and_bad_settings_refused():
    hc = HandCoincidence()
    assert not hc.hold(float("nan"), "x") and not hc.hold("soon", "y")
    hc.add_others([np.nan, np.inf, 1.0e9])
    assert hc.counts["rejected_nonfinite"] == 4 and hc.pending == 0
    assert hc.coincident([1.0e9 + 1e5]).tolist() == [True]
    for kw in ({"window_s": 0.0}, {"window_s": math.nan}, {"window_s": 1e-3, "wait_s": 1e-4},
               {"wait_s": 2.0}, {"keep_s": 1e-3}):
        with pytest.raises(ValueError):
            HandCoincidence(**kw)


@pytest.fixture(scope="module")
def hand_rows():
    return [r for s in (0, 3, 7) for r in ev.hand_interference_trial(s, duration_s=0.5)]


def test_a_hand_rejects_interference_without_wall_echoes_and_keeps_apex_touches(hand_rows):
    """Bursts into the amplifier's input of fingertips without wall echoes (seeds 0, 3, 7:
    22 Hz and 3.5 kHz at random times, 201 Hz at random times) are apex touches to each
    fingertip's packet tests; the hand's coincidence leaves no phantom event, no extra
    contact, no alarm, keeps every acoustic packet and, below 100 bursts / s, nearly every
    apex touch (the Poisson cost: 1 - exp(-2 window rate) ~ 1.3 % at 22 Hz)."""
    rows = hand_rows
    assert all(not r["echoes"] and r["coupling"] == "input" for r in rows)
    assert all(not r["periodic"] for r in rows)  # the timing test cannot catch them
    assert sum(r["n_rejected_coincidence"] for r in rows) >= 100
    assert sum(r["n_phantom_events"] for r in rows) == 0
    assert all(r["contacts_created"] == 1 for r in rows)
    assert sum(r["n_alarm_onsets"] for r in rows) == 0
    assert all(r["n_acoustic_kept"] == r["n_acoustic_packets"] for r in rows)
    slow = [r for r in rows if r["rate_hz"] < 100]
    n_touch = sum(r["n_apex_touches"] for r in slow)
    assert n_touch >= 4 and sum(r["n_apex_touches_kept"] for r in slow) >= n_touch - 1
    err = np.concatenate([r["stamp_error_us"] for r in rows])
    assert err.size and np.all(np.abs(err) < 300)  # the links' floors: 50 .. 200 us


def test_without_the_hand_the_same_bursts_become_phantom_touches(hand_rows):
    """The control: the same hands, each fingertip alone (no coincidence), take a third or
    more of those bursts for apex touches: extra contacts."""
    rows = hand_rows
    n = sum(r["n_interference"] for r in rows)
    assert sum(r["alone_phantom_events"] for r in rows) >= 0.3 * n > 0
    assert sum(r["alone_contacts_created"] - 1 for r in rows) >= len(rows)
    assert sum(r["n_phantom_events"] for r in rows) == 0
