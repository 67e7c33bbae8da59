# SPDX-License-Identifier: Apache-2.0
"""Localization benchmark: accuracy against the Cramer-Rao bound, and speed (issue 4).

    python3 bench/bench_localization.py [--quick]        (or: make bench-localization)

Simulated packets (ae_tactile.sim, the paper's water-skin tip: R = 10 mm, a = 1.5 mm,
c = 1480 m/s, 1 MHz front end, 12-bit ADC, wall echoes on) at P fixed contact points
spread uniformly over the usable surface (polar angle <= 60 deg), R noise realisations
each, random sub-sample trigger offsets; SNR 10, 20, 30, 40 dB (docs/conventions.md);
2, 5 and 10 MS/s with the simulator's default front end (1 MHz 4th-order low-pass; at
2 MS/s its anti-alias filter, 0.6 MHz 8th-order), and 2 MS/s behind the 1 MHz filter alone
(what aliasing costs). For each estimator of ae_tactile.localization and each baseline:

  * RMS in-plane position error (mm) over the accepted packets, and the RMS bias: the
    RMS over points of the mean error at each point (noise part removed: |mean|^2 -
    var / R), i.e. what averaging many packets would not remove;
  * the CRLB for the same pulse, noise (sigma_n^2 + LSB^2/12: the ADC's rounding noise is
    in the data too) and geometry, on the echo-free samples (ae_eval.crlb);
  * the time per packet on one core, batched and one packet per call.

Baselines: the paper's one-shot Eq. 2 inversion from plain cross-correlation peaks
(``xcorr_farfield``, a registered method) and pyroomacoustics' DOA algorithms SRP-PHAT
and MUSIC (far-field only), configured for this medium and band: c = 1480 m/s,
freq_range = the signal band, microphones at the element positions, STFT frames of the
same echo-free segment as one rectangular snapshot (short STFT frames bias them, see
`PraBaseline`), colatitude 0-90 deg (a planar array cannot tell +z from -z), a 2 deg
grid then a local 0.1 deg grid around its maximum. They are slow, so they run on fewer
packets per cell (the first realisations of a subset of the points; stated in the JSON).

Then the overlap sweep (bench/bench_overlap.py: two and three emissions in one window,
`resolve_overlaps` against the joint CRLB; `--no-overlap` skips it).

Writes bench/results/localization.json, bench/results/localization_speed_error.png,
bench/results/localization_table.md, bench/results/overlap.json, overlap_table.md,
overlap_success.png (docs/localization.md and docs/overlap.md link the tables).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_v, "1")  # one core

import argparse  # noqa: E402
import importlib.util  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ae_eval.crlb import simulated_crlb  # noqa: E402
from ae_eval.delays import learnt_channel_model  # noqa: E402
from ae_tactile.localization import (  # noqa: E402
    NUMBA_AVAILABLE,
    Localizer,
    available_methods,
    default_band_hz,
    localize,
)
from ae_tactile.localization.common import make_plan  # noqa: E402
from ae_tactile.sim import SimConfig, render_triggered  # noqa: E402

RESULTS = ROOT / "bench" / "results"
METHODS = ["ml", "ml_fixed_band", "gradient", "gcc_phat", "xcorr_farfield"]
BASELINES = ["pra_srp_phat", "pra_music"]
LABELS = {
    "ml": "ML exact sphere",
    "ml_fixed_band": "ML, fixed band",
    "gradient": "gradient (iterated)",
    "gcc_phat": "GCC-PHAT (band)",
    "xcorr_farfield": "paper: xcorr + Eq. 2",
    "pra_srp_phat": "pyroomacoustics SRP-PHAT",
    "pra_music": "pyroomacoustics MUSIC",
}


def cap_points(geo, n, max_deg=60.0, seed=0):
    """n points spread uniformly (in area) over the cap polar <= max_deg (golden spiral)."""
    i = np.arange(n) + 0.5
    ct = 1.0 - (1.0 - np.cos(np.deg2rad(max_deg))) * i / n
    az = np.pi * (1 + 5**0.5) * i + seed
    return geo.surface_point_from_angles(np.arccos(ct), az)


def error_stats(err_xy, point_id, accepted, n_points):
    """RMS error and RMS bias (noise-corrected) of in-plane errors (m)."""
    e = err_xy[accepted]
    pid = point_id[accepted]
    rms = float(np.sqrt(np.mean(np.sum(e**2, axis=1)))) if len(e) else float("nan")
    b2 = []
    for p in range(n_points):
        ep = e[pid == p]
        if len(ep) >= 2:
            m = ep.mean(axis=0)
            v = ep.var(axis=0, ddof=1).sum()
            b2.append(np.sum(m**2) - v / len(ep))
    bias = float(np.sqrt(max(np.mean(b2), 0.0))) if b2 else float("nan")
    return rms, bias


# ----------------------------------------------------------------- pyroomacoustics
class PraBaseline:
    """pyroomacoustics SRP-PHAT / MUSIC on the echo-free segment of each packet.

    One rectangular snapshot holding the whole segment (zero-padded to a power of 2):
    shorter STFT frames (e.g. 64 or 32 samples at 10 MS/s, Hann) see each channel's part
    of a pulse that moves by up to ~3 us between channels and bias the colatitude toward
    the pole by 0.3-6 mm (measured while configuring this baseline); with one snapshot the
    spatial covariance per bin is rank one, which MUSIC handles (noise subspace = its
    orthogonal complement). Grid search: 2 deg over the hemisphere, then a local grid of
    0.1 deg (+-2.5 deg) around the coarse maximum, both through pyroomacoustics.
    """

    def __init__(self, algo, geo, fs, n_samples, band):
        import pyroomacoustics as pra  # lazy: optional dependency, only for the pra_* baselines

        self.pra = pra
        self.algo = algo
        self.geo = geo
        self.fs = fs
        self.band = [band[0], band[1]]
        self.plan = make_plan(fs, geo, n_samples, band)
        self.nfft = int(2 ** np.ceil(np.log2(self.plan.seg_len)))
        self.hop = self.nfft
        self.mics = geo.element_positions_m.T  # (3, 4)
        az = np.deg2rad(np.arange(0.0, 360.0, 2.0))
        col = np.deg2rad(np.arange(0.0, 90.0 + 1e-9, 2.0))
        self.coarse = self._doa(az, col)

    def _doa(self, az, col):
        name = {"pra_srp_phat": "SRP", "pra_music": "MUSIC"}[self.algo]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return self.pra.doa.algorithms[name](
                self.mics,
                self.fs,
                self.nfft,
                c=self.geo.sound_speed_m_s,
                num_src=1,
                dim=3,
                azimuth=az,
                colatitude=col,
            )

    def locate(self, window, onset):
        start = onset - self.plan.pre
        seg = window[:, start : start + self.plan.seg_len]
        seg = seg - window[:, : max(start, 1)].mean(axis=1, keepdims=True)
        X = np.fft.rfft(seg, n=self.nfft, axis=1)[:, :, None]  # (M, F, 1 snapshot)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.coarse.locate_sources(X, num_src=1, freq_range=self.band)
            a0, c0 = float(self.coarse.azimuth_recon[0]), float(self.coarse.colatitude_recon[0])
            dc = np.deg2rad(2.5)
            col = np.clip(c0 + np.linspace(-dc, dc, 51), 0.0, np.pi / 2)
            da = min(np.pi, dc / max(np.sin(c0), np.deg2rad(2.5)))
            az = a0 + np.linspace(-da, da, 51)
            fine = self._doa(np.mod(az, 2 * np.pi), np.unique(col))
            fine.locate_sources(X, num_src=1, freq_range=self.band)
            a, c = float(fine.azimuth_recon[0]), float(fine.colatitude_recon[0])
        return self.geo.surface_point_from_angles(c, a)


# ----------------------------------------------------------------- benchmark
def _mahalanobis2(err, r):
    """Squared in-plane Mahalanobis distances of the accepted rows' errors ``err`` (K, 2)
    [m] under their covariances (result ``r``)."""
    cov = r.covariance_m2[r.accepted, :2, :2]
    e = err[r.accepted]
    return np.einsum("ki,kij,kj->k", e, np.linalg.inv(cov), e) if len(e) else np.zeros(0)


def _localize(method, x, fs, onset, band, geo, engine=None):
    """ml: data-driven band (band_hz=None); ml_fixed_band and the other methods: ``band``."""
    if method == "ml":
        return localize(x, fs, onset, method="ml", geometry=geo, engine=engine)
    if method == "ml_fixed_band":
        return localize(x, fs, onset, method="ml", band_hz=band, geometry=geo, engine=engine)
    return localize(x, fs, onset, method=method, band_hz=band, geometry=geo)


def _timing(label, fs, cfg, geo, P, band, rng, quick):
    """Time per packet on one core: batched (one call, all packets) and one packet per call
    (`localize` on a (1, 4, M) batch; for ml also `Localizer.localize_one`, p50 and p99),
    for ml with the compiled kernel (numba) and the numpy path."""
    pk = render_triggered(P, cfg, snr_db=20.0, rng=rng)
    n = len(P)
    x, on = pk.samples_v, pk.onset_index
    tm = {}
    variants = [(m, None) for m in METHODS]
    if NUMBA_AVAILABLE:
        variants += [("ml", "numpy")]
    for m, eng in variants:
        key = m if eng is None else f"{m}_numpy"
        _localize(m, x[:64], fs, on[:64], band, geo, eng)  # warm caches / compile
        best = cpu = np.inf
        for _ in range(3):
            t0, c0 = time.perf_counter(), time.process_time()
            _localize(m, x, fs, on, band, geo, eng)
            best = min(best, time.perf_counter() - t0)
            cpu = min(cpu, time.process_time() - c0)
        n1 = 60 if quick or eng == "numpy" or m != "ml" else 300
        t0 = time.perf_counter()
        for i in range(n1):
            _localize(m, x[i : i + 1], fs, on[i : i + 1], band, geo, eng)
        single = (time.perf_counter() - t0) / n1
        tm[key] = dict(
            batched_packets_per_s=n / best,
            batched_us_per_packet=best / n * 1e6,
            batched_cpu_us_per_packet=cpu / n * 1e6,
            batched_cpu_packets_per_s=n / cpu,
            single_packets_per_s=1.0 / single,
            single_us_per_packet=single * 1e6,
            batch_size=n,
            engine=eng or ("numba" if NUMBA_AVAILABLE and m.startswith("ml") else "numpy"),
        )
    # the hot path: Localizer.localize_one on float32 windows (what the link delivers)
    for eng in ("numba", "numpy") if NUMBA_AVAILABLE else ("numpy",):
        loc = Localizer("ml", engine=eng).warm_up(geo, fs, x.shape[2])
        x32 = x.astype(np.float32)
        n1 = min(n, 1000 if eng == "numba" and not quick else 100)
        dts = np.empty(n1)
        cps = np.empty(n1)
        for i in range(n1):
            t0, c0 = time.perf_counter(), time.process_time()
            loc.localize_one(x32[i], fs, int(on[i]))
            cps[i] = time.process_time() - c0
            dts[i] = time.perf_counter() - t0
        tm[f"localize_one_{eng}"] = dict(
            single_us_per_packet=float(np.mean(dts) * 1e6),
            p50_us=float(np.percentile(dts, 50) * 1e6),
            p99_us=float(np.percentile(dts, 99) * 1e6),
            cpu_us=float(np.mean(cps) * 1e6),
            cpu_p50_us=float(np.percentile(cps, 50) * 1e6),
            cpu_p99_us=float(np.percentile(cps, 99) * 1e6),
            single_packets_per_s=float(1.0 / np.mean(dts)),
            n=int(n1),
        )
    return tm


def run(quick=False):
    t_start = time.perf_counter()
    snrs = [10.0, 20.0, 30.0, 40.0]
    # (label, SimConfig, fixed band of the other methods; None: default_band_hz): the
    # simulator's default front end at 2, 5 and 10 MS/s (its low-pass follows the sample rate:
    # 0.6 MHz, 8th order at 2 MS/s), 2 MS/s behind the 1 MHz filter alone, the silicone tip.
    water = SimConfig(reflections=True)
    sil = SimConfig.for_medium("silicone").replace(reflections=True)
    rates = [
        ("2", water.replace(sample_rate_hz=2e6), None),
        (
            "2 (1 MHz filter: aliasing)",
            water.replace(sample_rate_hz=2e6, lowpass_hz=1e6, lowpass_order=4),
            None,
        ),
        ("5", water.replace(sample_rate_hz=5e6), None),
        ("10", water, None),
        ("10 silicone", sil, None),
    ]
    n_points, n_real = (20, 10) if quick else (100, 20)
    pra_points, pra_real = (10, 1) if quick else (20, 2)
    n_pra = pra_points * pra_real
    rng = np.random.default_rng(2024)
    # pyroomacoustics: the first pra_real realisations of every (n_points / pra_points)-th point
    pra_idx = np.array(
        [
            p * n_real + r
            for p in range(0, n_points, n_points // pra_points)
            for r in range(pra_real)
        ]
    )
    cells = []
    pra_ok = importlib.util.find_spec("pyroomacoustics") is not None
    timing = {}
    for label, cfg, band in rates:
        geo = cfg.geometry
        fs = cfg.sample_rate_hz
        # what the driver's learner makes of this front end from its first touches: the
        # delay noise its covariances then carry (the points do not change)
        noise = learnt_channel_model(cfg, np.random.default_rng([2024, len(cells)]),
                                     500 if quick else 2000).delay_noise
        pts = cap_points(geo, n_points)
        point_id = np.repeat(np.arange(n_points), n_real)
        P = pts[point_id]
        n = len(P)
        band = default_band_hz(fs) if band is None else band
        pras = (
            {b: PraBaseline(b, geo, fs, int(round(40e-6 * fs)), band) for b in BASELINES}
            if pra_ok
            else {}
        )
        for snr in snrs:
            u = rng.uniform(0.01, 0.99, n)
            pk = render_triggered(P, cfg, snr_db=snr, subsample_offset=u, rng=rng)
            bound = simulated_crlb(P, cfg, snr_db=snr, subsample_offset=u)
            bound_n = simulated_crlb(
                P, cfg, snr_db=snr, subsample_offset=u, include_quantization=False
            )
            cell = dict(
                label=label,
                sample_rate_hz=fs,
                lowpass_hz=cfg.lowpass_hz,
                lowpass_order=cfg.lowpass_order,
                sound_speed_m_s=geo.sound_speed_m_s,
                snr_db=snr,
                band_hz=list(band),
                n_packets=n,
                crlb_rms_mm=float(np.sqrt(np.mean(bound["rms_m"] ** 2)) * 1e3),
                crlb_unknown_waveform_rms_mm=float(
                    np.sqrt(np.mean(bound["rms_unknown_m"] ** 2)) * 1e3
                ),
                crlb_noise_only_rms_mm=float(np.sqrt(np.mean(bound_n["rms_m"] ** 2)) * 1e3),
                methods={},
            )
            cell["delay_noise_learnt"] = None if noise is None else [noise[0], noise[1] * 1e9]
            for m in METHODS:
                t0 = time.perf_counter()
                r = _localize(m, pk.samples_v, fs, pk.onset_index, band, geo)
                dt = time.perf_counter() - t0
                err = (r.point_m - P)[:, :2]
                rms, bias = error_stats(err, point_id, r.accepted, n_points)
                d2 = _mahalanobis2(err, r)
                if m == "ml":
                    learnt = localize(pk.samples_v, fs, pk.onset_index, geometry=geo,
                                      delay_noise=noise)
                    d2_l = _mahalanobis2(err, learnt)
                    cell["ml_in_1515sigma_ellipse_learnt_noise"] = (
                        float(np.mean(d2_l < 1.515**2)) if len(d2_l) else None)
                cell["methods"][m] = dict(
                    rms_mm=rms * 1e3,
                    bias_mm=bias * 1e3,
                    accepted=float(r.accepted.mean()),
                    ratio_to_crlb=rms * 1e3 / cell["crlb_rms_mm"],
                    in_1sigma_ellipse=float(np.mean(d2 < 1.0)) if len(d2) else None,
                    in_1515sigma_ellipse=float(np.mean(d2 < 1.515**2)) if len(d2) else None,
                    batched_us_per_packet=dt / n * 1e6,
                    touch_correct=float(np.mean(r.polarity == 1)),
                )
            for b, obj in pras.items():
                idx = pra_idx
                t0 = time.perf_counter()
                est = np.array([obj.locate(pk.samples_v[i], int(pk.onset_index[i])) for i in idx])
                dt = time.perf_counter() - t0
                err = (est - P[idx])[:, :2]
                rms, bias = error_stats(err, point_id[idx], np.ones(len(idx), bool), n_points)
                cell["methods"][b] = dict(
                    rms_mm=rms * 1e3,
                    bias_mm=bias * 1e3,
                    accepted=1.0,
                    ratio_to_crlb=rms * 1e3 / cell["crlb_rms_mm"],
                    n_packets=len(idx),
                    single_us_per_packet=dt / len(idx) * 1e6,
                    nfft=obj.nfft,
                    hop=obj.hop,
                )
            cells.append(cell)
            print(
                f"fs {label} MS/s  SNR {snr:4.1f} dB  CRLB {cell['crlb_rms_mm'] * 1e3:7.2f} um  "
                + "  ".join(f"{k} {v['rms_mm'] * 1e3:7.1f}" for k, v in cell["methods"].items())
                + f"  ml {cell['methods']['ml']['ratio_to_crlb']:.2f}x "
                f"cal {cell['methods']['ml']['in_1515sigma_ellipse']:.2f}",
                flush=True,
            )
        tm = _timing(label, fs, cfg, geo, P, band, rng, quick)
        for b in BASELINES:
            vals = [
                c["methods"][b]["single_us_per_packet"]
                for c in cells
                if c["label"] == label and b in c["methods"]
            ]
            if vals:
                t = float(np.median(vals))
                tm[b] = dict(single_us_per_packet=t, single_packets_per_s=1e6 / t)
        timing[f"{label} MS/s"] = tm
        print(
            "timing",
            label,
            {
                k: round(v.get("batched_packets_per_s", v["single_packets_per_s"]))
                for k, v in tm.items()
            },
            flush=True,
        )
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    out = dict(
        description="ae_tactile localization benchmark (bench/bench_localization.py)",
        setup=dict(
            geometry="per cell: the simulator's water-skin tip (R 10 mm, a 1.5 mm, "
            "c 1480 m/s) or its silicone preset (c 1000 m/s)",
            sim="SimConfig(reflections=True), default pulse (v0 0.3 m/s, a_c 1/mm), "
            "1 MHz low-pass (order 4) unless stated, 12-bit ADC",
            points=f"{n_points} points uniform over polar <= 60 deg x {n_real} noise realisations",
            ml="band_hz=None: each packet's upper band edge from its spectrum "
            "(data-driven); ml_fixed_band: the fixed default band "
            "(100 kHz, min(1 MHz, fs/4)) or the cell's band",
            pyroomacoustics_packets_per_cell=n_pra if pra_ok else 0,
            crlb="known pulse shape, unknown emission time and amplitude, echo-free samples, "
            "noise sigma_n^2 + LSB^2/12 (crlb_noise_only_rms_mm: sigma_n^2 only)",
            python=platform.python_version(),
            numpy=np.__version__,
            machine=platform.machine(),
            numba=_numba_version(),
            load_average_at_end=list(load) if load else None,
            cpu_count=os.cpu_count(),
            quick=quick,
            methods=available_methods(),
        ),
        cells=cells,
        timing=timing,
        run_time_s=time.perf_counter() - t_start,
    )
    return out


def _numba_version():
    try:
        import numba  # lazy: optional dependency

        return numba.__version__ if NUMBA_AVAILABLE else f"{numba.__version__} (disabled)"
    except ImportError:
        return None


TIMING_ROWS = [
    ("localize_one_numba", "ML `localize_one`, compiled (float32 window)"),
    ("localize_one_numpy", "ML `localize_one`, numpy path"),
    ("ml", "ML (data-driven band), `localize`"),
    ("ml_numpy", "ML, `localize`, numpy path"),
    ("ml_fixed_band", "ML, fixed band, `localize`"),
    ("gradient", "gradient (iterated)"),
    ("gcc_phat", "GCC-PHAT (band)"),
    ("xcorr_farfield", "paper: xcorr + Eq. 2"),
    ("pra_srp_phat", "pyroomacoustics SRP-PHAT"),
    ("pra_music", "pyroomacoustics MUSIC"),
]


def table_markdown(res):
    lines = []
    ms = [m for m in METHODS + BASELINES if any(m in c["methods"] for c in res["cells"])]
    head = "| fs (MS/s) | SNR (dB) | CRLB (um) | " + " | ".join(LABELS[m] for m in ms) + " |"
    lines.append(
        "RMS in-plane error / RMS bias in micrometres (polar angle <= 60 deg); for ML "
        "the ratio to the CRLB and the share of errors inside the reported 1.515-sigma "
        "ellipse (68 % when the covariance is right) in brackets, for ML also with the "
        "delay noise a driver learns from 2,000 touches of that front end where it "
        "learns one (docs/localization.md)."
    )
    lines.append("")
    lines.append(head)
    lines.append("|" + "---|" * (3 + len(ms)))
    for c in res["cells"]:
        row = [c["label"], f"{c['snr_db']:g}", f"{c['crlb_rms_mm'] * 1e3:.1f}"]
        for m in ms:
            v = c["methods"].get(m)
            if v is None:
                row.append("-")
                continue
            s = f"{v['rms_mm'] * 1e3:.1f} / {v['bias_mm'] * 1e3:.1f}"
            if m in ("ml", "ml_fixed_band"):
                s += f" ({v['ratio_to_crlb']:.2f}x, {100 * v['in_1515sigma_ellipse']:.0f} %"
                learnt = c.get("ml_in_1515sigma_ellipse_learnt_noise")
                if m == "ml" and c.get("delay_noise_learnt") and learnt is not None:
                    s += f"; {100 * learnt:.0f} % with the learnt delay noise"
                s += ")"
            if v.get("accepted", 1.0) < 0.995:
                s += f" [{100 * v['accepted']:.0f}% acc.]"
            row.append(s)
        lines.append("| " + " | ".join(row) + " |")
    lines.append("")
    load = res["setup"].get("load_average_at_end")
    loads = ", ".join(f"{x:.1f}" for x in load) if load else "n/a"
    lines.append(
        "Time per packet on one core (us, wall clock): batched (one call for all "
        "packets) / one packet per call; `localize_one`: mean (p50, p99) per call. "
        f"Compiled: numba {res['setup'].get('numba')}. Load average at the end of the "
        f"run: {loads} on {res['setup'].get('cpu_count')} cores"
        + (
            ": a busy machine, so wall figures are upper bounds (p99 holds the "
            "scheduler's preemptions)"
            if load and load[0] > 0.5 * (res["setup"].get("cpu_count") or 1)
            else " (otherwise idle)"
        )
        + "; the CPU-time table below is what the process itself spent."
    )
    lines.append("")
    rates = list(res["timing"])
    lines.append("| method | " + " | ".join(rates) + " |")
    lines.append("|---|" + "---|" * len(rates))
    for key, name in TIMING_ROWS:
        if not any(key in res["timing"][r] for r in rates):
            continue
        row = [name]
        for r in rates:
            v = res["timing"][r].get(key)
            if v is None:
                row.append("-")
            elif "p99_us" in v:
                row.append(
                    f"{v['single_us_per_packet']:.0f} ({v['p50_us']:.0f}, {v['p99_us']:.0f})"
                )
            elif "batched_us_per_packet" in v:
                row.append(
                    f"{v['batched_us_per_packet']:.0f} / {v['single_us_per_packet']:.0f} "
                    f"({v['batched_packets_per_s'] / 1e3:.1f} k/s batched)"
                )
            else:
                row.append(f"- / {v['single_us_per_packet']:.0f}")
        lines.append("| " + " | ".join(row) + " |")
    lines.append("")
    lines.append(
        "CPU time of the process per packet (us; `time.process_time`, insensitive to "
        "other processes): batched (packets/s), and `localize_one` mean (p50, p99)."
    )
    lines.append("")
    lines.append("| method | " + " | ".join(rates) + " |")
    lines.append("|---|" + "---|" * len(rates))
    for key, name in TIMING_ROWS:
        if not any(
            "batched_cpu_us_per_packet" in res["timing"][r].get(key, {})
            or "cpu_us" in res["timing"][r].get(key, {})
            for r in rates
        ):
            continue
        row = [name]
        for r in rates:
            v = res["timing"][r].get(key, {})
            if "cpu_us" in v:
                row.append(f"{v['cpu_us']:.0f} ({v['cpu_p50_us']:.0f}, {v['cpu_p99_us']:.0f})")
            elif "batched_cpu_us_per_packet" in v:
                row.append(
                    f"{v['batched_cpu_us_per_packet']:.1f} "
                    f"({v['batched_cpu_packets_per_s'] / 1e3:.0f} k/s)"
                )
            else:
                row.append("-")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def plot(res, path):
    import matplotlib  # lazy: only for the plot, slow to import

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: after the Agg backend is chosen

    fig, axes = plt.subplots(1, 3, figsize=(19, 5.6))
    ax = axes[0]
    keys = METHODS + BASELINES
    colors = dict(zip(keys, [f"C{i}" for i in range(len(keys))]))
    rate = "10 MS/s"
    tmr = res["timing"].get(rate, {})
    for snr, marker in ((20.0, "o"), (40.0, "s")):
        cell = next((c for c in res["cells"] if c["label"] == "10" and c["snr_db"] == snr), None)
        if cell is None:
            continue
        for m, v in cell["methods"].items():
            t = tmr.get(m, {})
            us = t.get("batched_us_per_packet", t.get("single_us_per_packet"))
            if us is None:
                continue
            ax.scatter(
                us,
                v["rms_mm"] * 1e3,
                color=colors[m],
                marker=marker,
                s=60,
                label=f"{LABELS[m]}" if snr == 20.0 else None,
            )
            if "single_us_per_packet" in t and "batched_us_per_packet" in t:
                ax.plot(
                    [t["batched_us_per_packet"], t["single_us_per_packet"]],
                    [v["rms_mm"] * 1e3] * 2,
                    color=colors[m],
                    lw=0.8,
                    alpha=0.5,
                )
        # the same ml estimates through the other paths (identical error)
        v = cell["methods"]["ml"]
        extra = (
            ("ml_numpy", "batched_us_per_packet", "x", "ML, numpy path (batched)"),
            ("localize_one_numba", "p99_us", "*", "ML localize_one, p99"),
            ("localize_one_numpy", "p99_us", "+", "ML localize_one numpy, p99"),
        )
        for key, field, mk, name in extra:
            if key in tmr:
                ax.scatter(
                    tmr[key][field],
                    v["rms_mm"] * 1e3,
                    color="k",
                    marker=mk,
                    s=60,
                    label=name if snr == 20.0 else None,
                )
        ax.axhline(
            cell["crlb_rms_mm"] * 1e3,
            color="k",
            ls="--" if snr == 20 else ":",
            lw=1,
            label=f"CRLB {snr:g} dB",
        )
    ax.axvline(100.0, color="r", lw=0.8, ls="-.", label="0.1 ms per packet")
    ax.axvline(20.0, color="g", lw=0.8, ls="-.", label="50 k packets/s")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time per packet, one core (us)  [marker: batched; line to: one per call]")
    ax.set_ylabel("RMS in-plane error (um)")
    ax.set_title("speed vs error, 10 MS/s (circles 20 dB, squares 40 dB)")
    ax.legend(fontsize=7, loc="upper right")
    ax.grid(True, which="both", alpha=0.3)
    styles = (
        ("10", "-"),
        ("10 silicone", (0, (5, 1))),
        ("5", "--"),
        ("2", ":"),
        ("2 (1 MHz filter: aliasing)", "-."),
    )
    ax = axes[1]
    for label, ls in styles:
        cs = [c for c in res["cells"] if c["label"] == label]
        if not cs:
            continue
        snr = [c["snr_db"] for c in cs]
        ax.plot(
            snr,
            [c["crlb_rms_mm"] * 1e3 for c in cs],
            color="k",
            ls=ls,
            lw=1.5,
            label=f"CRLB {label} MS/s",
        )
        for m in ("ml", "gcc_phat", "xcorr_farfield", "pra_srp_phat"):
            if m in cs[0]["methods"]:
                ax.plot(
                    snr,
                    [c["methods"][m]["rms_mm"] * 1e3 for c in cs],
                    color=colors[m],
                    ls=ls,
                    marker="o",
                    ms=3,
                    label=f"{LABELS[m]}" if label == "10" else None,
                )
    ax.set_yscale("log")
    ax.set_xlabel("SNR (dB, docs/conventions.md)")
    ax.set_ylabel("RMS in-plane error (um)")
    ax.set_title("error vs SNR")
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    ax = axes[2]
    for i, (label, _) in enumerate(styles):
        cs = [c for c in res["cells"] if c["label"] == label]
        if not cs:
            continue
        snr = [c["snr_db"] for c in cs]
        ax.plot(
            snr,
            [c["methods"]["ml"]["ratio_to_crlb"] for c in cs],
            color=f"C{i}",
            marker="o",
            label=f"ML {label} MS/s",
        )
        if "ml_fixed_band" in cs[0]["methods"]:
            ax.plot(
                snr,
                [c["methods"]["ml_fixed_band"]["ratio_to_crlb"] for c in cs],
                color=f"C{i}",
                ls=":",
                marker=".",
                label="fixed band" if i == 0 else None,
            )
    ax.axhline(1.1, color="k", lw=0.8, ls="--", label="1.1x / 1.2x")
    ax.axhline(1.2, color="k", lw=0.8, ls="--")
    ax.set_yscale("log")
    ax.set_ylim(0.9, 12)
    ax.set_xlabel("SNR (dB)")
    ax.set_ylabel("RMS error / CRLB")
    ax.set_title("ML against the bound (solid: data-driven band, dotted: fixed band)")
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer packets (a smoke run)")
    ap.add_argument("--no-overlap", action="store_true", help="skip the overlap sweep")
    ap.add_argument(
        "--report-only",
        action="store_true",
        help="redo the tables and plot from the last JSON without running",
    )
    args = ap.parse_args(argv)
    suffix = "_quick" if args.quick else ""
    if args.report_only:
        res = json.loads((RESULTS / f"localization{suffix}.json").read_text())
    else:
        res = run(quick=args.quick)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"localization{suffix}.json").write_text(json.dumps(res, indent=1))
    table = table_markdown(res)
    (RESULTS / f"localization_table{suffix}.md").write_text(table)
    plot(res, RESULTS / f"localization_speed_error{suffix}.png")
    print(table)
    print(f"run time {res['run_time_s']:.0f} s; results in {RESULTS}")
    if args.no_overlap:
        return
    sys.path.insert(0, str(ROOT / "bench"))
    import bench_overlap  # noqa: PLC0415 - lazy: the overlap sweep, same directory, after sys.path

    if args.report_only:
        ov = json.loads((RESULTS / f"overlap{suffix}.json").read_text())
        (RESULTS / f"overlap_table{suffix}.md").write_text(bench_overlap.make_table(ov))
    else:
        bench_overlap.main(["--quick"] if args.quick else [])


if __name__ == "__main__":
    main()
