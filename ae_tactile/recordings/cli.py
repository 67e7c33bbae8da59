# SPDX-License-Identifier: Apache-2.0
"""`ae-tactile-detect`: hits, located events and fingertip events of AE recordings.

    ae-tactile-detect FILE [FILE...] [--format F] [--threshold-db-ae 40]
        [--preamp-gain-db 0] [--ddt-us 250] [--rearm-us 0] [--floating-db DB]
        [--sensor-xy "x1,y1;x2,y2;..." --velocity-m-s V | --setup FILE.vaex]
        [--fingertip [--channel-map 0,1,2,3]] [--out hits.csv|hits.json]

Prints each file's hits (and located events / fingertip events where asked) and writes
them with ``--out``. Exit status 0, or 2 with a message when a file or a setting is bad.
docs/recordings.md describes the formats, the hit definition and the outputs.
"""

from __future__ import annotations

import argparse
import math
import sys

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.records import EVENT_NAMES

from .api import FINGERTIP_DDT_US, Detection, detect, write_detections
from .fingertip import parse_channel_map
from .readers import FORMATS, RecordingError


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="ae-tactile-detect",
        description="Find AE hits in recordings (WAV, Vallen pridb/tradb, CSV, NPY/NPZ), "
                    "locate events on a plate, replay fingertip recordings.")
    ap.add_argument("files", nargs="+", metavar="FILE")
    ap.add_argument("--format", choices=FORMATS, help="file format (default: from the suffix)")
    ap.add_argument("--sample-rate", type=float, metavar="HZ",
                    help="sample rate of files that do not store it (CSV, NPY)")
    ap.add_argument("--full-scale-v", type=float, metavar="V",
                    help="volts at full scale of integer PCM WAV (default 1.0)")
    g = ap.add_argument_group("hit definition")
    g.add_argument("--threshold-db-ae", type=float, default=40.0,
                   help="threshold at the sensor, 0 dB_AE = 1 uV (default 40)")
    g.add_argument("--preamp-gain-db", type=float, default=0.0,
                   help="gain between the sensor and the recorded volts (default 0)")
    g.add_argument("--ddt-us", type=float, default=None,
                   help="duration discrimination time, HDT (default 250; "
                        f"{FINGERTIP_DDT_US:g} with --fingertip)")
    g.add_argument("--rearm-us", type=float, default=0.0, help="rearm time, HLT (default 0)")
    g.add_argument("--pdt-us", type=float, default=None, help="peak definition time")
    g.add_argument("--max-duration-us", type=float, default=None, help="longest hit")
    g.add_argument("--floating-db", type=float, default=None,
                   help="threshold at least this far above each channel's noise rms")
    loc = ap.add_argument_group("plate location")
    loc.add_argument("--sensor-xy", help='sensor positions "x1,y1;x2,y2;..." [m], in sorted '
                                         "channel order")
    loc.add_argument("--velocity-m-s", type=float, help="wave speed [m/s]")
    loc.add_argument("--setup", help="Vallen setup (.vaex) with positions and speed (default: "
                                     "the one beside a pridb/tradb)")
    ft = ap.add_argument_group("fingertip")
    ft.add_argument("--fingertip", action="store_true",
                    help="replay 4 channels through the fingertip pipeline")
    ft.add_argument("--channel-map", help="file rows of fingertip channels 0..3 (default "
                                          "0,1,2,3; docs/conventions.md order)")
    ft.add_argument("--radius-m", type=float, default=10e-3)
    ft.add_argument("--element-offset-m", type=float, default=1.5e-3)
    ft.add_argument("--sound-speed-m-s", type=float, default=1480.0)
    ft.add_argument("--method", default="ml", help="localization estimator (default ml)")
    ap.add_argument("--out", help="write the results (.csv: hits, with .events/.contacts/"
                                  ".slip.csv beside it; .json: everything)")
    ap.add_argument("--max-print", type=int, default=50, help="rows printed per table")
    return ap


def _options(a) -> dict:
    hit = {"threshold_db_ae": a.threshold_db_ae, "preamp_gain_db": a.preamp_gain_db,
           "rearm_us": a.rearm_us, "pdt_us": a.pdt_us, "max_duration_us": a.max_duration_us,
           "floating_db": a.floating_db}
    if a.ddt_us is not None:
        hit["ddt_us"] = a.ddt_us
    geometry = FingertipGeometry(a.radius_m, a.element_offset_m, a.sound_speed_m_s) \
        if a.fingertip else None
    return {"format": a.format, "sample_rate_hz": a.sample_rate, "full_scale_v": a.full_scale_v,
            "sensor_xy": a.sensor_xy, "velocity_m_s": a.velocity_m_s, "setup": a.setup,
            "fingertip": a.fingertip, "channel_map": parse_channel_map(a.channel_map),
            "geometry": geometry, "method": a.method, **hit}


