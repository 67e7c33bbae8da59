"""Offline replay of recorded raw packets: rosbag2 (sqlite3 or MCAP) -> events, without ROS.

Like velodyne's raw-packet bags, a bag of `PacketArray` can be re-interpreted later with
other parameters: this reads it with the pure-Python `rosbags` library, re-runs the
localization core (any estimator) and the slip detector, and writes the events to a new
rosbag2 (topics `contacts` and `slip`, ContactEvent; same namespace as the packets) or to
a CSV file. The `sensor_info` recorded with the packets (latched by the driver) sets the
geometry, so the bag is self-describing.

    python -m ae_tactile.bagtools IN_BAG OUT(.csv | bag dir) [--method ml] [--storage mcap]
"""
from __future__ import annotations

import argparse
import csv
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ae_tactile.geometry import FingertipGeometry

MSG_NAMES = ("Packet", "PacketArray", "ContactEvent", "ContactState", "SensorInfo")
TOUCH, DETOUCH, SLIP_PRECURSOR, SLIP, TEXTURE = 1, 2, 3, 4, 5
EVENT_NAMES = {TOUCH: "TOUCH", DETOUCH: "DETOUCH", SLIP_PRECURSOR: "SLIP_PRECURSOR", SLIP: "SLIP",
               TEXTURE: "TEXTURE"}


def msg_dir() -> Path:
    """Directory of the package's .msg files (source tree, or the installed share dir)."""
    here = Path(__file__).resolve().parent
    candidates = [here.parent / "msg", here / "msg_definitions"]
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            candidates.append(Path(prefix) / "share" / "ae_tactile" / "msg")
    for c in candidates:
        if (c / "PacketArray.msg").exists():
            return c
    raise FileNotFoundError("ae_tactile .msg definitions not found (source tree or AMENT_PREFIX_PATH)")


