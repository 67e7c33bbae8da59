# SPDX-License-Identifier: Apache-2.0
"""Summaries of the slip trial families (percentiles, rates, failures) and
``run_evaluation``, which runs every family with consecutive seeds."""

from __future__ import annotations

import time

import numpy as np

from ae_tactile.records import ContactState
from ae_tactile.slip import SlipConfig

from .alarms import random_touches_trial, touch_hold_release_trial
from .incipient import INCIPIENT_RANGES, closed_loop_trial, incipient_slip_trial
from .texture import drift_slip_trial, texture_trial


def _pct(x, qs=(0, 5, 50, 95, 100)):
    """Percentiles ``qs`` of the values of ``x`` that are not None ('min', 'p5', ...,
    'max'); None when there are none."""
    x = np.asarray([v for v in x if v is not None], dtype=float)
    if x.size == 0:
        return None
    return {
        ("min" if q == 0 else "max" if q == 100 else f"p{q}"): float(np.percentile(x, q))
        for q in qs
    }


def summarize_incipient(trials: list[dict]) -> dict:
    """Incipient-slip trials: precursor before gross slip (rate, lead [ms], q), SLIP
    (rate, delay [ms], q), the precursor's distance to the ring [m], failures (seeds)."""
    n = len(trials)
    ok = [t for t in trials if t["precursor_before_gross"]]
    return {
        "n_trials": n,
        "precursor_before_gross_rate": len(ok) / n if n else None,
        "n_precursor_before_gross": len(ok),
        "lead_ms": _pct([t["lead_ms"] for t in ok]),
        "lead_fraction_of_ramp": _pct(
            [t["lead_ms"] / (1e3 * t["time_to_gross_slip_s"]) for t in ok]
        ),
        "q_at_precursor": _pct([t["q_at_precursor"] for t in ok]),
        "lead_ge_100ms_rate": (sum(t["lead_ms"] >= 100 for t in ok) / n) if n else None,
        "lead_ge_74ms_rate": (sum(t["lead_ms"] >= 74 for t in ok) / n) if n else None,
        "slip_detected_rate": sum(t["slip_time_ns"] is not None for t in trials) / n
        if n
        else None,
        "slip_delay_ms": _pct([t["slip_delay_ms"] for t in trials]),
        "q_at_slip": _pct([t["q_at_slip"] for t in trials]),
        "slip_before_gross_rate": (
            sum(t["slip_delay_ms"] is not None and t["slip_delay_ms"] < 0 for t in trials) / n
            if n
            else None
        ),
        "precursor_error_to_ring_m": _pct([t["precursor_error_to_ring_m"] for t in trials]),
        "texture_events_total": int(sum(t["n_texture_events"] for t in trials)),
        "failures": [t["seed"] for t in trials if not t["precursor_before_gross"]],
    }


def summarize_alarms(trials: list[dict]) -> dict:
    """False-alarm trials: alarm onsets per minute, events by kind, the trials with an
    alarm (seeds), and the latched state after the releases (`_release_summary`)."""
    minutes = sum(t["duration_s"] for t in trials) / 60.0
    onsets = sum(t["n_alarm_onsets"] for t in trials)
    return {
        "n_trials": len(trials),
        "minutes": minutes,
        "alarm_onsets": onsets,
        "false_alarms_per_minute": onsets / minutes if minutes else None,
        "precursor_events": sum(t["n_precursor"] for t in trials),
        "slip_events": sum(t["n_slip"] for t in trials),
        "texture_events": sum(t["n_texture"] for t in trials),
        "trials_with_alarm": [t["seed"] for t in trials if t["n_alarm_onsets"]],
        **_release_summary(trials),
    }


def _release_summary(trials: list[dict]) -> dict:
    """Trials whose every touch is released (touch-hold-release, cycles): how often the
    finger was free 0.1 s after the last release (the latched state NO_CONTACT); for
    touch-hold-release also for holds within / beyond the evidence window."""
    rel = [t for t in trials if "state_after_all_released" in t]
    if not rel:
        return {}
    free = [t["state_after_all_released"] == ContactState.NO_CONTACT for t in rel]
    out = {"free_after_release_rate": sum(free) / len(rel)}
    held = [t for t in rel if "hold_s" in t]
    if not held:
        return out
    w_s = SlipConfig().evidence_window_s
    out["evidence_window_s"] = w_s
    for name, rows in (
        ("short", [t for t in held if t["hold_s"] <= w_s]),
        ("long", [t for t in held if t["hold_s"] > w_s]),
    ):
        out[f"n_holds_{name}"] = len(rows)
        out[f"ended_at_release_rate_{name}"] = (
            sum(t["state_after_all_released"] == ContactState.NO_CONTACT for t in rows)
            / len(rows)
            if rows
            else None
        )
    return out


def summarize_texture(trials: list[dict]) -> dict:
    """Texture trials: detected rate, relative spatial period errors, detection time
    [ms], failures (seeds)."""
    det = [t for t in trials if t["n_texture"]]
    n = len(trials)
    return {
        "n_trials": n,
        "detected_rate": len(det) / n if n else None,
        "abs_rel_error_first": _pct([abs(t["rel_error_first"]) for t in det]),
        "abs_rel_error_median": _pct([abs(t["rel_error_median"]) for t in det]),
        "abs_rel_error_max_over_events": _pct([t["rel_error_max"] for t in det]),
        "within_10pct_rate": (sum(t["rel_error_max"] <= 0.10 for t in det) / n) if n else None,
        "detection_time_ms": _pct([t["texture_time_ms"] for t in det]),
        "failures": [t["seed"] for t in trials if not t["n_texture"]],
    }


