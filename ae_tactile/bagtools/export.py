# SPDX-License-Identifier: Apache-2.0
"""A replay's events out: a CSV file, a new rosbag2 (ContactEvent), a PNG summary."""

from __future__ import annotations

import csv
import math
import sys
from pathlib import Path

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.records import EVENT_NAMES
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
]


def _rows(result: ReplayResult):
    for topic, events in (("contacts", result.contacts), ("slip", result.slip)):
        for e in events:
            cov = np.asarray(e["covariance_m2"], float)
            d = e.get("slip_direction", np.full(3, np.nan))
            yield {
                "time_ns": e["time_ns"],
                "topic": topic,
                "event_type": EVENT_NAMES[e["event_type"]],
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
    """The events as ContactEvent messages on <ns>/contacts and <ns>/slip of a new rosbag2.

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
    ContactEvent = store.types["ae_tactile/msg/ContactEvent"]
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    n = 0
    with Writer(Path(path), version=9, storage_plugin=plugin) as writer:
        conns = {}
        for topic, events in (("contacts", result.contacts), ("slip", result.slip)):
            for e in events:
                full = f"{e['topic_ns']}/{topic}" if e["topic_ns"] else f"/{topic}"
                if full not in conns:
                    conns[full] = writer.add_connection(
                        full, "ae_tactile/msg/ContactEvent", typestore=store
                    )
                writer.write(
                    conns[full],
                    int(e["time_ns"]),
                    store.serialize_cdr(_contact_event(store, e), ContactEvent.__msgtype__),
                )
                n += 1
    return n


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
    )


def write_png(res: ReplayResult, path: str, title: str = "") -> None:
    """PNG summary of a replay (ae_tactile.report): the events on the fingertip from above and
    on a timeline; a missing matplotlib is reported, not raised."""
    events = res.contacts + res.slip
    t0 = min((e["time_ns"] for e in events), default=0)
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
        write_run_summary(
            path, rows, radius_m=geo.radius_m, element_offset_m=geo.element_offset_m, title=title
        )
        print(f"picture of the replay: {path}")
    except ReportUnavailable as exc:
        print(f"ae-tactile-replay: no PNG summary: {exc}", file=sys.stderr)
