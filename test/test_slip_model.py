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


# ------------------------------------------------------------------ the fingertip model
# Hand-built scenes with their truth (what each emission is, when the state changes); the
# detector reads them with ``model=True``. Each test also states what the per-emission
# rules (`model=False`) did wrong on the same scene.


def run_model(events, end_ns, model=True, tick_ns=10 * MS):
    """(outputs, [(t_ns, state)]) of a detector fed ``events`` with a timer every tick."""
    det = SlipDetector(model=model, contact_events=True)
    outs, trace, t_prev = [], [], None
    for e in sorted(events, key=lambda e: e.time_ns):
        if t_prev is not None:
            for tt in range(t_prev + tick_ns, e.time_ns, tick_ns):
                det.advance(tt)
                outs += det.pop_events()
                trace.append((tt, det.state.state))
        outs += det.process(e)
        trace.append((e.time_ns, det.state.state))
        t_prev = e.time_ns
    for tt in range(t_prev + tick_ns, end_ns, tick_ns):
        det.advance(tt)
        outs += det.pop_events()
        trace.append((tt, det.state.state))
    return outs, trace


def state_at(trace, t_ns):
    s = ContactState.NO_CONTACT
    for t, st in trace:
        if t > t_ns:
            break
        s = st
    return s


def alarms(outs):
    return [o for o in outs if o.kind in ALARMS]


def disc(rng, cx, cy, r_lo, r_hi, n):
    r = np.sqrt(rng.uniform(r_lo**2, r_hi**2, n))
    th = rng.uniform(0.0, 2.0 * math.pi, n)
    return np.column_stack([cx + r * np.cos(th), cy + r * np.sin(th)])


def test_a_four_point_touch_is_touches_not_micro_slips():
    """An object touching at 4 points 1.6-3 mm apart within 3 ms, held 0.8 s, released
    within 3 ms: no alarm; the finger reads STICK while held and NO_CONTACT 0.2 s after
    the release; every contact reported begun is reported ended. (The rules: a precursor
    from the 3rd and 4th touches, the contact never ends.)"""
    pts = [(0.0, 0.0), (1.6e-3, 0.0), (0.0, 2.0e-3), (1.7e-3, 1.8e-3)]
    evs = [ev((10 + 1.0 * i) * MS, x, y, +1, i) for i, (x, y) in enumerate(pts)]
    evs += [ev((810 + 0.7 * i) * MS, x + 4e-6, y, -1, 10 + i) for i, (x, y) in enumerate(pts)]
    outs, trace = run_model(evs, 1300 * MS)
    assert alarms(outs) == []
    assert state_at(trace, 400 * MS) == ContactState.STICK
    assert state_at(trace, 1015 * MS) == ContactState.NO_CONTACT
    touch = sorted(o.contact_id for o in outs if o.kind == EventType.TOUCH)
    detouch = sorted(o.contact_id for o in outs if o.kind == EventType.DETOUCH)
    assert touch and touch == detouch
    outs_rules, _ = run_model(evs, 1300 * MS, model=False)
    assert alarms(outs_rules)  # what the issue reports


def test_touches_beside_a_held_one_are_new_contacts():
    """A touch held 1 s; three touches 2.6-4 mm from it and from each other, 25-60 ms
    apart, each held 0.3 s and released: four contacts, no alarm, the held one's release
    ends the last."""
    pts = [(0.0, 0.0), (2.6e-3, 0.0), (0.0, -3.0e-3), (-2.8e-3, 1.5e-3)]
    t_on = [10, 35, 70, 130]
    evs = [ev(t * MS, x, y, +1, i) for i, ((x, y), t) in enumerate(zip(pts, t_on))]
    evs += [ev((t + 300) * MS, x + 5e-6, y, -1, 10 + i)
            for i, ((x, y), t) in enumerate(zip(pts[1:], t_on[1:]))]
    evs.append(ev(1010 * MS, 5e-6, 0.0, -1, 20))
    outs, trace = run_model(evs, 1500 * MS)
    assert alarms(outs) == []
    assert len({o.contact_id for o in outs if o.kind == EventType.TOUCH}) == 4
    assert state_at(trace, 800 * MS) == ContactState.STICK
    assert state_at(trace, 1210 * MS) == ContactState.NO_CONTACT
    assert alarms(run_model(evs, 1500 * MS, model=False)[0])