def run_evaluation(
    *,
    n_incipient: int = 100,
    n_incipient_touch: int = 30,
    n_closed_loop: int = 30,
    n_thr: int = 100,
    n_random: int = 12,
    random_duration_s: float = 10.0,
    n_texture: int = 50,
    n_drift: int = 20,
    n_incipient_stream: int = 0,
    n_thr_stream: int = 0,
    seed: int = 0,
    config: SlipConfig | None = None,
    post_s: float = 0.25,
    progress=None,
) -> dict:
    """Every trial family with consecutive seeds from ``seed``; returns the summaries and
    the per-trial records (JSON-able)."""
    cfg = config or SlipConfig()
    out = {
        "config": cfg.as_dict(),
        "ranges": {k: list(v) if isinstance(v, tuple) else v for k, v in INCIPIENT_RANGES.items()},
    }
    timing = {}

    def run(name, fn, n):
        t0 = time.perf_counter()
        rows = []
        for i in range(n):
            rows.append(fn(seed + i))
            if progress:
                progress(name, i + 1, n)
        timing[name] = time.perf_counter() - t0
        return rows

    trials = {
        "incipient_slip": run(
            "incipient", lambda s: incipient_slip_trial(s, cfg, post_s=post_s), n_incipient
        ),
        "incipient_slip_announced": run(
            "incipient_touch",
            lambda s: incipient_slip_trial(s, cfg, announce_touch=True, post_s=post_s),
            n_incipient_touch,
        ),
        "closed_loop": run("closed_loop", lambda s: closed_loop_trial(s, cfg), n_closed_loop),
        "touch_hold_release": run(
            "touch_hold_release", lambda s: touch_hold_release_trial(s, cfg), n_thr
        ),
        "random_touches": run(
            "random_touches",
            lambda s: random_touches_trial(s, cfg, duration_s=random_duration_s),
            n_random,
        ),
        "random_touches_dense": run(
            "random_touches_dense",
            lambda s: random_touches_trial(
                s + 10_000, cfg, duration_s=random_duration_s, rate_hz=50.0, hold_max_s=0.5
            ),
            n_random,
        ),
        "texture": run("texture", lambda s: texture_trial(s, cfg), n_texture),
        "drift": run("drift", lambda s: drift_slip_trial(s, cfg), n_drift),
        "incipient_slip_stream": run(
            "incipient_stream",
            lambda s: incipient_slip_trial(s, cfg, post_s=post_s, pipeline="stream"),
            n_incipient_stream,
        ),
        "touch_hold_release_stream": run(
            "touch_hold_release_stream",
            lambda s: touch_hold_release_trial(s, cfg, pipeline="stream"),
            n_thr_stream,
        ),
    }
    out["summary"] = _summaries(trials)
    out["timing_s"] = timing
    out["trials"] = trials
    return out


def _summaries(trials: dict) -> dict:
    """`run_evaluation`'s summary of each family's trials (None: the family did not run)."""
    inc_t, cl, thr = trials["incipient_slip_announced"], trials["closed_loop"], trials[
        "touch_hold_release"]
    inc_s, thr_s = trials["incipient_slip_stream"], trials["touch_hold_release_stream"]
    rnd, rnd_dense = trials["random_touches"], trials["random_touches_dense"]
    tex, drift = trials["texture"], trials["drift"]
    return {
        "incipient_slip": summarize_incipient(trials["incipient_slip"]),
        "incipient_slip_announced": summarize_incipient(inc_t) if inc_t else None,
        "closed_loop": summarize_closed_loop(cl) if cl else None,
        "touch_hold_release": dict(
            summarize_alarms(thr),
            **{
                "state_mid_hold_stick_rate": (
                    sum(t["state_mid_hold"] == ContactState.STICK for t in thr) / len(thr)
                    if thr
                    else None
                ),
                "state_end_no_contact_rate": (
                    sum(t["state_end"] == ContactState.NO_CONTACT for t in thr) / len(thr)
                    if thr
                    else None
                ),
            },
        ),
        "incipient_slip_stream": summarize_incipient(inc_s) if inc_s else None,
        "touch_hold_release_stream": summarize_alarms(thr_s) if thr_s else None,
        "random_touches": summarize_alarms(rnd) if rnd else None,
        "random_touches_dense": summarize_alarms(rnd_dense) if rnd_dense else None,
        "texture": summarize_texture(tex) if tex else None,
        "drift": summarize_drift(drift) if drift else None,
    }


def summarize_closed_loop(trials: list[dict]) -> dict:
    """Closed-loop trials: how often the reflex averted gross slip, q at the reflex."""
    return {
        "n_trials": len(trials),
        "averted_rate": sum(t["averted"] for t in trials) / len(trials),
        "latency_s": trials[0]["latency_s"],
        "load_factor": trials[0]["load_factor"],
        "q_at_reflex": _pct([t["q_at_reflex"] for t in trials]),
        "failures": [t["seed"] for t in trials if not t["averted"]],
    }


def summarize_drift(trials: list[dict]) -> dict:
    """Drifting plane slip: SLIP detected, its delay [ms], direction errors [deg]."""
    n = len(trials)
    return {
        "n_trials": n,
        "slip_detected_rate": sum(t["slip_delay_ms"] is not None for t in trials) / n,
        "slip_delay_ms": _pct([t["slip_delay_ms"] for t in trials]),
        "direction_reported_rate": sum(t["n_with_direction"] > 0 for t in trials) / n,
        "direction_error_deg_median": _pct([t["direction_error_deg_median"] for t in trials]),
        "direction_error_deg_max": _pct([t["direction_error_deg_max"] for t in trials]),
    }
