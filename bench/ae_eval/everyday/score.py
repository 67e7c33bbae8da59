# SPDX-License-Identifier: Apache-2.0
"""Scoring a detector's outputs on an everyday scene against its truth (issue 38's
targets) and summarising a family.

Per trial (`score_trial`): every SLIP_PRECURSOR / SLIP / TEXTURE is true when the truth
backs it (a precursor: the finger INCIPIENT_SLIP or GROSS_SLIP within the last `GRACE_S`;
a SLIP: GROSS_SLIP within `GRACE_S` or q >= 0.9; a TEXTURE: GROSS_SLIP within `GRACE_S`),
else false; per slide from the start, whether SLIP came first (no precursor, no
INCIPIENT_SLIP before it), its delay and the slide's emissions up to it; per load, a SLIP
before q = 0.9, the precursor's lead and q, the micro-slips before gross slip; per textured
stroke, the first TEXTURE's period error; the share of time the finger's state equals the
truth (`SETTLE_S` after each change of the truth excepted); NO_CONTACT `AFTER_RELEASE_S`
after each last release.
"""

from __future__ import annotations

import numpy as np

from ae_tactile.records import ContactState, EventType

NS = 1_000_000_000
GRACE_S = 0.3  # [s] an alarm this long after the truth left a slip state is still backed
SETTLE_S = 0.1  # [s] after each change of the truth, the state is not scored
AFTER_RELEASE_S = 0.2  # [s] after the last release, the finger must read NO_CONTACT
GRID_S = 1e-3  # [s] step of the state comparison
STAMP_S = 1e-6  # [s] an output may precede its emission's true time by the time stamp error
PRE, SLIP, TEX = EventType.SLIP_PRECURSOR, EventType.SLIP, EventType.TEXTURE
KIND_NAME = {PRE: "precursor", SLIP: "slip", TEX: "texture"}
TOUCH_FAMILIES = ("hold", "multi_point", "touch_beside_held", "broad_press", "tap_beside_held")
LOADED_FAMILIES = ("slide_restick_ramp", "grasp_load", "regrasp", "mixed")


def _timeline_arrays(timeline):
    t = np.array([x[0] for x in timeline], float)
    s = np.array([int(x[1]) for x in timeline], int)
    return t, s


def _state_at(t_arr, s_arr, t):
    i = np.searchsorted(t_arr, t, side="right") - 1
    return np.where(i >= 0, s_arr[np.maximum(i, 0)], 0)


def _max_state(t_arr, s_arr, t0, t1):
    """The most severe truth state over [t0, t1] [s]."""
    i0 = max(np.searchsorted(t_arr, t0, side="right") - 1, 0)
    i1 = np.searchsorted(t_arr, t1, side="right")
    return int(s_arr[i0:i1].max()) if i1 > i0 else int(s_arr[i0])


def _q_at(scene, t):
    """The largest load fraction q of the scene's loads at t [s] (0 outside loads)."""
    q = 0.0
    for ep in scene.episodes:
        if ep["type"] == "load":
            k = np.array(ep["q_knots"])
            if k[0, 0] <= t <= k[-1, 0]:
                q = max(q, float(np.interp(t, k[:, 0], k[:, 1])))
    return q


def _backed(kind, scene, tt, ts, t):
    st = _max_state(tt, ts, t - GRACE_S, t + STAMP_S)
    if kind == PRE:
        return st >= ContactState.INCIPIENT_SLIP
    if kind == SLIP:
        return st == ContactState.GROSS_SLIP or _q_at(scene, t) >= 0.9
    return st == ContactState.GROSS_SLIP


def _alarms(scene, outs, tt, ts):
    """(counts of false outputs and onsets by kind, their times [s])."""
    res = {f"false_{n}": 0 for n in KIND_NAME.values()}
    res.update({f"false_onsets_{n}": 0 for n in KIND_NAME.values()})
    res.update({f"n_{n}": 0 for n in KIND_NAME.values()})
    times = []
    for o in outs:
        if o.kind not in KIND_NAME:
            continue
        n = KIND_NAME[o.kind]
        res[f"n_{n}"] += 1
        t = o.time_ns / NS
        if not _backed(o.kind, scene, tt, ts, t):
            res[f"false_{n}"] += 1
            res[f"false_onsets_{n}"] += int(bool(o.onset))
            times.append(round(t, 4))
    res["false_any"] = sum(res[f"false_{n}"] for n in KIND_NAME.values())
    res["false_times_s"] = times[:20]
    return res


def _slides(scene, outs, trace_t, trace_s):
    out = []
    for ep in (e for e in scene.episodes if e["type"] == "slide"):
        t0, t1 = ep["t_start_s"], ep["t_end_s"] + GRACE_S
        al = [o for o in outs if o.kind in KIND_NAME and t0 - 0.05 <= o.time_ns / NS <= t1]
        first = al[0] if al else None
        slip = next((o for o in al if o.kind == SLIP), None)
        r = {"rate_hz": ep["rate_hz"], "process": ep["process"], "slip": slip is not None}
        if slip is not None:
            ts_ = slip.time_ns / NS
            m = (trace_t >= t0) & (trace_t <= ts_)
            r["slip_first"] = bool(first.kind == SLIP
                                   and not np.any(trace_s[m] == ContactState.INCIPIENT_SLIP))
            r["delay_s"] = ts_ - t0
            r["n_emissions"] = int(np.sum(np.array(ep["times_s"]) <= ts_ + 1e-6))
            fast = r["delay_s"] <= 0.1 if ep["rate_hz"] >= 50 else r["n_emissions"] <= 5
            r["pass"] = bool(r["slip_first"] and fast)
        else:
            r.update(slip_first=False, delay_s=None, n_emissions=None, **{"pass": False})
        out.append(r)
    return out


