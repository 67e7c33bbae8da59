# SPDX-License-Identifier: Apache-2.0
"""Bags of 200 packet messages with flipped bytes (sqlite3: record headers and b-tree
pages; MCAP: a record's length inside a chunk): what is readable is recovered record by
record, the damaged records are skipped and counted, the command says how much."""

import shutil
import struct

import numpy as np
import pytest

pytest.importorskip(
    "rosbags", reason="rosbags is installed by `make test` (tools/requirements.txt)"
)

from ae_tactile.bagtools import main as replay_main  # noqa: E402
from ae_tactile.bagtools import replay, typestore  # noqa: E402
from ae_tactile.geometry import FingertipGeometry  # noqa: E402
from ae_tactile.sim import SimConfig, render_triggered  # noqa: E402

N = 200
FILES = {"sqlite3": "*.db3", "mcap": "*.mcap"}


def write_bag(path, storage):
    """N PacketArray messages of one packet each (6 touches, repeated)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    T = store.types
    geo = FingertipGeometry()
    pts = geo.surface_point_from_xy(
        np.array([0.0, 2.5e-3, 5e-3, -3e-3, 3e-3, 0.0]),
        np.array([0.0, 0.0, 0.0, 2e-3, 2e-3, -3e-3]),
    )
    pk = render_triggered(pts, SimConfig(), snr_db=30, rng=3)
    t0 = 1_700_000_000_000_000_000
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    with Writer(path, version=9, storage_plugin=plugin) as w:
        c = w.add_connection("/f/packets", "ae_tactile/msg/PacketArray", typestore=store)
        for k in range(N):
            sec, nsec = divmod(t0 + k * 5_000_000, 1_000_000_000)
            p = T["ae_tactile/msg/Packet"](
                stamp=Time(sec=sec, nanosec=nsec),
                sample_rate_hz=10e6,
                channel_count=4,
                samples_per_channel=pk.samples_v.shape[2],
                samples=pk.samples_v[k % 6].astype(np.float32).ravel(),
                onset_index=int(pk.onset_index[k % 6]),
                sequence_id=k,
                noise_rms_v=float(pk.noise_rms_v[k % 6]),
                saturated=False,
            )
            arr = T["ae_tactile/msg/PacketArray"](
                header=Header(stamp=Time(sec=sec, nanosec=nsec), frame_id="tip"),
                packets=[p],
                packets_dropped=0,
                frames_bad_crc=0,
            )
            w.write(c, t0 + k * 5_000_000, store.serialize_cdr(arr, "ae_tactile/msg/PacketArray"))


def varint(b, i):
    """SQLite's big-endian varint at b[i]: (value, next offset)."""
    v = 0
    for k in range(9):
        c = b[i + k]
        if k == 8:
            return (v << 8) | c, i + 9
        v = (v << 7) | (c & 0x7F)
        if not c & 0x80:
            return v, i + k + 1
    raise AssertionError