def test_a_broad_press_released_elsewhere_on_its_disc_ends_without_alarm():
    """One compression, held 0.5 s, then 4 rarefactions within 5 ms elsewhere on a disc
    of radius 1.8 mm round it: one contact, no alarm, NO_CONTACT 0.2 s after."""
    rng = np.random.default_rng(3)
    evs = [ev(10 * MS, 1e-3, 1e-3, +1, 0)]
    for i, (x, y) in enumerate(disc(rng, 1e-3, 1e-3, 0.8e-3, 1.8e-3, 4)):
        evs.append(ev((510 + 1.2 * i) * MS, x, y, -1, 1 + i))
    outs, trace = run_model(evs, 1000 * MS)
    assert alarms(outs) == []
    assert state_at(trace, 300 * MS) == ContactState.STICK
    assert state_at(trace, 720 * MS) == ContactState.NO_CONTACT
    assert alarms(run_model(evs, 1000 * MS, model=False)[0])


def test_a_broad_press_of_several_compressions_released_once_off_them_ends():
    """Five compressions within 4 ms over a disc of radius 1.3 mm, held 0.6 s, then one
    rarefaction on the disc 0.1-0.25 mm from the nearest compression, off its spot (a
    broad object leaves where it pleases; its other release emissions lost; 3
    localization sigmas are 60 um): the object is released, the
    finger reads NO_CONTACT 0.2 s after it, no alarm."""
    rng = np.random.default_rng(5)
    pc = disc(rng, 0.0, 2e-3, 0.0, 1.3e-3, 5)
    evs = [ev((10 + 0.8 * i) * MS, x, y, +1, i) for i, (x, y) in enumerate(pc)]
    # a point of the disc 0.1-0.25 mm from the nearest compression
    for x, y in disc(rng, 0.0, 2e-3, 0.0, 1.3e-3, 400):
        d = np.hypot(pc[:, 0] - x, pc[:, 1] - y)
        if 0.1e-3 < d.min() < 0.25e-3:
            break
    else:
        raise AssertionError("no such point")
    evs.append(ev(620 * MS, x, y, -1, 9))
    outs, trace = run_model(evs, 1200 * MS)
    assert alarms(outs) == []
    assert state_at(trace, 400 * MS) == ContactState.STICK
    assert state_at(trace, 830 * MS) == ContactState.NO_CONTACT


def test_objects_arriving_together_released_apart_end_with_the_last():
    """Four touches 2.2-4 mm apart within 12 ms (one arrival window: read as one
    object's points), then released one by one on their spots 0.2-0.6 s apart: the
    points left separately, so the finger stays in contact until the last release (a
    lost release is allowed for only when the others left together) and reads
    NO_CONTACT 0.2 s after it."""
    pts = [(0.0, 0.0), (2.2e-3, 0.0), (0.0, -3.0e-3), (-2.8e-3, 1.5e-3)]
    evs = [ev((10 + 4 * i) * MS, x, y, +1, i) for i, (x, y) in enumerate(pts)]
    t_off = [1300, 300, 600, 1000]
    evs += [ev(t * MS, x + 5e-6, y, -1, 10 + i) for i, ((x, y), t) in enumerate(zip(pts, t_off))]
    outs, trace = run_model(evs, 1800 * MS)
    assert alarms(outs) == []
    for t in (400, 700, 1100, 1250):
        assert state_at(trace, t * MS) == ContactState.STICK, t
    assert state_at(trace, 1510 * MS) == ContactState.NO_CONTACT


def slide_events(rng, t0_ms, rate_hz, n, cx=0.0, cy=0.0, a=1.0e-3, pid0=0):
    t = t0_ms * MS + np.cumsum(np.r_[0.0, rng.exponential(1e9 / rate_hz, n - 1)])
    xy = disc(rng, cx, cy, 0.0, a, n)
    pol = rng.choice([-1, 1], n)
    return [ev(int(ti), x, y, int(p), pid0 + i) for i, (ti, (x, y), p) in
            enumerate(zip(t, xy, pol))]


