# SPDX-License-Identifier: Apache-2.0
"""Sliding families: an object sliding from the start over a fixed spot of the tip
(emissions over its contact disc at 20-200 Hz, periodic or Poisson), and a textured
stylus moving over the tip (emissions at v / lambda along its path)."""

from __future__ import annotations

import math

import numpy as np

from .truth import GEOMETRY, GROSS, SceneBuilder, cap_xy, disc_xy, draw


def renewal_times(rng, process, rate_hz, t0, t1, jitter=0.05):
    """Emission times [s] in [t0, t1) of a renewal process at ``rate_hz``: 'periodic'
    (interval sd ``jitter`` of the period), 'poisson' or 'bursty' (gamma intervals,
    shape 0.5)."""
    n = int((t1 - t0) * rate_hz * 3) + 8
    if process == "periodic":
        iv = np.maximum(rng.normal(1.0, jitter, n), 0.05) / rate_hz
    elif process == "poisson":
        iv = rng.exponential(1.0 / rate_hz, n)
    elif process == "bursty":
        iv = rng.gamma(0.5, 2.0 / rate_hz, n)
    else:
        raise ValueError(process)
    t = t0 + np.concatenate([[0.0], np.cumsum(iv[:-1])])
    return t[t < t1]


def add_slide(b, cid, cx, cy, a_m, t0, t1, rate_hz, process, jitter=0.05):
    """Slip emissions of a contact sliding over its fixed disc of radius a_m [m] from t0
    to t1 [s]; the contact is GROSS_SLIP meanwhile; records the slide episode. Returns
    the emission times."""
    t = renewal_times(b.rng, process, rate_hz, t0, t1, jitter)
    b.emit_many(t, disc_xy(b.rng, cx, cy, 0.0, a_m, t.size), b.rng.choice([-1, 1], t.size),
                "slip", cid)
    b.state(t0, cid, GROSS)
    b.episodes.append({"type": "slide", "contact": cid, "t_start_s": float(t0),
                       "t_end_s": float(t1), "rate_hz": float(rate_hz), "process": process,
                       "times_s": [float(x) for x in t]})
    return t


def slide_start(seed, held_out=False):
    """An object landing and sliding at once over a fixed spot (contact disc radius
    0.5-1.5 mm) for 0.3-1.5 s, emissions at 20-200 Hz (log), periodic (5 % jitter) or
    Poisson, random polarity, then lifted (a rarefaction) (held out: 10-300 Hz, periodic
    with 0-25 % jitter, Poisson or bursty, a touch 0-20 ms before the slide in half)."""
    rng = np.random.default_rng([38005, int(seed), int(held_out)])
    b = SceneBuilder("slide_start", seed, held_out, rng)
    cx, cy = cap_xy(rng, 5e-3)
    a = draw(rng, 0.5e-3, 1.5e-3)
    rate = draw(rng, 10.0, 300.0, True) if held_out else draw(rng, 20.0, 200.0, True)
    proc = rng.choice(["periodic", "poisson", "bursty"] if held_out else ["periodic", "poisson"])
    jit = draw(rng, 0.0, 0.25) if held_out else 0.05
    lead = draw(rng, 0.0, 0.02) if held_out and rng.uniform() < 0.5 else None
    t0 = 0.01 + (lead or 0.0)
    t1 = t0 + draw(rng, 0.3, 1.5)
    cid = b.contact(cx, cy, 0.01, t1, touch=lead is not None, release=True,
                    state=GROSS if lead is None else 1)
    add_slide(b, cid, cx, cy, a, t0, t1, rate, str(proc), jit)
    b.params.update(rate_hz=rate, process=str(proc), jitter=jit, disc_radius_m=a,
                    touch_lead_s=lead, slide_s=t1 - t0)
    return b.build()


def surface_path(x0, y0, heading, n, step_m, curvature_1_m=0.0, geometry=GEOMETRY):
    """(n, 2) [m] tangent-plane (x, y) of n points ``step_m`` apart along the sphere's
    surface from (x0, y0), starting along ``heading`` [rad]: a great circle, or a path
    turning at ``curvature_1_m`` [1/m] (geodesic curvature)."""
    R = geometry.radius_m
    p = geometry.surface_point_from_xy(x0, y0).astype(float)
    d = np.array([math.cos(heading), math.sin(heading), 0.0])
    out = np.empty((n, 2))
    for k in range(n):
        nrm = p / R
        d = d - (d @ nrm) * nrm
        d /= np.linalg.norm(d)
        a = step_m * curvature_1_m
        d = math.cos(a) * d + math.sin(a) * np.cross(nrm, d)
        p = p + step_m * d
        p *= R / np.linalg.norm(p)
        out[k] = p[:2]
    return out


def stylus(seed, held_out=False):
    """A stylus touching, dragged over the tip along a straight stroke of 8-14 mm at
    5-50 mm/s (log) over a texture of period 0.2-0.8 mm (log), timing jitter 0-20 % of
    the period, lifted at the end (held out: a path turning at a radius of 8-30 mm, speed
    changing by up to +-20 % along the stroke, jitter 0-30 %, 10 % of the emissions
    missing)."""
    rng = np.random.default_rng([38006, int(seed), int(held_out)])
    b = SceneBuilder("stylus", seed, held_out, rng)
    v0 = draw(rng, 5e-3, 50e-3, True)
    lam = draw(rng, 0.2e-3, 0.8e-3, True)
    jit = draw(rng, 0.0, 0.3 if held_out else 0.2)
    path = min(14e-3, max(8e-3, 40 * lam))
    dv = draw(rng, -0.2, 0.2) if held_out else 0.0
    s = np.arange(1, int(path / lam)) * lam  # [m] arc length of each texture ridge
    v_of_s = v0 * (1.0 + dv * s / path)
    t_rel = np.cumsum(lam / v_of_s)  # [s] passing each ridge
    t_rel += rng.normal(0.0, jit, s.size) * lam / v_of_s
    h = rng.uniform(0.0, 2.0 * math.pi)
    x0, y0 = -0.5 * path * math.cos(h), -0.5 * path * math.sin(h)
    curv = draw(rng, 1 / 30e-3, 1 / 8e-3) * rng.choice([-1, 1]) if held_out else 0.0
    xy = surface_path(x0, y0, h, s.size, lam, curv)
    keep = rng.uniform(size=s.size) >= (0.1 if held_out else 0.0)
    t0 = 0.01
    t = t0 + t_rel
    t_end = float(t0 + t_rel[-1] + lam / v_of_s[-1])
    cid = b.contact(x0, y0, t0, t_end, touch=True, release=True)
    b.emit_many(t[keep], xy[keep], rng.choice([-1, 1], int(keep.sum())), "texture", cid)
    b.state(float(t[0]), cid, GROSS)
    b.episodes.append({"type": "texture", "contact": cid, "t_start_s": float(t[0]),
                       "t_end_s": t_end, "spatial_period_m": lam,
                       "times_s": [float(x) for x in t], "period_s": [float(x) for x in
                                                                       lam / v_of_s]})
    b.params.update(speed_m_s=v0, spatial_period_m=lam, jitter=jit, speed_change=dv,
                    path_m=path)
    return b.build()
