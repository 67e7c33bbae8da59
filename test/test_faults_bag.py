# SPDX-License-Identifier: Apache-2.0
"""Bag replay on damaged and hostile bags: truncated and corrupted files (sqlite3, MCAP),
foreign message types, bad packets. What is readable is recovered, the rest is counted,
the command ends with a summary and a documented exit code, never a traceback."""

import shutil

import numpy as np
import pytest

pytest.importorskip(
    "rosbags", reason="rosbags is installed by `make test` (tools/requirements.txt)"
)

from test_bag_replay import write_packet_bag  # noqa: E402

from ae_tactile.bagtools import main as replay_main  # noqa: E402
from ae_tactile.bagtools import replay, typestore  # noqa: E402

FILES = {"sqlite3": "*.db3", "mcap": "*.mcap"}


def damaged_copy(src, dst, storage, edit):
    shutil.copytree(src, dst)
    (f,) = list(dst.glob(FILES[storage]))
    data = bytearray(f.read_bytes())
    f.write_bytes(bytes(edit(data)))
    return dst


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("bags")
    out = {}
    for storage in FILES:
        write_packet_bag(root / storage, storage)
        out[storage] = (root / storage, replay(root / storage, method="gradient"))
    return root, out


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
@pytest.mark.parametrize("fraction", [0.97, 0.9, 0.6, 0.3, 0.05])
def test_truncated_bag_recovers_what_is_readable(bags, tmp_path, capsys, storage, fraction):
    src, intact = bags[1][storage]
    assert intact.packets == 6 and not intact.damaged
    bag = damaged_copy(src, tmp_path / "cut", storage, lambda d: d[: int(len(d) * fraction)])
    res = replay(bag, method="gradient")
    assert res.read_errors and res.damaged
    assert res.packets <= 6
    # what was recovered is exactly what the intact bag gives for those packets
    want = {e["packet_id"]: e["point_m"] for e in intact.contacts}
    for e in res.contacts:
        assert np.allclose(e["point_m"], want[e["packet_id"]], atol=1e-12)
    if storage == "mcap" and fraction >= 0.9:
        assert res.packets >= 5  # records before the cut are all there
    if storage == "sqlite3" and fraction >= 0.97:
        assert res.packets >= 5
    code = replay_main([str(bag), str(tmp_path / "ev.csv"), "--method", "gradient"])
    text = capsys.readouterr()
    assert "Traceback" not in text.out + text.err
    assert code == (3 if res.packets else 2)
    assert ("damaged" in text.out) if code == 3 else ("nothing readable" in text.err)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
@pytest.mark.parametrize("seed", range(6))
def test_corrupted_bag_never_raises(bags, tmp_path, capsys, storage, seed):
    src, intact = bags[1][storage]
    rng = np.random.default_rng(seed)

    def corrupt(d):
        for _ in range(int(rng.integers(1, 40))):
            k = int(rng.integers(0, len(d)))
            n = int(rng.integers(1, 64))
            d[k : k + n] = rng.integers(0, 256, len(d[k : k + n]), dtype=np.uint8).tobytes()
        return d

    bag = damaged_copy(src, tmp_path / "bad", storage, corrupt)
    res = replay(bag, method="gradient")
    assert res.packets <= 6 + sum(res.rejected.values())
    assert all(np.all(np.isfinite(e["point_m"])) for e in res.contacts)
    code = replay_main([str(bag), str(tmp_path / "ev.csv")])
    text = capsys.readouterr()
    assert code in (0, 2, 3) and "Traceback" not in text.out + text.err
    assert code == (
        3 if res.damaged and (res.packets or res.contacts) else 2 if res.damaged else 0
    )


def test_bag_of_other_types_only_is_skipped_with_a_count(tmp_path, capsys):
    from rosbags.rosbag2 import Writer

    store = typestore()
    String = store.types["std_msgs/msg/String"]
    with Writer(tmp_path / "chat", version=9) as w:
        c = w.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        for k in range(3):
            w.write(c, k + 1, store.serialize_cdr(String(data=f"hi {k}"), "std_msgs/msg/String"))
    res = replay(tmp_path / "chat")
    assert res.packets == 0 and res.skipped == {"std_msgs/msg/String": 3} and not res.damaged
    assert replay_main([str(tmp_path / "chat"), str(tmp_path / "ev.csv")]) == 0
    assert "skipped messages of other types" in capsys.readouterr().out


