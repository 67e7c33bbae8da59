# SPDX-License-Identifier: Apache-2.0
"""Offline replay of recorded raw packets: rosbag2 (sqlite3 or MCAP) -> events, without ROS.

Like velodyne's raw-packet bags, a bag of `PacketArray` can be re-interpreted later with
other parameters: this reads it with the pure-Python `rosbags` library, re-runs the
localization core (any estimator) and the slip detector, and writes the events to a new
rosbag2 (topics `contacts` and `slip`, ContactEvent; same namespace as the packets) or to
a CSV file. The `sensor_info` recorded with the packets (latched by the driver) sets the
geometry, so the bag is self-describing.

    python -m ae_tactile.bagtools IN_BAG OUT(.csv | bag dir) [--method ml] [--storage mcap]

Damaged bags: what is readable is recovered. A bag that rosbags cannot open or stops
reading (truncated by a crash or a full disk, corrupted pages) is read again record by
record (sqlite3: row by row around the damaged pages; MCAP: the records up to the
damage, without the summary section). Messages of other types are skipped and counted,
messages that do not deserialize are counted, and every packet is checked on its own
(sample rate > 0 and finite, 4 channels, sizes, finite samples, onset in range): a bad
one is rejected with its reason, never the whole replay. The replay ends with a summary.

Exit codes of the command: 0 the bag was read completely; 3 the bag is damaged or had
undecodable messages: the events of what was readable were written, the summary says
what was lost; 2 nothing to replay (input missing or unreadable, bad arguments) or the
output could not be written.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sqlite3
import struct
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.records import EVENT_NAMES, EventType

MSG_NAMES = ("Packet", "PacketArray", "ContactEvent", "ContactState", "SensorInfo")
TOUCH, DETOUCH = int(EventType.TOUCH), int(EventType.DETOUCH)


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
    raise FileNotFoundError(
        "ae_tactile .msg definitions not found (source tree or AMENT_PREFIX_PATH)"
    )


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
    """What a replay produced (events as plain dicts, SI units, integer ns).

    rejected: packets refused, by reason. skipped: messages of other types, by type.
    undecodable: messages that did not deserialize, by type. read_errors: what stopped
    or hampered reading the bag (damage). recovered: messages read by the record-by-record
    fallback after the normal reader failed.
    """

    packets: int = 0
    rejected: dict = field(default_factory=dict)
    contacts: list = field(default_factory=list)
    slip: list = field(default_factory=list)
    geometry: FingertipGeometry | None = None
    skipped: dict = field(default_factory=dict)
    undecodable: dict = field(default_factory=dict)
    read_errors: list = field(default_factory=list)
    recovered: int = 0

    @property
    def damaged(self) -> bool:
        """True if anything in the bag could not be read or decoded."""
        return bool(self.read_errors or self.undecodable)

    def summary(self) -> str:
        lines = [
            f"{self.packets} packets -> {len(self.contacts)} contact events,"
            f" {len(self.slip)} slip events; rejected: {self.rejected or 'none'}"
        ]
        if self.skipped:
            lines.append(f"skipped messages of other types: {self.skipped}")
        if self.undecodable:
            lines.append(f"undecodable messages: {self.undecodable}")
        if self.read_errors:
            lines.append(
                f"bag damaged ({len(self.read_errors)} read error(s)): "
                + "; ".join(self.read_errors[:5])
            )
            lines.append(f"{self.recovered} message(s) recovered record by record")
        return "\n".join(lines)


def _count(d: dict, key, n: int = 1) -> None:
    d[key] = d.get(key, 0) + n


def _topic_ns(topic: str) -> str:
    return topic.rsplit("/", 1)[0] if "/" in topic.strip("/") else ""


WANTED = ("ae_tactile/msg/PacketArray", "ae_tactile/msg/SensorInfo")


def read_bag(path, store, packet_topic: str | None = None, report: ReplayResult | None = None):
    """Yield (topic, msgtype, timestamp_ns, message) for the ae_tactile topics of a bag.

    Never raises for a damaged bag when ``report`` is given: read errors, skipped and
    undecodable messages are recorded there, and if the normal reader (rosbags) fails,
    the rest is read record by record (`_raw_messages`)."""
    report = report if report is not None else ReplayResult()

    def wanted(topic, msgtype):
        return msgtype in WANTED and (
            packet_topic is None or msgtype != WANTED[0] or topic == packet_topic
        )

    seen: set = set()
    try:
        from rosbags.highlevel import AnyReader

        with AnyReader([Path(path)], default_typestore=store) as reader:
            conns = []
            for c in reader.connections:
                if wanted(c.topic, c.msgtype):
                    conns.append(c)
                else:
                    _count(report.skipped, c.msgtype, int(getattr(c, "msgcount", 0) or 0))
            if not conns:  # (an empty list would mean "all connections" to rosbags)
                return
            for conn, t_ns, raw in reader.messages(connections=conns):
                seen.add((conn.topic, int(t_ns), len(raw)))
                msg = _deserialize(store, raw, conn.msgtype, report)
                if msg is not None:
                    yield conn.topic, conn.msgtype, t_ns, msg
        return
    except FileNotFoundError:
        if not Path(path).exists():
            raise
        report.read_errors.append("file missing")
    except Exception as exc:  # noqa: BLE001 - a damaged bag: fall back below
        report.read_errors.append(f"{type(exc).__name__}: {exc}")
    skipped_before = dict(report.skipped)
    report.skipped.clear()
    n_raw = 0
    for topic, msgtype, t_ns, raw in _raw_messages(Path(path), report):
        if not wanted(topic, msgtype):
            _count(report.skipped, msgtype)
            continue
        if (topic, int(t_ns), len(raw)) in seen:
            continue  # already delivered by the normal reader
        n_raw += 1
        msg = _deserialize(store, raw, msgtype, report)
        if msg is not None:
            yield topic, msgtype, t_ns, msg
    report.recovered += n_raw
    if not report.skipped:
        report.skipped.update(skipped_before)


def _deserialize(store, raw, msgtype: str, report: ReplayResult):
    try:
        return store.deserialize_cdr(bytes(raw), msgtype)
    except Exception:  # noqa: BLE001 - corrupted or foreign bytes
        _count(report.undecodable, msgtype)
        return None


def _bag_files(path: Path, suffix: str) -> list[Path]:
    if path.is_file():
        return [path] if path.suffix == suffix else []
    return sorted(path.glob(f"*{suffix}")) if path.is_dir() else []


def _raw_messages(path: Path, report: ReplayResult):
    """(topic, msgtype, timestamp_ns, cdr bytes) of every record still readable."""
    for f in _bag_files(path, ".db3"):
        yield from _raw_sqlite(f, report)
    for f in _bag_files(path, ".mcap"):
        yield from _raw_mcap(f, report)


def _raw_sqlite(f: Path, report: ReplayResult):
    """Rows of a rosbag2 sqlite3 file, stepping over damaged pages (bounded probing).

    A file cut short is read from a copy padded with zero pages up to the size its
    header states (SQLite refuses the short file as a whole; the zero pages then fail
    alone and are stepped over)."""
    import shutil
    import tempfile

    with tempfile.TemporaryDirectory(prefix="ae_tactile_bag_") as tmp:
        try:
            with open(f, "rb") as fh:
                head = fh.read(100)
            size = f.stat().st_size
            page = struct.unpack_from(">H", head, 16)[0] if len(head) >= 100 else 0
            page = 65536 if page == 1 else page
            pages = struct.unpack_from(">I", head, 28)[0] if len(head) >= 100 else 0
            if head.startswith(b"SQLite format 3\0") and page and size < page * pages <= 1 << 34:
                padded = Path(tmp) / f.name
                shutil.copyfile(f, padded)
                with open(padded, "r+b") as fh:
                    fh.truncate(page * pages)
                report.read_errors.append(f"{f.name}: cut short at {size} of {page * pages} bytes")
                f = padded
        except OSError as exc:
            report.read_errors.append(f"{f.name}: {exc}")
            return
        yield from _sqlite_rows(f, report)


def _sqlite_rows(f: Path, report: ReplayResult):
    try:
        con = sqlite3.connect(f"file:{f}?mode=ro", uri=True)
    except sqlite3.Error as exc:
        report.read_errors.append(f"{f.name}: {exc}")
        return
    try:
        try:
            topics = {
                int(i): (n, t) for i, n, t in con.execute("SELECT id, name, type FROM topics")
            }
        except sqlite3.Error as exc:
            report.read_errors.append(f"{f.name}: topics table unreadable: {exc}")
            return
        last, probes = 0, 0
        while probes < 64:
            try:
                for rid, tid, t_ns, data in con.execute(
                    "SELECT id, topic_id, timestamp, data FROM messages WHERE id > ? ORDER BY id",
                    (last,),
                ):
                    last = int(rid)
                    name, msgtype = topics.get(int(tid), (None, None))
                    if name is None:
                        _count(report.undecodable, f"topic id {tid}")
                        continue
                    yield name, msgtype, int(t_ns), data
                break
            except sqlite3.Error as exc:
                if probes == 0:
                    report.read_errors.append(f"{f.name}: rows after id {last}: {exc}")
                probes += 1
                last += 1 << probes if probes < 20 else 1 << 20  # step over the damage
    finally:
        con.close()


_MCAP_MAGIC = b"\x89MCAP0\r\n"


def _raw_mcap(f: Path, report: ReplayResult):
    """Schema, channel and message records of an MCAP file, up to the first damage."""
    try:
        data = f.read_bytes()
    except OSError as exc:
        report.read_errors.append(f"{f.name}: {exc}")
        return
    if not data.startswith(_MCAP_MAGIC):
        report.read_errors.append(f"{f.name}: not an MCAP file")
        return
    schemas: dict = {}
    channels: dict = {}
    yield from _mcap_records(
        memoryview(data), len(_MCAP_MAGIC), len(data), schemas, channels, report, f.name
    )


def _mcap_str(mv, i):
    (n,) = struct.unpack_from("<I", mv, i)
    return bytes(mv[i + 4 : i + 4 + n]).decode("utf-8", "replace"), i + 4 + n


def _mcap_records(mv, i, end, schemas, channels, report, name):
    while i + 9 <= end:
        op = mv[i]
        (n,) = struct.unpack_from("<Q", mv, i + 1)
        body, i_next = i + 9, i + 9 + n
        if i_next > end:
            report.read_errors.append(f"{name}: record 0x{op:02x} at byte {i} cut short")
            if op != 0x06:
                return
            i_next = end  # a chunk cut short: its complete records still count
        try:
            if op == 0x03:  # Schema
                (sid,) = struct.unpack_from("<H", mv, body)
                sname, _ = _mcap_str(mv, body + 2)
                schemas[sid] = sname
            elif op == 0x04:  # Channel
                cid, sid = struct.unpack_from("<HH", mv, body)
                topic, _ = _mcap_str(mv, body + 4)
                channels[cid] = (topic, schemas.get(sid, ""))
            elif op == 0x05:  # Message
                cid, _, log_time, _ = struct.unpack_from("<HIQQ", mv, body)
                if cid in channels:
                    topic, msgtype = channels[cid]
                    yield topic, msgtype, int(log_time), bytes(mv[body + 22 : i_next])
                else:
                    _count(report.undecodable, f"channel {cid}")
            elif op == 0x06:  # Chunk
                comp, j = _mcap_str(mv, body + 28)
                (clen,) = struct.unpack_from("<Q", mv, j)
                if comp:
                    _count(report.undecodable, f"{comp}-compressed chunk")
                else:
                    yield from _mcap_records(
                        mv, j + 8, min(j + 8 + clen, i_next), schemas, channels, report, name
                    )
            elif op == 0x02:  # Footer
                return
        except (struct.error, IndexError) as exc:
            report.read_errors.append(f"{name}: record 0x{op:02x} at byte {i}: {exc}")
            return
        i = i_next


def check_packet(p) -> tuple[str | None, np.ndarray | None, float]:
    """(reason or None, samples (4, N) float32, sample rate) of one recorded Packet."""
    try:
        n = int(p.samples_per_channel)
        x = np.asarray(p.samples, dtype=np.float32)
        fs = float(p.sample_rate_hz)
        onset = int(p.onset_index)
        if int(p.channel_count) != 4 or n < 1 or x.size != 4 * n:
            return "MALFORMED", None, 0.0
    except (TypeError, ValueError, OverflowError):
        return "MALFORMED", None, 0.0
    if not (math.isfinite(fs) and fs > 0):
        return "BAD_SAMPLE_RATE", None, 0.0
    if not 0 <= onset < n:
        return "BAD_ONSET_INDEX", None, 0.0
    if not np.isfinite(x).all():
        return "NON_FINITE_SAMPLES", None, 0.0
    return None, x.reshape(4, n), fs


def replay(
    path,
    *,
    method: str = "ml",
    packet_topic: str | None = None,
    slip_config=None,
    localize_options: dict | None = None,
) -> ReplayResult:
    """Re-localize every PacketArray of a bag and run the slip detector over the events.

    Damaged bags, foreign messages and bad packets are counted in the result (see
    `ReplayResult`), never raised; FileNotFoundError if ``path`` does not exist."""
    from ae_tactile.localization import Localizer, Reason
    from ae_tactile.slip import LocalizedEvent, SlipConfig, SlipDetector

    if not Path(path).exists():
        raise FileNotFoundError(f"no such bag: {path}")
    store = typestore()
    loc = Localizer(method, **(localize_options or {}))
    det = SlipDetector(slip_config or SlipConfig())
    out = ReplayResult(geometry=FingertipGeometry())
    gains = None
    frame = ""
    for topic, msgtype, _, msg in read_bag(path, store, packet_topic, out):
        if msgtype.endswith("SensorInfo"):
            try:
                geo = FingertipGeometry(msg.radius_m, msg.element_offset_m, msg.sound_speed_m_s)
            except Exception:  # noqa: BLE001 - values out of range
                _count(out.undecodable, f"{msgtype} (invalid values, ignored)")
                continue
            out.geometry = geo
            g = np.asarray(msg.channel_gains, dtype=float)
            gains = g if g.shape == (4,) and np.all(g > 0) and np.all(np.isfinite(g)) else None
            continue
        try:
            frame = str(msg.header.frame_id)
            packets = list(msg.packets)
        except Exception:  # noqa: BLE001 - a foreign definition
            _count(out.undecodable, msgtype)
            continue
        groups: dict = {}
        for p in packets:
            out.packets += 1
            reason, x, fs = check_packet(p)
            if reason is not None:
                _count(out.rejected, reason)
                continue
            groups.setdefault((x.shape[1], fs), []).append((p, x))
        for (_, fs), items in groups.items():
            for sub, res in _localize(loc, items, fs, out.geometry, gains, out):
                _contacts(out, sub, res, fs, frame, topic, Reason)
    out.contacts.sort(key=lambda e: e["time_ns"])
    for e in out.contacts:
        ev = LocalizedEvent(
            time_ns=e["time_ns"],
            point_m=e["point_m"],
            covariance_m2=e["covariance_m2"],
            polarity=1 if e["event_type"] == TOUCH else -1,
            amplitude_v=e["amplitude_v"],
            confidence=e["confidence"],
            packet_id=e["packet_id"],
        )
        try:
            slips = det.process(ev)
        except Exception:  # noqa: BLE001 - counted, replay goes on
            _count(out.rejected, "SLIP_DETECTOR_ERROR")
            continue
        for s in slips:
            out.slip.append(
                {
                    "time_ns": int(s.time_ns),
                    "frame_id": e["frame_id"],
                    "topic_ns": e["topic_ns"],
                    "event_type": int(s.kind),
                    "point_m": np.asarray(s.position_m, float),
                    "covariance_m2": np.asarray(s.covariance_m2, float),
                    "tau_x_s": math.nan,
                    "tau_y_s": math.nan,
                    "amplitude_v": math.nan,
                    "confidence": float(s.confidence),
                    "packet_ids": [int(i) for i in s.packet_ids],
                    "emission_rate_hz": float(s.emission_rate_hz),
                    "spatial_period_m": float(s.spatial_period_m),
                    "slip_direction": np.asarray(s.slip_direction, float),
                }
            )
    return out


def _localize(loc, items, fs, geometry, gains, out):
    """Localize a group of packets; if the estimator raises, each packet on its own."""

    def run(group):
        onsets = np.array([int(p.onset_index) for p, _ in group])
        return loc(
            np.stack([x for _, x in group]),
            fs,
            onsets,
            geometry=geometry,
            channel_gains=gains,
            saturated=np.array([bool(p.saturated) for p, _ in group]),
        )

    try:
        return [(items, run(items))]
    except Exception:  # noqa: BLE001
        done = []
        for item in items:
            try:
                done.append(([item], run([item])))
            except Exception:  # noqa: BLE001
                _count(out.rejected, "LOCALIZER_ERROR")
        return done


def _contacts(out, items, res, fs, frame, topic, Reason):
    travel = out.geometry.arrival_times_s(np.nan_to_num(res.point_m)).min(axis=-1)
    for i, (p, _) in enumerate(items):
        if not res.accepted[i]:
            _count(out.rejected, Reason(int(res.reason[i])).name)
            continue
        if not (np.all(np.isfinite(res.point_m[i])) and np.isfinite(travel[i])):
            _count(out.rejected, "NON_FINITE_RESULT")
            continue
        stamp = int(p.stamp.sec) * 1_000_000_000 + int(p.stamp.nanosec)
        t_ns = stamp + int(round(int(p.onset_index) * 1e9 / fs - travel[i] * 1e9))
        out.contacts.append(
            {
                "time_ns": t_ns,
                "frame_id": frame,
                "topic_ns": _topic_ns(topic),
                "event_type": DETOUCH if res.polarity[i] < 0 else TOUCH,
                "point_m": res.point_m[i].copy(),
                "covariance_m2": res.covariance_m2[i].copy(),
                "tau_x_s": float(res.tau_x_s[i]),
                "tau_y_s": float(res.tau_y_s[i]),
                "amplitude_v": float(res.amplitude_v[i]),
                "confidence": float(res.confidence[i]),
                "packet_id": int(p.sequence_id),
            }
        )


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
                    conns[full] = writer.add_connection(
                        full, "ae_tactile/msg/ContactEvent", typestore=store
                    )
                sec, nsec = divmod(int(e["time_ns"]), 1_000_000_000)
                p = e["point_m"]
                d = e.get("slip_direction", np.full(3, np.nan))
                x, y, z = (float(v) for v in p)
                msg = ContactEvent(
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
                writer.write(
                    conns[full],
                    int(e["time_ns"]),
                    store.serialize_cdr(msg, ContactEvent.__msgtype__),
                )
                n += 1
    return n


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="ae-tactile-replay", description=__doc__.split("\n\n")[0])
    ap.add_argument("bag", help="input rosbag2 directory (or .mcap / .db3 file) with PacketArray")
    ap.add_argument("out", help="output: a .csv file, or a new rosbag2 directory")
    from ae_tactile.localization import available_methods

    ap.add_argument(
        "--method", default="ml", choices=available_methods(), help="localization estimator"
    )
    ap.add_argument("--topic", default=None, help="PacketArray topic (default: all)")
    ap.add_argument(
        "--storage", default="sqlite3", choices=("sqlite3", "mcap"), help="output bag storage"
    )
    ap.add_argument(
        "--sliding-speed", type=float, default=0.0, help="known sliding speed (m/s) for textures"
    )
    ap.add_argument(
        "--png", default="", help="also write a PNG summary of the replay (needs matplotlib)"
    )
    args = ap.parse_args(argv)
    from ae_tactile.slip import SlipConfig

    cfg = SlipConfig(sliding_speed_m_s=args.sliding_speed or None)
    try:
        res = replay(args.bag, method=args.method, packet_topic=args.topic, slip_config=cfg)
    except (FileNotFoundError, ValueError) as exc:
        print(f"ae-tactile-replay: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - a summary, no traceback
        print(
            f"ae-tactile-replay: cannot replay {args.bag}: {type(exc).__name__}: {exc}",
            file=sys.stderr,
        )
        return 2
    if res.damaged and not res.packets and not res.contacts:
        print(
            f"ae-tactile-replay: nothing readable in {args.bag}\n{res.summary()}", file=sys.stderr
        )
        return 2
    try:
        if args.out.endswith(".csv"):
            n = write_csv(res, args.out)
        else:
            n = write_bag(res, args.out, args.storage)
    except Exception as exc:  # noqa: BLE001
        print(
            f"ae-tactile-replay: cannot write {args.out}: {type(exc).__name__}: {exc}",
            file=sys.stderr,
        )
        return 2
    print(f"{res.summary()}\n{n} events written to {args.out}")
    if args.png:
        write_png(res, args.png, title=f"replay of {Path(args.bag).name}")
    return 3 if res.damaged else 0


def write_png(res: ReplayResult, path: str, title: str = "") -> None:
    """PNG summary of a replay (ae_tactile.report): the events on the fingertip from above and
    on a timeline; a missing matplotlib is reported, not raised."""
    from ae_tactile.report import ReportUnavailable, write_run_summary

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


if __name__ == "__main__":
    sys.exit(main())
