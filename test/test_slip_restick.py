# SPDX-License-Identifier: Apache-2.0
"""The fingertip model after a slide's lift and after a loaded grasp's release: a load's
micro-slips on the stick front's ring soon after a slide stopped are a re-stuck object
being loaded (not the slide going on), a slide's emissions over its disc after a long gap
are the slide going on, and the touch of a re-grasp just after a loaded grasp's release
begins a contact of its own (its load's micro-slips are not read against the first
grasp's ring). Expectations from the scenes' truth: no SLIP before q = 0.9."""

import math

import numpy as np
from test_slip_model import run_model

from ae_tactile.records import ContactState, EventType
from ae_tactile.slip import LocalizedEvent

R = 0.01  # [m] fingertip radius of the hand-built events
MS = 1_000_000  # [ns]
SIG = 20e-6  # [m] localization 1-sigma of the hand-built events


def ev(t_ns, x, y, pol, pid=0):
    p = np.array([x, y, math.sqrt(R * R - x * x - y * y)])
    return LocalizedEvent(int(t_ns), p, np.eye(3) * SIG * SIG, pol, 0.01 * pol, 0.9, pid)


def run(events, end_ns, tick_ns=10 * MS):
    """(outputs, [(t_ns, state)]) of a default detector fed ``events`` with a timer."""
    return run_model(events, end_ns, model=True, tick_ns=tick_ns)


def disc(rng, cx, cy, a, n):
    r = a * np.sqrt(rng.uniform(0.0, 1.0, n))
    th = rng.uniform(0.0, 2.0 * math.pi, n)
    return np.column_stack([cx + r * np.cos(th), cy + r * np.sin(th)])


def slide(rng, t0_ns, rate_hz, t1_ns, cx=0.0, cy=0.0, a=1e-3, pid0=0):
    """Poisson emissions over the disc from t0_ns up to t1_ns, random polarity."""
    t = t0_ns + np.cumsum(np.r_[0.0, rng.exponential(1e9 / rate_hz, 400)])
    t = t[t < t1_ns]
    xy = disc(rng, cx, cy, a, t.size)
    pol = rng.choice([-1, 1], t.size)
    return [ev(int(ti), x, y, int(p), pid0 + i) for i, (ti, (x, y), p) in
            enumerate(zip(t, xy, pol))]


def ramp(rng, t0_ns, ramp_s, n_micro, q_max=1.0, cx=0.0, cy=0.0, a=1e-3, pid0=1000):
    """Cattaneo-Mindlin micro-slips of a load q = (t - t0) / ramp_s up to q_max at the
    stick front c = a (1 - q)^(1/3) (count up to q: n_micro (1 - (1 - q)^(2/3))), then,
    at q_max = 1, gross slip over the disc at 120 Hz for 0.2 s. Returns (events, time of
    q = 0.9 [ns], end of the micro-slips [ns])."""
    f = (np.arange(n_micro) + rng.uniform(0.0, 1.0, n_micro)) / n_micro
    q = 1.0 - (1.0 - f) ** 1.5
    q = q[q < q_max]
    t = t0_ns + q * ramp_s * 1e9
    c = a * (1.0 - q) ** (1.0 / 3.0)
    r = c + rng.uniform(0.0, 0.1, q.size) * (a - c)
    th = rng.uniform(0.0, 2.0 * math.pi, q.size)
    pol = rng.choice([-1, 1], q.size)
    evs = [ev(int(ti), cx + ri * math.cos(h), cy + ri * math.sin(h), int(p), pid0 + i)
           for i, (ti, ri, h, p) in enumerate(zip(t, r, th, pol))]
    t_end = int(t0_ns + q_max * ramp_s * 1e9)
    if q_max >= 1.0:
        evs += slide(rng, t_end, 120.0, t_end + 200 * MS, cx, cy, a, pid0 + 500)
    return evs, int(t0_ns + 0.9 * ramp_s * 1e9), t_end


def early_slips(outs, t_from, t09):
    return [o for o in outs if o.kind == EventType.SLIP and t_from < o.time_ns < t09]


