# SPDX-License-Identifier: Apache-2.0
"""One call from a recording file to hits, located events and fingertip events.

    from ae_tactile.recordings import detect, write_detections
    det = detect("run.wav", threshold_db_ae=45, preamp_gain_db=34)
    det = detect("plate.pridb")                  # the .vaex beside it locates the events
    det = detect("tip.npy", sample_rate_hz=10e6, fingertip=True, floating_db=15)
    write_detections([det], "hits.csv")          # or .json

`detect` reads the file (`readers`), finds the hits of every record (`hits`), locates
events on a plane when sensor positions and a wave speed are given or a Vallen setup
(.vaex) lies beside the file (`locate`), and replays a 4-channel fingertip recording
through the live device's pipeline (`fingertip`).
"""

from __future__ import annotations

import csv
import json
import math
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ae_tactile.geometry import FingertipGeometry

from .fingertip import FingertipReplay, contact_row, replay_fingertip
from .hits import (
    MAX_HITS_PER_CHANNEL,
    HitDefinition,
    find_hits,
    noise_floor_v,
    threshold_warnings,
)
from .locate import (
    PlanarEvent,
    locate_events,
    parse_sensor_xy,
    read_vallen_setup,
    setup_beside,
)
from .readers import Recording, RecordingError, read_recording

#: the fingertip's default DDT [us]: its emissions are ~20 us packets that may follow each
#: other within a few hundred us (micro-slip trains); the plate default would merge them
FINGERTIP_DDT_US = 20.0

HIT_COLUMNS = ("source", "record", "channel", "onset_time_s", "crossing_time_s",
               "amplitude_db_ae", "peak_v", "rise_time_s", "duration_s", "counts",
               "energy_v2s", "energy_eu", "threshold_v", "noise_rms_v", "snr_db",
               "truncated")
EVENT_COLUMNS = ("source", "time_s", "x_m", "y_m", "lucy_m", "channels",
                 "arrival_times_s", "reason")


@dataclass
class Detection:
    """What `detect` found in one file.

    ``hits`` in time order; ``events`` the plane-located events (empty unless asked);
    ``fingertip`` the pipeline's replay (None unless asked); ``notes`` what the readers
    assumed; ``warnings`` what makes the results doubtful.
    """

    source: str
    definition: HitDefinition
    recordings: list = field(default_factory=list, repr=False)
    hits: list = field(default_factory=list)
    events: list = field(default_factory=list)
    fingertip: FingertipReplay | None = None
    notes: list = field(default_factory=list)
    warnings: list = field(default_factory=list)


def detect(path, *, format: str | None = None, definition: HitDefinition | None = None,
           sample_rate_hz: float | None = None, full_scale_v: float | None = None,
           sensor_xy=None, velocity_m_s: float | None = None, setup=None,
           fingertip: bool = False, channel_map=None, geometry: FingertipGeometry | None = None,
           method: str = "ml", **hit_definition) -> Detection:
    """Hits, located events and fingertip events of one recording file.

    Parameters
    ----------
    path : str or os.PathLike
        WAV, Vallen pridb/tradb, CSV, NPY or NPZ (`read_recording`).
    format : str or None
        Format name (None: from the suffix).
    definition : HitDefinition or None
        The hit definition; None: one from ``hit_definition`` keywords
        (``threshold_db_ae=40``, ``preamp_gain_db``, ``ddt_us``, ``rearm_us``, ...), the
        DDT defaulting to `FINGERTIP_DDT_US` with ``fingertip``.
    sample_rate_hz, full_scale_v : float or None
        For files that do not store them (`read_recording`).
    sensor_xy : str, dict, array_like or None
        Plate sensor positions [m]: ``"x1,y1;x2,y2;..."``, an (n, 2) array in sorted channel
        order, or channel -> (x, y).
    velocity_m_s : float or None
        Wave speed of the plate [m/s] (needed with ``sensor_xy``).
    setup : str, os.PathLike or None
        A Vallen setup file (.vaex) with both; None: the one beside a Vallen file, if any
        (used only when ``sensor_xy`` is None).
    fingertip : bool
        Replay the 4 channels through the fingertip pipeline.
    channel_map : sequence of 4 int or None
        File row of fingertip channel k (docs/conventions.md order; None: rows 0..3).
    geometry : FingertipGeometry or None
        The fingertip (None: the default sensor).
    method : str
        The fingertip's localization estimator.

    Returns
    -------
    Detection

    Raises
    ------
    RecordingError
        The file cannot be read.
    ValueError
        Bad settings.
    """
    if definition is None:
        if fingertip:
            hit_definition.setdefault("ddt_us", FINGERTIP_DDT_US)
        definition = HitDefinition(**hit_definition)
    elif hit_definition:
        raise ValueError("give either a HitDefinition or its keywords, not both")
    recs = read_recording(path, format=format, sample_rate_hz=sample_rate_hz,
                          full_scale_v=full_scale_v)
    det = Detection(str(path), definition, recs)
    per_record = []
    for i, rec in enumerate(recs):
        noise = noise_floor_v(rec)
        det.warnings += threshold_warnings(rec, definition, noise)
        per_record.append(find_hits(rec, definition, record=i, noise_rms_v=noise))
        det.warnings += _capped(rec, per_record[-1])
        det.notes += [n for n in rec.notes if n not in det.notes and not n.startswith("Vallen")]
    det.hits = sorted((h for hs in per_record for h in hs),
                      key=lambda h: (h.onset_time_s, str(h.channel)))
    _locate(det, path, sensor_xy, velocity_m_s, setup)
    if fingertip:
        det.fingertip = replay_fingertip(recs, per_record, geometry=geometry,
                                         channel_map=channel_map, method=method)
    return det


