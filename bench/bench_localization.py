"""Localization benchmark: accuracy against the Cramer-Rao bound, and speed (issue 4).

    python3 bench/bench_localization.py [--quick]        (or: make bench-localization)

Simulated packets (ae_tactile.sim, the paper's water-skin tip: R = 10 mm, a = 1.5 mm,
c = 1480 m/s, 1 MHz front end, 12-bit ADC, wall echoes on) at P fixed contact points
spread uniformly over the usable surface (polar angle <= 60 deg), R noise realisations
each, random sub-sample trigger offsets; SNR 10, 20, 30, 40 dB (docs/conventions.md);
2, 5 and 10 MS/s with the default 1 MHz front end, and 2 MS/s behind a 0.6 MHz 8th-order
anti-alias filter (band 0.1-0.7 MHz). For each estimator of ae_tactile.localization and each baseline:

  * RMS in-plane position error (mm) over the accepted packets, and the RMS bias: the
    RMS over points of the mean error at each point (noise part removed: |mean|^2 -
    var / R), i.e. what averaging many packets would not remove;
  * the CRLB for the same pulse, noise (sigma_n^2 + LSB^2/12: the ADC's rounding noise is
    in the data too) and geometry, on the echo-free samples (ae_tactile.localization.crlb);
  * the time per packet on one core, batched and one packet per call.

Baselines: the paper's one-shot Eq. 2 inversion from plain cross-correlation peaks
(``xcorr_farfield``, a registered method) and pyroomacoustics' DOA algorithms SRP-PHAT
and MUSIC (far-field only), configured for this medium and band: c = 1480 m/s,
freq_range = the signal band, microphones at the element positions, STFT frames of the
same echo-free segment as one rectangular snapshot (short STFT frames bias them, see
`PraBaseline`), colatitude 0-90 deg (a planar array cannot tell +z from -z), a 2 deg
grid then a local 0.1 deg grid around its maximum. They are slow, so they run on fewer
packets per cell (the first realisations of a subset of the points; stated in the JSON).

Writes bench/results/localization.json, bench/results/localization_speed_error.png,
bench/results/localization_table.md, and the table into docs/localization.md (between
the bench markers).
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_v, "1")              # one core

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

from ae_tactile.localization import available_methods, default_band_hz, localize  # noqa: E402
from ae_tactile.localization.common import make_plan  # noqa: E402
from ae_tactile.localization.crlb import simulated_crlb  # noqa: E402
from ae_tactile.sim import SimConfig, render_triggered  # noqa: E402

RESULTS = ROOT / "bench" / "results"
DOC = ROOT / "docs" / "localization.md"
BEGIN, END = "<!-- bench:localization:begin -->", "<!-- bench:localization:end -->"
METHODS = ["ml", "gradient", "gcc_phat", "xcorr_farfield"]
BASELINES = ["pra_srp_phat", "pra_music"]
LABELS = {"ml": "ML exact sphere", "gradient": "gradient (iterated)", "gcc_phat": "GCC-PHAT (band)",
          "xcorr_farfield": "paper: xcorr + Eq. 2", "pra_srp_phat": "pyroomacoustics SRP-PHAT",
          "pra_music": "pyroomacoustics MUSIC"}


def cap_points(geo, n, max_deg=60.0, seed=0):
    """n points spread uniformly (in area) over the cap polar <= max_deg (golden spiral)."""
    i = np.arange(n) + 0.5
    ct = 1.0 - (1.0 - np.cos(np.deg2rad(max_deg))) * i / n
    az = np.pi * (1 + 5 ** 0.5) * i + seed
    return geo.surface_point_from_angles(np.arccos(ct), az)


def error_stats(err_xy, point_id, accepted, n_points):
    """RMS error and RMS bias (noise-corrected) of in-plane errors (m)."""
    e = err_xy[accepted]
    pid = point_id[accepted]
    rms = float(np.sqrt(np.mean(np.sum(e ** 2, axis=1)))) if len(e) else float("nan")
    b2 = []
    for p in range(n_points):
        ep = e[pid == p]
        if len(ep) >= 2:
            m = ep.mean(axis=0)
            v = ep.var(axis=0, ddof=1).sum()
            b2.append(np.sum(m ** 2) - v / len(ep))
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
        import pyroomacoustics as pra
        self.pra = pra
        self.algo = algo
        self.geo = geo
        self.fs = fs
        self.band = [band[0], band[1]]
        self.plan = make_plan(fs, geo, n_samples, band)
        self.nfft = int(2 ** np.ceil(np.log2(self.plan.seg_len)))
        self.hop = self.nfft
        self.mics = geo.element_positions_m.T                     # (3, 4)
        az = np.deg2rad(np.arange(0.0, 360.0, 2.0))
        col = np.deg2rad(np.arange(0.0, 90.0 + 1e-9, 2.0))
        self.coarse = self._doa(az, col)

    def _doa(self, az, col):
        name = {"pra_srp_phat": "SRP", "pra_music": "MUSIC"}[self.algo]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return self.pra.doa.algorithms[name](self.mics, self.fs, self.nfft, c=self.geo.sound_speed_m_s,
                                                 num_src=1, dim=3, azimuth=az, colatitude=col)

    def locate(self, window, onset):
        start = onset - self.plan.pre
        seg = window[:, start: start + self.plan.seg_len]
        seg = seg - window[:, : max(start, 1)].mean(axis=1, keepdims=True)
        X = np.fft.rfft(seg, n=self.nfft, axis=1)[:, :, None]    # (M, F, 1 snapshot)
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
def run(quick=False):
    t_start = time.perf_counter()
    snrs = [10.0, 20.0, 30.0, 40.0]
    # (label, sample rate, SimConfig changes, band): the default 1 MHz front end at 2, 5 and
    # 10 MS/s, and 2 MS/s behind a matched anti-alias filter (0.6 MHz, 8th order).
    rates = [("2", 2e6, {}, None), ("2 (0.6 MHz anti-alias)", 2e6, dict(lowpass_hz=0.6e6, lowpass_order=8),
                                                                        (100e3, 0.7e6)),
             ("5", 5e6, {}, None), ("10", 10e6, {}, None)]
    n_points, n_real = (20, 10) if quick else (50, 20)
    pra_points, pra_real = (10, 1) if quick else (20, 2)
    n_pra = pra_points * pra_real
    rng = np.random.default_rng(2024)
    base_cfg = SimConfig(reflections=True)
    geo = base_cfg.geometry
    pts = cap_points(geo, n_points)
    point_id = np.repeat(np.arange(n_points), n_real)
    P = pts[point_id]
    n = len(P)
    # pyroomacoustics: the first pra_real realisations of every (n_points / pra_points)-th point
    pra_idx = np.array([p * n_real + r for p in range(0, n_points, n_points // pra_points) for r in range(pra_real)])
    cells = []
    pra_ok = importlib.util.find_spec("pyroomacoustics") is not None
    timing = {}
    for label, fs, changes, band in rates:
        cfg = base_cfg.replace(sample_rate_hz=fs, **changes)
        band = default_band_hz(fs) if band is None else band
        pras = {b: PraBaseline(b, geo, fs, int(round(40e-6 * fs)), band) for b in BASELINES} if pra_ok else {}
        for snr in snrs:
            u = rng.uniform(0.01, 0.99, n)
            pk = render_triggered(P, cfg, snr_db=snr, subsample_offset=u, rng=rng)
            bound = simulated_crlb(P, cfg, snr_db=snr, subsample_offset=u)
            bound_n = simulated_crlb(P, cfg, snr_db=snr, subsample_offset=u, include_quantization=False)
            cell = dict(label=label, sample_rate_hz=fs, lowpass_hz=cfg.lowpass_hz, lowpass_order=cfg.lowpass_order,
                        snr_db=snr, band_hz=list(band), n_packets=n,
                        crlb_rms_mm=float(np.sqrt(np.mean(bound["rms_m"] ** 2)) * 1e3),
                        crlb_unknown_waveform_rms_mm=float(np.sqrt(np.mean(bound["rms_unknown_m"] ** 2)) * 1e3),
                        crlb_noise_only_rms_mm=float(np.sqrt(np.mean(bound_n["rms_m"] ** 2)) * 1e3),
                        methods={})
            for m in METHODS:
                t0 = time.perf_counter()
                r = localize(pk.samples_v, fs, pk.onset_index, method=m, band_hz=band)
                dt = time.perf_counter() - t0
                err = (r.point_m - P)[:, :2]
                rms, bias = error_stats(err, point_id, r.accepted, n_points)
                cov = r.covariance_m2[r.accepted, :2, :2]
                e = err[r.accepted]
                d2 = np.einsum("ki,kij,kj->k", e, np.linalg.inv(cov), e) if len(e) else np.zeros(0)
                cell["methods"][m] = dict(rms_mm=rms * 1e3, bias_mm=bias * 1e3, accepted=float(r.accepted.mean()),
                                          ratio_to_crlb=rms * 1e3 / cell["crlb_rms_mm"],
                                          in_1sigma_ellipse=float(np.mean(d2 < 1.0)) if len(d2) else None,
                                          in_1515sigma_ellipse=float(np.mean(d2 < 1.515 ** 2)) if len(d2) else None,
                                          batched_us_per_packet=dt / n * 1e6,
                                          touch_correct=float(np.mean(r.polarity == 1)))
            for b, obj in pras.items():
                idx = pra_idx
                t0 = time.perf_counter()
                est = np.array([obj.locate(pk.samples_v[i], int(pk.onset_index[i])) for i in idx])
                dt = time.perf_counter() - t0
                err = (est - P[idx])[:, :2]
                rms, bias = error_stats(err, point_id[idx], np.ones(len(idx), bool), n_points)
                cell["methods"][b] = dict(rms_mm=rms * 1e3, bias_mm=bias * 1e3, accepted=1.0,
                                          ratio_to_crlb=rms * 1e3 / cell["crlb_rms_mm"], n_packets=len(idx),
                                          single_us_per_packet=dt / len(idx) * 1e6,
                                          nfft=obj.nfft, hop=obj.hop)
            cells.append(cell)
            print(f"fs {label} MS/s  SNR {snr:4.1f} dB  CRLB {cell['crlb_rms_mm'] * 1e3:7.2f} um  " +
                  "  ".join(f"{k} {v['rms_mm'] * 1e3:7.1f}" for k, v in cell["methods"].items()), flush=True)
        # Speed: batched (all packets of the 20 dB cell, one call) and one packet per call.
        pk = render_triggered(P, cfg, snr_db=20.0, rng=rng)
        tm = {}
        for m in METHODS:
            localize(pk.samples_v[:64], fs, pk.onset_index[:64], method=m, band_hz=band)     # warm caches
            best = np.inf
            for _ in range(3):
                t0 = time.perf_counter()
                localize(pk.samples_v, fs, pk.onset_index, method=m, band_hz=band)
                best = min(best, time.perf_counter() - t0)
            n1 = 200 if not quick else 60
            t0 = time.perf_counter()
            for i in range(n1):
                localize(pk.samples_v[i: i + 1], fs, pk.onset_index[i: i + 1], method=m, band_hz=band)
            single = (time.perf_counter() - t0) / n1
            tm[m] = dict(batched_packets_per_s=n / best, batched_us_per_packet=best / n * 1e6,
                         single_packets_per_s=1.0 / single, single_us_per_packet=single * 1e6, batch_size=n)
        for b in BASELINES:
            vals = [c["methods"][b]["single_us_per_packet"] for c in cells
                    if c["label"] == label and b in c["methods"]]
            if vals:
                t = float(np.median(vals))
                tm[b] = dict(single_us_per_packet=t, single_packets_per_s=1e6 / t)
        timing[f"{label} MS/s"] = tm
        print("timing", label, {k: round(v.get("batched_packets_per_s", v["single_packets_per_s"])) for k, v in tm.items()},
              flush=True)
    out = dict(
        description="ae_tactile localization benchmark (bench/bench_localization.py)",
        setup=dict(geometry=dict(radius_m=geo.radius_m, element_offset_m=geo.element_offset_m,
                                 sound_speed_m_s=geo.sound_speed_m_s),
                   sim="SimConfig(reflections=True), default pulse (v0 0.3 m/s, a_c 1/mm), 1 MHz low-pass, 12-bit ADC",
                   points=f"{n_points} points uniform over polar <= 60 deg x {n_real} noise realisations",
                   pyroomacoustics_packets_per_cell=n_pra if pra_ok else 0,
                   crlb="known pulse shape, unknown emission time and amplitude, echo-free samples, "
                        "noise sigma_n^2 + LSB^2/12 (crlb_noise_only_rms_mm: sigma_n^2 only)",
                   python=platform.python_version(), numpy=np.__version__, machine=platform.machine(),
                   quick=quick, methods=available_methods()),
        cells=cells, timing=timing, run_time_s=time.perf_counter() - t_start)
    return out


def table_markdown(res):
    lines = []
    ms = [m for m in METHODS + BASELINES if any(m in c["methods"] for c in res["cells"])]
    head = "| fs (MS/s) | SNR (dB) | CRLB (um) | " + " | ".join(LABELS[m] for m in ms) + " |"
    lines.append("RMS in-plane error / RMS bias in micrometres (polar angle <= 60 deg); ratio to the CRLB "
                 "in brackets for the best estimator.")
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
            if m == "ml":
                s += f" ({v['ratio_to_crlb']:.2f}x)"
            if v.get("accepted", 1.0) < 0.995:
                s += f" [{100 * v['accepted']:.0f}% acc.]"
            row.append(s)
        lines.append("| " + " | ".join(row) + " |")
    lines.append("")
    lines.append("Time per packet on one core (us): batched (one call for all packets) / one packet per call.")
    lines.append("")
    rates = list(res["timing"])
    lines.append("| method | " + " | ".join(rates) + " |")
    lines.append("|---|" + "---|" * len(rates))
    for m in ms:
        row = [LABELS[m]]
        for r in rates:
            v = res["timing"][r].get(m)
            if v is None:
                row.append("-")
            elif "batched_us_per_packet" in v:
                row.append(f"{v['batched_us_per_packet']:.0f} / {v['single_us_per_packet']:.0f} "
                           f"({v['batched_packets_per_s'] / 1e3:.1f} k/s batched)")
            else:
                row.append(f"- / {v['single_us_per_packet']:.0f}")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def plot(res, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 5.2))
    ax = axes[0]
    colors = dict(zip(METHODS + BASELINES, ["C0", "C1", "C2", "C3", "C4", "C5"]))
    rate = "10 MS/s"
    for snr, marker in ((20.0, "o"), (30.0, "s")):
        cell = next(c for c in res["cells"] if c["label"] == "10" and c["snr_db"] == snr)
        for m, v in cell["methods"].items():
            t = res["timing"][rate].get(m, {})
            us = t.get("batched_us_per_packet", t.get("single_us_per_packet"))
            if us is None:
                continue
            ax.scatter(us, v["rms_mm"] * 1e3, color=colors[m], marker=marker, s=60,
                       label=f"{LABELS[m]}" if snr == 20.0 else None)
            if "single_us_per_packet" in t and "batched_us_per_packet" in t:
                ax.plot([t["batched_us_per_packet"], t["single_us_per_packet"]], [v["rms_mm"] * 1e3] * 2,
                        color=colors[m], lw=0.8, alpha=0.5)
        ax.axhline(cell["crlb_rms_mm"] * 1e3, color="k", ls="--" if snr == 20 else ":", lw=1,
                   label=f"CRLB {snr:g} dB")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time per packet, one core (us)  [marker: batched; line to: one per call]")
    ax.set_ylabel("RMS in-plane error (um)")
    ax.set_title("speed vs error, 10 MS/s (circles 20 dB, squares 30 dB)")
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(True, which="both", alpha=0.3)
    ax = axes[1]
    for label, ls in (("10", "-"), ("5", "--"), ("2", ":"), ("2 (0.6 MHz anti-alias)", "-.")):
        cs = [c for c in res["cells"] if c["label"] == label]
        if not cs:
            continue
        snr = [c["snr_db"] for c in cs]
        ax.plot(snr, [c["crlb_rms_mm"] * 1e3 for c in cs], color="k", ls=ls, lw=1.5,
                label=f"CRLB {label} MS/s")
        for m in ("ml", "gcc_phat", "xcorr_farfield", "pra_srp_phat"):
            if m in cs[0]["methods"]:
                ax.plot(snr, [c["methods"][m]["rms_mm"] * 1e3 for c in cs], color=colors[m], ls=ls, marker="o",
                        ms=3, label=f"{LABELS[m]}" if label == "10" else None)
    ax.set_yscale("log")
    ax.set_xlabel("SNR (dB, docs/conventions.md)")
    ax.set_ylabel("RMS in-plane error (um)")
    ax.set_title("error vs SNR (solid 10, dashed 5, dotted 2, dash-dot 2 MS/s + anti-alias)")
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def update_doc(table):
    if not DOC.exists():
        return False
    text = DOC.read_text()
    if BEGIN not in text or END not in text:
        return False
    a = text.index(BEGIN) + len(BEGIN)
    b = text.index(END)
    DOC.write_text(text[:a] + "\n" + table + text[b:])
    return True


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer packets (a smoke run)")
    ap.add_argument("--report-only", action="store_true",
                    help="redo the table, plot and docs from the last JSON without running")
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
    if not args.quick:
        update_doc(table)
    print(table)
    print(f"run time {res['run_time_s']:.0f} s; results in {RESULTS}")


if __name__ == "__main__":
    main()
