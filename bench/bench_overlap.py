# SPDX-License-Identifier: Apache-2.0
"""Overlapping emissions: accuracy of `resolve_overlaps` against the joint Cramer-Rao bound.

    python3 bench/bench_overlap.py [--quick]        (or: make bench-overlap)
    python3 bench/bench_overlap.py --zoo [--pairs 20] [--held-out 3] [--only a,b]

`make bench-localization` (bench/bench_localization.py) runs this sweep too, after the
single-source figures; docs/overlap.md links the table (bench/results/overlap_table.md).

Windows from the simulator (ae_tactile.sim; 10 MS/s, 1 MHz front end, 12-bit ADC, two
wall echoes) holding two emissions (`ae_eval.overlap_trials.simulate_overlaps`:
each rendered alone and summed with an exact sub-sample delay, then noise and the ADC):
points uniform over the cap polar <= 60 deg and >= 2 mm apart, emission-time separation
1-10 us, strength ratio (stronger / weaker) 1, 2, 4 (which one comes first is random),
random polarities, SNR uniform in 20-30 dB for the *weaker* emission (docs/conventions.md
definition over its own 30 us window), water-skin and silicone tips.

Per cell: success rate (both points reported, each within 0.1 mm), RMS in-plane error of
reported points, wrong accepts (a reported point > 0.5 mm off), the fraction of reported points
inside their 1.515-sigma ellipse (68.3 % if the covariance is right), the joint CRLB
(`joint_crlb`) and the single-emission bound on the same samples. Also: single-emission
packets (how often they stay one emission), the single-source `localize` (ml) on the
pairs (rejected as OVERLAP / accepted, how far off), `suspect_overlap` on what ml
accepted, three emissions, the stronger-emission SNR reference, pulse-shape mismatch; the
cost of one window per call (the quick answer, as the driver's reader runs it, and the
exhaustive search of its worker), compiled and numpy.

Writes bench/results/overlap.json, bench/results/overlap_table.md,
bench/results/overlap_success.png.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_v, "1")  # one core

import argparse  # noqa: E402
import itertools  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ae_eval.crlb import joint_crlb  # noqa: E402
from ae_eval.delays import DELAY_WARM_TOUCHES  # noqa: E402
from ae_eval.overlap_trials import live_device, simulate_overlaps  # noqa: E402
from ae_eval.zoo import ZOO, held_out  # noqa: E402
from ae_tactile.localization import NUMBA_AVAILABLE, localize  # noqa: E402
from ae_tactile.localization.overlap import (  # noqa: E402
    PulseModel,
    calibrate_pulse,
    fit_pulse,
    resolve_overlaps,
    suspect_overlap,
)
from ae_tactile.sim import SimConfig, render_triggered  # noqa: E402

RESULTS = ROOT / "bench" / "results"
SEPARATIONS_US = [1, 2, 3, 5, 7, 10]
RATIOS = [1, 2, 4]
KEY = {(2, 1), (2, 4), (5, 1), (5, 4)}  # (separation us, ratio) cells with the most pairs
CHI2_683 = 2.2957  # chi^2(2) quantile 0.683 (1.515 sigma in 2-D)


def configs():
    return {
        "water": SimConfig(reflections=True),
        "silicone": SimConfig.for_medium("silicone", reflections=True),
    }


def match_errors(truth, sources):
    """3-D errors (m) of reported sources against the best assignment to true points, the
    normalised squared in-plane errors, the per-truth 3-D error (inf when not reported),
    and the in-plane errors (m)."""
    J = truth.shape[0]
    per_truth = np.full(J, np.inf)
    errs, nrm, errs_xy = [], [], []
    if not sources:
        return errs, nrm, per_truth, errs_xy
    pts = np.array([s.point_m for s in sources])
    d = np.linalg.norm(pts[:, None, :] - truth[None, :, :], axis=2)  # (S, J)
    best, best_cost = None, np.inf
    S = len(sources)
    for perm in itertools.permutations(range(J), min(S, J)):
        cost = sum(d[i, perm[i]] for i in range(len(perm)))
        if cost < best_cost:
            best, best_cost = perm, cost
    for i, j in enumerate(best):
        e = pts[i] - truth[j]
        c = sources[i].covariance_m2[:2, :2]
        errs.append(float(np.linalg.norm(e)))
        errs_xy.append(float(np.linalg.norm(e[:2])))
        try:
            nrm.append(float(e[:2] @ np.linalg.solve(c, e[:2])))
        except np.linalg.LinAlgError:
            nrm.append(float("inf"))
        per_truth[j] = min(per_truth[j], np.linalg.norm(e))
    for i in range(len(best), S):  # extra reported sources: matched to nearest truth
        errs.append(float(d[i].min()))
        errs_xy.append(float(d[i].min()))
        nrm.append(float("inf"))
    return errs, nrm, per_truth, errs_xy


def evaluate(d, res, cfg, crlb=True):
    n, J = d["points_m"].shape[:2]
    ok = np.zeros(n, bool)
    errs, nrms, wrong, wrong_small, rejected, extra, missing = [], [], 0, 0, 0, 0, 0
    errs_xy = []
    weak_err, strong_err = [], []
    for i, r in enumerate(res):
        if not r.accepted:
            rejected += 1
            continue
        e, q, per_truth, exy = match_errors(d["points_m"][i], r.sources)
        errs += e
        errs_xy += exy
        nrms += q
        wrong += sum(x > 0.5e-3 for x in e)
        wrong_small += sum(x > 0.5e-3 and s.sigma_m < 0.1e-3 for x, s in zip(e, r.sources))
        extra += max(len(r.sources) - J, 0)
        missing += max(J - len(r.sources), 0)
        ok[i] = len(r.sources) == J and np.all(per_truth <= 0.1e-3)
        st = d["strength"][i]
        for j in range(J):
            if np.isfinite(per_truth[j]):
                (weak_err if st[j] < st.max() else strong_err).append(per_truth[j])
    out = dict(
        n=n,
        success=float(ok.mean()),
        rejected=rejected / n,
        wrong_accepts=int(wrong),
        wrong_accepts_sigma_lt_0p1mm=int(wrong_small),
        extra_sources=int(extra),
        missing_sources=int(missing),
        rms_um=float(np.sqrt(np.mean(np.square(errs_xy))) * 1e6) if errs_xy else None,
        rms_3d_um=float(np.sqrt(np.mean(np.square(errs))) * 1e6) if errs else None,
        rms_weak_um=float(np.sqrt(np.mean(np.square(np.minimum(weak_err, 0.5e-3)))) * 1e6)
        if weak_err
        else None,
        inside_1p515_sigma=float(np.mean(np.array(nrms) <= CHI2_683)) if nrms else None,
    )
    if crlb:
        var = d["noise_rms_v"] ** 2 + cfg.lsb_v**2 / 12.0
        b = joint_crlb(
            d["clean_v"],
            d["sample_rate_hz"],
            d["onset_index"],
            d["points_m"],
            d["emission_time_s"],
            var,
            geometry=cfg.geometry,
        )
        out["crlb_um"] = float(np.sqrt(np.mean(b["rms_m"] ** 2)) * 1e6)
        out["crlb_single_um"] = float(np.sqrt(np.mean(b["single_rms_m"] ** 2)) * 1e6)
        out["model_mismatch_max"] = float(b["model_mismatch"].max())
    return out, ok


def timed_resolve(d, cfg, **kw):
    t0 = time.perf_counter()
    res = resolve_overlaps(
        d["samples_v"], d["sample_rate_hz"], d["onset_index"], geometry=cfg.geometry, **kw
    )
    return res, time.perf_counter() - t0


def one_window_cost(rng, n, config=None, pulse=None):
    """ms per window, one window per call: two emissions 1-8 us apart, strength ratio 1-4,
    SNR of the weaker 15-35 dB, water; the quick answer (``exhaustive=False``, as the
    driver's reader and overlap thread run it) and the exhaustive search (as its worker
    process runs it), each with the compiled kernels and the numpy path on the same
    windows. Median / p90 / max, and whether the two paths gave the same points.
    ``config`` / ``pulse``: another device and the pulse learnt on it (default: the
    nominal device and pulse)."""
    d = simulate_overlaps(
        n,
        SimConfig(reflections=True) if config is None else config,
        separation_s=rng.uniform(1e-6, 8e-6, n),
        amplitude_ratio=4.0,
        snr_db=rng.uniform(15, 35, n),
        rng=rng,
    )
    x, fs, on = d["samples_v"], d["sample_rate_hz"], d["onset_index"]
    out, points = {}, {}
    for mode, exhaustive in (("quick", False), ("exhaustive", True)):
        for engine in ("auto", "numpy"):
            kw = dict(engine=engine, exhaustive=exhaustive, pulse=pulse)
            resolve_overlaps(x[:1], fs, on[:1], **kw)  # warm (kernels loaded)
            ts, pts = [], []
            for i in range(n):
                t0 = time.perf_counter()
                r = resolve_overlaps(x[i : i + 1], fs, on[i : i + 1], **kw)[0]
                ts.append(time.perf_counter() - t0)
                pts.append([s.point_m for s in r.sources])
            ms = 1e3 * np.array(ts)
            name = "compiled" if engine == "auto" and NUMBA_AVAILABLE else engine
            out.setdefault(mode, {})[name] = dict(
                n=n,
                median=float(np.median(ms)),
                p90=float(np.percentile(ms, 90)),
                max=float(ms.max()),
            )
            points[mode, engine] = pts
    out["same_points"] = all(
        len(a) == len(b) and all(np.allclose(p, q, rtol=0, atol=1e-9) for p, q in zip(a, b))
        for mode in ("quick", "exhaustive")
        for a, b in zip(points[mode, "auto"], points[mode, "numpy"])
    )
    return out


def learnt_pulse_cost(rng, n, device="rc2_bessel6", n_singles=32):
    """`one_window_cost` on a zoo device with the pulse learnt from ``n_singles`` of its
    single touches (`PulseLearner`; 13 poles against the default's 8), and the learning's
    own cost [s]."""
    cfg = ZOO[device].config("water_skin", 10e6, reflections=True)
    geo = cfg.geometry
    cos_t = rng.uniform(math.cos(math.radians(60.0)), 1.0, n_singles)
    pts = geo.surface_point_from_angles(np.arccos(cos_t), rng.uniform(0, 2 * math.pi, n_singles))
    pk = render_triggered(pts, cfg, snr_db=30.0, rng=rng)
    t0 = time.perf_counter()
    fit = fit_pulse(pk.samples_v, cfg.sample_rate_hz, pk.onset_index, geometry=geo)
    learn_s = time.perf_counter() - t0
    out = one_window_cost(rng, n, cfg, fit.pulse)
    out.update(device=device, learn_s=learn_s, converged=fit.converged,
               n_poles=len(fit.pulse.poles_rad_s))
    return out


def main(argv=None):
    """Run the sweep, write the results files; returns (results dict, markdown table)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="few pairs per cell (smoke run)")
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--zoo", action="store_true",
                    help="the device zoo through the driver's pipeline, cold and warm "
                         "(bench/results/overlap_zoo.{json,md}; `zoo_main`)")
    ap.add_argument("--pairs", type=int, default=20, help="--zoo: pairs per device")
    ap.add_argument("--held-out", type=int, default=3, help="--zoo: held-out devices")
    ap.add_argument("--only", default="", help="--zoo: comma-separated device names")
    ap.add_argument("--out", default=str(RESULTS), help="--zoo: directory of the results")
    ap.add_argument("--fit-process", action="store_true",
                    help="--zoo: fit in the learner's niced process, as the driver does")
    args = ap.parse_args(argv)
    if args.zoo:
        return zoo_main(args)
    n_key, n_other = (30, 10) if args.quick else (200, 40)
    rng = np.random.default_rng(args.seed)
    t_start = time.perf_counter()
    cpu_start = time.process_time()
    out = dict(
        setup=dict(
            fs_hz=10e6,
            snr_db="uniform 20-30 (weaker emission)",
            max_polar_deg=60,
            min_distance_mm=2.0,
            pairs_per_key_cell=n_key,
            pairs_per_other_cell=n_other,
            key_cells="separation 2 and 5 us x ratio 1 and 4",
            machine=platform.platform(),
            load_before=os.getloadavg(),
        ),
        cells=[],
        singles={},
        ml_on_pairs={},
        three={},
        stronger_reference={},
        mismatch={},
    )
    t_resolve, n_resolve = 0.0, 0
    for medium, cfg in configs().items():
        for sep in SEPARATIONS_US:
            for ratio in RATIOS:
                n = n_key if (sep, ratio) in KEY else n_other
                d = simulate_overlaps(
                    n,
                    cfg,
                    separation_s=sep * 1e-6,
                    amplitude_ratio=ratio,
                    snr_db=rng.uniform(20, 30, n),
                    rng=rng,
                )
                res, dt = timed_resolve(d, cfg)
                t_resolve += dt
                n_resolve += n
                cell, _ = evaluate(d, res, cfg)
                cell.update(medium=medium, separation_us=sep, ratio=ratio)
                out["cells"].append(cell)
                print(
                    f"{medium:8s} sep {sep:2d} us ratio 1:{ratio}  n {n:3d}  success "
                    f"{cell['success']:.3f}  rms {cell['rms_um'] or 0:6.1f} um  crlb "
                    f"{cell['crlb_um']:5.1f}  wrong {cell['wrong_accepts']}  "
                    f"rej {cell['rejected']:.2f}",
                    flush=True,
                )
        # single emissions: stay single?
        n = n_key
        pts = cfg.geometry.surface_point_from_angles(
            np.arccos(rng.uniform(0.5, 1.0, n)), rng.uniform(0, 2 * np.pi, n)
        )
        pk = render_triggered(pts, cfg, snr_db=rng.uniform(20, 30, n), rng=rng)
        t0 = time.perf_counter()
        res = resolve_overlaps(
            pk.samples_v, pk.sample_rate_hz, pk.onset_index, geometry=cfg.geometry
        )
        t_single = time.perf_counter() - t0
        one = [r.accepted and len(r.sources) == 1 for r in res]
        err1 = [
            np.linalg.norm(r.sources[0].point_m[:2] - pts[i, :2])
            for i, r in enumerate(res)
            if r.accepted and len(r.sources) == 1
        ]
        localize(pk.samples_v[:2], pk.sample_rate_hz, pk.onset_index[:2], geometry=cfg.geometry)
        t0 = time.perf_counter()  # (after a warm-up call: any one-off compilation excluded)
        ml = localize(pk.samples_v, pk.sample_rate_hz, pk.onset_index, geometry=cfg.geometry)
        t_ml = time.perf_counter() - t0
        suspect_overlap(  # warm-up: kernels loaded before the timing
            pk.samples_v[:2], pk.sample_rate_hz, pk.onset_index[:2],
            localize(pk.samples_v[:2], pk.sample_rate_hz, pk.onset_index[:2],
                     geometry=cfg.geometry),
            geometry=cfg.geometry,
        )
        t0 = time.perf_counter()
        sus = suspect_overlap(
            pk.samples_v, pk.sample_rate_hz, pk.onset_index, ml, geometry=cfg.geometry
        )
        t_sus = time.perf_counter() - t0
        out["singles"][medium] = dict(
            n=n,
            one_source=float(np.mean(one)),
            split=float(np.mean([r.accepted and len(r.sources) > 1 for r in res])),
            rejected=float(np.mean([not r.accepted for r in res])),
            rms_um=float(np.sqrt(np.mean(np.square(err1))) * 1e6) if err1 else None,
            ml_accepted=float(ml.accepted.mean()),
            suspect_false_positive=float(sus[ml.accepted].mean()) if ml.accepted.any() else None,
            ms_per_packet_resolve=1e3 * t_single / n,
            us_per_packet_ml=1e6 * t_ml / n,
            us_per_packet_suspect=1e6 * t_sus / n,
        )
        print(medium, "singles", out["singles"][medium], flush=True)
        # the single-source localizer on pairs, and suspect_overlap on what it accepted
        rows = {}
        for sep in (2, 5, 8.5, 10):
            n = n_other
            d = simulate_overlaps(
                n,
                cfg,
                separation_s=sep * 1e-6,
                amplitude_ratio=2,
                snr_db=rng.uniform(20, 30, n),
                rng=rng,
            )
            ml = localize(
                d["samples_v"], d["sample_rate_hz"], d["onset_index"], geometry=cfg.geometry
            )
            sus = suspect_overlap(
                d["samples_v"], d["sample_rate_hz"], d["onset_index"], ml, geometry=cfg.geometry
            )
            near = np.min(np.linalg.norm(d["points_m"] - ml.point_m[:, None, :], axis=2), axis=1)
            acc = ml.accepted
            rows[str(sep)] = dict(
                n=n,
                ml_rejected_overlap=float(np.mean(ml.reason == 6)),
                ml_accepted=float(acc.mean()),
                ml_accepted_off_gt_0p1mm=float(np.mean(acc & (near > 0.1e-3))),
                ml_accepted_off_gt_0p5mm=float(np.mean(acc & (near > 0.5e-3))),
                suspect_flagged_of_accepted=float(sus[acc].mean()) if acc.any() else None,
            )
        out["ml_on_pairs"][medium] = rows
        print(medium, "ml on pairs", rows, flush=True)
    cfg = configs()["water"]
    # three emissions, 3 us apart
    n = n_other
    d = simulate_overlaps(
        n,
        cfg,
        n_sources=3,
        separation_s=3e-6,
        amplitude_ratio=2,
        snr_db=rng.uniform(20, 30, n),
        rng=rng,
    )
    res, dt = timed_resolve(d, cfg)
    out["three"], _ = evaluate(d, res, cfg)
    out["three"].update(separation_us=3, ratio=2, ms_per_packet=1e3 * dt / n)
    print("three", out["three"], flush=True)
    # SNR of the stronger emission 20-30 dB, ratio 4 (the weaker one at 8-18 dB)
    for sep in (2, 5):
        d = simulate_overlaps(
            n_other,
            cfg,
            separation_s=sep * 1e-6,
            amplitude_ratio=4,
            snr_db=rng.uniform(20, 30, n_other),
            snr_reference="stronger",
            rng=rng,
        )
        res, _ = timed_resolve(d, cfg)
        out["stronger_reference"][str(sep)], _ = evaluate(d, res, cfg)
        print("stronger ref", sep, out["stronger_reference"][str(sep)], flush=True)
    # pulse-shape mismatch: the data's front end or medium differs from the default model;
    # then the model calibrated on 40 single touches of the same sensor (calibrate_pulse),
    # with the medium's loss in the model when the medium is lossy
    cases = {
        "high-pass 90 kHz (model 100 kHz)": cfg.replace(highpass_hz=90e3),
        "low-pass 1.1 MHz (model 1.0 MHz)": cfg.replace(lowpass_hz=1.1e6),
        "silicone with attenuation (2 dB/cm at 1 MHz)": SimConfig.for_medium(
            "silicone", reflections=True, attenuation=True
        ),
    }
    for name, c2 in cases.items():
        d = simulate_overlaps(
            n_other,
            c2,
            separation_s=5e-6,
            amplitude_ratio=2,
            snr_db=rng.uniform(20, 30, n_other),
            rng=rng,
        )
        res, _ = timed_resolve(d, c2, pulse=PulseModel())
        row, _ = evaluate(d, res, c2, crlb=False)
        pts = c2.geometry.surface_point_from_angles(
            np.arccos(rng.uniform(0.5, 1.0, 40)), rng.uniform(0, 2 * np.pi, 40)
        )
        cal = render_triggered(pts, c2, snr_db=30, rng=rng)
        t0 = time.perf_counter()
        # start: default corners, the medium's (known) loss
        loss = PulseModel.from_config(c2).attenuation_db_per_m_at_1mhz
        pm = calibrate_pulse(
            cal.samples_v,
            cal.sample_rate_hz,
            cal.onset_index,
            geometry=c2.geometry,
            initial=PulseModel(attenuation_db_per_m_at_1mhz=loss),
        )
        t_cal = time.perf_counter() - t0
        res, _ = timed_resolve(d, c2, pulse=pm)
        row_cal, _ = evaluate(d, res, c2, crlb=False)
        out["mismatch"][name] = dict(
            default_model=row,
            calibrated=row_cal,
            calibrated_model=dict(highpass_hz=pm.highpass_hz, lowpass_hz=pm.lowpass_hz),
            calibration_s=t_cal,
        )
        print("mismatch", name, out["mismatch"][name], flush=True)
    one_window = one_window_cost(rng, 20 if args.quick else 100)
    print("one window at a time", one_window, flush=True)
    learnt = learnt_pulse_cost(rng, 20 if args.quick else 100)
    print("one window at a time, learnt pulse", learnt, flush=True)
    out["timing"] = dict(
        one_window_ms=one_window,
        one_window_learnt_pulse_ms=learnt,
        ms_per_pair_resolve=1e3 * t_resolve / max(n_resolve, 1),
        total_s=time.perf_counter() - t_start,
        total_cpu_s=time.process_time() - cpu_start,
        load_after=os.getloadavg(),
    )
    RESULTS.mkdir(parents=True, exist_ok=True)
    name = "overlap_quick" if args.quick else "overlap"
    (RESULTS / f"{name}.json").write_text(json.dumps(out, indent=1))
    table = make_table(out)
    (RESULTS / f"{name}_table.md").write_text(table)
    plot(out, RESULTS / f"{name}_success.png")
    print(table)
    print(f"total {out['timing']['total_s']:.1f} s")
    return out, table


