# SPDX-License-Identifier: Apache-2.0
"""Running today's detector on everyday scenes ('events' pipeline, as bench_slip feeds
it) and summarising a family's scored trials against issue 38's targets."""

from __future__ import annotations

import numpy as np

from ae_eval.slip import run_detector

from .score import LOADED_FAMILIES, NS, TOUCH_FAMILIES, score_trial
from .truth import to_events

TICK_S = 0.01  # [s] the detector's timer between emissions (bench_slip's tick)


def run_trial(generator, seed, held_out=False, config=None):
    """Generate a scene, feed its events to a fresh ``SlipDetector`` and score it.

    Parameters
    ----------
    generator : callable
        A family generator ``(seed, held_out) -> Scene``.
    seed : int
        The trial's seed (the events' errors draw from it too).
    held_out : bool
        Draw from the held-out ranges.
    config : SlipConfig or None
        The detector's configuration (None: its defaults).

    Returns
    -------
    dict
        `score.score_trial`'s record.
    """
    scene = generator(seed, held_out)
    ev = to_events(scene, np.random.default_rng([38100, int(seed), int(held_out)]))
    end_ns = int(round(scene.duration_s * NS))
    _, outs, trace = run_detector(ev, config, end_ns, tick_ns=int(TICK_S * NS))
    return score_trial(scene, outs, trace)


def _share(x):
    x = [bool(v) for v in x]
    return (float(np.mean(x)) if x else None), len(x)


def _pct(x, q):
    x = [v for v in x if v is not None]
    return float(np.percentile(x, q)) if x else None


def summarize(family, trials):
    """A family's figures and each target's verdict (None: not applicable)."""
    hours = sum(t["duration_s"] for t in trials) / 3600.0
    s = {"family": family, "n_trials": len(trials), "hours": hours}
    for k in ("precursor", "slip", "texture"):
        s[f"false_{k}_per_h"] = sum(t[f"false_{k}"] for t in trials) / hours
    s["false_per_h"] = sum(t["false_any"] for t in trials) / hours
    s["false_onsets_per_h"] = sum(sum(t[f"false_onsets_{k}"] for k in ("precursor", "slip",
                                      "texture")) for t in trials) / hours
    s["trials_with_false"], _ = _share(t["false_any"] > 0 for t in trials)
    s["state_share"] = (sum(t["state_ok_ms"] for t in trials)
                        / max(sum(t["state_ms"] for t in trials), 1))
    s["no_contact_after_release"] = (sum(t["released_ok"] for t in trials)
                                     / max(sum(t["released"] for t in trials), 1))
    sl = [x for t in trials for x in t["slides"]]
    if sl:
        s["slides"] = _slide_summary(sl)
    ld = [x for t in trials for x in t["loads"]]
    if ld:
        s["loads"] = _load_summary(ld)
    tx = [x for t in trials for x in t["textures"]]
    if tx:
        s["texture_pass"], s["n_textures"] = _share(x["pass"] for x in tx)
        s["texture_found"], _ = _share(x["found"] for x in tx)
        s["texture_detect_p50_s"] = _pct([x.get("detect_s") for x in tx], 50)
    s["targets"] = targets(family, s)
    return s


def _slide_summary(sl):
    hi = [x for x in sl if x["rate_hz"] >= 50]
    lo = [x for x in sl if x["rate_hz"] < 50]
    return {
        "n": len(sl), "pass": _share(x["pass"] for x in sl)[0],
        "pass_ge_50hz": _share(x["pass"] for x in hi)[0],
        "pass_lt_50hz": _share(x["pass"] for x in lo)[0],
        "slip_first": _share(x["slip_first"] for x in sl)[0],
        "slip_found": _share(x["slip"] for x in sl)[0],
        "delay_p50_s": _pct([x["delay_s"] for x in sl], 50),
        "delay_p95_s": _pct([x["delay_s"] for x in sl], 95),
        "within_100ms_ge_50hz": _share((x["delay_s"] or 1e9) <= 0.1 for x in hi)[0],
        "n_emissions_p50_lt_50hz": _pct([x["n_emissions"] for x in lo], 50),
    }


def _load_summary(ld):
    g = [x for x in ld if x["gross"]]
    many = [x for x in g if x["n_micro"] >= 10]
    mid = [x for x in g if 5 <= x["n_micro"] < 10]
    few = [x for x in g if x["n_micro"] < 5]
    return {
        "n": len(ld), "n_gross": len(g),
        "slip_before_q09": _share(x["slip_before_q09"] for x in ld)[0],
        "precursor_ge10": _share(x["precursor"] for x in many)[0], "n_ge10": len(many),
        "precursor_5_10": _share(x["precursor"] for x in mid)[0], "n_5_10": len(mid),
        "precursor_lt5": _share(x["precursor"] for x in few)[0], "n_lt5": len(few),
        "lead_p50_s": _pct([x.get("lead_s") for x in g], 50),
        "lead_min_s": _pct([x.get("lead_s") for x in g], 0),
        "q_precursor_p50": _pct([x.get("q_precursor") for x in g], 50),
        "slip_delay_p50_s": _pct([x.get("slip_delay_s") for x in g], 50),
        "slip_delay_p95_s": _pct([x.get("slip_delay_s") for x in g], 95),
    }


def _ok(value, lo=None, hi=None):
    if value is None:
        return None
    return bool((lo is None or value >= lo) and (hi is None or value <= hi))


def targets(family, s):
    """{target: [value, verdict]} of issue 38's targets that apply to the family."""
    t = {"state_share>=0.95": [s["state_share"], _ok(s["state_share"], 0.95)],
         "no_contact_after_release>=0.99": [s["no_contact_after_release"],
                                            _ok(s["no_contact_after_release"], 0.99)]}
    if family in TOUCH_FAMILIES:
        t["false_alarms==0"] = [s["false_per_h"], s["false_per_h"] == 0]
    if family == "mixed":
        t["false_alarms_per_h<=1"] = [s["false_per_h"], s["false_per_h"] <= 1]
    if family == "slide_start":
        p = s["slides"]["pass"]
        t["slide_slip_first_fast>=0.95"] = [p, _ok(p, 0.95)]
    if family in LOADED_FAMILIES and "loads" in s:
        ld = s["loads"]
        t["slip_before_q09<=0.01"] = [ld["slip_before_q09"], _ok(ld["slip_before_q09"],
                                                                hi=0.01)]
        t["precursor_ge10>=0.99"] = [ld["precursor_ge10"], _ok(ld["precursor_ge10"], 0.99)]
        t["precursor_5_10>=0.95"] = [ld["precursor_5_10"], _ok(ld["precursor_5_10"], 0.95)]
    if family == "stylus":
        t["texture_within_3pct>=0.95"] = [s["texture_pass"], _ok(s["texture_pass"], 0.95)]
    return t
