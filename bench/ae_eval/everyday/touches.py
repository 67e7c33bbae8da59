# SPDX-License-Identifier: Apache-2.0
"""Touch families (no tangential load: every SLIP_PRECURSOR / SLIP / TEXTURE is false):
multi-point touches (the paper's Fig. 8), touches next to a held one (Fig. 7's sequence),
a broad object pressed on, tapping beside a held contact. ``held_out=True`` draws from
shifted / wider ranges and other processes (Poisson instead of periodic, more points)."""

from __future__ import annotations

import math

import numpy as np

from .truth import SceneBuilder, around_xy, cap_xy, disc_xy, draw, skin_distance_m

CAP_R_MAX_M = 7.5e-3  # [m] points stay within this tangent radius (polar angle ~ 49 deg)


def spaced_points(rng, n, d_lo, d_hi, first=None, tries=400):
    """(n, 2) [m] points on the cap, every pair d_lo .. d_hi [m] apart along the skin (each
    new point at a drawn distance from a random earlier one); ``first`` fixes the first."""
    for _ in range(tries):
        pts = [first if first is not None else cap_xy(rng, 4e-3)]
        while len(pts) < n:
            b = pts[rng.integers(len(pts))]
            d, a = rng.uniform(d_lo, d_hi), rng.uniform(0.0, 2.0 * math.pi)
            p = tuple(float(v) for v in around_xy(b[0], b[1], d, a)[0])
            dd = [skin_distance_m(p, q) for q in pts]
            if math.hypot(*p) <= CAP_R_MAX_M and min(dd) >= d_lo and max(dd) <= d_hi:
                pts.append(p)
            elif rng.uniform() < 0.05:
                break
        if len(pts) == n:
            return np.array(pts)
    raise RuntimeError("could not place the points")


def multi_point(seed, held_out=False):
    """An object touching at 2-4 points 1.5-7 mm apart within 0.2-5 ms, held 0.1-3 s
    (log), released within 0.2-5 ms in a random order (held out: 2-6 points 1-9 mm apart,
    touches within 0.05-10 ms, holds 0.05-6 s, releases within 0.2-20 ms in touch order)."""
    rng = np.random.default_rng([38001, int(seed), int(held_out)])
    b = SceneBuilder("multi_point", seed, held_out, rng)
    n = int(rng.integers(2, 7 if held_out else 5))
    d = (1.0e-3, 9e-3) if held_out else (1.5e-3, 7e-3)
    win = draw(rng, 0.05e-3, 10e-3, True) if held_out else draw(rng, 0.2e-3, 5e-3)
    hold = draw(rng, 0.05, 6.0, True) if held_out else draw(rng, 0.1, 3.0, True)
    rwin = draw(rng, 0.2e-3, 20e-3, True) if held_out else draw(rng, 0.2e-3, 5e-3)
    pts = spaced_points(rng, n, *d)
    t_on = 0.01 + np.sort(rng.uniform(0.0, win, n))
    t_on[0] = 0.01
    order = np.arange(n) if held_out else rng.permutation(n)
    t_off = np.empty(n)
    t_off[order] = 0.01 + win + hold + np.sort(rng.uniform(0.0, rwin, n))
    for i in range(n):
        b.contact(pts[i, 0], pts[i, 1], float(t_on[i]), float(t_off[i]))
    b.params.update(n_points=n, window_s=win, hold_s=hold, release_window_s=rwin,
                    min_spacing_m=float(min(skin_distance_m(p, q) for i, p in enumerate(pts)
                                             for q in pts[i + 1:])))
    return b.build()


def touch_beside_held(seed, held_out=False):
    """A touch held for the trial, then 1-3 touches 2-5 mm from it and from each other,
    2-50 ms apart (log), each held 0.05-1 s and released (held out: 1-5 touches 1.5-6 mm
    apart, Poisson at a mean interval of 1-100 ms)."""
    rng = np.random.default_rng([38002, int(seed), int(held_out)])
    b = SceneBuilder("touch_beside_held", seed, held_out, rng)
    k = int(rng.integers(1, 6 if held_out else 4))
    d = (1.5e-3, 6e-3) if held_out else (2e-3, 5e-3)
    pts = spaced_points(rng, k + 1, *d)
    if held_out:
        gaps = rng.exponential(draw(rng, 1e-3, 100e-3, True), k)
    else:
        gaps = np.array([draw(rng, 2e-3, 50e-3, True) for _ in range(k)])
    t = 0.01 + np.concatenate([[0.0], np.cumsum(gaps)])
    holds = rng.uniform(0.05, 1.0, k)
    end = float(max(t[1:] + holds) + draw(rng, 0.05, 0.5))
    b.contact(pts[0, 0], pts[0, 1], float(t[0]), end)
    for i in range(k):
        b.contact(pts[i + 1, 0], pts[i + 1, 1], float(t[i + 1]), float(t[i + 1] + holds[i]))
    b.params.update(n_beside=k, gaps_s=[float(g) for g in gaps])
    return b.build()


