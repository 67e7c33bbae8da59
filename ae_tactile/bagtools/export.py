# SPDX-License-Identifier: Apache-2.0
"""A replay's events out: a CSV file, a new rosbag2 (Emission, ContactEvent), a PNG summary."""

from __future__ import annotations

import csv
import math
import sys
from pathlib import Path

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.records import EVENT_NAMES, READING_NAMES
from ae_tactile.report import ReportUnavailable, write_run_summary

from .reader import ReplayResult, typestore

CSV_FIELDS = [
    "time_ns",
    "topic",
    "event_type",
    "x_m",
    "y_m",
    "z_m",
    "sigma_xy_m",
    "tau_x_s",
    "tau_y_s",
    "amplitude_v",
    "confidence",
    "packet_ids",
    "emission_rate_hz",
    "spatial_period_m",
    "slip_dir_x",
    "slip_dir_y",
    "slip_dir_z",
    "polarity",
    "reading",
    "contact_id",
]

#: (topic, ReplayResult field, message type) of what a replay writes
OUTPUTS = (
    ("emissions", "contacts", "Emission"),
    ("contacts", "contact_events", "ContactEvent"),
    ("slip", "slip", "ContactEvent"),
)


def _rows(result: ReplayResult):
    for topic, attr, msgtype in OUTPUTS:
        for e in getattr(result, attr):
            cov = np.asarray(e["covariance_m2"], float)
            d = e.get("slip_direction", np.full(3, np.nan))
            yield {
                "time_ns": e["time_ns"],
                "topic": topic,
                "event_type": "EMISSION" if msgtype == "Emission"
                else EVENT_NAMES[e["event_type"]],
                "x_m": e["point_m"][0],
                "y_m": e["point_m"][1],
                "z_m": e["point_m"][2],
                "sigma_xy_m": math.sqrt(max(cov[0, 0] + cov[1, 1], 0.0) / 2.0),
                "tau_x_s": e["tau_x_s"],
                "tau_y_s": e["tau_y_s"],
                "amplitude_v": e["amplitude_v"],
                "confidence": e["confidence"],
                "packet_ids": " ".join(map(str, e.get("packet_ids", [e.get("packet_id")]))),
                "emission_rate_hz": e.get("emission_rate_hz", math.nan),
                "spatial_period_m": e.get("spatial_period_m", math.nan),
                "slip_dir_x": d[0],
                "slip_dir_y": d[1],
                "slip_dir_z": d[2],
                "polarity": e.get("polarity", ""),
                "reading": READING_NAMES.get(e["reading"], "") if "reading" in e else "",
                "contact_id": e.get("contact_id", ""),
            }


def write_csv(result: ReplayResult, path) -> int:
    """The events, one row each (CSV_FIELDS), in time order.

    Parameters
    ----------
    result : ReplayResult
        What `replay` produced.
    path : str or os.PathLike
        The CSV file.

    Returns
    -------
    int
        Rows written.
    """
    rows = sorted(_rows(result), key=lambda r: r["time_ns"])
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=CSV_FIELDS)
        w.writeheader()
        w.writerows(rows)
    return len(rows)


def write_bag(result: ReplayResult, path, storage: str = "sqlite3") -> int:
    """The emissions (Emission, <ns>/emissions) and events (ContactEvent, <ns>/contacts: a
    contact's begin / end; <ns>/slip) of a replay, in a new rosbag2.

    Parameters
    ----------
    result : ReplayResult
        What `replay` produced.
    path : str or os.PathLike
        The new bag's directory (must not exist).
    storage : str
        "sqlite3" or "mcap".

    Returns
    -------
    int
        Messages written.
    """
    # lazy: rosbags is an optional dependency (the 'bag' extra)
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    build = {"Emission": _emission, "ContactEvent": _contact_event}
    n = 0
    with Writer(Path(path), version=9, storage_plugin=plugin) as writer:
        conns = {}
        for topic, attr, msgtype in OUTPUTS:
            full_type = f"ae_tactile/msg/{msgtype}"
            for e in getattr(result, attr):
                full = f"{e['topic_ns']}/{topic}" if e["topic_ns"] else f"/{topic}"
                if full not in conns:
                    conns[full] = writer.add_connection(full, full_type, typestore=store)
                writer.write(
                    conns[full],
                    int(e["time_ns"]),
                    store.serialize_cdr(build[msgtype](store, e), full_type),
                )
                n += 1
    return n


