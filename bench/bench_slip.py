"""Slip detector benchmark: precursor / gross slip / texture / false alarms on the
simulator (issue 6), and the detector's cost per event.

    python3 bench/bench_slip.py [--quick]        (or: make bench-slip)

Runs ``ae_tactile.slip.evaluate.run_evaluation``: per trial a randomised scene (own
seed) -> the simulator's triggered windows -> ``localize`` (default estimator) ->
``SlipDetector`` with default parameters. Families: open-loop incipient slip (never
announced by a touch, and announced by a touch at the contact centre), closed-loop
grip reflex, touch-hold-release, random touches (20 Hz, holds <= 50 ms; and dense: 50 Hz,
holds <= 0.5 s), textures, and drifting plane slip; and some incipient-slip and
touch-hold-release trials through the stream path instead (StreamingSource -> dsp
PacketDetector -> localize_packets). Parameter ranges: see
``ae_tactile.slip.evaluate`` and docs/slip.md.

Writes bench/results/slip.json (``--quick``: slip_quick.json) and the table in
docs/slip.md between the bench markers (full run only).
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_v, "1")              # one core

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ae_tactile.slip import LocalizedEvent, SlipDetector  # noqa: E402
from ae_tactile.slip import evaluate as ev  # noqa: E402

RESULTS = ROOT / "bench" / "results"
DOC = ROOT / "docs" / "slip.md"
BEGIN, END = "<!-- bench:slip:begin -->", "<!-- bench:slip:end -->"


def detector_speed(n_events: int = 20000, seed: int = 0) -> dict:
    """Cost per event of SlipDetector.process on a dense mixed stream (ring micro-slips,
    gross slip, touches elsewhere), one core."""
    rng = np.random.default_rng(seed)
    R = 0.01
    evs = []
    t = 0
    for i in range(n_events):
        t += int(rng.exponential(1e6))                          # ~1000 events/s
        if rng.uniform() < 0.7:
            r, th = 1.5e-3 * np.sqrt(rng.uniform(0.3, 1.0)), rng.uniform(0, 2 * np.pi)
            x, y = r * np.cos(th), r * np.sin(th)
        else:
            x, y = rng.uniform(-6e-3, 6e-3, 2)
        p = np.array([x, y, np.sqrt(R * R - x * x - y * y)])
        evs.append(LocalizedEvent(t, p, np.eye(3) * 4e-10, int(rng.choice([-1, 1])), 0.01, 0.8, i))
    det = SlipDetector()
    t0 = time.perf_counter()
    n_out = 0
    for e in evs:
        n_out += len(det.process(e))
    dt = time.perf_counter() - t0
    return {"n_events": n_events, "us_per_event": 1e6 * dt / n_events, "events_per_s": n_events / dt,
            "n_outputs": n_out}


def fmt(d, key, scale=1.0, nd=0):
    if d is None or d.get(key) is None:
        return "-"
    v = d[key]
    return f"{v * scale:.{nd}f}"


def table(res: dict) -> str:
    s = res["summary"]
    inc, inc_t = s["incipient_slip"], s["incipient_slip_announced"]
    lines = ["| measure | value |", "|---|---|"]

    def pct_row(name, d, scale=1.0, nd=0, unit=""):
        if d is None:
            lines.append(f"| {name} | - |")
            return
        lines.append(f"| {name} | min {fmt(d, 'min', scale, nd)}, p5 {fmt(d, 'p5', scale, nd)}, "
                     f"median {fmt(d, 'p50', scale, nd)}, p95 {fmt(d, 'p95', scale, nd)}, "
                     f"max {fmt(d, 'max', scale, nd)}{unit} |")

    for label, d in (("incipient slip, contact never announced", inc),
                     ("incipient slip, announced by a touch", inc_t),
                     ("incipient slip, stream + dsp packet detector (not ideal triggers)", s.get("incipient_slip_stream"))):
        if d is None:
            continue
        lines.append(f"| **{label}** ({d['n_trials']} trials) | |")
        lines.append(f"| precursor before gross slip | {d['n_precursor_before_gross']}/{d['n_trials']} "
                     f"= {100 * d['precursor_before_gross_rate']:.1f} % |")
        pct_row("lead time (ms)", d["lead_ms"])
        pct_row("load fraction q = Q/(mu P) at the precursor", d["q_at_precursor"], nd=3)
        pct_row("lead / (mu P / Qdot)", d["lead_fraction_of_ramp"], nd=3)
        lines.append(f"| lead >= 74 ms / >= 100 ms | {100 * d['lead_ge_74ms_rate']:.1f} % / "
                     f"{100 * d['lead_ge_100ms_rate']:.1f} % of trials |")
        lines.append(f"| SLIP detected | {100 * d['slip_detected_rate']:.1f} % |")
        pct_row("SLIP delay after the true gross-slip onset (ms)", d["slip_delay_ms"], nd=1)
        pct_row("q at SLIP", d["q_at_slip"], nd=3)
        pct_row("precursor position: distance from the ring r = a_H (mm)", d["precursor_error_to_ring_m"],
                1e3, 2)
    cl = s["closed_loop"]
    if cl:
        lines.append(f"| **closed loop** ({cl['n_trials']} trials): P x {cl['load_factor']:g} "
                     f"{1e3 * cl['latency_s']:.0f} ms after the first precursor, Q ramps to 1.2 mu P | "
                     f"gross slip averted in {100 * cl['averted_rate']:.1f} % |")
        pct_row("q when P was raised", cl["q_at_reflex"], nd=3)
    for key, label in (("touch_hold_release", "touch-hold-release"),
                       ("touch_hold_release_stream", "touch-hold-release, stream + dsp detector"),
                       ("random_touches", "random touches 20 Hz"),
                       ("random_touches_dense", "random touches 50 Hz, holds <= 0.5 s")):
        a = s.get(key)
        if a:
            lines.append(f"| **{label}** ({a['n_trials']} trials, {a['minutes']:.1f} min) | false alarms "
                         f"{a['alarm_onsets']} = {a['false_alarms_per_minute']:.2f} /min "
                         f"(events: {a['precursor_events']} precursor, {a['slip_events']} slip, "
                         f"{a['texture_events']} texture) |")
    thr = s["touch_hold_release"]
    if thr and thr["n_trials"]:
        lines.append(f"| touch-hold-release state | STICK mid-hold {100 * thr['state_mid_hold_stick_rate']:.1f} %, "
                     f"NO_CONTACT at the end {100 * thr['state_end_no_contact_rate']:.1f} % |")
    tx = s["texture"]
    if tx:
        lines.append(f"| **texture** ({tx['n_trials']} trials) | detected {100 * tx['detected_rate']:.1f} %, "
                     f"every reported period within 10 %: {100 * tx['within_10pct_rate']:.1f} % |")
        pct_row("spatial period error, first TEXTURE event (%)", tx["abs_rel_error_first"], 100, 2)
        pct_row("worst spatial period error over a trial's events (%)", tx["abs_rel_error_max_over_events"],
                100, 2)
        pct_row("time to the first TEXTURE event (ms)", tx["detection_time_ms"])
    dr = s["drift"]
    if dr:
        lines.append(f"| **drifting plane slip** ({dr['n_trials']} trials) | SLIP detected "
                     f"{100 * dr['slip_detected_rate']:.1f} %, direction reported {100 * dr['direction_reported_rate']:.1f} % |")
        pct_row("SLIP delay after the slip start (ms)", dr["slip_delay_ms"], nd=1)
        pct_row("direction error, trial median (deg)", dr["direction_error_deg_median"], nd=1)
    sp = res.get("detector_speed")
    if sp:
        lines.append(f"| detector cost | {sp['us_per_event']:.0f} us per event on one core "
                     f"({sp['events_per_s'] / 1e3:.1f} k events/s) |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="reduced trial counts (smoke run)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    n = dict(n_incipient=20, n_incipient_touch=6, n_closed_loop=6, n_thr=30, n_random=1, random_duration_s=10.0,
             n_texture=10, n_drift=5, n_incipient_stream=2, n_thr_stream=5) if args.quick else dict(
        n_incipient=200, n_incipient_touch=50, n_closed_loop=50, n_thr=300, n_random=6, random_duration_s=60.0,
        n_texture=100, n_drift=30, n_incipient_stream=30, n_thr_stream=50)
    t0 = time.perf_counter()

    def progress(name, i, total):
        if i == total or i % 25 == 0:
            print(f"  {name}: {i}/{total} ({time.perf_counter() - t0:.0f} s)", flush=True)

    res = ev.run_evaluation(seed=args.seed, progress=progress, **n)
    res["detector_speed"] = detector_speed()
    res["meta"] = {"quick": args.quick, "seed": args.seed, "trial_counts": n, "python": platform.python_version(),
                   "numpy": np.__version__, "machine": platform.machine(), "wall_s": time.perf_counter() - t0}
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / ("slip_quick.json" if args.quick else "slip.json")
    out.write_text(json.dumps(res, indent=1, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))
    tab = table(res)
    print(tab)
    if not args.quick and DOC.exists():
        text = DOC.read_text()
        if BEGIN in text and END in text:
            head, rest = text.split(BEGIN, 1)
            _, tail = rest.split(END, 1)
            DOC.write_text(head + BEGIN + "\n" + tab + "\n" + END + tail)
    print(f"wrote {out} ({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
