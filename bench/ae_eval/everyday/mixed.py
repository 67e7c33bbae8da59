# SPDX-License-Identifier: Apache-2.0
"""A mixed everyday stream: scenes of every family one after another with idle gaps, in a
realistic mix (mostly touches and holds, a grasp now and then loaded to slip)."""

from __future__ import annotations

import numpy as np

from .loaded import grasp_load, regrasp, slide_restick_ramp
from .slides import slide_start, stylus
from .touches import broad_press, multi_point, tap_beside_held, touch_beside_held
from .truth import Scene, SceneBuilder, cap_xy, draw


def hold(seed, held_out=False):
    """A single touch held 0.1-10 s (log) and released."""
    rng = np.random.default_rng([38010, int(seed), int(held_out)])
    b = SceneBuilder("hold", seed, held_out, rng)
    x, y = cap_xy(rng, 6e-3)
    h = draw(rng, 0.1, 10.0, True)
    b.contact(x, y, 0.01, 0.01 + h)
    b.params.update(hold_s=h)
    return b.build()


#: (generator, share of scenes) of the nominal mix: loaded scenes ~ 7 %
MIX = ((hold, 0.25), (multi_point, 0.2), (touch_beside_held, 0.12), (broad_press, 0.15),
       (tap_beside_held, 0.08), (slide_start, 0.08), (stylus, 0.05), (grasp_load, 0.04),
       (regrasp, 0.015), (slide_restick_ramp, 0.015))
#: the held-out mix: more slides and loads, shorter gaps
MIX_HELD_OUT = ((hold, 0.15), (multi_point, 0.2), (touch_beside_held, 0.15),
                (broad_press, 0.15), (tap_beside_held, 0.1), (slide_start, 0.1),
                (stylus, 0.05), (grasp_load, 0.05), (regrasp, 0.025),
                (slide_restick_ramp, 0.025))


def mixed_stream(seed, held_out=False, duration_s=60.0):
    """Scenes drawn from `MIX` (held out: `MIX_HELD_OUT`, scenes drawn held out) one after
    another, idle gaps 0.3 s + exponential (mean 2 s; held out 0.5 s), until
    ``duration_s`` [s]; every scene's truth shifted to its start, contact ids offset."""
    rng = np.random.default_rng([38011, int(seed), int(held_out)])
    mix = MIX_HELD_OUT if held_out else MIX
    gens, w = [m[0] for m in mix], np.array([m[1] for m in mix])
    parts, t, k = [], 0.0, 0
    while True:
        g = gens[rng.choice(len(gens), p=w / w.sum())]
        sc = g(int(seed) * 1000 + k, held_out)
        k += 1
        if t + sc.duration_s > duration_s:
            break
        parts.append((t, sc))
        t += sc.duration_s + 0.3 + rng.exponential(0.5 if held_out else 2.0)
    return concat(parts, "mixed", seed, held_out, duration_s)


def _shift_episode(ep, t0, c0):
    out = dict(ep, contact=ep["contact"] + c0)
    for key in ("t_start_s", "t_end_s", "t_load_s"):
        if key in ep:
            out[key] = ep[key] + t0
    if ep.get("t_gross_s") is not None:
        out["t_gross_s"] = ep["t_gross_s"] + t0
    for key in ("times_s", "micro_times_s"):
        if key in ep:
            out[key] = [x + t0 for x in ep[key]]
    if "q_knots" in ep:
        out["q_knots"] = [(x + t0, q) for x, q in ep["q_knots"]]
    return out


def concat(parts, family, seed, held_out, duration_s):
    """One Scene of scenes [(start [s], Scene)] laid one after another."""
    cols = {k: [] for k in ("t_s", "xy_m", "polarity", "amplitude", "kind", "contact")}
    contacts, changes, episodes, c0 = [], [], [], 0
    for t0, sc in parts:
        for k in cols:
            v = getattr(sc, k)
            cols[k].append(v + t0 if k == "t_s" else v + c0 if k == "contact" else v)
        contacts += [dict(c, id=c["id"] + c0, t_on_s=c["t_on_s"] + t0,
                          t_off_s=c["t_off_s"] + t0, scene=sc.family) for c in sc.contacts]
        changes += [(t + t0, cid + c0, st) for t, cid, st in sc.changes]
        episodes += [_shift_episode(e, t0, c0) for e in sc.episodes]
        c0 += len(sc.contacts)
    cat = {k: (np.concatenate(v) if v else np.zeros((0, 2) if k == "xy_m" else 0))
           for k, v in cols.items()}
    o = np.argsort(cat["t_s"], kind="stable")
    return Scene(family, int(seed), held_out,
                 {"scenes": [sc.family for _, sc in parts]},
                 cat["t_s"][o], cat["xy_m"][o].reshape(-1, 2), cat["polarity"][o].astype(int),
                 cat["amplitude"][o], cat["kind"][o].astype(int), cat["contact"][o].astype(int),
                 contacts, changes, episodes, float(duration_s))
