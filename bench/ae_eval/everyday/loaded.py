# SPDX-License-Identifier: Apache-2.0
"""Loaded families: Cattaneo-Mindlin load ramps (micro-slips at the edge of the stick
zone, their count growing as the slipped area fraction f(q) = 1 - (1 - q)^(2/3), gross
slip at q = Q / (mu P) = 1): after a slide and a re-stick, after a grasp's touch, and
re-grasps (a partial load, a release, a grasp beside it loaded to slip)."""

from __future__ import annotations

import math

import numpy as np

from .slides import add_slide, renewal_times
from .truth import GROSS, INC, STICK, SceneBuilder, around_xy, cap_xy, disc_xy, draw


def slipped_fraction(q):
    """Cattaneo-Mindlin slipped area fraction of a contact at load fraction q."""
    return 1.0 - (1.0 - np.clip(q, 0.0, 1.0)) ** (2.0 / 3.0)


def q_of_fraction(f):
    """The load fraction q whose slipped area fraction is f (the inverse of
    `slipped_fraction`)."""
    return 1.0 - (1.0 - np.clip(f, 0.0, 1.0)) ** 1.5


def add_load(b, cid, cx, cy, a_m, t0, ramp_s, n_micro, q_max=1.0, power=1.0,
             gross=(100.0, 0.2), process="poisson"):
    """A load ramp on contact ``cid`` (disc radius a_m [m] at (cx, cy)): q(t) = ((t - t0) /
    ramp_s)^power up to q_max; ``n_micro`` micro-slips over a full ramp, placed at equal
    steps of f(q) jittered (so their count up to q is n_micro f(q)), each at the stick
    front r = c(q) = a (1 - q)^(1/3) (+ up to 10 % of the annulus); the contact
    INCIPIENT_SLIP from the first micro-slip; at q = 1 gross slip: emissions over the disc
    at ``gross`` = (rate [Hz], duration [s]). Returns the end time [s]."""
    rng = b.rng
    f = (np.arange(n_micro) + rng.uniform(0.0, 1.0, n_micro)) / n_micro
    q = q_of_fraction(f)
    q = q[q < q_max]
    t = t0 + ramp_s * q ** (1.0 / power)
    c = a_m * (1.0 - q) ** (1.0 / 3.0)
    r = c + rng.uniform(0.0, 0.1, q.size) * (a_m - c)
    th = rng.uniform(0.0, 2.0 * math.pi, q.size)
    b.emit_many(t, around_xy(cx, cy, r, th), rng.choice([-1, 1], q.size), "micro_slip", cid)
    if q.size:
        b.state(float(t[0]), cid, INC)
    t_q = t0 + ramp_s * q_max ** (1.0 / power)
    knots = [(float(t0 + ramp_s * x ** (1.0 / power)), float(x))
             for x in np.linspace(0.0, q_max, 21)]
    ep = {"type": "load", "contact": cid, "t_load_s": float(t0), "q_knots": knots,
          "t_gross_s": None, "n_micro": int(q.size),
          "micro_times_s": [float(x) for x in t], "q_micro": [float(x) for x in q]}
    b.episodes.append(ep)
    if q_max < 1.0:
        b.state(t_q, cid, STICK)  # unloaded: the stick zone grows back, silent
        return t_q
    ep["t_gross_s"] = float(t_q)
    ep["q_knots"].append((float(t_q + gross[1]), 1.0))
    tg = renewal_times(rng, process, gross[0], t_q, t_q + gross[1])
    b.emit_many(tg, disc_xy(rng, cx, cy, 0.0, a_m, tg.size), rng.choice([-1, 1], tg.size),
                "slip", cid)
    b.state(t_q, cid, GROSS)
    return t_q + gross[1]


def _ramp_draws(rng, held_out):
    """(ramp [s], micro-slips per full ramp, power of q(t), gross rate [Hz], gross [s])."""
    if held_out:
        return (draw(rng, 0.2, 5.0, True), int(draw(rng, 3, 100, True)),
                draw(rng, 0.5, 2.0, True), draw(rng, 30.0, 300.0, True), draw(rng, 0.1, 0.5))
    return (draw(rng, 0.3, 3.0, True), int(draw(rng, 5, 60, True)), 1.0,
            draw(rng, 50.0, 200.0, True), draw(rng, 0.1, 0.4))