def message_cells(b):
    """Offsets of the topic_id column's serial-type byte of each message row (leaf table
    cells whose record has 4 columns: id (the rowid, NULL), topic_id = 1 (serial type 9,
    no body bytes), timestamp (8-byte integer), data (a blob))."""
    page = struct.unpack_from(">H", b, 16)[0]
    out = []
    for p in range(len(b) // page):
        base = p * page
        head = base + (100 if p == 0 else 0)
        if b[head] != 0x0D:
            continue
        for c in range(struct.unpack_from(">H", b, head + 3)[0]):
            cell = base + struct.unpack_from(">H", b, head + 8 + 2 * c)[0]
            if not base < cell < base + page:
                continue
            _, i = varint(b, cell)  # payload size
            _, i = varint(b, i)  # rowid
            h, j = varint(b, i)
            types, k = [], j
            while k < i + h and len(types) < 5:
                t, k = varint(b, k)
                types.append((t, k))
            if len(types) == 4 and types[1][0] == 9 and types[2][0] == 6 and types[3][0] >= 12:
                out.append(types[0][1])  # the byte where the 2nd type starts
    return out


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("bags200")
    out = {}
    for storage in FILES:
        write_bag(root / storage, storage)
        intact = replay(root / storage, method="gradient")
        assert intact.packets == N and not intact.damaged
        out[storage] = (root / storage, intact)
    return out


def damaged(src, dst, storage, edit):
    shutil.copytree(src, dst)
    (f,) = list(dst.glob(FILES[storage]))
    f.write_bytes(bytes(edit(bytearray(f.read_bytes()))))
    return dst


def check_recovered(res, intact, capsys, bag, tmp_path):
    want = {e["packet_id"]: e["point_m"] for e in intact.contacts}
    for e in res.contacts:
        assert np.allclose(e["point_m"], want[e["packet_id"]], atol=1e-12)
    code = replay_main([str(bag), str(tmp_path / "ev.csv"), "--method", "gradient"])
    text = capsys.readouterr()
    assert code == 3 and "Traceback" not in text.out + text.err
    assert "recovered record by record" in text.out
    assert f"{res.damaged_records} damaged record(s) skipped" in text.out
    assert f"lists {N} message(s)" in text.out
    with capsys.disabled():
        print(f" {res.packets} of {N} packets, {res.damaged_records} damaged record(s) skipped")


@pytest.mark.parametrize("rows", [1, 10])
def test_sqlite_rows_with_flipped_type_bytes_are_skipped_and_the_rest_recovered(
    bags, tmp_path, capsys, rows
):
    src, intact = bags["sqlite3"]

    def flip(b):
        cells = message_cells(b)
        assert len(cells) == N
        for at in cells[5 :: N // rows][:rows]:
            b[at] ^= 0x09  # topic_id's serial type 9 (the integer 1) -> 0 (NULL)
        return b

    bag = damaged(src, tmp_path / "bad", "sqlite3", flip)
    res = replay(bag, method="gradient")
    assert res.damaged and res.damaged_records == rows
    assert res.packets == N - rows  # every other record, once
    assert res.expected_records == N
    check_recovered(res, intact, capsys, bag, tmp_path)


def test_sqlite_pages_with_flipped_bytes_recover_the_readable_rows(bags, tmp_path, capsys):
    src, intact = bags["sqlite3"]

    def flip(b):
        cells = message_cells(b)
        page = struct.unpack_from(">H", b, 16)[0]
        for at in (cells[40], cells[120]):  # two leaf pages: their b-tree headers
            base = at // page * page
            b[base : base + 8] = bytes(x ^ 0xFF for x in b[base : base + 8])
        b[cells[80]] ^= 0x09
        return b

    bag = damaged(src, tmp_path / "bad", "sqlite3", flip)
    res = replay(bag, method="gradient")
    assert res.damaged and res.read_errors
    assert res.packets >= N - 10  # the damaged pages' rows and the NULL one at most
    check_recovered(res, intact, capsys, bag, tmp_path)


@pytest.mark.parametrize("which", [1, 77, 150])
def test_mcap_record_with_a_flipped_length_is_stepped_over(bags, tmp_path, capsys, which):
    src, intact = bags["mcap"]

    def flip(b):
        i = b.find(b"\x05", 8)  # Message records inside the first chunk, in order
        seen = 0
        while True:
            (n,) = struct.unpack_from("<Q", b, i + 1)
            if b[i] == 0x05 and 22 <= n < 1 << 20:
                seen += 1
                if seen == which:
                    b[i + 6] ^= 0xFF  # a byte of its length: it now runs past the chunk
                    return b
                i += 9 + n
            else:
                i = b.find(b"\x05", i + 1)

    bag = damaged(src, tmp_path / "bad", "mcap", flip)
    res = replay(bag, method="gradient")
    assert res.damaged and res.damaged_records >= 1
    assert res.packets >= N - 2
    check_recovered(res, intact, capsys, bag, tmp_path)
