# SPDX-License-Identifier: Apache-2.0
"""The slip detector's interpretation of the emission stream as a hand sees it: TOUCH when
a contact begins and DETOUCH when it ends (with the contact's id), the reading of every
emission (``last_reading``) and the contacts listed (``contact_infos``)."""

import math

import numpy as np

from ae_tactile.records import ContactState, EventType, Reading
from ae_tactile.slip import LocalizedEvent, SlipConfig, SlipDetector

R = 0.01  # [m] fingertip radius of the hand-built events
MS = 1_000_000  # [ns]
SIG = 20e-6  # [m] localization 1-sigma of the hand-built events
ALARMS = (EventType.SLIP_PRECURSOR, EventType.SLIP, EventType.TEXTURE)


def ev(t_ns, x, y, pol, pid=0):
    p = np.array([x, y, math.sqrt(R * R - x * x - y * y)])
    return LocalizedEvent(int(t_ns), p, np.eye(3) * SIG * SIG, pol, 0.01 * pol, 0.9, pid)


def kinds(outs):
    return [(o.kind, o.contact_id) for o in outs]


def test_a_touch_begins_a_contact_and_its_release_ends_it():
    det = SlipDetector(contact_events=True)
    outs = det.process(ev(10 * MS, 2e-3, 0.0, +1, 1))
    assert [o.kind for o in outs] == [EventType.TOUCH]
    cid = outs[0].contact_id
    np.testing.assert_allclose(outs[0].position_m[:2], (2e-3, 0.0), atol=1e-9)
    assert det.last_reading == (Reading.TOUCH, cid)
    assert [i.contact_id for i in det.contact_infos()] == [cid]
    outs = det.process(ev(600 * MS, 2e-3 + 5e-6, 0.0, -1, 2))
    assert det.last_reading == (Reading.RELEASE, cid)
    assert not [o for o in outs if o.kind == EventType.TOUCH]
    # the contact ends by time passing: its DETOUCH waits in pop_events, once
    state = det.advance(900 * MS)
    assert state.state == ContactState.NO_CONTACT
    detouch = det.pop_events()
    assert kinds(detouch) == [(EventType.DETOUCH, cid)]
    assert detouch[0].time_ns == 600 * MS  # when the contact was released
    np.testing.assert_allclose(detouch[0].position_m[:2], (2e-3, 0.0), atol=2e-5)
    assert det.pop_events() == [] and det.contact_infos() == []


def test_a_detouch_not_popped_comes_with_the_next_emission():
    det = SlipDetector(contact_events=True)
    cid = det.process(ev(0, 0.0, 0.0, +1, 1))[0].contact_id
    det.process(ev(300 * MS, 1e-6, 0.0, -1, 2))
    det.advance(600 * MS)  # ends it
    outs = det.process(ev(2000 * MS, -3e-3, 0.0, +1, 3))
    assert [o.kind for o in outs] == [EventType.DETOUCH, EventType.TOUCH]
    assert outs[0].contact_id == cid and outs[1].contact_id != cid
    assert det.pop_events() == []


def test_every_touch_gets_one_detouch_and_ids_are_distinct():
    """Touches and releases at separate spots, 8 mm apart: one TOUCH and one DETOUCH per
    spot, the ids distinct, no alarm."""
    det = SlipDetector(contact_events=True)
    outs = []
    spots = [(-4e-3, 0.0), (4e-3, 0.0), (0.0, 4e-3)]
    for i, (x, y) in enumerate(spots):
        outs += det.process(ev((100 * i) * MS, x, y, +1, 10 + i))
    for i, (x, y) in enumerate(spots):
        outs += det.process(ev((500 + 100 * i) * MS, x + 3e-6, y, -1, 20 + i))
        assert det.last_reading[0] == Reading.RELEASE
    det.advance(2000 * MS)
    outs += det.pop_events()
    touch = [o.contact_id for o in outs if o.kind == EventType.TOUCH]
    detouch = [o.contact_id for o in outs if o.kind == EventType.DETOUCH]
    assert len(set(touch)) == 3 and sorted(touch) == sorted(detouch)
    assert not [o for o in outs if o.kind in ALARMS]


def test_contact_events_off_keeps_only_alarms():
    det = SlipDetector(SlipConfig())  # the default: off
    assert det.process(ev(0, 0.0, 0.0, +1, 1)) == []
    assert det.last_reading[0] == Reading.TOUCH


def test_a_rejected_emission_reads_unknown():
    det = SlipDetector(contact_events=True)
    det.process(ev(0, 0.0, 0.0, +1, 1))
    bad = LocalizedEvent(MS, np.array([np.nan, 0.0, R]), None, 1, 0.0, 0.9, 2)
    assert det.process(bad) == []
    assert det.last_reading == (Reading.UNKNOWN, -1)