def test_a_slide_from_the_start_is_slip_first_within_100_ms():
    """An object landing and sliding at once (Poisson 80 Hz over a 1 mm disc, random
    polarity): over 40 slides the first alarm is SLIP within 100 ms (issue 38's target;
    decided at the 4th-5th emission), never a precursor nor INCIPIENT_SLIP first, in at
    least 30 (the rest read as a load's ring: the bound of docs/slip.md); NO_CONTACT 0.2 s
    after the slide stops (lifted). (The rules: a precursor first in every slide.)"""
    ok = lifted = ok_rules = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        evs = slide_events(rng, 10, 80.0, 40)
        end = evs[-1].time_ns
        outs, trace = run_model(evs, end + 400 * MS)
        al = alarms(outs)
        ok += bool(al and al[0].kind == EventType.SLIP and al[0].time_ns <= 110 * MS
                   and all(s != ContactState.INCIPIENT_SLIP for _, s in trace))
        lifted += state_at(trace, end + 200 * MS) == ContactState.NO_CONTACT
        al_r = alarms(run_model(evs, end + 400 * MS, model=False)[0])
        ok_rules += bool(al_r and al_r[0].kind == EventType.SLIP)
    assert ok >= 30 and lifted >= 38
    assert ok_rules <= 4


def ramp_events(rng, t0_ms, ramp_s, n_micro, a=1.0e-3, cx=0.0, cy=0.0, pid0=100,
                gross_hz=120.0, gross_s=0.2):
    """Cattaneo-Mindlin micro-slips at the stick front c = a (1 - q)^(1/3) of a load ramp
    q = t / ramp_s (their count up to q: n_micro (1 - (1 - q)^(2/3))), then gross slip over
    the disc. Returns (events, t_q09_ns, t_gross_ns)."""
    f = (np.arange(n_micro) + rng.uniform(0.0, 1.0, n_micro)) / n_micro
    q = 1.0 - (1.0 - f) ** 1.5
    t = t0_ms * MS + q * ramp_s * 1e9
    c = a * (1.0 - q) ** (1.0 / 3.0)
    r = c + rng.uniform(0.0, 0.1, n_micro) * (a - c)
    th = rng.uniform(0.0, 2.0 * math.pi, n_micro)
    pol = rng.choice([-1, 1], n_micro)
    evs = [ev(int(ti), cx + ri * math.cos(h), cy + ri * math.sin(h), int(p), pid0 + i)
           for i, (ti, ri, h, p) in enumerate(zip(t, r, th, pol))]
    tg = int(t0_ms * MS + ramp_s * 1e9)
    evs += slide_events(rng, tg / MS, gross_hz, int(gross_hz * gross_s), cx, cy, a,
                        pid0 + 1000)
    return evs, int(t0_ms * MS + 0.9 * ramp_s * 1e9), tg


def test_a_grasp_then_load_gives_the_precursor_before_gross_slip_and_slip_after_q09():
    """A touch at the centre, held 0.3 s, loaded over 1 s with 20 micro-slips, gross slip
    at q = 1, released: over 30 grasps the precursor comes before gross slip in all and
    no SLIP before q = 0.9 in at least 29."""
    pre = early = 0
    for seed in range(30):
        rng = np.random.default_rng(100 + seed)
        evs, t09, tg = ramp_events(rng, 310, 1.0, 20)
        evs = [ev(10 * MS, 0.0, 0.0, +1, 0)] + evs
        evs.append(ev(evs[-1].time_ns + 5 * MS, 3e-6, 0.0, -1, 9999))
        outs, _ = run_model(evs, evs[-1].time_ns + 300 * MS)
        p = [o for o in outs if o.kind == EventType.SLIP_PRECURSOR]
        pre += bool(p and p[0].time_ns < tg)
        early += any(o.kind == EventType.SLIP and o.time_ns < t09 for o in outs)
    assert pre == 30 and early <= 1


def test_slide_restick_then_ramp_gives_the_precursor_before_slip():
    """A slide (Poisson 100 Hz, 0.3 s), a re-stick (silent 0.6 s), then a load ramp of
    1.5 s with 25 micro-slips to gross slip: over 30 trials, a precursor between the
    re-stick and gross slip in at least 28, SLIP at q < 0.9 in at most 1. (The rules: the
    slide's contact never ends, the ramp's micro-slips are read as its slip emissions.)"""
    pre = early = early_rules = 0
    for seed in range(30):
        rng = np.random.default_rng(200 + seed)
        slide = slide_events(rng, 10, 100.0, 30)
        t_stick = slide[-1].time_ns
        ramp, t09, tg = ramp_events(rng, t_stick / MS + 600, 1.5, 25)
        evs = slide + ramp
        outs, _ = run_model(evs, evs[-1].time_ns + 300 * MS)
        p = [o for o in outs if o.kind == EventType.SLIP_PRECURSOR
             and t_stick < o.time_ns < tg]
        pre += bool(p)
        early += any(o.kind == EventType.SLIP and t_stick + 100 * MS < o.time_ns < t09
                     for o in outs)
        outs_r, _ = run_model(evs, evs[-1].time_ns + 300 * MS, model=False)
        early_rules += any(o.kind == EventType.SLIP and t_stick + 100 * MS < o.time_ns < t09
                           for o in outs_r)
    assert pre >= 28 and early <= 1
    assert early_rules >= 5


