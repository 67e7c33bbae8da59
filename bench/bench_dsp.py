# SPDX-License-Identifier: Apache-2.0
"""Benchmark of the stream packet detector (issue 4, ae_tactile.dsp).

Throughput on one core of `PacketDetector.process` on simulated streams (ae_tactile.sim:
the paper's water tip with wall echoes, 12-bit ADC, 25 dB SNR, float64 volts as the
driver hands them over), fed in STREAM-sized chunks (8192 samples per channel, the
protocol's largest block) unless stated otherwise:

  sparse  20 touches/s (the simulator's default touch rate)
  dense   1000 emissions/s (touches and releases; 2x the simulator's gross-slip rate)
  stress  5000 emissions/s

Reported per case: sample instants per second (each instant = 4 channel samples), the
real-time factor for 4 ch x 10 MS/s (x real time = stream duration / CPU time), and
detection figures against the simulator's ground truth (recall, precision, onset error
in samples). Timing is the best of ``--repeat`` runs of process_time (CPU time of this
process, less sensitive to other load than wall time; wall time is reported too).

    python3 bench/bench_dsp.py [--duration 0.25] [--repeat 3] [--accuracy]
                               [--out bench/results/dsp.json]

With --accuracy it also computes the accuracy tables of docs/detection.md (recall,
precision and onset error vs SNR on the simulator, with and without wall echoes, the
resolution of overlapping pairs on simulated and analytic streams, false packets in
noise).

docs/detection.md summarises the results.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one core, before numpy loads BLAS
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from ae_eval.synth import SynthEvent, random_delays, snr_amplitude, synth_stream  # noqa: E402
from ae_tactile.dsp import DetectorConfig, PacketBatch, PacketDetector  # noqa: E402
from ae_tactile.sim import SimConfig  # noqa: E402
from ae_tactile.sim.scene import reference_noise_rms  # noqa: E402
from ae_tactile.sim.stream import (
    EmissionList,
    StaticEmissions,
    StreamingSource,  # noqa: E402
    sample_index_of_ns,
)

CASES = {"sparse": 20.0, "dense": 1000.0, "stress": 5000.0}
SNR_DB = 25.0


def make_stream(rate_hz, duration_s, fs, seed=1):
    """(samples (4, n) float64 volts, true onset indices, SimConfig)."""
    cfg = SimConfig(sample_rate_hz=fs, reflections=True)
    rng = np.random.default_rng(seed)
    n_em = max(1, rng.poisson(rate_hz * duration_s))
    t = np.sort(rng.uniform(0.5e-3, duration_s - 0.2e-3, n_em))
    th = np.arccos(rng.uniform(np.cos(np.radians(70.0)), 1.0, n_em))
    pts = cfg.geometry.surface_point_from_angles(th, rng.uniform(0, 2 * np.pi, n_em))
    em = EmissionList.create(
        (t * 1e9).astype(np.int64),
        pts,
        "touch",
        polarity=rng.choice([-1, 1], n_em),
        speed_m_s=rng.uniform(0.15, 0.45, n_em),
        curvature_1_m=1000.0,
        alpha_1_s=3000.0,
        density_kg_m3=cfg.density,
        event_id=np.arange(n_em),
    )
    src = StreamingSource(
        StaticEmissions(em), cfg, noise_rms_v=reference_noise_rms(cfg, SNR_DB), seed=seed
    )
    n = int(duration_s * fs)
    x = np.empty((4, n))
    for i in range(0, n, 65536):
        ch = src.next_chunk(min(65536, n - i))
        x[:, i : i + ch.samples_v.shape[1]] = ch.samples_v
    ne, frac = sample_index_of_ns(em.time_ns, fs)
    first = frac + cfg.geometry.arrival_times_s(em.point_m).min(axis=1)
    truth = np.sort(ne + np.ceil(first * fs - 1e-9).astype(np.int64))
    return x, truth, cfg


def detector_for(cfg, **kw):
    geo = cfg.geometry
    return PacketDetector(
        DetectorConfig(
            sample_rate_hz=cfg.sample_rate_hz,
            full_scale_v=cfg.adc_full_scale_v,
            adc_bits=cfg.adc_bits,
            echo_delay_s=2.0 * geo.radius_m / geo.sound_speed_m_s,
            channel_spread_s=max(
                3e-6, 2.0 * np.sqrt(2.0) * geo.element_offset_m / geo.sound_speed_m_s
            ),
            **kw,
        )
    )


def time_detector(x, cfg, chunk, repeat):
    chunks = [np.ascontiguousarray(x[:, i : i + chunk]) for i in range(0, x.shape[1], chunk)]
    best_cpu, best_wall, batch = np.inf, np.inf, None
    for _ in range(repeat):
        det = detector_for(cfg)
        out = []
        w0, c0 = time.perf_counter(), time.process_time()
        for j, c in enumerate(chunks):
            out.append(det.process(c, j * chunk))
        out.append(det.flush())
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        best_cpu, best_wall = min(best_cpu, cpu), min(best_wall, wall)
        batch, stats = PacketBatch.concatenate(out), det.stats
    return best_cpu, best_wall, batch, stats


def accuracy(batch, truth, tol=6):
    found = np.sort(batch.start_index + batch.onset_index)
    hit = 0
    err = []
    used = np.zeros(len(found), bool)
    for t in truth:
        j = np.searchsorted(found, t)
        best = None
        for k in (j - 1, j):
            if 0 <= k < len(found) and not used[k] and abs(found[k] - t) <= tol:
                if best is None or abs(found[k] - t) < abs(found[best] - t):
                    best = k
        if best is not None:
            used[best] = True
            hit += 1
            err.append(int(found[best] - t))
    err = np.array(err) if err else np.zeros(0)
    return {
        "emissions": int(len(truth)),
        "windows": int(len(found)),
        "recall": hit / max(len(truth), 1),
        "precision": hit / max(len(found), 1),
        "onset_error_median_samples": float(np.median(err)) if err.size else None,
        "onset_error_p95_abs_samples": float(np.percentile(np.abs(err - np.median(err)), 95))
        if err.size
        else None,
        "overlap_flagged": int(batch.overlap.sum()),
    }


# ---------------------------------------------------------------- accuracy tables
def _sim_touches(cfg, times_s, polar_max_deg, rng, speed=0.3):
    n = len(times_s)
    th = np.arccos(rng.uniform(np.cos(np.radians(polar_max_deg)), 1.0, n))
    pts = cfg.geometry.surface_point_from_angles(th, rng.uniform(0, 2 * np.pi, n))
    return EmissionList.create(
        (np.asarray(times_s) * 1e9).astype(np.int64),
        pts,
        "touch",
        polarity=rng.choice([-1, 1], n),
        speed_m_s=speed,
        curvature_1_m=1000.0,
        alpha_1_s=3000.0,
        density_kg_m3=cfg.density,
        event_id=np.arange(n),
    )


def _detect_sim(em, cfg, snr_db, seed, t_end, **kw):
    fs = cfg.sample_rate_hz
    src = StreamingSource(
        StaticEmissions(em), cfg, noise_rms_v=reference_noise_rms(cfg, snr_db), seed=seed
    )
    det = PacketDetector(DetectorConfig(sample_rate_hz=fs, **kw))
    out = []
    while src.position < int(t_end * fs):
        ch = src.next_chunk(8192)
        out.append(det.process(ch.samples_v, ch.start_index))
    out.append(det.flush())
    ne, frac = sample_index_of_ns(em.time_ns, fs)
    first = frac + cfg.geometry.arrival_times_s(em.point_m).min(axis=1)
    truth = ne + np.ceil(first * fs - 1e-9).astype(np.int64)
    return PacketBatch.concatenate(out), dict(zip(em.event_id.tolist(), truth.tolist())), det


def accuracy_tables(seed=5):
    """Recall / precision / onset error vs SNR on the simulator, and the resolution of
    overlapping pairs on the simulator and on analytic streams."""
    out = {"snr_sweep": [], "pairs_sim": [], "pairs_analytic": []}
    for refl, echo in ((False, None), (True, 13.5e-6), (True, None)):
        for snr in (30.0, 20.0, 10.0, 5.0, 0.0) if not refl else (20.0,):
            cfg = SimConfig(reflections=refl)
            rng = np.random.default_rng(seed)
            times = 0.5e-3 + np.cumsum(rng.uniform(100e-6, 400e-6, 300))
            em = _sim_touches(cfg, times, 60.0, rng)
            b, truth, det = _detect_sim(em, cfg, snr, 1, times[-1] + 1e-3, echo_delay_s=echo)
            acc = accuracy(b, np.sort(np.array(list(truth.values()))), tol=10)
            found = np.sort(b.start_index + b.onset_index)
            t = np.sort(np.array(list(truth.values())))
            err = [int(found[np.argmin(np.abs(found - x))] - x) for x in t] if len(found) else []
            vals, counts = np.unique(err, return_counts=True)
            sigma = reference_noise_rms(cfg, snr)
            true_rms = float(np.sqrt(sigma**2 + cfg.lsb_v**2 / 12))
            row = {
                "snr_db": snr,
                "reflections": refl,
                "echo_delay_s": echo,
                **acc,
                "onset_error_histogram": {int(v): int(c) for v, c in zip(vals, counts)},
                "noise_rms_ratio_mean": float(np.mean(b.noise_rms_v) / true_rms),
                "noise_rms_ratio_std": float(np.std(b.noise_rms_v / true_rms)),
                "snr_db_median_estimate": float(np.median(b.snr_db)) if len(b) else None,
                "echoes_rejected": det.stats.echoes,
            }
            out["snr_sweep"].append(row)
            print(
                f"sim {snr:4.0f} dB refl {refl!s:5} echo {echo}: recall {acc['recall']:.3f} "
                f"precision {acc['precision']:.3f} onset err {row['onset_error_histogram']} "
                f"noise ratio {row['noise_rms_ratio_mean']:.3f}",
                flush=True,
            )
    fs = 10e6
    for ratio in (1.0, 0.5):
        for dt in (3e-6, 5e-6, 8e-6, 15e-6, 30e-6):
            cfg = SimConfig()
            rng = np.random.default_rng(seed + int(dt * 1e7))
            n = 40
            t1 = 1e-3 + np.arange(n) * 300e-6 + rng.uniform(0, 1e-6, n)
            speed = np.concatenate([np.full(n, 0.3), np.full(n, 0.3 * np.sqrt(ratio))])
            em = _sim_touches(cfg, np.concatenate([t1, t1 + dt]), 60.0, rng, speed=speed)
            b, truth, _ = _detect_sim(em, cfg, 20.0, 3, t1[-1] + 1e-3)
            on = b.start_index + b.onset_index
            both = 0
            for i in range(n):
                a, c = truth[i] + 2, truth[n + i] + 2  # the picks sit ~2 samples late
                ia, ic = np.flatnonzero(np.abs(on - a) <= 3), np.flatnonzero(np.abs(on - c) <= 3)
                both += bool(ia.size and ic.size and b.overlap[ia[0]] and b.overlap[ic[0]])
            out["pairs_sim"].append(
                {
                    "snr_db": 20.0,
                    "amplitude_ratio": ratio,
                    "dt_s": dt,
                    "pairs": n,
                    "resolved": both,
                    "windows": len(b),
                }
            )
            print(
                f"sim pairs ratio {ratio} dt {dt * 1e6:4.0f} us: {both}/{n} windows {len(b)}",
                flush=True,
            )
    sigma = 2e-3
    for snr in (20.0, 30.0):
        amp = snr_amplitude(snr, sigma, fs)
        for ratio in (1.0, 0.5, 2.0):
            for dt in (3e-6, 5e-6, 6e-6, 8e-6, 10e-6, 60e-6):
                rng = np.random.default_rng(seed + int(dt * 1e7) + int(10 * ratio))
                evs, truth = [], []
                for i in range(40):
                    t0 = 1e-3 + i * 300e-6 + rng.uniform(0, 1e-7)
                    e1 = SynthEvent(t0, amp * rng.choice([-1, 1]), random_delays(rng))
                    e2 = SynthEvent(t0 + dt, ratio * amp * rng.choice([-1, 1]), random_delays(rng))
                    evs += [e1, e2]
                    truth.append((e1.onset_index(fs), e2.onset_index(fs)))
                x = synth_stream(
                    int((1e-3 + 40 * 300e-6 + 1e-3) * fs),
                    fs,
                    evs,
                    noise_rms_v=sigma,
                    seed=int(dt * 1e7),
                )
                det = PacketDetector()
                b = PacketBatch.concatenate([det.process(x, 0), det.flush()])
                on = b.start_index + b.onset_index
                both = 0
                for a, c in truth:
                    ia, ic = (
                        np.flatnonzero(np.abs(on - a) <= 2),
                        np.flatnonzero(np.abs(on - c) <= 2),
                    )
                    both += bool(
                        ia.size
                        and ic.size
                        and (dt >= 40e-6 or (b.overlap[ia[0]] and b.overlap[ic[0]]))
                    )
                out["pairs_analytic"].append(
                    {
                        "snr_db": snr,
                        "amplitude_ratio": ratio,
                        "dt_s": dt,
                        "pairs": 40,
                        "resolved": both,
                        "windows": len(b),
                    }
                )
                print(
                    f"analytic {snr:.0f} dB pairs ratio {ratio} dt {dt * 1e6:4.0f} us: {both}/40 "
                    f"windows {len(b)}",
                    flush=True,
                )
    noise = np.random.default_rng(0).normal(0, 1e-3, (4, 5_000_000))
    det = PacketDetector()
    k = sum(len(det.process(noise[:, i : i + 65536], i)) for i in range(0, noise.shape[1], 65536))
    k += len(det.flush())
    out["false_packets_in_0.5s_noise"] = k
    print("false packets in 0.5 s of noise:", k)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=0.25, help="stream length (s) per case")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument(
        "--accuracy",
        action="store_true",
        help="also compute the accuracy tables of docs/detection.md (a few minutes)",
    )
    ap.add_argument(
        "--out",
        default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "dsp.json"),
    )
    args = ap.parse_args(argv)
    results = {
        "benchmark": "ae_tactile.dsp PacketDetector stream throughput",
        "python": platform.python_version(),
        "numpy": np.__version__,
        "machine": platform.machine(),
        "processor": platform.processor(),
        "snr_db": SNR_DB,
        "duration_s": args.duration,
        "cases": [],
    }
    plan = [
        ("sparse", 10e6, 8192),
        ("dense", 10e6, 8192),
        ("stress", 10e6, 8192),
        ("sparse", 10e6, 1024),
        ("sparse", 10e6, 65536),
        ("dense", 10e6, 65536),
        ("sparse", 1e6, 8192),
        ("sparse", 20e6, 8192),
        ("dense", 20e6, 8192),
    ]
    streams = {}
    for name, fs, chunk in plan:
        key = (name, fs)
        if key not in streams:
            streams[key] = make_stream(CASES[name], args.duration, fs)
        x, truth, cfg = streams[key]
        cpu, wall, batch, stats = time_detector(x, cfg, chunk, args.repeat)
        n = x.shape[1]
        rt = (n / fs) / cpu
        row = {
            "case": name,
            "emission_rate_hz": CASES[name],
            "sample_rate_hz": fs,
            "chunk": chunk,
            "samples_per_channel": n,
            "cpu_s": round(cpu, 4),
            "wall_s": round(wall, 4),
            "instants_per_s": round(n / cpu),
            "channel_samples_per_s": round(4 * n / cpu),
            "x_real_time": round(rt, 2),
            "x_real_time_wall": round((n / fs) / wall, 2),
            "detector_stats": stats.as_dict(),
            **accuracy(batch, truth),
        }
        results["cases"].append(row)
        print(
            f"{name:7s} fs {fs / 1e6:4.0f} MS/s chunk {chunk:6d}: "
            f"{n / cpu / 1e6:6.2f} M instants/s "
            f"= x{rt:5.2f} real time (wall x{row['x_real_time_wall']:5.2f}); "
            f"recall {row['recall']:.3f} precision {row['precision']:.3f} "
            f"windows {row['windows']} / {row['emissions']}",
            flush=True,
        )
    print(
        "\n| case | emissions/s | fs (MS/s) | chunk | M instants/s | x real time "
        "| recall | precision |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in results["cases"]:
        print(
            f"| {r['case']} | {r['emission_rate_hz']:.0f} | {r['sample_rate_hz'] / 1e6:.0f} | "
            f"{r['chunk']} | {r['instants_per_s'] / 1e6:.1f} | {r['x_real_time']:.2f} | "
            f"{r['recall']:.3f} | {r['precision']:.3f} |"
        )
    if args.accuracy:
        results["accuracy"] = accuracy_tables()
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