def _emission(store, e: dict):
    """One emission dict as a rosbags Emission message."""
    Emission = store.types["ae_tactile/msg/Emission"]
    Header = store.types["std_msgs/msg/Header"]
    Time = store.types["builtin_interfaces/msg/Time"]
    Point = store.types["geometry_msgs/msg/Point"]
    sec, nsec = divmod(int(e["time_ns"]), 1_000_000_000)
    x, y, z = (float(v) for v in e["point_m"])
    return Emission(
        header=Header(stamp=Time(sec=sec, nanosec=nsec), frame_id=e["frame_id"]),
        device_time_ns=int(e.get("device_time_ns", -1)),
        packet_ids=np.asarray(e.get("packet_ids", [e.get("packet_id", 0)]), np.uint64),
        position=Point(x=x, y=y, z=z),
        position_covariance=np.asarray(e["covariance_m2"], np.float64).ravel(),
        polar_angle_rad=math.atan2(math.hypot(x, y), z),
        azimuth_angle_rad=math.atan2(y, x),
        tau_x_s=e["tau_x_s"],
        tau_y_s=e["tau_y_s"],
        polarity=int(e.get("polarity", -1 if e["event_type"] == 2 else 1)),
        amplitude_v=e["amplitude_v"],
        confidence=e["confidence"],
        reading=int(e.get("reading", 0)),
        contact_id=int(e.get("contact_id", 0)),
    )


def _contact_event(store, e: dict):
    """One event dict as a rosbags ContactEvent message."""
    ContactEvent = store.types["ae_tactile/msg/ContactEvent"]
    Header = store.types["std_msgs/msg/Header"]
    Time = store.types["builtin_interfaces/msg/Time"]
    Point = store.types["geometry_msgs/msg/Point"]
    Vector3 = store.types["geometry_msgs/msg/Vector3"]
    sec, nsec = divmod(int(e["time_ns"]), 1_000_000_000)
    p = e["point_m"]
    d = e.get("slip_direction", np.full(3, np.nan))
    x, y, z = (float(v) for v in p)
    return ContactEvent(
        header=Header(stamp=Time(sec=sec, nanosec=nsec), frame_id=e["frame_id"]),
        event_type=e["event_type"],
        position=Point(x=x, y=y, z=z),
        position_covariance=np.asarray(e["covariance_m2"], np.float64).ravel(),
        polar_angle_rad=math.atan2(math.hypot(x, y), z),
        azimuth_angle_rad=math.atan2(y, x),
        tau_x_s=e["tau_x_s"],
        tau_y_s=e["tau_y_s"],
        amplitude_v=e["amplitude_v"],
        confidence=e["confidence"],
        packet_ids=np.asarray(e.get("packet_ids", [e.get("packet_id", 0)]), np.uint64),
        emission_rate_hz=e.get("emission_rate_hz", math.nan),
        spatial_period_m=e.get("spatial_period_m", math.nan),
        slip_direction=Vector3(x=float(d[0]), y=float(d[1]), z=float(d[2])),
        contact_id=int(e.get("contact_id", 0)),
    )


def write_png(res: ReplayResult, path: str, title: str = "") -> None:
    """PNG summary of a replay (ae_tactile.report): the contacts' begin / end and the slip
    events on the fingertip from above and on a timeline, the emissions as dots; a missing
    matplotlib is reported, not raised."""
    events = res.contact_events + res.slip
    t0 = min((e["time_ns"] for e in events + res.contacts), default=0)
    rows = [
        {
            "time_s": (e["time_ns"] - t0) * 1e-9,
            "type": int(e["event_type"]),
            "x_m": float(e["point_m"][0]),
            "y_m": float(e["point_m"][1]),
            "z_m": float(e["point_m"][2]),
        }
        for e in events
        if "point_m" in e
    ]
    geo = res.geometry or FingertipGeometry()
    try:
        emissions = [{"time_s": (e["time_ns"] - t0) * 1e-9, "x_m": float(e["point_m"][0]),
                      "y_m": float(e["point_m"][1])} for e in res.contacts]
        write_run_summary(
            path, rows, emissions=emissions, radius_m=geo.radius_m,
            element_offset_m=geo.element_offset_m, title=title
        )
        print(f"picture of the replay: {path}")
    except ReportUnavailable as exc:
        print(f"ae-tactile-replay: no PNG summary: {exc}", file=sys.stderr)