def annulus_ramp_events(rng, t0_ms, ramp_s, n_micro, a=1.6e-3, gross_hz=150.0):
    """A load ramp nobody announced (no touch: a hand holding when the driver started, or
    its touch lost): Poisson micro-slips at the rate of Cattaneo-Mindlin's slipped area,
    n_micro (2/3) (1 - q)^(-1/3) / ramp_s, each uniform by area over the slip annulus
    c(q) < r < a, c = a (1 - q)^(1/3); then gross slip over the disc. Returns (events,
    t_q09_ns, t_gross_ns)."""
    f = np.sort(rng.uniform(0.0, 1.0, rng.poisson(n_micro)))
    q = 1.0 - (1.0 - f) ** 1.5
    t = t0_ms * MS + q * ramp_s * 1e9
    c = a * (1.0 - q) ** (1.0 / 3.0)
    r = np.sqrt(rng.uniform(c**2, a**2))
    th = rng.uniform(0.0, 2.0 * math.pi, q.size)
    pol = rng.choice([-1, 1], q.size)
    evs = [ev(int(ti), ri * math.cos(h), ri * math.sin(h), int(p), 100 + i)
           for i, (ti, ri, h, p) in enumerate(zip(t, r, th, pol))]
    tg = int(t0_ms * MS + ramp_s * 1e9)
    evs += slide_events(rng, tg / MS, gross_hz, int(gross_hz * 0.2), 0.0, 0.0, a, 2000)
    return evs, int(t0_ms * MS + 0.9 * ramp_s * 1e9), tg


def test_a_load_nobody_announced_on_its_annulus_is_a_load_not_a_slide():
    """Micro-slips over the whole slip annulus (not a thin front), 40 over a 1 s ramp, no
    touch before them: the first emissions of an object still 'arriving', yet on a ring
    round a centre (the annulus is thin while q is small). Over 30 ramps the precursor
    comes before gross slip in at least 28 and SLIP before q = 0.9 in at most 3 (a slide
    read there would be SLIP at q ~ 0.1)."""
    pre = early = 0
    for seed in range(30):
        rng = np.random.default_rng(300 + seed)
        evs, t09, tg = annulus_ramp_events(rng, 10, 1.0, 40)
        outs, _ = run_model(evs, evs[-1].time_ns + 300 * MS)
        p = [o for o in outs if o.kind == EventType.SLIP_PRECURSOR]
        pre += bool(p and p[0].time_ns < tg)
        early += any(o.kind == EventType.SLIP and o.time_ns < t09 for o in outs)
    assert pre >= 28 and early <= 3


def test_a_stylus_along_a_line_reads_sliding_not_a_ring_on_a_short_arc():
    """A stylus touching, then dragged along a straight line (emissions 0.4 mm apart every
    25 ms, 5 % timing jitter, random polarity): its points lie on a line in time order,
    which no load's ring gives (micro-slips on a short arc of a ring come in any order).
    Over 20 strokes the finger reads GROSS_SLIP from the 8th emission to the end of the
    stroke in at least 18, and no precursor comes."""
    ok = pre = 0
    for seed in range(20):
        rng = np.random.default_rng(400 + seed)
        h = rng.uniform(0.0, 2.0 * math.pi)
        n = 30
        s = 0.4e-3 * np.arange(n) - 6e-3
        t = 10 * MS + 25 * MS * np.arange(1, n + 1) * (1.0 + rng.normal(0.0, 0.05, n) / 25)
        s0 = s[0] - 0.4e-3  # the touch, a ridge before the first emission
        evs = [ev(10 * MS, s0 * math.cos(h), s0 * math.sin(h), +1, 0)]
        evs += [ev(int(ti), si * math.cos(h), si * math.sin(h), int(p), 1 + i) for i, (ti, si, p)
                in enumerate(zip(t, s, rng.choice([-1, 1], n)))]
        outs, trace = run_model(evs, evs[-1].time_ns + 10 * MS)
        t8, t_end = evs[8].time_ns, evs[-1].time_ns
        ok += all(st == ContactState.GROSS_SLIP for tt, st in trace if t8 <= tt <= t_end)
        pre += any(o.kind == EventType.SLIP_PRECURSOR for o in outs)
    assert ok >= 18 and pre == 0
