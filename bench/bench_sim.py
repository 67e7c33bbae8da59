# SPDX-License-Identifier: Apache-2.0
"""Benchmark of the simulated fingertip.

Triggered packets as the virtual device serves them (every built-in scene of
config/scenes/): emissions rendered per CPU second (one core) when packets are taken one
at a time and 16 at a time, the real-time factor of the device's own polling (a call
every 0.5 ms of scene time, idle calls included) and the densest scene's margin; the
reference path (each window rendered by the stream renderer, numpy engine) for
comparison. Then, on one core, samples generated per second (4 channels x sample rate counted
as 4 samples per instant), the real-time factor at 4 ch x 10 MS/s, and the peak Python
heap (tracemalloc) while streaming a scene in 100 ms chunks into a reused buffer, for a
sparse touch scene and a dense slip scene, with every effect off, each effect on alone,
and every effect on. Also times the batch triggered renderer.

    python3 bench/bench_sim.py [--duration 1.0] [--out bench/results/sim.json] [--png]
        [--packets-only] [--repeats 2]

Results go to bench/results/sim.json (and sim.png with --png if matplotlib exists);
docs/simulator.md summarises them.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import sys
import time
import tracemalloc

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")   # one core, before numpy loads BLAS
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from ae_tactile.geometry import FingertipGeometry  # noqa: E402
from ae_tactile.sim import render_triggered  # noqa: E402
from ae_tactile.sim.kernels import HAVE_NUMBA, warm_up  # noqa: E402
from ae_tactile.sim.scene import load_scene  # noqa: E402

SCENES = {
    "sparse_touch": {"generator": "random_touches",
                     "params": {"rate_hz": 20.0, "max_polar_deg": 60.0}},
    "dense_slip": {"generator": "incipient_slip",
                   "params": {"tangential_load_rate_n_per_s": 10.0, "normal_load_n": 1.0,
                              "friction_coefficient": 0.5, "background_rate_hz": 500.0,
                              "slip_rate_hz": 2000.0, "front_density_per_m2": 1e8}},
}
_OFF = {"attenuation": False, "reflections": False, "quantization": False}
VARIANTS = {
    "all_off": {"effects": dict(_OFF), "noise": None},
    "attenuation": {"effects": {**_OFF, "attenuation": True}, "noise": None},
    "reflections": {"effects": {**_OFF, "reflections": True}, "noise": None},
    "noise": {"effects": {"attenuation": False, "reflections": False, "quantization": False},
              "noise": {"snr_db": 30.0}},
    "quantization": {"effects": {**_OFF, "quantization": True}, "noise": None},
    "all_on": {"effects": {"attenuation": True, "reflections": True, "quantization": True},
               "noise": {"snr_db": 30.0}},
}


def make_scene(name, variant, duration):
    spec = {**SCENES[name], "duration_s": duration, "seed": 1, "sensor": {"medium": "silicone"},
            **{k: v for k, v in VARIANTS[variant].items() if v is not None}}
    spec["effects"] = dict(VARIANTS[variant]["effects"], release_emissions=True)
    return load_scene(spec)


def stream(scene, chunk):
    src = scene.streaming_source()
    buf = np.empty((4, chunk))
    n_total = scene.n_samples
    pos, n_em = 0, 0
    while pos < n_total:
        n = min(chunk, n_total - pos)
        c = src.next_chunk(n, out=buf if n == chunk else None)
        n_em += len(c.emissions)
        pos += n
    return n_em


def run_case(name, variant, duration, chunk, repeats):
    times = []
    for _ in range(repeats):
        sc = make_scene(name, variant, duration)
        t0 = time.process_time()
        n_em = stream(sc, chunk)
        times.append(time.process_time() - t0)
    best = min(times)
    sc = make_scene(name, variant, duration)
    tracemalloc.start()
    stream(sc, chunk)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    n = sc.n_samples
    return {"scene": name, "variant": variant, "duration_s": duration, "emissions": n_em,
            "emissions_per_s": n_em / duration, "cpu_s": best, "cpu_s_all": times,
            "samples_per_s": 4 * n / best, "realtime_factor": duration / best,
            "peak_heap_mb": peak / 1e6}


SCENE_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                         "config", "scenes")
PRE, N_SAMPLES = 80, 400            # the virtual device's defaults


def _packet_loop(path, batch, render_path="fast", engine=None, poll_s=None):
    """CPU seconds to serve every packet of a scene; (n_packets, cpu_s, duration_s)."""
    sc = load_scene(path)
    fs = sc.config.sample_rate_hz
    src = sc.triggered_source(pretrigger_s=PRE / fs, window_s=N_SAMPLES / fs,
                              render_path=render_path, engine=engine)
    end = int(sc.duration_s * 1e9)
    n = 0
    t0 = time.process_time()
    if poll_s is None:
        while True:
            k = len(src.next_packets(batch, horizon_ns=end))
            if k == 0:
                break
            n += k
    else:                         # the device: a call per poll, horizon = scene time now
        step = int(poll_s * 1e9)
        for h in range(step, end + step, step):
            while True:
                k = len(src.next_packets(batch, horizon_ns=min(h, end)))
                n += k
                if k < batch:
                    break
    return n, time.process_time() - t0, sc.duration_s


def run_device_packets(repeats):
    """Per built-in scene: emissions/s per core (1 and 16 per call), the device's
    real-time factor, and the reference path."""
    warm_up()
    rows = []
    for path in sorted(glob.glob(os.path.join(SCENE_DIR, "*.yaml"))):
        name = os.path.splitext(os.path.basename(path))[0]
        r = {"scene": name}
        for label, kw in (("one_per_call", {"batch": 1}), ("sixteen_per_call", {"batch": 16}),
                          ("device_poll", {"batch": 16, "poll_s": 0.5e-3})):
            best = None
            for _ in range(repeats):
                n, cpu, dur = _packet_loop(path, **kw)
                best = cpu if best is None else min(best, cpu)
            r["packets"], r["duration_s"] = n, dur
            r[label + "_cpu_s"] = best
            r[label + "_emissions_per_s"] = n / best if best > 0 else float("inf")
        n, cpu, _ = _packet_loop(path, 1, render_path="reference", engine="numpy")
        r["reference_cpu_s"] = cpu
        r["reference_emissions_per_s"] = n / cpu if cpu > 0 else float("inf")
        r["scene_emissions_per_s"] = r["packets"] / r["duration_s"]
        r["device_realtime_factor"] = r["duration_s"] / r["device_poll_cpu_s"]
        r["one_per_call_realtime_factor"] = (r["one_per_call_emissions_per_s"]
                                             / r["scene_emissions_per_s"])
        rows.append(r)
        print(f"{name:20s} {r['packets']:5d} pk {r['scene_emissions_per_s']:6.0f} em/s(scene)"
              f"  fast 1/call {r['one_per_call_emissions_per_s']:7.0f} em/s"
              f"  16/call {r['sixteen_per_call_emissions_per_s']:7.0f}"
              f"  device poll {r['device_realtime_factor']:6.1f}x real time"
              f"  reference {r['reference_emissions_per_s']:6.0f} em/s", flush=True)
    dense = max(rows, key=lambda x: x["scene_emissions_per_s"])
    return {"engine": "numba" if HAVE_NUMBA else "numpy", "pre_trigger": PRE,
            "packet_samples": N_SAMPLES, "poll_s": 0.5e-3, "scenes": rows,
            "densest_scene": dense["scene"],
            "densest_one_per_call_realtime_factor": dense["one_per_call_realtime_factor"],
            "densest_device_realtime_factor": dense["device_realtime_factor"],
            "min_one_per_call_emissions_per_s": min(x["one_per_call_emissions_per_s"]
                                                    for x in rows)}


def run_triggered(n_packets=10_000):
    rng = np.random.default_rng(0)
    g = FingertipGeometry()
    pts = g.surface_point_from_angles(np.arccos(rng.uniform(0.2, 1, n_packets)),
                                      rng.uniform(0, 2 * np.pi, n_packets))
    render_triggered(pts[:100], snr_db=30, rng=1)
    times = []
    for _ in range(3):
        t0 = time.process_time()
        render_triggered(pts, snr_db=30, rng=1)
        times.append(time.process_time() - t0)
    dt = min(times)
    return {"n_packets": n_packets, "samples_per_packet": "4 x 400", "cpu_s": dt,
            "cpu_s_all": times,
            "packets_per_s": n_packets / dt}


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=1.0, help="simulated seconds per case")
    ap.add_argument("--chunk", type=int, default=1_000_000,
                    help="samples per chunk (100 ms at 10 MS/s)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out",
                    default=os.path.join(os.path.dirname(__file__), "results", "sim.json"))
    ap.add_argument("--png", action="store_true", help="also write a bar chart (needs matplotlib)")
    ap.add_argument("--packets-only", action="store_true", help="only the triggered-packet part")
    args = ap.parse_args(argv)
    load = os.getloadavg()
    packets = run_device_packets(args.repeats)
    rows = []
    for name in ([] if args.packets_only else SCENES):
        for variant in VARIANTS:
            r = run_case(name, variant, args.duration, args.chunk, args.repeats)
            rows.append(r)
            print(f"{name:13s} {variant:13s} {r['emissions_per_s']:7.0f} em/s"
                  f"  {r['samples_per_s'] / 1e6:7.1f} MS/s  {r['realtime_factor']:5.2f}x real time"
                  f"  peak heap {r['peak_heap_mb']:6.1f} MB", flush=True)
    trig = run_triggered() if not args.packets_only else None
    if trig:
        print(f"render_triggered: {trig['n_packets']} packets of 4 x 400 in"
              f" {trig['cpu_s']:.2f} s")
    load_end = os.getloadavg()
    print(f"load average (1, 5, 15 min) at start {load}, at end {load_end},"
          f" {os.cpu_count()} cores")
    res = {"machine": {"python": platform.python_version(), "numpy": np.__version__,
                       "processor": platform.processor() or platform.machine(), "cores_used": 1,
                       "cpu_count": os.cpu_count(), "loadavg_start": load,
                       "loadavg_end": load_end},
           "device_packets": packets,
           "sensor": "silicone preset, 4 ch x 10 MS/s, 12 bit; chunk = %d samples" % args.chunk,
           "target_realtime_factor": 2.0, "cases": rows, "triggered": trig,
           "timestamp": time.strftime("%Y-%m-%dT%H:%M:%S")}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(res, fh, indent=1)
    print("wrote", args.out)
    if args.png and rows:
        try:
            import matplotlib  # lazy: optional, only for --png
            matplotlib.use("Agg")
            import matplotlib.pyplot as plt  # lazy: optional, only for --png
        except ImportError:
            print("matplotlib not available: no PNG")
            return 0
        fig, ax = plt.subplots(figsize=(8, 4))
        labels = [f"{r['scene']}\n{r['variant']}" for r in rows]
        ax.bar(range(len(rows)), [r["realtime_factor"] for r in rows])
        ax.axhline(2.0, color="r", ls="--", label="target 2x")
        ax.set_xticks(range(len(rows)), labels, rotation=90, fontsize=7)
        ax.set_ylabel("real-time factor (4 ch x 10 MS/s)")
        ax.legend()
        fig.tight_layout()
        fig.savefig(os.path.splitext(args.out)[0] + ".png", dpi=120)
    return 0


if __name__ == "__main__":
    sys.exit(main())