def make_table(out):
    lines = [
        "Success (both points within 0.1 mm) / RMS in-plane error of reported points (um) /"
        " joint CRLB (um) / wrong accepts (> 0.5 mm); pairs per cell in brackets.",
        "",
    ]
    for medium in ("water", "silicone"):
        cells = [c for c in out["cells"] if c["medium"] == medium]
        lines.append(f"**{medium}** (SNR of the weaker emission 20-30 dB)")
        lines.append("")
        lines.append(
            "| ratio \\ separation | " + " | ".join(f"{s} us" for s in SEPARATIONS_US) + " |"
        )
        lines.append("|---" * (len(SEPARATIONS_US) + 1) + "|")
        for ratio in RATIOS:
            row = [f"1:{ratio}"]
            for s in SEPARATIONS_US:
                c = next(c for c in cells if c["separation_us"] == s and c["ratio"] == ratio)
                rms = "-" if c["rms_um"] is None else f"{c['rms_um']:.0f}"
                row.append(
                    f"{100 * c['success']:.1f} % / {rms} / {c['crlb_um']:.0f} / "
                    f"{c['wrong_accepts']} ({c['n']})"
                )
            lines.append("| " + " | ".join(row) + " |")
        lines.append("")
    allc = [c for c in out["cells"] if c["separation_us"] >= 2]
    n = sum(c["n"] for c in allc)
    lines.append(
        f"Separation >= 2 us, all ratios and media: success "
        f"{100 * sum(c['success'] * c['n'] for c in allc) / n:.1f} % of {n} pairs; "
        f"wrong accepts {sum(c['wrong_accepts'] for c in out['cells'])} of "
        f"{sum(c['n'] for c in out['cells'])} pairs (all separations); reported points "
        f"inside their 1.515-sigma ellipse: "
        f"{100 * np.mean([c['inside_1p515_sigma'] for c in allc if c['inside_1p515_sigma']]):.1f}"
        " %"
        " (68.3 % expected)."
    )
    lines.append("")
    lines.append(
        "Single emissions (resolve_overlaps on one-emission packets, SNR 20-30 dB, "
        "polar <= 60 deg):"
    )
    lines.append("")
    lines.append(
        "| medium | n | one source | split into more | rejected | RMS in-plane (um) |"
        " ml accepted | suspect_overlap false flags | time: resolve / ml / suspect per packet |"
    )
    lines.append("|---|---|---|---|---|---|---|---|---|")
    for m, r in out["singles"].items():
        lines.append(
            f"| {m} | {r['n']} | {100 * r['one_source']:.1f} % | {100 * r['split']:.1f} % | "
            f"{100 * r['rejected']:.1f} % | {r['rms_um']:.1f} | {100 * r['ml_accepted']:.1f} % | "
            f"{100 * (r['suspect_false_positive'] or 0):.1f} % | "
            f"{r['ms_per_packet_resolve']:.1f} ms"
            f" / {r['us_per_packet_ml']:.0f} us / {r['us_per_packet_suspect']:.0f} us |"
        )
    lines.append("")
    lines.append(
        "The single-source localizer (ml) on pairs (ratio 1:2, SNR of the weaker 20-30 dB), and"
        " suspect_overlap on what it accepted:"
    )
    lines.append("")
    lines.append(
        "| medium | separation (us) | n | ml OVERLAP | ml accepted | accepted > 0.1 mm off |"
        " accepted > 0.5 mm off | flagged by suspect_overlap (of accepted) |"
    )
    lines.append("|---|---|---|---|---|---|---|---|")
    for m, rows in out["ml_on_pairs"].items():
        for sep, r in rows.items():
            fl = (
                "-"
                if r["suspect_flagged_of_accepted"] is None
                else f"{100 * r['suspect_flagged_of_accepted']:.0f} %"
            )
            lines.append(
                f"| {m} | {sep} | {r['n']} | {100 * r['ml_rejected_overlap']:.0f} % | "
                f"{100 * r['ml_accepted']:.0f} % | {100 * r['ml_accepted_off_gt_0p1mm']:.0f} % | "
                f"{100 * r['ml_accepted_off_gt_0p5mm']:.0f} % | {fl} |"
            )
    lines.append("")
    t = out["three"]
    lines.append(
        f"Three emissions 3 us apart (water, strengths log-uniform within 1:2): success "
        f"{100 * t['success']:.1f} % of {t['n']}, RMS {t['rms_um']:.1f} um, joint CRLB "
        f"{t['crlb_um']:.1f} um, wrong accepts {t['wrong_accepts']}, "
        f"{t['ms_per_packet']:.0f} ms per window."
    )
    lines.append("")
    lines.append(
        "SNR of the *stronger* emission 20-30 dB, ratio 1:4 (the weaker at 8-18 dB), water:"
    )
    lines.append("")
    lines.append(
        "| separation (us) | n | success | RMS in-plane all / 3-D weaker (um) | joint CRLB (um)"
        " | wrong accepts | rejected |"
    )
    lines.append("|---|---|---|---|---|---|---|")
    for sep, r in out["stronger_reference"].items():
        lines.append(
            f"| {sep} | {r['n']} | {100 * r['success']:.1f} % | {r['rms_um']:.0f} / "
            f"{r['rms_weak_um']:.0f} | {r['crlb_um']:.0f} | {r['wrong_accepts']} | "
            f"{100 * r['rejected']:.0f} % |"
        )
    lines.append("")
    lines.append(
        "Pulse-shape mismatch (5 us apart, ratio 1:2, water unless stated): default model, then"
        " the model calibrated on 40 single touches (calibrate_pulse from the default corners;"
        " for the lossy silicone with the medium's loss in the model):"
    )
    lines.append("")
    lines.append(
        "| data | n | success default / calibrated | rejected default / calibrated |"
        " wrong accepts default / calibrated | calibrated corners |"
    )
    lines.append("|---|---|---|---|---|---|")
    for name, r in out["mismatch"].items():
        a, b = r["default_model"], r["calibrated"]
        cm = r["calibrated_model"]
        lines.append(
            f"| {name} | {a['n']} | {100 * a['success']:.0f} % / {100 * b['success']:.0f} % | "
            f"{100 * a['rejected']:.0f} % / {100 * b['rejected']:.0f} % | {a['wrong_accepts']} / "
            f"{b['wrong_accepts']} | {cm['highpass_hz'] / 1e3:.1f} kHz, "
            f"{cm['lowpass_hz'] / 1e6:.3f} MHz |"
        )
    lines.append("")
    tm = out["timing"]
    ow = tm.get("one_window_ms")
    if ow and "quick" in ow:

        def costs(d):
            return "; ".join(
                f"{k} {v['median']:.2f} ms median, {v['p90']:.2f} p90, {v['max']:.1f} max"
                for k, v in d.items()
            )

        lines.append(
            f"One window per call ({ow['quick']['numpy']['n']} two-emission windows 1-8 us "
            "apart, ratio up to 1:4, weaker 15-35 dB, water): the quick answer "
            "(`exhaustive=False`, as the driver's reader and overlap thread run it) "
            f"{costs(ow['quick'])}; the exhaustive search (as its worker process runs it) "
            f"{costs(ow['exhaustive'])}; same points from both paths: "
            f"{'yes' if ow['same_points'] else 'NO'}."
        )
        lines.append("")
    lines.append(
        f"Run: {tm['total_s']:.0f} s wall, {tm['total_cpu_s']:.0f} s CPU, one core; "
        f"{tm['ms_per_pair_resolve']:.1f} ms wall per pair in resolve_overlaps (batched); "
        f"load average before {out['setup']['load_before'][0]:.1f}, "
        f"after {tm['load_after'][0]:.1f}."
    )
    lines.append("")
    return "\n".join(lines) + "\n"


