# SPDX-License-Identifier: Apache-2.0
"""Reading a bag: the ae_tactile message types for rosbags, and the messages of a bag.

The normal reader is rosbags' ``AnyReader`` (sqlite3 and MCAP); if it cannot open a
bag or stops reading it, the rest is read record by record (`recovery`). Messages of
other types are skipped and counted, messages that do not deserialize are counted.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from ae_tactile.geometry import FingertipGeometry

from .recovery import _count, _raw_messages

MSG_NAMES = ("Packet", "PacketArray", "ContactEvent", "Contact", "ContactState", "Emission",
             "SensorInfo")
#: The message types a replay reads (the packets and the sensor they came from).
WANTED = ("ae_tactile/msg/PacketArray", "ae_tactile/msg/SensorInfo")


def msg_dir() -> Path:
    """Directory of the package's .msg files (source tree, or the installed share dir)."""
    here = Path(__file__).resolve().parents[1]  # the ae_tactile package
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
    """A rosbags typestore (ROS 2 Kilted) with the ae_tactile messages registered.

    Returns
    -------
    rosbags.typesys.store.Typestore
        The store, for `read_bag` and the writers.

    Raises
    ------
    ImportError
        rosbags is not installed (``pip install ae_tactile[bag]``).
    """
    # lazy: rosbags is an optional dependency (the 'bag' extra)
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

    Parameters
    ----------
    packets : int
        Packets read.
    rejected : dict
        Packets refused, by reason.
    contacts : list of dict
        The localized emissions, one each (time, point, polarity, packet id, ...), with
        what the slip detector read each as ("reading", a Reading value) and its contact
        ("contact_id", 0: none).
    contact_events : list of dict
        A contact's TOUCH when it begins and DETOUCH when it ends (with "contact_id").
    slip : list of dict
        Slip events (with "contact_id").
    geometry : FingertipGeometry or None
        The fingertip the packets came from (the bag's sensor_info).
    skipped : dict
        Messages of other types, by type.
    undecodable : dict
        Messages that did not deserialize, by type.
    read_errors : list of str
        What stopped or hampered reading the bag (damage).
    recovered : int
        Messages read by the record-by-record fallback after the normal reader failed.
    damaged_records : int
        Records the fallback found but could not use (a damaged row or record), skipped.
    expected_records : int or None
        Messages the bag's metadata.yaml lists (None: no readable metadata).
    """

    packets: int = 0
    rejected: dict = field(default_factory=dict)
    contacts: list = field(default_factory=list)
    contact_events: list = field(default_factory=list)
    slip: list = field(default_factory=list)
    geometry: FingertipGeometry | None = None
    skipped: dict = field(default_factory=dict)
    undecodable: dict = field(default_factory=dict)
    read_errors: list = field(default_factory=list)
    recovered: int = 0
    damaged_records: int = 0
    expected_records: int | None = None

    @property
    def damaged(self) -> bool:
        """True if anything in the bag could not be read or decoded."""
        return bool(self.read_errors or self.undecodable)

    def summary(self) -> str:
        """A few lines saying what was read, produced, refused and lost."""
        lines = [
            f"{self.packets} packets -> {len(self.contacts)} emissions,"
            f" {len(self.contact_events)} contact events (begin / end),"
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
            listed = (
                f"; the bag's metadata lists {self.expected_records} message(s) in all"
                if self.expected_records is not None
                else ""
            )
            lines.append(
                f"{self.recovered} message(s) recovered record by record,"
                f" {self.damaged_records} damaged record(s) skipped{listed}"
            )
        return "\n".join(lines)


def read_bag(path, store, packet_topic: str | None = None, report: ReplayResult | None = None):
    """The ae_tactile messages of a bag, in order.

    Never raises for a damaged bag: read errors, skipped and undecodable messages are
    recorded in ``report``, and if the normal reader (rosbags) fails, the rest is read
    record by record.

    Parameters
    ----------
    path : str or os.PathLike
        A rosbag2 directory, or one .db3 / .mcap file.
    store : rosbags typestore
        From `typestore`.
    packet_topic : str or None
        Only this topic's PacketArray messages (None: every topic's).
    report : ReplayResult or None
        Where skipped, undecodable and damaged parts are counted.

    Yields
    ------
    tuple
        (topic, msgtype, timestamp_ns, message) of each PacketArray and SensorInfo.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    """
    report = report if report is not None else ReplayResult()

    def wanted(topic, msgtype):
        return msgtype in WANTED and (
            packet_topic is None or msgtype != WANTED[0] or topic == packet_topic
        )

    seen: set = set()
    try:
        yield from _read_with_rosbags(path, store, wanted, report, seen)
        return
    except FileNotFoundError:
        if not Path(path).exists():
            raise
        report.read_errors.append("file missing")
    except Exception as exc:  # noqa: BLE001 - a damaged bag: fall back below
        report.read_errors.append(f"{type(exc).__name__}: {exc}")
    yield from _read_record_by_record(path, store, wanted, report, seen)


class IncompleteBag(RuntimeError):
    """rosbags read fewer messages than the bag's metadata lists (a damaged sqlite3 row it
    drops without a word, e.g. a topic_id a flipped byte made NULL)."""


def _read_with_rosbags(path, store, wanted, report: ReplayResult, seen: set):
    """The wanted messages through rosbags' reader; each one's (topic, time, size) goes
    to ``seen``, so that a fallback after a failure does not deliver it again.

    Raises
    ------
    IncompleteBag
        Fewer messages came than the metadata lists for the wanted topics.
    """
    # lazy: rosbags is an optional dependency (the 'bag' extra)
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
        listed = sum(int(getattr(c, "msgcount", 0) or 0) for c in conns)
        n = 0
        for conn, t_ns, raw in reader.messages(connections=conns):
            seen.add((conn.topic, int(t_ns), len(raw)))
            n += 1
            msg = _deserialize(store, raw, conn.msgtype, report)
            if msg is not None:
                yield conn.topic, conn.msgtype, t_ns, msg
        if n < listed:
            raise IncompleteBag(f"{listed - n} of the {listed} messages listed were not read")


def _read_record_by_record(path, store, wanted, report: ReplayResult, seen: set):
    """The wanted messages the normal reader did not deliver, record by record."""
    skipped_before = dict(report.skipped)
    report.skipped.clear()
    report.expected_records = _listed_messages(Path(path))
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


def _listed_messages(path: Path) -> int | None:
    """The message count of a bag directory's metadata.yaml (None: none readable)."""
    try:
        with open(path / "metadata.yaml", encoding="utf-8") as fh:
            info = yaml.safe_load(fh)["rosbag2_bagfile_information"]
        return int(info["message_count"])
    except Exception:  # noqa: BLE001 - no file, a file cut short, not a mapping: unknown
        return None


def _deserialize(store, raw, msgtype: str, report: ReplayResult):
    try:
        return store.deserialize_cdr(bytes(raw), msgtype)
    except Exception:  # noqa: BLE001 - corrupted or foreign bytes
        _count(report.undecodable, msgtype)
        return None