def test_a_load_soon_after_a_slide_stopped_is_a_re_stuck_object_not_the_slide():
    """A slow slide (Poisson 30 Hz over a 1 mm disc, 0.3 s), silent 0.15-0.25 s (longer
    than its lift, shorter than twice it), then a load ramp of 1 s with 30 micro-slips
    to gross slip: SLIP between the re-stick (+ 0.1 s) and q = 0.9 in at most 2 of 30
    trials; a precursor before gross slip in at least 27; SLIP after gross slip in all."""
    early = pre = slip_after = 0
    for seed in range(30):
        rng = np.random.default_rng(3800 + seed)
        s = slide(rng, 10 * MS, 30.0, 310 * MS)
        t_stick = s[-1].time_ns
        t_load = t_stick + int(rng.uniform(150, 250) * MS)
        r, t09, tg = ramp(rng, t_load, 1.0, 30)
        outs, _ = run(s + r, tg + 600 * MS)
        early += bool(early_slips(outs, t_stick + 100 * MS, t09))
        pre += any(o.kind == EventType.SLIP_PRECURSOR and t_stick < o.time_ns < tg
                   for o in outs)
        slip_after += any(o.kind == EventType.SLIP and o.time_ns >= tg for o in outs)
    assert early <= 2 and pre >= 27 and slip_after == 30


def test_a_slide_going_on_after_a_long_gap_reads_sliding_again():
    """A slide over a 1 mm disc at 80 Hz for 0.3 s, silent 0.2 s (it reads lifted), then
    the same slide again for 0.5 s: over its last 0.2 s the finger reads GROSS_SLIP in at
    least 18 of 30 trials (its emissions over the disc are no load's ring; the rest a
    Poisson gap longer than its lift in that span), and NO_CONTACT 0.2 s after it stops in all."""
    again = lifted = 0
    for seed in range(30):
        rng = np.random.default_rng(3900 + seed)
        s1 = slide(rng, 10 * MS, 80.0, 310 * MS)
        t2 = s1[-1].time_ns + 200 * MS
        s2 = slide(rng, t2, 80.0, t2 + 500 * MS, pid0=500)
        t_end = s2[-1].time_ns
        outs, trace = run(s1 + s2, t_end + 400 * MS)
        late = [s for t, s in trace if t_end - 200 * MS <= t <= t_end]
        again += all(s == ContactState.GROSS_SLIP for s in late)
        st = [s for t, s in trace if t <= t_end + 200 * MS][-1]
        lifted += st == ContactState.NO_CONTACT
    assert again >= 18 and lifted == 30


def test_a_re_grasp_just_after_a_loaded_release_is_a_contact_of_its_own():
    """A grasp touched at the centre, loaded over 0.6 s to q = 0.6 (24 micro-slips per full
    ramp) and unloaded (silent 0.05 s), released on its touch; 40-200 ms later a second
    grasp touched 1 mm away, held 0.3 s, loaded over 0.4 s with 40 micro-slips to gross
    slip. Where the silence round the release (last micro-slip to the second touch) is
    more than 6 of the first load's latest 4 intervals (the model's lift: 5), the second
    touch begins a new contact (a TOUCH with a new id) and no SLIP comes before the second
    load's q = 0.9, save in 1 trial; such trials are at least 10 of 40."""
    n = own = early = 0
    for seed in range(40):
        rng = np.random.default_rng(4000 + seed)
        evs = [ev(10 * MS, 0.0, 0.0, +1, 0)]
        r1, _, t_un = ramp(rng, 300 * MS, 0.6, 24, q_max=0.6)
        t_rel = t_un + 50 * MS
        evs += r1 + [ev(t_rel, 3e-6, 0.0, -1, 1)]
        t2 = t_rel + int(rng.uniform(40, 200) * MS)
        h = rng.uniform(0.0, 2.0 * math.pi)
        x2, y2 = 1e-3 * math.cos(h), 1e-3 * math.sin(h)
        evs.append(ev(t2, x2, y2, +1, 2))
        r2, t09, tg = ramp(rng, t2 + 300 * MS, 0.4, 40, cx=x2, cy=y2, pid0=3000)
        tm = sorted(e.time_ns for e in r1)
        if len(tm) < 5 or t2 - tm[-1] <= 6 * (tm[-1] - tm[-5]) / 4:
            continue  # the release's silence is no clear stop of the first load's stream
        n += 1
        outs, _ = run(evs + r2, tg + 600 * MS)
        first = next(o.contact_id for o in outs if o.kind == EventType.TOUCH)
        own += any(o.kind == EventType.TOUCH and o.time_ns == t2 and o.contact_id != first
                   for o in outs)
        early += bool(early_slips(outs, t2, t09))
    assert n >= 10 and own == n and early <= 1
