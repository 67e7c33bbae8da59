"""Reduced statistical evaluation of the slip detector on the simulator (the full one is
bench/bench_slip.py): scene -> triggered windows -> localize -> SlipDetector."""
import numpy as np
import pytest

from ae_tactile.slip import ContactState, SlipEventType
from ae_tactile.slip import evaluate as ev


@pytest.fixture(scope="module")
def incipient():
    return [ev.incipient_slip_trial(s, post_s=0.15) for s in range(24)]


def test_precursor_before_gross_slip(incipient):
    s = ev.summarize_incipient(incipient)
    assert s["precursor_before_gross_rate"] >= 0.95, s["failures"]
    # comfortably early: q at detection well below 1 and a lead above the human reflex
    assert s["q_at_precursor"]["p95"] < 0.3
    assert s["lead_ge_74ms_rate"] >= 0.95
    # the precursor is a micro-slip emission on the ring at the contact edge
    assert s["precursor_error_to_ring_m"]["p95"] < 0.5e-3


def test_gross_slip_detected_near_the_true_onset(incipient):
    s = ev.summarize_incipient(incipient)
    assert s["slip_detected_rate"] >= 0.95
    # the stick zone vanishes continuously (c = a_H (1 - q)^(1/3)): SLIP fires when it is
    # below ~0.4 a_H, i.e. q > ~0.94, and within ~150 ms after the true onset
    assert s["q_at_slip"]["min"] > 0.9
    assert s["slip_delay_ms"]["max"] < 150
    assert s["texture_events_total"] == 0


def test_announced_contact_and_closed_loop():
    rows = [ev.incipient_slip_trial(s, announce_touch=True, post_s=0.1) for s in range(100, 106)]
    assert all(r["precursor_before_gross"] for r in rows)
    assert all(r["states"][0][1] == int(ContactState.STICK) for r in rows)   # the touch: STICK first
    loop = [ev.closed_loop_trial(s) for s in range(200, 205)]
    assert all(r["averted"] for r in loop), [r["seed"] for r in loop if not r["averted"]]


def test_no_false_alarms_touch_hold_release():
    rows = [ev.touch_hold_release_trial(s) for s in range(30)]
    s = ev.summarize_alarms(rows)
    assert s["alarm_onsets"] == 0 and s["precursor_events"] == 0 and s["slip_events"] == 0
    assert s["texture_events"] == 0
    assert sum(r["state_mid_hold"] == ContactState.STICK for r in rows) >= 29
    assert sum(r["state_end"] == ContactState.NO_CONTACT for r in rows) >= 29


def test_no_false_alarms_random_touches():
    rows = [ev.random_touches_trial(0, duration_s=10.0),
            ev.random_touches_trial(10_000, duration_s=5.0, rate_hz=50.0, hold_max_s=0.5)]
    s = ev.summarize_alarms(rows)
    assert s["alarm_onsets"] == 0, s


def test_texture_spatial_period_within_10_percent():
    rows = [ev.texture_trial(s) for s in range(10)]
    s = ev.summarize_texture(rows)
    assert s["detected_rate"] == 1.0, s["failures"]
    assert s["within_10pct_rate"] == 1.0
    assert all(r["final_state"] == ContactState.GROSS_SLIP for r in rows)


def test_drifting_slip_direction():
    rows = [ev.drift_slip_trial(s) for s in range(4)]
    assert all(r["slip_delay_ms"] is not None for r in rows)
    med = [r["direction_error_deg_median"] for r in rows if r["direction_error_deg_median"] is not None]
    assert len(med) >= 3 and np.median(med) < 20