def slide_restick_ramp(seed, held_out=False):
    """A slide over a fixed spot (0.1-0.5 s at 20-200 Hz, periodic or Poisson), a re-stick
    (silent, 0.1-1 s), then a load ramp of 0.3-3 s (log) with 5-60 micro-slips per full
    ramp to gross slip at q = 1 (50-200 Hz over the disc for 0.1-0.4 s), then the release
    (held out: ramps 0.2-5 s, 3-100 micro-slips, q(t) = (t/T)^p, p 0.5-2, gross 30-300 Hz)."""
    rng = np.random.default_rng([38007, int(seed), int(held_out)])
    b = SceneBuilder("slide_restick_ramp", seed, held_out, rng)
    cx, cy = cap_xy(rng, 5e-3)
    a = draw(rng, 0.5e-3, 1.5e-3)
    rate = draw(rng, 20.0, 200.0, True)
    proc = str(rng.choice(["periodic", "poisson"]))
    t1 = 0.01 + draw(rng, 0.1, 0.5)
    ramp, n, pw, g_rate, g_s = _ramp_draws(rng, held_out)
    t_load = t1 + draw(rng, 0.1, 1.0)
    cid = b.contact(cx, cy, 0.01, 0.0, touch=False, release=False, state=GROSS)
    add_slide(b, cid, cx, cy, a, 0.01, t1, rate, proc)
    b.state(t1, cid, STICK)
    t_end = add_load(b, cid, cx, cy, a, t_load, ramp, n, power=pw, gross=(g_rate, g_s))
    _release(b, cid, cx, cy, t_end)
    b.params.update(slide_rate_hz=rate, process=proc, ramp_s=ramp, n_micro_full=n,
                    power=pw, gross_rate_hz=g_rate, restick_s=t_load - t1)
    return b.build()


def _release(b, cid, x, y, t):
    """The contact ``cid`` lifted at t [s]: a rarefaction at its centre, NO_CONTACT."""
    b.emit(t, x, y, -1, "release", cid)
    b.contacts[cid]["t_off_s"] = float(t)
    b.state(t, cid, 0)


def grasp_load(seed, held_out=False):
    """A grasp announced by its touch, held 0.1-0.5 s, then loaded to gross slip (ramp as
    `slide_restick_ramp`), released (held out: held 0.05-3 s)."""
    rng = np.random.default_rng([38008, int(seed), int(held_out)])
    b = SceneBuilder("grasp_load", seed, held_out, rng)
    cx, cy = cap_xy(rng, 5e-3)
    a = draw(rng, 0.5e-3, 1.5e-3)
    hold = draw(rng, 0.05, 3.0, True) if held_out else draw(rng, 0.1, 0.5)
    ramp, n, pw, g_rate, g_s = _ramp_draws(rng, held_out)
    cid = b.contact(cx, cy, 0.01, 0.0, touch=True, release=False)
    t_end = add_load(b, cid, cx, cy, a, 0.01 + hold, ramp, n, power=pw, gross=(g_rate, g_s))
    _release(b, cid, cx, cy, t_end)
    b.params.update(hold_s=hold, ramp_s=ramp, n_micro_full=n, power=pw, gross_rate_hz=g_rate)
    return b.build()


def regrasp(seed, held_out=False):
    """A grasp (touch, held 0.1-1 s) loaded to q_max 0.3-0.8 and unloaded, released; 50-500
    ms later a new grasp 0.5-3 mm away (touch, held 0.1-0.5 s) loaded to gross slip,
    released (held out: q_max 0.2-0.9, 1-3 mm apart, 20-1000 ms between)."""
    rng = np.random.default_rng([38009, int(seed), int(held_out)])
    b = SceneBuilder("regrasp", seed, held_out, rng)
    cx, cy = cap_xy(rng, 4e-3)
    a = draw(rng, 0.5e-3, 1.5e-3)
    ramp, n, pw, g_rate, g_s = _ramp_draws(rng, held_out)
    qm = draw(rng, 0.2, 0.9) if held_out else draw(rng, 0.3, 0.8)
    c1 = b.contact(cx, cy, 0.01, 0.0, touch=True, release=False)
    t_un = add_load(b, c1, cx, cy, a, 0.01 + draw(rng, 0.1, 1.0), ramp, n, q_max=qm, power=pw)
    t_rel = t_un + draw(rng, 0.02, 0.2)
    _release(b, c1, cx, cy, t_rel)
    d = draw(rng, 1e-3, 3e-3) if held_out else draw(rng, 0.5e-3, 3e-3)
    h = rng.uniform(0.0, 2.0 * math.pi)
    x2, y2 = (float(v) for v in around_xy(cx, cy, d, h)[0])
    t2 = t_rel + (draw(rng, 0.02, 1.0, True) if held_out else draw(rng, 0.05, 0.5))
    c2 = b.contact(x2, y2, t2, 0.0, touch=True, release=False)
    ramp2, n2, _, _, _ = _ramp_draws(rng, held_out)
    t_end = add_load(b, c2, x2, y2, a, t2 + draw(rng, 0.1, 0.5), ramp2, n2, power=pw,
                     gross=(g_rate, g_s))
    _release(b, c2, x2, y2, t_end)
    b.params.update(q_max_first=qm, regrasp_distance_m=d, ramp_s=ramp2, n_micro_full=n2)
    return b.build()