def plot(out, path):
    try:
        import matplotlib  # lazy: optional, only for the plot

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # lazy: after the Agg backend is chosen
    except ImportError:
        print("matplotlib missing: no plot")
        return
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for medium, ls in (("water", "-"), ("silicone", "--")):
        for ratio, col in zip(RATIOS, ("C0", "C1", "C2")):
            cells = sorted(
                [c for c in out["cells"] if c["medium"] == medium and c["ratio"] == ratio],
                key=lambda c: c["separation_us"],
            )
            x = [c["separation_us"] for c in cells]
            axes[0].plot(
                x,
                [100 * c["success"] for c in cells],
                ls,
                color=col,
                marker="o",
                label=f"{medium} 1:{ratio}",
            )
            axes[1].plot(
                x,
                [c["rms_um"] or np.nan for c in cells],
                ls,
                color=col,
                marker="o",
                label=f"{medium} 1:{ratio}",
            )
            axes[1].plot(x, [c["crlb_um"] for c in cells], ls, color=col, alpha=0.35)
    axes[0].axhline(90, color="k", lw=0.8)
    axes[0].set_xlabel("emission separation (us)")
    axes[0].set_ylabel("both points within 0.1 mm (%)")
    axes[0].set_ylim(0, 102)
    axes[0].legend(fontsize=7)
    axes[1].set_xlabel("emission separation (us)")
    axes[1].set_ylabel("RMS in-plane error (um); pale: joint CRLB")
    axes[1].set_yscale("log")
    fig.suptitle("Two overlapping emissions, 10 MS/s, SNR of the weaker 20-30 dB")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def zoo_main(args):
    """The overlap resolver over the device zoo (`ae_eval.zoo`: every member and
    ``--held-out`` random devices of seed ``--seed``) through the driver's own pipeline
    (`ae_eval.overlap_trials.live_device`): pairs cold (the nominal pulse), then the
    pipeline's pulse learner fed single touches until it trusts a pulse (at most 48),
    then the same pairs warm. Writes overlap_zoo.json and overlap_zoo.md to ``--out``;
    returns (results, markdown)."""
    only = {s.strip() for s in args.only.split(",") if s.strip()}
    devices = [(d, "zoo") for d in ZOO.values()]
    devices += [(d, "held-out") for d in held_out(args.seed, int(args.held_out))]
    # each device's random stream is its index in the whole list: a run --only some of
    # them draws the very windows the full run drew for those
    devices = [(i, d, k) for i, (d, k) in enumerate(devices) if not only or d.name in only]
    t0, cpu0 = time.perf_counter(), time.process_time()
    rows = []
    for i, dev, kind in devices:
        r = live_device(dev, n_pairs=args.pairs, rng=np.random.default_rng([args.seed, i]),
                        fit_in_process=args.fit_process)
        r["set"] = kind
        rows.append(r)
        print(f"{dev.name:16s} cold {r['cold_resolved_pct']:5.1f} %  warm "
              f"{r['warm_resolved_pct']:5.1f} %  trusted {r['converged']}  silent "
              f"{r['cold_silent']}/{r['warm_silent']}  learn {r['learn_wall_s']} s", flush=True)
    out = dict(
        setup=dict(pairs_per_device=args.pairs, seed=args.seed, held_out=args.held_out,
                   medium="water_skin", fs_hz=10e6, separation_us="uniform 2-10",
                   ratio=2, snr_db_weaker=25, singles_snr_db=30, max_singles=48,
                   delay_touches=DELAY_WARM_TOUCHES,
                   fit="learner's process (niced)" if args.fit_process else "inline",
                   machine=platform.platform(), load_before=os.getloadavg(),
                   wall_s=round(time.perf_counter() - t0, 1),
                   cpu_s_main=round(time.process_time() - cpu0, 1)),
        devices=rows,
    )
    for kind in ("zoo", "held-out"):
        sub = [r for r in rows if r["set"] == kind]
        if sub:
            worst = min(sub, key=lambda r: r["warm_resolved_pct"])
            trusted = [r for r in sub if r["converged"]
                       and r["warm_resolved_of_reached_pct"] is not None]
            w_reach = min(trusted, key=lambda r: r["warm_resolved_of_reached_pct"],
                          default=None)
            out[f"worst_{kind.replace('-', '_')}"] = dict(
                device=worst["device"], warm_resolved_pct=worst["warm_resolved_pct"],
                trusted_reached_device=None if w_reach is None else w_reach["device"],
                trusted_reached_pct=None if w_reach is None else w_reach[
                    "warm_resolved_of_reached_pct"],
                silent=sum(r["cold_silent"] + r["warm_silent"] for r in sub),
                wrong=sum(r["cold_wrong"] + r["warm_wrong"] for r in sub))
    md = zoo_table(out)
    dest = Path(args.out)
    dest.mkdir(parents=True, exist_ok=True)
    (dest / "overlap_zoo.json").write_text(json.dumps(out, indent=1))
    (dest / "overlap_zoo.md").write_text(md)
    print(md)
    return out, md