def typestore():
    """A rosbags typestore (ROS 2 Kilted) with the ae_tactile messages registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    store = get_typestore(Stores.ROS2_KILTED)
    types = {}
    for name in MSG_NAMES:
        text = (msg_dir() / f"{name}.msg").read_text(encoding="utf-8")
        types.update(get_types_from_msg(text, f"ae_tactile/msg/{name}"))
    store.register(types)
    return store


@dataclass
class ReplayResult:
    """What a replay produced (events as plain dicts, SI units, integer ns)."""

    packets: int = 0
    rejected: dict = field(default_factory=dict)
    contacts: list = field(default_factory=list)
    slip: list = field(default_factory=list)
    geometry: FingertipGeometry | None = None


def _topic_ns(topic: str) -> str:
    return topic.rsplit("/", 1)[0] if "/" in topic.strip("/") else ""


def read_bag(path, store, packet_topic: str | None = None):
    """Yield (topic, msgtype, timestamp_ns, message) for the ae_tactile topics of a bag."""
    from rosbags.highlevel import AnyReader
    with AnyReader([Path(path)], default_typestore=store) as reader:
        conns = [c for c in reader.connections if c.msgtype in
                 ("ae_tactile/msg/PacketArray", "ae_tactile/msg/SensorInfo")
                 and (packet_topic is None or c.msgtype != "ae_tactile/msg/PacketArray" or c.topic == packet_topic)]
        for conn, t_ns, raw in reader.messages(connections=conns):
            yield conn.topic, conn.msgtype, t_ns, reader.deserialize(raw, conn.msgtype)


def replay(path, *, method: str = "ml", packet_topic: str | None = None, slip_config=None,
           localize_options: dict | None = None) -> ReplayResult:
    """Re-localize every PacketArray of a bag and run the slip detector over the events."""
    from ae_tactile.localization import Localizer, Reason
    from ae_tactile.slip import LocalizedEvent, SlipConfig, SlipDetector
    store = typestore()
    loc = Localizer(method, **(localize_options or {}))
    det = SlipDetector(slip_config or SlipConfig())
    out = ReplayResult(geometry=FingertipGeometry())
    gains = None
    frame = ""
    for topic, msgtype, _, msg in read_bag(path, store, packet_topic):
        if msgtype.endswith("SensorInfo"):
            out.geometry = FingertipGeometry(msg.radius_m, msg.element_offset_m, msg.sound_speed_m_s)
            g = np.asarray(msg.channel_gains, dtype=float)
            gains = g if g.shape == (4,) and np.all(g > 0) else None
            continue
        frame = msg.header.frame_id
        groups: dict = {}
        for p in msg.packets:
            out.packets += 1
            x = np.asarray(p.samples, dtype=np.float32)
            n = int(p.samples_per_channel)
            if int(p.channel_count) != 4 or x.size != 4 * n:
                out.rejected["MALFORMED"] = out.rejected.get("MALFORMED", 0) + 1
                continue
            groups.setdefault((n, float(p.sample_rate_hz)), []).append((p, x.reshape(4, n)))
        for (_, fs), items in groups.items():
            res = loc(np.stack([x for _, x in items]), fs, np.array([p.onset_index for p, _ in items]),
                      geometry=out.geometry, channel_gains=gains,
                      saturated=np.array([bool(p.saturated) for p, _ in items]))
            travel = out.geometry.arrival_times_s(np.nan_to_num(res.point_m)).min(axis=-1)
            for i, (p, _) in enumerate(items):
                if not res.accepted[i]:
                    name = Reason(int(res.reason[i])).name
                    out.rejected[name] = out.rejected.get(name, 0) + 1
                    continue
                stamp = int(p.stamp.sec) * 1_000_000_000 + int(p.stamp.nanosec)
                t_ns = stamp + int(round(int(p.onset_index) * 1e9 / fs - travel[i] * 1e9))
                out.contacts.append({
                    "time_ns": t_ns, "frame_id": frame, "topic_ns": _topic_ns(topic),
                    "event_type": DETOUCH if res.polarity[i] < 0 else TOUCH,
                    "point_m": res.point_m[i].copy(), "covariance_m2": res.covariance_m2[i].copy(),
                    "tau_x_s": float(res.tau_x_s[i]), "tau_y_s": float(res.tau_y_s[i]),
                    "amplitude_v": float(res.amplitude_v[i]), "confidence": float(res.confidence[i]),
                    "packet_id": int(p.sequence_id)})
    out.contacts.sort(key=lambda e: e["time_ns"])
    for e in out.contacts:
        ev = LocalizedEvent(time_ns=e["time_ns"], point_m=e["point_m"], covariance_m2=e["covariance_m2"],
                            polarity=1 if e["event_type"] == TOUCH else -1, amplitude_v=e["amplitude_v"],
                            confidence=e["confidence"], packet_id=e["packet_id"])
        for s in det.process(ev):
            out.slip.append({"time_ns": int(s.time_ns), "frame_id": e["frame_id"], "topic_ns": e["topic_ns"],
                             "event_type": int(s.kind), "point_m": np.asarray(s.position_m, float),
                             "covariance_m2": np.asarray(s.covariance_m2, float), "tau_x_s": math.nan,
                             "tau_y_s": math.nan, "amplitude_v": math.nan, "confidence": float(s.confidence),
                             "packet_ids": [int(i) for i in s.packet_ids],
                             "emission_rate_hz": float(s.emission_rate_hz),
                             "spatial_period_m": float(s.spatial_period_m),
                             "slip_direction": np.asarray(s.slip_direction, float)})
    return out


CSV_FIELDS = ["time_ns", "topic", "event_type", "x_m", "y_m", "z_m", "sigma_xy_m", "tau_x_s", "tau_y_s",
              "amplitude_v", "confidence", "packet_ids", "emission_rate_hz", "spatial_period_m",
              "slip_dir_x", "slip_dir_y", "slip_dir_z"]


def _rows(result: ReplayResult):
    for topic, events in (("contacts", result.contacts), ("slip", result.slip)):
        for e in events:
            cov = np.asarray(e["covariance_m2"], float)
            d = e.get("slip_direction", np.full(3, np.nan))
            yield {"time_ns": e["time_ns"], "topic": topic, "event_type": EVENT_NAMES[e["event_type"]],
                   "x_m": e["point_m"][0], "y_m": e["point_m"][1], "z_m": e["point_m"][2],
                   "sigma_xy_m": math.sqrt(max(cov[0, 0] + cov[1, 1], 0.0) / 2.0),
                   "tau_x_s": e["tau_x_s"], "tau_y_s": e["tau_y_s"], "amplitude_v": e["amplitude_v"],
                   "confidence": e["confidence"],
                   "packet_ids": " ".join(map(str, e.get("packet_ids", [e.get("packet_id")]))),
                   "emission_rate_hz": e.get("emission_rate_hz", math.nan),
                   "spatial_period_m": e.get("spatial_period_m", math.nan),
                   "slip_dir_x": d[0], "slip_dir_y": d[1], "slip_dir_z": d[2]}


def write_csv(result: ReplayResult, path) -> int:
    rows = sorted(_rows(result), key=lambda r: r["time_ns"])
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=CSV_FIELDS)
        w.writeheader()
        w.writerows(rows)
    return len(rows)


def write_bag(result: ReplayResult, path, storage: str = "sqlite3") -> int:
    """The events as ContactEvent messages on <ns>/contacts and <ns>/slip of a new rosbag2."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    store = typestore()
    ContactEvent = store.types["ae_tactile/msg/ContactEvent"]
    Header = store.types["std_msgs/msg/Header"]
    Time = store.types["builtin_interfaces/msg/Time"]
    Point = store.types["geometry_msgs/msg/Point"]
    Vector3 = store.types["geometry_msgs/msg/Vector3"]
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    n = 0
    with Writer(Path(path), version=9, storage_plugin=plugin) as writer:
        conns = {}
        for topic, events in (("contacts", result.contacts), ("slip", result.slip)):
            for e in events:
                full = f"{e['topic_ns']}/{topic}" if e["topic_ns"] else f"/{topic}"
                if full not in conns:
                    conns[full] = writer.add_connection(full, "ae_tactile/msg/ContactEvent", typestore=store)
                sec, nsec = divmod(int(e["time_ns"]), 1_000_000_000)
                p = e["point_m"]
                d = e.get("slip_direction", np.full(3, np.nan))
                x, y, z = (float(v) for v in p)
                msg = ContactEvent(
                    header=Header(stamp=Time(sec=sec, nanosec=nsec), frame_id=e["frame_id"]),
                    event_type=e["event_type"], position=Point(x=x, y=y, z=z),
                    position_covariance=np.asarray(e["covariance_m2"], np.float64).ravel(),
                    polar_angle_rad=math.atan2(math.hypot(x, y), z), azimuth_angle_rad=math.atan2(y, x),
                    tau_x_s=e["tau_x_s"], tau_y_s=e["tau_y_s"], amplitude_v=e["amplitude_v"],
                    confidence=e["confidence"],
                    packet_ids=np.asarray(e.get("packet_ids", [e.get("packet_id", 0)]), np.uint64),
                    emission_rate_hz=e.get("emission_rate_hz", math.nan),
                    spatial_period_m=e.get("spatial_period_m", math.nan),
                    slip_direction=Vector3(x=float(d[0]), y=float(d[1]), z=float(d[2])))
                writer.write(conns[full], int(e["time_ns"]), store.serialize_cdr(msg, ContactEvent.__msgtype__))
                n += 1
    return n


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="ae-tactile-replay", description=__doc__.split("\n\n")[0])
    ap.add_argument("bag", help="input rosbag2 directory (or .mcap / .db3 file) with PacketArray")
    ap.add_argument("out", help="output: a .csv file, or a new rosbag2 directory")
    from ae_tactile.localization import available_methods
    ap.add_argument("--method", default="ml", choices=available_methods(), help="localization estimator")
    ap.add_argument("--topic", default=None, help="PacketArray topic (default: all)")
    ap.add_argument("--storage", default="sqlite3", choices=("sqlite3", "mcap"), help="output bag storage")
    ap.add_argument("--sliding-speed", type=float, default=0.0, help="known sliding speed (m/s) for textures")
    args = ap.parse_args(argv)
    from ae_tactile.slip import SlipConfig
    cfg = SlipConfig(sliding_speed_m_s=args.sliding_speed or None)
    try:
        res = replay(args.bag, method=args.method, packet_topic=args.topic, slip_config=cfg)
    except (FileNotFoundError, ValueError) as exc:
        print(f"ae-tactile-replay: {exc}", file=sys.stderr)
        return 2
    if args.out.endswith(".csv"):
        n = write_csv(res, args.out)
    else:
        n = write_bag(res, args.out, args.storage)
    print(f"{res.packets} packets -> {len(res.contacts)} contact events, {len(res.slip)} slip events "
          f"({n} written to {args.out}); rejected: {res.rejected or 'none'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