def _loads(scene, outs):
    out = []
    for ep in (e for e in scene.episodes if e["type"] == "load"):
        tl, tg = ep["t_load_s"], ep["t_gross_s"]
        t_hi = tg if tg is not None else ep["q_knots"][-1][0]
        early = [o for o in outs if o.kind == SLIP and tl <= o.time_ns / NS < t_hi
                 and _q_at(scene, o.time_ns / NS) < 0.9]
        r = {"gross": tg is not None, "slip_before_q09": bool(early)}
        if early:
            r["q_early_slip"] = _q_at(scene, early[0].time_ns / NS)
        if tg is not None:
            mt = np.array(ep["micro_times_s"])
            r["n_micro"] = int(np.sum(mt < tg))
            pre = next((o for o in outs if o.kind == PRE and tl <= o.time_ns / NS < tg), None)
            r["precursor"] = pre is not None
            if pre is not None:
                r["lead_s"] = tg - pre.time_ns / NS
                r["q_precursor"] = _q_at(scene, pre.time_ns / NS)
            t_end = ep["q_knots"][-1][0] + GRACE_S
            sl = next((o for o in outs if o.kind == SLIP and tl <= o.time_ns / NS <= t_end
                       and _q_at(scene, o.time_ns / NS + STAMP_S) >= 0.9), None)
            r["slip_delay_s"] = None if sl is None else sl.time_ns / NS - tg
        out.append(r)
    return out


def _textures(scene, outs):
    out = []
    for ep in (e for e in scene.episodes if e["type"] == "texture"):
        t0, t1 = ep["t_start_s"], ep["t_end_s"] + GRACE_S
        tx = next((o for o in outs if o.kind == TEX and t0 <= o.time_ns / NS <= t1), None)
        r = {"found": tx is not None}
        if tx is not None:
            T = float(np.interp(tx.time_ns / NS, ep["times_s"], ep["period_s"]))
            rate = getattr(tx, "emission_rate_hz", float("nan"))
            r["period_rel_err"] = abs(1.0 / rate - T) / T if rate > 0 else None
            sp = getattr(tx, "spatial_period_m", float("nan"))
            lam = ep["spatial_period_m"]
            r["spatial_rel_err"] = abs(sp - lam) / lam if np.isfinite(sp) else None
            r["detect_s"] = tx.time_ns / NS - t0
            err = r["spatial_rel_err"] if r["spatial_rel_err"] is not None else r[
                "period_rel_err"]
            r["pass"] = err is not None and err <= 0.03
        else:
            r["pass"] = False
        out.append(r)
    return out


def _state_share(scene, trace, tt, ts):
    """(ms of agreement, ms scored, NO_CONTACT checks passed, checks)."""
    grid = np.arange(0.0, scene.duration_s, GRID_S)
    truth = _state_at(tt, ts, grid)
    dt = np.array([x[0] / NS for x in trace], float)
    ds = np.array([int(x[1]) for x in trace], int)
    det = _state_at(dt, ds, grid) if dt.size else np.zeros_like(truth)
    mask = np.ones(grid.size, bool)
    for t in tt[1:]:
        mask[(grid >= t) & (grid < t + SETTLE_S)] = False
    ok = int(np.sum((truth == det) & mask))
    n_rel = n_rel_ok = 0
    for i in range(1, tt.size):
        nxt = tt[i + 1] if i + 1 < tt.size else scene.duration_s
        if ts[i] == 0 and nxt - tt[i] > AFTER_RELEASE_S:
            n_rel += 1
            n_rel_ok += int(_state_at(dt, ds, tt[i] + AFTER_RELEASE_S) == 0) if dt.size else 1
    return ok, int(mask.sum()), n_rel_ok, n_rel


def score_trial(scene, outs, trace):
    """Score a detector's outputs and state trace on a scene.

    Parameters
    ----------
    scene : everyday.truth.Scene
        The trial's truth.
    outs : list
        The detector's outputs (``SlipEvent`` or anything with kind, time_ns, onset and,
        for TEXTURE, emission_rate_hz and spatial_period_m), time order.
    trace : list of (int, ContactState)
        The finger's latched state from each time [ns] on.

    Returns
    -------
    dict
        JSON-able: false alarms, slides, loads, textures, state agreement.
    """
    tt, ts = _timeline_arrays(scene.finger_timeline())
    trace_t = np.array([x[0] / NS for x in trace], float)
    trace_s = np.array([int(x[1]) for x in trace], int)
    r = {"family": scene.family, "seed": scene.seed, "held_out": scene.held_out,
         "duration_s": scene.duration_s, "n_emissions": int(scene.t_s.size),
         "params": {k: v for k, v in scene.params.items() if k != "scenes"}}
    r.update(_alarms(scene, outs, tt, ts))
    r["slides"] = _slides(scene, outs, trace_t, trace_s)
    r["loads"] = _loads(scene, outs)
    r["textures"] = _textures(scene, outs)
    ok, n, rel_ok, rel = _state_share(scene, trace, tt, ts)
    r.update(state_ok_ms=ok, state_ms=n, released_ok=rel_ok, released=rel)
    return r