def zoo_table(out) -> str:
    """The markdown of `zoo_main`'s results."""
    s = out["setup"]
    lines = [
        "# Overlapping pairs over the device zoo, through the driver's pipeline",
        "",
        f"Generated by `python3 bench/bench_overlap.py --zoo` (seed {s['seed']}, "
        f"{s['pairs_per_device']} pairs per device, {s['held_out']} held-out devices; "
        f"{s['wall_s']} s wall). Pairs: water, 10 MS/s, 2-10 us apart, 1:{s['ratio']}, "
        f"{s['snr_db_weaker']} dB on the weaker, wall echo unless the device has none; "
        "each window through `ContactPipeline.process` (its resolver and worker). "
        "*Cold*: the nominal pulse; *warm*: the pipeline's localizer applying the channel "
        f"delays a driver learns from {s.get('delay_touches', 0):,} ordinary touches "
        "(`ae_eval.delays`), then its "
        "pulse learner fed "
        f"single touches ({s['singles_snr_db']} dB, batches of 12, at most "
        f"{s['max_singles']}) until it trusted a pulse (fit: {s['fit']}). Resolved: both "
        "emissions within 0.1 mm of the simulator's truth. Wrong: a point > 0.5 mm from "
        "both. Silent: a window giving fewer than two points without a count of the loss.",
        "",
        "| device | set | cold resolved % | warm resolved % | warm: of the windows "
        "reaching the resolver | pulse trusted (inliers / candidates, fits) | singles "
        "given | wrong cold / warm | silent cold / warm |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in out["devices"]:
        trusted = "yes" if r["converged"] else "no"
        reached = r["warm_resolved_of_reached_pct"]
        reached = "-" if reached is None else f"{reached:g} % of {r['warm_reached']}"
        lines.append(
            f"| {r['device']} | {r['set']} | {r['cold_resolved_pct']:g} | "
            f"{r['warm_resolved_pct']:g} | {reached} | {trusted} ({r['inliers']} / "
            f"{r['candidates']}, {r['fits']}) | {r['singles_given']} | "
            f"{r['cold_wrong']} / {r['warm_wrong']} | "
            f"{r['cold_silent']} / {r['warm_silent']} |")
    lines.append("")
    for kind in ("zoo", "held_out"):
        w = out.get(f"worst_{kind}")
        if w:
            lines.append(
                f"Worst warm over the {kind.replace('_', '-')} devices: {w['device']} "
                f"{w['warm_resolved_pct']:g} %; where the pulse is trusted, of the windows "
                f"reaching the resolver: {w['trusted_reached_device']} "
                f"{w['trusted_reached_pct']} %; silent losses {w['silent']}, wrong points "
                f"{w['wrong']} (cold and warm, all its devices).")
    trusted = [r for r in out["devices"] if r["converged"]]
    if trusted:
        worst = min(trusted, key=lambda r: r["warm_resolved_pct"])
        lines.append(
            f"Worst warm where the learner trusts a pulse: {worst['device']} "
            f"{worst['warm_resolved_pct']:g} % ({len(trusted)} of {len(out['devices'])} "
            "devices).")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
