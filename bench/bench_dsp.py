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

    python3 bench/bench_dsp.py [--duration 0.25] [--repeat 3] [--out bench/results/dsp.json]

docs/detection.md summarises the results.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")   # one core, before numpy loads BLAS
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from ae_tactile.dsp import DetectorConfig, PacketBatch, PacketDetector  # noqa: E402
from ae_tactile.sim import SimConfig  # noqa: E402
from ae_tactile.sim.scene import reference_noise_rms  # noqa: E402
from ae_tactile.sim.stream import (EmissionList, StaticEmissions, StreamingSource,  # noqa: E402
                                   sample_index_of_ns)

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
    em = EmissionList.create((t * 1e9).astype(np.int64), pts, "touch",
                             polarity=rng.choice([-1, 1], n_em), speed_m_s=rng.uniform(0.15, 0.45, n_em),
                             curvature_1_m=1000.0, alpha_1_s=3000.0, density_kg_m3=cfg.density,
                             event_id=np.arange(n_em))
    src = StreamingSource(StaticEmissions(em), cfg, noise_rms_v=reference_noise_rms(cfg, SNR_DB), seed=seed)
    n = int(duration_s * fs)
    x = np.empty((4, n))
    for i in range(0, n, 65536):
        ch = src.next_chunk(min(65536, n - i))
        x[:, i:i + ch.samples_v.shape[1]] = ch.samples_v
    ne, frac = sample_index_of_ns(em.time_ns, fs)
    first = frac + cfg.geometry.arrival_times_s(em.point_m).min(axis=1)
    truth = np.sort(ne + np.ceil(first * fs - 1e-9).astype(np.int64))
    return x, truth, cfg


def detector_for(cfg, **kw):
    geo = cfg.geometry
    return PacketDetector(DetectorConfig(
        sample_rate_hz=cfg.sample_rate_hz, full_scale_v=cfg.adc_full_scale_v, adc_bits=cfg.adc_bits,
        echo_delay_s=2.0 * geo.radius_m / geo.sound_speed_m_s,
        channel_spread_s=max(3e-6, 2.0 * np.sqrt(2.0) * geo.element_offset_m / geo.sound_speed_m_s), **kw))


def time_detector(x, cfg, chunk, repeat):
    chunks = [np.ascontiguousarray(x[:, i:i + chunk]) for i in range(0, x.shape[1], chunk)]
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
    return {"emissions": int(len(truth)), "windows": int(len(found)),
            "recall": hit / max(len(truth), 1), "precision": hit / max(len(found), 1),
            "onset_error_median_samples": float(np.median(err)) if err.size else None,
            "onset_error_p95_abs_samples": float(np.percentile(np.abs(err - np.median(err)), 95))
            if err.size else None,
            "overlap_flagged": int(batch.overlap.sum())}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=0.25, help="stream length (s) per case")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                                  "results", "dsp.json"))
    args = ap.parse_args(argv)
    results = {"benchmark": "ae_tactile.dsp PacketDetector stream throughput",
               "python": platform.python_version(), "numpy": np.__version__,
               "machine": platform.machine(), "processor": platform.processor(),
               "snr_db": SNR_DB, "duration_s": args.duration, "cases": []}
    plan = [("sparse", 10e6, 8192), ("dense", 10e6, 8192), ("stress", 10e6, 8192),
            ("sparse", 10e6, 1024), ("sparse", 10e6, 65536), ("dense", 10e6, 65536),
            ("sparse", 1e6, 8192), ("sparse", 20e6, 8192), ("dense", 20e6, 8192)]
    streams = {}
    for name, fs, chunk in plan:
        key = (name, fs)
        if key not in streams:
            streams[key] = make_stream(CASES[name], args.duration, fs)
        x, truth, cfg = streams[key]
        cpu, wall, batch, stats = time_detector(x, cfg, chunk, args.repeat)
        n = x.shape[1]
        rt = (n / fs) / cpu
        row = {"case": name, "emission_rate_hz": CASES[name], "sample_rate_hz": fs, "chunk": chunk,
               "samples_per_channel": n, "cpu_s": round(cpu, 4), "wall_s": round(wall, 4),
               "instants_per_s": round(n / cpu), "channel_samples_per_s": round(4 * n / cpu),
               "x_real_time": round(rt, 2), "x_real_time_wall": round((n / fs) / wall, 2),
               "detector_stats": stats.as_dict(), **accuracy(batch, truth)}
        results["cases"].append(row)
        print(f"{name:7s} fs {fs / 1e6:4.0f} MS/s chunk {chunk:6d}: {n / cpu / 1e6:6.2f} M instants/s "
              f"= x{rt:5.2f} real time (wall x{row['x_real_time_wall']:5.2f}); "
              f"recall {row['recall']:.3f} precision {row['precision']:.3f} "
              f"windows {row['windows']} / {row['emissions']}", flush=True)
    print("\n| case | emissions/s | fs (MS/s) | chunk | M instants/s | x real time | recall | precision |")
    print("|---|---|---|---|---|---|---|---|")
    for r in results["cases"]:
        print(f"| {r['case']} | {r['emission_rate_hz']:.0f} | {r['sample_rate_hz'] / 1e6:.0f} | "
              f"{r['chunk']} | {r['instants_per_s'] / 1e6:.1f} | {r['x_real_time']:.2f} | "
              f"{r['recall']:.3f} | {r['precision']:.3f} |")
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