def _fmt(v, spec: str) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def print_detection(det: Detection, max_rows: int = 50, out=None) -> None:
    """A detection as text (on ``out``, default stdout): a summary line, notes, warnings,
    then its tables."""
    out = out or sys.stdout
    d = det.definition
    recs = det.recordings
    r0 = recs[0]
    what = (f"{len(recs)} transient records" if len(recs) > 1 else
            f"{r0.n_channels} channel(s), {r0.duration_s:.6g} s")
    print(f"{det.source}: {what} at {r0.sample_rate_hz / 1e6:g} MS/s; {len(det.hits)} hit(s) "
          f"(threshold {d.threshold_db_ae:g} dB_AE, gain {d.preamp_gain_db:g} dB, DDT "
          f"{d.ddt_us:g} us, rearm {d.rearm_us:g} us"
          + (f", floating {d.floating_db:g} dB" if d.floating_db is not None else "") + ")",
          file=out)
    for n in det.notes:
        print(f"  note: {n}", file=out)
    for w in det.warnings:
        print(f"  warning: {w}", file=out)
    _rows(out, "  channel   onset [s]        crossing [s]     amp [dB_AE]  peak [V]   rise [us]"
               "  dur [us]  counts  energy [eu]", det.hits, max_rows, lambda h: (
        f"  {str(h.channel):>7}  {h.onset_time_s:15.9f}  {h.crossing_time_s:15.9f}  "
        f"{h.amplitude_db_ae:11.1f}  {h.peak_v:9.3g}  {h.rise_time_s * 1e6:9.1f}  "
        f"{h.duration_s * 1e6:8.1f}  {h.counts:6d}  {h.energy_eu:11.4g}"
        + (f"  (truncated at the {h.truncated})" if h.truncated else "")))
    if det.events:
        _rows(out, "  located events:  time [s]       x [m]     y [m]     LUCY [mm]  channels",
              det.events, max_rows, lambda e: (
                  f"  {e.time_s:24.9f}  {_fmt(e.x_m, '8.4f')}  {_fmt(e.y_m, '8.4f')}  "
                  f"{_fmt(e.lucy_m * 1e3 if e.lucy_m == e.lucy_m else None, '9.3f')}  "
                  f"{' '.join(map(str, e.channels))}" + (f"  ({e.reason})" if e.reason else "")))
    if det.fingertip is not None:
        _print_fingertip(det, max_rows, out)


def _print_fingertip(det: Detection, max_rows: int, out) -> None:
    ft = det.fingertip
    counts = ", ".join(f"{k} {v}" for k, v in sorted(ft.counts.items()) if v)
    print(f"  fingertip: {len(ft.windows)} window(s) -> {len(ft.contacts)} contact event(s), "
          f"{len(ft.slip)} slip event(s); counts: {counts or 'none'}", file=out)
    _rows(out, "  time [s]          event           x [mm]   y [mm]   z [mm]  confidence",
          ft.contacts + ft.slip, max_rows, lambda c: (
              f"  {c.time_ns * 1e-9:15.9f}  {EVENT_NAMES.get(int(c.event_type), '?'):14s}  "
              f"{c.point_m[0] * 1e3:7.3f}  {c.point_m[1] * 1e3:7.3f}  {c.point_m[2] * 1e3:7.3f}"
              f"  {c.confidence:10.3f}"))


def _rows(out, header: str, items, max_rows: int, line) -> None:
    if not items:
        return
    print(header, file=out)
    for it in items[:max(0, max_rows)]:
        print(line(it), file=out)
    if len(items) > max_rows:
        print(f"  ... {len(items) - max_rows} more (all of them with --out)", file=out)


def main(argv=None) -> int:
    """Entry point of ``ae-tactile-detect``; returns the exit status."""
    ap = build_parser()
    a = ap.parse_args(argv)
    try:
        opts = _options(a)
        dets = []
        for f in a.files:
            dets.append(detect(f, **opts))
            print_detection(dets[-1], a.max_print)
        if a.out:
            for p in write_detections(dets, a.out):
                print(f"wrote {p}")
    except (RecordingError, ValueError) as exc:
        print(f"ae-tactile-detect: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
