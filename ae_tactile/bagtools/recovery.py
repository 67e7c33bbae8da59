# SPDX-License-Identifier: Apache-2.0
"""Damaged bags: the records still readable, without rosbags.

A bag that rosbags cannot open or stops reading (truncated by a crash or a full disk,
corrupted pages) is read again record by record: sqlite3 row by row around the damaged
pages (a file cut short is padded with zero pages first), MCAP record by record up to the
damage, without the summary section, and on past it from the next record that parses.
A row or record that is read but damaged (a NULL or mistyped column, a length that runs
past its chunk) is skipped and counted in the report's ``damaged_records``. Every
problem met is appended to the report's ``read_errors`` (a `ReplayResult`); nothing here
raises for a damaged file.
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
    """The message rows in id order. A damaged stretch is stepped over by reading on
    after the next id, one id at a time for 64 failures, then in growing steps (at most
    128 failures in a row). A row whose columns a flipped byte made NULL or of the wrong
    type, or whose id is never read (rosbag2 numbers its rows 1, 2, ...), is counted in
    ``damaged_records``."""
    last_read, pos, fails = 0, 0, 0  # last row read; rows are asked for with id > pos
    while fails < 128:
        try:
            for rid, tid, t_ns, data in con.execute(_SQLITE_ROWS, (pos,)):
                report.damaged_records += max(int(rid) - last_read - 1, 0)  # never read
                last_read = pos = int(rid)  # the rowid: always an integer
                fails = 0
                if not (
                    isinstance(tid, int) and isinstance(t_ns, int) and isinstance(data, bytes)
                ):
                    _damaged_row(report, f, rid, tid, t_ns, data)
                    continue
                name, msgtype = topics.get(tid, (None, None))
                if name is None:
                    _count(report.undecodable, f"topic id {tid}")
                    continue
                yield name, msgtype, t_ns, data
            return
        except sqlite3.Error as exc:
            if fails == 0:
                report.read_errors.append(f"{f.name}: rows after id {last_read}: {exc}")
            fails += 1
            pos += 1 if fails <= 64 else 1 << min(fails - 64, 20)  # step over the damage


def _damaged_row(report, f: Path, rid, tid, t_ns, data) -> None:
    """Count a row read with a column of the wrong type (the first one is described)."""
    report.damaged_records += 1
    if not any("damaged row" in e for e in report.read_errors):
        report.read_errors.append(
            f"{f.name}: damaged row id {rid} (topic_id {tid!r}, timestamp {t_ns!r},"
            f" data {type(data).__name__}) skipped"
        )


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
                i = _mcap_resync(mv, i + 1, end, channels, report)
                continue
            i_next = end  # a chunk cut short: its complete records still count
        try:
            if op == 0x02:  # Footer
                return
            yield from _mcap_record(mv, op, body, i_next, schemas, channels, report, name)
        except (struct.error, IndexError, UnicodeDecodeError) as exc:
            report.read_errors.append(f"{name}: record 0x{op:02x} at byte {i}: {exc}")
            i = _mcap_resync(mv, i + 1, end, channels, report)
            continue
        i = i_next


def _mcap_record(mv, op, body, i_next, schemas, channels, report, name):
    """The messages of one record (a Message, or the records of a Chunk); Schema and
    Channel records fill ``schemas`` and ``channels``."""
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


#: Opcodes a record after a Message may have (a resynced Message is checked against them).
_MCAP_NEXT_OPS = frozenset(range(0x01, 0x10))


def _mcap_resync(mv, i: int, end: int, channels: dict, report) -> int:
    """The next offset from ``i`` on where a Message record of a known channel parses and
    is followed by another record (or the end): reading goes on there. The bytes in
    between are a damaged record (counted in ``damaged_records``); ``end`` if none."""
    report.damaged_records += 1
    data = mv.obj if isinstance(mv.obj, bytes) else bytes(mv)
    j = i
    while True:
        j = data.find(b"\x05", j, end - 9)
        if j < 0:
            return end
        (n,) = struct.unpack_from("<Q", data, j + 1)
        k = j + 9 + n
        if 22 <= n and k <= end and (k == end or (k < end and data[k] in _MCAP_NEXT_OPS)):
            (cid,) = struct.unpack_from("<H", data, j + 9)
            if cid in channels:
                return j
        j += 1