def broad_press(seed, held_out=False):
    """A broad object pressed on: 1-6 compressions over a 2-4 mm disc within 1-10 ms, held
    0.1-2 s (log), then 1-6 rarefactions elsewhere on the disc within 1-10 ms (held out:
    1-8 emissions over a 1.5-5 mm disc within 0.5-20 ms, each release on a touch's spot
    with probability 0.5). One contact at the disc's centre."""
    rng = np.random.default_rng([38003, int(seed), int(held_out)])
    b = SceneBuilder("broad_press", seed, held_out, rng)
    hi = 8 if held_out else 6
    nc, nr = int(rng.integers(1, hi + 1)), int(rng.integers(1, hi + 1))
    rad = 0.5 * (draw(rng, 1.5e-3, 5e-3) if held_out else draw(rng, 2e-3, 4e-3))
    win = draw(rng, 0.5e-3, 20e-3, True) if held_out else draw(rng, 1e-3, 10e-3)
    rwin = draw(rng, 0.5e-3, 20e-3, True) if held_out else draw(rng, 1e-3, 10e-3)
    hold = draw(rng, 0.1, 2.0, True)
    cx, cy = cap_xy(rng, 4.5e-3)
    tc = 0.01 + np.sort(rng.uniform(0.0, win, nc))
    tc[0] = 0.01
    t0 = 0.01 + win + hold
    tr = t0 + np.sort(rng.uniform(0.0, rwin, nr))
    cid = b.contact(cx, cy, 0.01, float(tr[-1]), touch=False, release=False)
    pc = disc_xy(rng, cx, cy, 0.0, rad, nc)
    pr = disc_xy(rng, cx, cy, 0.0, rad, nr)
    if held_out:
        same = rng.uniform(size=nr) < 0.5
        pr[same] = pc[rng.integers(nc, size=int(same.sum()))]
    b.emit_many(tc, pc, +1, "touch", cid)
    b.emit_many(tr, pr, -1, "release", cid)
    b.params.update(n_compressions=nc, n_releases=nr, disc_radius_m=rad, window_s=win)
    return b.build()


def tap_beside_held(seed, held_out=False, duration_s=None):
    """A touch held for 1-5 s while a spot 1.5-8 mm away is tapped at 1-10 Hz (periodic,
    jitter up to 20 % of the period; each tap a touch held 10-100 ms and its release)
    (held out: Poisson taps at 0.5-15 Hz scattered within 1 mm of the tapped spot, held
    5-200 ms)."""
    rng = np.random.default_rng([38004, int(seed), int(held_out)])
    b = SceneBuilder("tap_beside_held", seed, held_out, rng)
    dur = duration_s or draw(rng, 1.0, 5.0)
    p = spaced_points(rng, 2, 1.5e-3, 8e-3)
    rate = draw(rng, 0.5, 15.0, True) if held_out else draw(rng, 1.0, 10.0)
    if held_out:
        t = 0.05 + np.cumsum(rng.exponential(1.0 / rate, int(dur * rate * 3) + 3))
        hold = rng.uniform(5e-3, 0.2, t.size)
    else:
        n = int(dur * rate) + 1
        t = 0.05 + np.arange(n) / rate + rng.uniform(0.0, 0.2 / rate, n)
        hold = rng.uniform(0.01, 0.1, n)
    ok = t + hold < dur - 0.05
    t, hold = t[ok], hold[ok]
    # a tap before the previous one ended would be two objects at one spot: keep them apart
    keep = np.concatenate([[True], t[1:] > (t + hold)[:-1] + 1e-3]) if t.size else ok[:0]
    t, hold = t[keep], hold[keep]
    b.contact(p[0, 0], p[0, 1], 0.01, dur)
    for ti, hi in zip(t, hold):
        x, y = (disc_xy(rng, p[1, 0], p[1, 1], 0.0, 1e-3, 1)[0] if held_out else p[1])
        b.contact(float(x), float(y), float(ti), float(ti + hi))
    b.params.update(tap_rate_hz=rate, n_taps=int(t.size), duration_s=dur,
                    distance_m=skin_distance_m(p[0], p[1]))
    return b.build()
