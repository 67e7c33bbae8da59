# SPDX-License-Identifier: Apache-2.0
"""A new object's touch against a held contact's next micro-slip, told by amplitude: a
source's strength is rho v^2 / a_c (a touch at the object's approach speed, a micro-slip
at the slower local slip speed of a contact already formed), and the sensor at the centre
of the spherical tip hears every surface point from the same distance, so a finger's
touches and micro-slips keep their own amplitude scales whatever the device's gain."""

import math

import numpy as np
import pytest

from ae_tactile.records import EventType, Reading
from ae_tactile.slip import LocalizedEvent, SlipDetector
from ae_tactile.slip.model import AMP_SPREAD_LN, LOST_RELEASE_LLR, P_LOST, touch_llr

R = 0.01  # [m] fingertip radius of the hand-built events
MS = 1_000_000  # [ns]
SIG = 20e-6  # [m] localization 1-sigma of the hand-built events
TOUCH_V, MICRO_V = 1.0e-2, 2.0e-3  # [V] a touch, a micro-slip (strength ratio 0.2)
ALARMS = (EventType.SLIP_PRECURSOR, EventType.SLIP)


def ev(t_ms, x, y, pol, amp_v, pid):
    p = np.array([x, y, math.sqrt(R * R - x * x - y * y)])
    return LocalizedEvent(int(t_ms * MS), p, np.eye(3) * SIG * SIG, pol, pol * amp_v, 0.9,
                          pid)


def test_the_likelihood_ratio_is_the_gaussian_one_in_ln_amplitude():
    mu_t, mu_m = math.log(TOUCH_V), math.log(MICRO_V)
    v = 2.0 * AMP_SPREAD_LN**2
    for x in np.linspace(mu_m - 2.0, mu_t + 2.0, 9):
        want = (-(x - mu_t) ** 2 / (2 * v)) - (-(x - mu_m) ** 2 / (2 * v))
        assert touch_llr(x, mu_t, mu_m) == pytest.approx(want, abs=1e-12)
    assert touch_llr(0.5 * (mu_t + mu_m), mu_t, mu_m) == pytest.approx(0.0, abs=1e-12)
    # no evidence: an amplitude or a scale unknown, the scales alike, touches the quieter
    assert touch_llr(None, mu_t, mu_m) == 0.0
    assert touch_llr(mu_t, None, mu_m) == 0.0 and touch_llr(mu_t, mu_t, None) == 0.0
    assert touch_llr(mu_t + 1.0, mu_t, mu_t) == 0.0
    # touches louder by less than SCALE_SIGMAS standard errors of the two means: none
    se = AMP_SPREAD_LN * math.sqrt(1.0 / 3 + 1.0 / 2)
    assert touch_llr(mu_t, mu_t, mu_t - 1.9 * se, 3, 2) == 0.0
    assert touch_llr(mu_t, mu_t, mu_t - 2.1 * se, 3, 2) > 0.0
    assert touch_llr(mu_m - 3.0, mu_m, mu_t) == 0.0


def scene(amp_new_v):
    """A grasp at (-3, 0) mm loaded (5 micro-slips on its 1 mm ring) and released: the
    finger learns its micro-slip scale. Then an object touched at (2.5, 0) mm, held 0.5 s,
    a rarefaction on its disc off its touch (its release, a broad object's, or a
    micro-slip), and 0.3 s later a compression 1.2 mm from its touch of amplitude
    ``amp_new_v`` [V]. Returns the events and the index of the last."""
    evs = [ev(0, -3e-3, 0.0, +1, TOUCH_V, 0)]
    for i in range(5):
        a = 2.0 * math.pi * i / 5
        evs.append(ev(300 + 40 * i, -3e-3 + 1e-3 * math.cos(a), 1e-3 * math.sin(a),
                      (-1) ** i, MICRO_V, 1 + i))
    evs.append(ev(800, -3e-3 + 5e-6, 0.0, -1, 0.5 * TOUCH_V, 9))
    evs.append(ev(2000, 2.5e-3, 0.0, +1, TOUCH_V, 10))
    evs.append(ev(2500, 2.5e-3, 1.0e-3, -1, 0.5 * TOUCH_V, 11))
    evs.append(ev(2800, 3.7e-3, 0.0, +1, amp_new_v, 12))
    return evs


def run(evs):
    det = SlipDetector(contact_events=True)
    outs, readings = [], []
    for e in evs:
        for t in range(int(det.now_ns or e.time_ns), e.time_ns, 10 * MS):
            det.advance(t)
        outs += det.process(e)
        readings.append(det.last_reading)
    return det, outs, readings


def test_a_touch_loud_compression_after_a_release_is_a_new_object():
    det, outs, rd = run(scene(TOUCH_V))
    held = rd[-3][1]  # the object touched at (2.5, 0) mm
    assert rd[-3][0] == Reading.TOUCH
    assert rd[-1][0] == Reading.TOUCH and rd[-1][1] != held
    assert [o.contact_id for o in outs if o.kind == EventType.DETOUCH].count(held) == 1
    assert not [o for o in outs if o.kind in ALARMS and o.time_ns >= 2000 * MS]


def test_a_micro_slip_loud_compression_after_a_release_revives_the_contact():
    det, outs, rd = run(scene(MICRO_V))
    held = rd[-3][1]
    assert rd[-1] == (Reading.MICRO_SLIP, held)
    assert held in [c.id for c in det.contacts]


def test_without_amplitudes_the_compression_revives_the_contact():
    evs = [LocalizedEvent(e.time_ns, e.point_m, e.covariance_m2, e.polarity, math.nan,
                          e.confidence, e.packet_id) for e in scene(TOUCH_V)]
    det, outs, rd = run(evs)
    assert rd[-1] == (Reading.MICRO_SLIP, rd[-3][1])


def test_a_compression_on_a_silent_held_contact_needs_the_prior_odds_of_a_lost_release():
    """The same scene with the held object's release lost: a new touch there means that
    release went unseen (prior probability P_LOST), so the compression is a new object's
    touch only when its amplitude beats the prior odds (LOST_RELEASE_LLR): three times a
    touch's median amplitude does (ln-ratio ~6 here), a median touch (~2.6) does not."""
    mu_t, mu_m = math.log(TOUCH_V), math.log(MICRO_V)
    assert touch_llr(math.log(3 * TOUCH_V), mu_t, mu_m) > LOST_RELEASE_LLR
    assert 0.0 < touch_llr(mu_t, mu_t, mu_m) < LOST_RELEASE_LLR
    assert LOST_RELEASE_LLR == pytest.approx(math.log((1 - P_LOST) / P_LOST))
    for amp_v, new in ((3 * TOUCH_V, True), (TOUCH_V, False)):
        evs = [e for e in scene(amp_v) if e.packet_id != 11]  # its release lost
        det, outs, rd = run(evs)
        held = rd[-2][1]
        assert rd[-2][0] == Reading.TOUCH
        if new:
            assert rd[-1][0] == Reading.TOUCH and rd[-1][1] != held
            assert [o.contact_id for o in outs if o.kind == EventType.DETOUCH].count(held) == 1
        else:
            assert rd[-1] == (Reading.MICRO_SLIP, held)
