# SPDX-License-Identifier: Apache-2.0
"""The demo's truth (ae_tactile.scoring): contacts and the finger's true state from a
scene's ground-truth emissions and gross-slip intervals, and a run's scores against it,
on hand-built scenes whose answers are counted by hand."""
import pytest

from ae_tactile.records import ContactState, EventType
from ae_tactile.scoring import finger_timeline, score_run, truth_contacts

MS = 1_000_000
S = 1_000_000_000
T, D, P, SL, TX = (int(EventType.TOUCH), int(EventType.DETOUCH), int(EventType.SLIP_PRECURSOR),
                   int(EventType.SLIP), int(EventType.TEXTURE))
NO, STICK, INC, GROSS = (int(s) for s in ContactState)


def test_three_pins_are_three_contacts_and_a_release_ends_the_one_it_is_on():
    pins = [(-3e-3, 2e-3, 9.3e-3), (3e-3, 2e-3, 9.3e-3), (0.0, -3e-3, 9.5e-3)]
    ev = [(0, T, pins[0]), (700_000, T, pins[1]), (1_900_000, T, pins[2]),
          (S, D, (3.1e-3, 2.1e-3, 9.3e-3))]
    cs = truth_contacts(ev)
    assert [c.changes for c in cs] == [[(0, STICK)], [(700_000, STICK), (S, NO)],
                                      [(1_900_000, STICK)]]
    assert finger_timeline(cs) == [(0, STICK)]  # two pins still held


def test_a_retouch_on_the_same_spot_is_the_same_contact():
    ev = [(0, T, (0.0, 0.0, 0.01)), (5 * MS, T, (0.2e-3, 0.0, 0.01)),
          (100 * MS, D, (0.0, 0.0, 0.01))]
    cs = truth_contacts(ev)
    assert len(cs) == 1 and cs[0].changes == [(0, STICK), (100 * MS, NO)]


def test_micro_slips_then_the_scenes_gross_slip():
    """A held contact loaded: INCIPIENT_SLIP from its first micro-slip, GROSS_SLIP from the
    scene's gross-slip onset until the scene ends (its interval is open)."""
    c = (0.0, 1e-3, 9.95e-3)
    ev = [(0, T, c)] + [(t * MS, P, (1.5e-3, 1e-3, 9.9e-3)) for t in (200, 250, 300)] \
        + [(t * MS, SL, c) for t in (510, 530)]
    scene = {"parts": [{"name": "load", "start_time_ns": 0, "gross_slip_time_ns": 500 * MS,
                        "gross_slip_intervals_ns": [[500 * MS, None]],
                        "contact_center_m": list(c)}]}
    cs = truth_contacts(ev, scene, end_ns=2 * S)
    assert len(cs) == 1
    assert cs[0].changes == [(0, STICK), (200 * MS, INC), (500 * MS, GROSS)]


def test_a_part_that_holds_an_object_from_its_start_begins_its_contact_there():
    """The incipient-slip part holds its object from its start (its first emissions are
    micro-slips): its contact begins at the part's start, beside one held 3 mm away."""
    other, c = (3e-3, 1e-3, 9.5e-3), (0.0, 1e-3, 9.95e-3)
    ev = [(0, T, other), (400 * MS, P, (0.5e-3, 1e-3, 9.9e-3))]
    scene = {"parts": [{"name": "touch", "start_time_ns": 0},
                       {"name": "load", "start_time_ns": 300 * MS, "gross_slip_time_ns": None,
                        "gross_slip_intervals_ns": [], "contact_center_m": list(c)}]}
    cs = truth_contacts(ev, scene, end_ns=S)
    assert [x.changes for x in cs] == [[(0, STICK)], [(300 * MS, STICK), (400 * MS, INC)]]


def test_a_slide_that_stops_sticks_again_after_the_quiet_time():
    ev = [(0, T, (0.0, 0.0, 0.01)), (100 * MS, SL, (0.0, 0.0, 0.01)),
          (120 * MS, SL, (0.1e-3, 0.0, 0.01))]
    cs = truth_contacts(ev, end_ns=S)
    assert cs[0].changes == [(0, STICK), (100 * MS, GROSS), (420 * MS, STICK)]


def test_a_stylus_stroke_slides_from_its_first_to_its_last_emission_then_lifts():
    ev = [(t * 25 * MS, TX, (t * 0.5e-3, 0.0, 0.01)) for t in range(10)]  # 4.5 mm travel
    cs = truth_contacts(ev, end_ns=2 * S)
    assert len(cs) == 1 and cs[0].changes == [(0, GROSS), (225 * MS, NO)]


def test_the_score_of_a_run_counted_by_hand():
    """Touch at 0, micro-slips from 0.5 s, the scene's gross slip at 1 s (to the end, 2 s).
    The run: STICK from 0.05 s, INCIPIENT_SLIP from 0.8 s, GROSS_SLIP from 1.02 s; a
    precursor at 0.3 s (false: the truth is STICK then and 0.3 s before), one at 0.55 s
    (true), a SLIP at 0.9 s (false: not gross yet), one at 1.02 s (true)."""
    c = (0.0, 0.0, 0.01)
    ev = [(0, T, c)] + [(t * MS, P, c) for t in range(500, 1000, 50)]
    scene = {"parts": [{"name": "load", "start_time_ns": 0, "gross_slip_time_ns": S,
                        "gross_slip_intervals_ns": [[S, None]], "contact_center_m": list(c)}]}
    reported = [(50 * MS, STICK), (800 * MS, INC), (1020 * MS, GROSS)]
    outputs = [(300 * MS, P), (550 * MS, P), (900 * MS, SL), (1020 * MS, SL)]
    r = score_run(ev, reported, outputs, scene, [(0, T)], end_ns=2 * S)
    assert r["truth_timeline"] == [(0.0, "STICK"), (0.5, "INCIPIENT_SLIP"), (1.0, "GROSS_SLIP")]
    # scored: [0, 2 s) without [0.5, 0.6) and [1.0, 1.1) -> 1,800 ms; wrong: [0, 50) before
    # the first report, [600, 800) STICK against INCIPIENT_SLIP -> 250 ms
    assert r["state_scored_s"] == pytest.approx(1.8)
    assert r["state_right_share"] == pytest.approx(1550 / 1800)
    assert r["false_alarms"] == 2 and r["true_alarms"] == 2
    assert [k for _, k in r["false_alarm_list"]] == ["SLIP_PRECURSOR", "SLIP"]
    # the first SLIP 100 ms early; the lead counts from the first true precursor (0.55 s)
    assert r["gross_slips"] == [{"part": "load", "slip_delay_ms": -100.0,
                                 "precursor_lead_ms": 450.0}]
    assert r["contacts"] == {"truth_begun": 1, "truth_ended": 0, "touch_events": 1,
                             "detouch_events": 0}