def write_bad_packet_bag(path):
    """6 good packets (from write_packet_bag's simulation) and 5 bad ones, one per defect."""
    from rosbags.rosbag2 import Writer

    from ae_tactile.geometry import FingertipGeometry
    from ae_tactile.sim import SimConfig, render_triggered

    store = typestore()
    T = store.types
    geo = FingertipGeometry()
    pts = geo.surface_point_from_xy(
        np.array([0.0, 2.5e-3, 5e-3, -3e-3, 3e-3, 0.0]),
        np.array([0.0, 0.0, 0.0, 2e-3, 2e-3, -3e-3]),
    )
    pk = render_triggered(pts, SimConfig(), snr_db=30, rng=3)
    n = pk.samples_v.shape[2]
    Time, Header, Packet = (
        T["builtin_interfaces/msg/Time"],
        T["std_msgs/msg/Header"],
        T["ae_tactile/msg/Packet"],
    )

    def packet(k, fs=10e6, channels=4, per_channel=n, samples=None, onset=None):
        x = pk.samples_v[k % 6].astype(np.float32).ravel() if samples is None else samples
        return Packet(
            stamp=Time(sec=1, nanosec=k * 1000),
            sample_rate_hz=fs,
            channel_count=channels,
            samples_per_channel=per_channel,
            samples=x,
            onset_index=int(pk.onset_index[k % 6]) if onset is None else onset,
            sequence_id=k,
            noise_rms_v=1e-3,
            saturated=False,
        )

    nan = pk.samples_v[0].astype(np.float32).ravel().copy()
    nan[5] = np.nan
    bad = [
        packet(100, fs=0.0),
        packet(101, fs=-1e6),
        packet(102, fs=float("nan")),
        packet(103, channels=3),
        packet(104, samples=nan),
        packet(105, onset=n + 7),
        packet(106, per_channel=n + 1),
    ]
    good = [packet(k) for k in range(6)]
    with Writer(path, version=9) as w:
        c = w.add_connection("/packets", "ae_tactile/msg/PacketArray", typestore=store)
        for k, group in enumerate([good[:3] + bad[:4], bad[4:] + good[3:]]):
            arr = T["ae_tactile/msg/PacketArray"](
                header=Header(stamp=Time(sec=1, nanosec=k), frame_id="tip"),
                packets=group,
                packets_dropped=0,
                frames_bad_crc=0,
            )
            w.write(c, k + 1, store.serialize_cdr(arr, "ae_tactile/msg/PacketArray"))
    return pts


def test_bad_packets_are_rejected_one_by_one_with_their_reason(tmp_path):
    pts = write_bad_packet_bag(tmp_path / "mixed")
    res = replay(tmp_path / "mixed", method="gradient")
    assert res.packets == 13 and not res.damaged
    assert res.rejected == {
        "BAD_SAMPLE_RATE": 3,
        "MALFORMED": 2,
        "NON_FINITE_SAMPLES": 1,
        "BAD_ONSET_INDEX": 1,
    }
    assert sorted(e["packet_id"] for e in res.contacts) == list(range(6))
    got = np.array([e["point_m"] for e in sorted(res.contacts, key=lambda e: e["packet_id"])])
    assert np.max(np.linalg.norm(got - pts, axis=1)) < 0.05e-3


@pytest.mark.parametrize("content", [b"", b"\x89MCAP0\r\n", b"not a bag at all" * 100])
def test_garbage_files_end_with_a_message_and_exit_code_2(tmp_path, capsys, content):
    d = tmp_path / "junk"
    d.mkdir()
    (d / "junk.mcap").write_bytes(content)
    assert replay_main([str(d), str(tmp_path / "ev.csv")]) == 2
    text = capsys.readouterr()
    assert "Traceback" not in text.out + text.err and "ae-tactile-replay" in text.err