def _capped(rec: Recording, hits) -> list[str]:
    """A warning for each channel whose hits reached `MAX_HITS_PER_CHANNEL`."""
    n = Counter(h.channel for h in hits)
    return [f"{rec.source}: channel {c}: stopped at {MAX_HITS_PER_CHANNEL} hits (the rest "
            "of the record is not analysed): is the threshold in the noise?"
            for c, k in n.items() if k >= MAX_HITS_PER_CHANNEL]


def _locate(det: Detection, path, sensor_xy, velocity_m_s, setup) -> None:
    if sensor_xy is None:
        setup = setup or setup_beside(path)
        if setup is None:
            if velocity_m_s is not None:
                raise ValueError("velocity_m_s given without sensor positions")
            return
        sensor_xy, v_setup = read_vallen_setup(setup)
        velocity_m_s = v_setup if velocity_m_s is None else velocity_m_s
        det.notes.append(f"sensor positions and {velocity_m_s:g} m/s from {setup}")
    elif isinstance(sensor_xy, str):
        sensor_xy = parse_sensor_xy(sensor_xy)
    if velocity_m_s is None:
        raise ValueError("sensor positions given without velocity_m_s")
    det.events = locate_events(det.hits, sensor_xy, velocity_m_s)


def hit_row(det_source: str, h) -> dict:
    """A hit as a flat dict (`HIT_COLUMNS`)."""
    d = asdict(h)
    d["source"] = det_source
    return {k: d[k] for k in HIT_COLUMNS}


def event_row(det_source: str, e: PlanarEvent) -> dict:
    """A located event as a flat dict (`EVENT_COLUMNS`)."""
    return {"source": det_source, "time_s": e.time_s, "x_m": e.x_m, "y_m": e.y_m,
            "lucy_m": e.lucy_m, "channels": " ".join(map(str, e.channels)),
            "arrival_times_s": " ".join(f"{t:.9f}" for t in e.arrival_times_s),
            "reason": e.reason}


def tables(detections) -> dict[str, list[dict]]:
    """Rows of the hits, located events, contact events and slip events of detections."""
    out = {"hits": [], "events": [], "contacts": [], "slip": []}
    for det in detections:
        out["hits"] += [hit_row(det.source, h) for h in det.hits]
        out["events"] += [event_row(det.source, e) for e in det.events]
        if det.fingertip is not None:
            for key, items in (("contacts", det.fingertip.contacts),
                               ("slip", det.fingertip.slip)):
                out[key] += [{"source": det.source, **contact_row(c)} for c in items]
    return out


def write_detections(detections, path) -> list[Path]:
    """Write detections: .json one document; .csv the hits there and the other tables
    (events, contacts, slip) beside it as ``<stem>.<table>.csv`` when they have rows.

    Parameters
    ----------
    detections : list of Detection
    path : str or os.PathLike

    Returns
    -------
    list of pathlib.Path
        The files written.
    """
    p = Path(path)
    rows = tables(detections)
    if p.suffix.lower() == ".json":
        doc = {"files": [{"source": d.source, "notes": d.notes, "warnings": d.warnings,
                          "hit_definition": asdict(d.definition),
                          "fingertip_counts": dict(d.fingertip.counts) if d.fingertip else None}
                         for d in detections], **rows}
        p.write_text(json.dumps(_json_safe(doc), indent=1) + "\n")
        return [p]
    if p.suffix.lower() != ".csv":
        raise ValueError(f"{path}: write .csv or .json")
    written = [_write_csv(p, rows["hits"], HIT_COLUMNS)]
    for key in ("events", "contacts", "slip"):
        if rows[key]:
            written.append(_write_csv(p.with_name(f"{p.stem}.{key}.csv"), rows[key],
                                      tuple(rows[key][0])))
    return written


def _write_csv(path: Path, rows: list[dict], columns) -> Path:
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(columns))
        w.writeheader()
        w.writerows(rows)
    return path


def _json_safe(v):
    """NaN / inf as null (strict JSON), numpy scalars as Python numbers."""
    if isinstance(v, dict):
        return {str(k): _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    if hasattr(v, "item") and not isinstance(v, (str, bytes)):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


__all__ = ["Detection", "detect", "write_detections", "tables", "Recording", "RecordingError",
           "FINGERTIP_DDT_US"]
