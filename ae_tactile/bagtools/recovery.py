# SPDX-License-Identifier: Apache-2.0
"""Damaged bags: the records still readable, without rosbags.

A bag that rosbags cannot open or stops reading (truncated by a crash or a full disk,
corrupted pages) is read again record by record: sqlite3 row by row around the damaged
pages (a file cut short is padded with zero pages first), MCAP record by record up to the
damage, without the summary section. Every problem met is appended to the report's
``read_errors`` (a `ReplayResult`); nothing here raises for a damaged file.
"""

from __future__ import annotations

import shutil
import sqlite3
import struct
import tempfile
from pathlib import Path

_MCAP_MAGIC = b"\x89MCAP0\r\n"
_SQLITE_ROWS = "SELECT id, topic_id, timestamp, data FROM messages WHERE id > ? ORDER BY id"


def _count(d: dict, key, n: int = 1) -> None:
    d[key] = d.get(key, 0) + n


def _bag_files(path: Path, suffix: str) -> list[Path]:
    if path.is_file():
        return [path] if path.suffix == suffix else []
    return sorted(path.glob(f"*{suffix}")) if path.is_dir() else []


def _raw_messages(path: Path, report):
    """(topic, msgtype, timestamp_ns, cdr bytes) of every record still readable."""
    for f in _bag_files(path, ".db3"):
        yield from _raw_sqlite(f, report)
    for f in _bag_files(path, ".mcap"):
        yield from _raw_mcap(f, report)


def _raw_sqlite(f: Path, report):
    """Rows of a rosbag2 sqlite3 file, stepping over damaged pages (bounded probing).

    A file cut short is read from a copy padded with zero pages up to the size its
    header states (SQLite refuses the short file as a whole; the zero pages then fail
    alone and are stepped over)."""
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


def _sqlite_rows(f: Path, report):
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
        yield from _sqlite_messages(con, topics, f, report)
    finally:
        con.close()


def _sqlite_messages(con, topics: dict, f: Path, report):
    """The message rows in id order; a damaged stretch is stepped over by probing ids
    further on (at most 64 probes, growing steps)."""
    last, probes = 0, 0
    while probes < 64:
        try:
            for rid, tid, t_ns, data in con.execute(_SQLITE_ROWS, (last,)):
                last = int(rid)
                name, msgtype = topics.get(int(tid), (None, None))
                if name is None:
                    _count(report.undecodable, f"topic id {tid}")
                    continue
                yield name, msgtype, int(t_ns), data
            return
        except sqlite3.Error as exc:
            if probes == 0:
                report.read_errors.append(f"{f.name}: rows after id {last}: {exc}")
            probes += 1
            last += 1 << probes if probes < 20 else 1 << 20  # step over the damage


def _raw_mcap(f: Path, report):
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
