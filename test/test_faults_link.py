# SPDX-License-Identifier: Apache-2.0
"""Fault injection on a real pty (and TCP) with a real FingertipLink and VirtualFingertip:
a device reset mid-frame with the port open, a device that only sends garbage, repeated
frames, spurious wake-ups, overload, non-finite packets, stuck TCP clients.

No wall-clock bounds: every wait is on a condition with a generous timeout, and the
assertions are on counters and on what is delivered.
"""

import ctypes
import mmap
import os
import socket
import struct
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml
from test_hardware_link import SCENE, Rig

from ae_tactile.link import FingertipLink, LinkConfig
from ae_tactile.protocol import MAX_FRAME_LEN, Packet
from ae_tactile.virtual_device import PtyTransport, TcpTransport

LONG = dict(yaml.safe_load(open(SCENE)), duration_s=8.0, name="long_random_touches")


def now_ns():
    return time.monotonic_ns()


def sent_after(rig, log_index):
    return [
        p.first_sample_index
        for kind, _, p, f in rig.device.sent_log[log_index:]
        if kind == "packet" and f == "sent"
    ]


def test_device_reset_mid_frame_with_the_port_open_recovers_without_reconnecting(tmp_path):
    with Rig(PtyTransport(str(tmp_path / "fingertip")), scene=LONG) as rig:
        rig.wait_connected()
        rig.run(0.5)
        before = len(rig.records)
        log_at_reset = len(rig.device.sent_log)
        missing = rig.runner.call(rig.device.reset_mid_frame, now_ns())  # 8192-sample frame
        assert missing > 30_000  # bytes the cut frame still claims
        rig.run(
            20.0,
            until=lambda: (
                rig.link.stats()["device_restarts_handled"] == 1 and len(rig.records) > before + 3
            ),
        )
        resent = sent_after(rig, log_at_reset)
        rig.run(10.0, until=lambda: len(rig.records) - before >= len(resent))
        s = rig.link.stats()
        assert s["device_restarts_handled"] == 1 and rig.device.boots == 1
        assert s["truncated_frames"] == 1 and s["crc_errors"] == 0  # the cut frame
        assert s["disconnects"] == 0 and s["link_timeouts"] == 0 and s["stalled_frames"] == 0
        assert s["state"] == "connected"
        after = [r.device_sample_index for r in rig.records[before:]]
        assert len(after) > 3 and after[: len(resent)] == resent  # all of them, once
        assert s["pending_bytes"] < MAX_FRAME_LEN


def test_device_sending_only_garbage_is_not_connected_and_recovers(tmp_path):
    with Rig(
        PtyTransport(str(tmp_path / "fingertip")),
        scene=LONG,
        link_timeout_s=1.0,
        reconnect_initial_s=0.1,
        reconnect_max_s=0.3,
    ) as rig:
        rig.wait_connected()
        rig.run(0.3)
        rig.device.garble(True)  # a wrong baud rate: bytes, no frames
        rig.run(20.0, until=lambda: rig.link.stats()["link_timeouts"] >= 1)
        s0 = rig.link.stats()
        assert s0["state"] != "connected" and s0["link_timeouts"] >= 1
        assert "no valid frame" in s0["last_error"]
        states, worst_pending = set(), 0
        t_end = time.monotonic() + 2.5  # sample the state for a while
        while time.monotonic() < t_end:
            s = rig.link.stats()
            states.add(s["state"])
            worst_pending = max(worst_pending, s["pending_bytes"])
            rig.run(0.02)
        s1 = rig.link.stats()
        assert states <= {"connecting", "disconnected"}  # never "connected"
        assert s1["frames_ok"] == s0["frames_ok"]  # nothing decoded from noise
        assert s1["bytes_received"] > s0["bytes_received"]  # although bytes arrive
        assert s1["link_timeouts"] > s0["link_timeouts"]  # and it keeps retrying
        assert worst_pending < MAX_FRAME_LEN + rig.link.config.read_chunk_bytes
        n_records = len(rig.records)
        rig.device.garble(False)
        rig.run(
            20.0,
            until=lambda: (
                rig.link.stats()["state"] == "connected" and len(rig.records) > n_records
            ),
        )
        assert rig.link.stats()["state"] == "connected" and len(rig.records) > n_records


def test_repeated_frames_are_delivered_once_and_are_not_a_reboot(tmp_path):
    with Rig(PtyTransport(str(tmp_path / "fingertip"))) as rig:
        rig.wait_connected()
        rig.run(0.2)
        rig.device.repeat_next(3)
        rig.run(10.0, until=lambda: rig.device.finished(time.monotonic_ns()))
        sent = rig.sent_packets()
        rig.run(5.0, until=lambda: len(rig.records) >= len(sent))
        rig.run(0.2)
        assert getattr(rig.device, "frames_repeated", 0) == 3
        assert [r.device_sample_index for r in rig.records] == [p.first_sample_index for p in sent]
        s = rig.link.stats()
        assert s["duplicate_frames"] == 3
        assert s["device_restarts"] == 0 and s["device_restarts_handled"] == 0
        assert s["dropped_frames"] == 0 and s["packets_dropped"] == 0


STEALER = r"""
import mmap, os, select, struct, sys, time
slave = os.open(sys.argv[1], os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
shared = mmap.mmap(os.open(sys.argv[2], os.O_RDWR), 24)
readable = select.poll()
readable.register(slave, select.POLLIN)
done = 0
while True:
    armed = struct.unpack_from("<q", shared)[0]
    if armed < 0:
        break
    if armed == done:
        time.sleep(0.0005)
        continue
    stolen = 0
    if readable.poll(5000):
        time.sleep(0.2)  # the link is woken by now, waiting for the GIL the test holds
        while True:
            try:
                data = os.read(slave, 1 << 16)  # b"" when empty: the port has VMIN = 0
            except BlockingIOError:
                break
            if not data:
                break
            stolen += len(data)
    done = armed
    struct.pack_into("<qq", shared, 8, done, stolen)
"""


def test_spurious_wakeups_and_eagain_are_not_disconnects(tmp_path):
    """Readable, then nothing to read (EAGAIN), made to happen: the test writes bytes to the
    device end and keeps the GIL while a second reader, in its own process, takes them from
    the port between the link's poll() and its read(). That is no lost device."""
    libc = ctypes.PyDLL(None)  # PyDLL: write() without releasing the GIL
    with Rig(PtyTransport(str(tmp_path / "fingertip")), link_timeout_s=60.0) as rig:
        rig.wait_connected()
        rig.run(60.0, until=lambda: rig.device.finished(time.monotonic_ns()))
        sent = rig.sent_packets()
        rig.run(20.0, until=lambda: len(rig.records) >= len(sent))
        shared_path = tmp_path / "stealer.shm"
        shared_path.write_bytes(bytes(24))
        with open(shared_path, "r+b") as f:
            shared = mmap.mmap(f.fileno(), 24)
        stealer = subprocess.Popen(
            [sys.executable, "-c", STEALER, rig.transport.path, str(shared_path)]
        )
        stolen, attempts, interval = 0, 0, sys.getswitchinterval()
        try:
            while rig.link.stats()["spurious_wakeups"] < 3 and attempts < 30:
                attempts += 1
                rig.run(0.02)
                sys.setswitchinterval(30.0)  # this thread keeps the GIL while it spins
                try:
                    struct.pack_into("<q", shared, 0, attempts)
                    libc.write(rig.transport.master, b"\xaa" * 16, 16)  # the link wakes up
                    t_end = time.monotonic() + 10.0
                    while struct.unpack_from("<q", shared, 8)[0] != attempts:
                        if time.monotonic() > t_end:
                            break
                finally:
                    sys.setswitchinterval(interval)
                stolen += struct.unpack_from("<q", shared, 16)[0]
                rig.run(0.02)  # the link gets the GIL: os.read() -> EAGAIN
        finally:
            struct.pack_into("<q", shared, 0, -1)
            try:
                stealer.wait(10.0)
            finally:
                stealer.kill()
                shared.close()
        s = rig.link.stats()
        assert s["spurious_wakeups"] >= 3 and stolen > 0
        assert s["disconnects"] == 0 and s["read_errors"] == 0 and s["connects"] == 1
        assert s["hangups"] == 0 and s["state"] == "connected"
        assert len(rig.records) == len(sent)
        body = Packet(np.full((4, 64), 100, np.int16), 10_000_000, 1e-4, 10_000_000, pre_trigger=8)
        rig.runner.call(rig.device.inject_frame, body, now_ns())
        rig.run(10.0, until=lambda: len(rig.records) > len(sent))  # still delivering
        assert [r.device_sample_index for r in rig.records[len(sent) :]] == [10_000_000]
        assert rig.link.stats()["disconnects"] == 0


def test_overload_is_bounded_and_every_packet_accounted_for(tmp_path):
    """Nobody polls: the hand-over queue stays at its bound, the rest is counted as drops."""
    t = PtyTransport(str(tmp_path / "fingertip"))
    rig = Rig(t, queue_max_batches=4)
    with rig:
        deadline = time.monotonic() + 30.0
        depth = 0
        while not rig.device.finished(time.monotonic_ns()) and time.monotonic() < deadline:
            depth = max(depth, rig.link.stats()["queue_depth"])
            time.sleep(0.01)
        sent = rig.sent_packets()
        rig.run(0.01)  # poll once: takes what the queue holds
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            s = rig.link.stats()
            if s["packets_out"] + s["queue_overflow_packets"] >= len(sent):
                break
            time.sleep(0.01)
        rig.run(0.2)
        s = rig.link.stats()
    assert depth <= 4 and s["queue_overflow_packets"] > 0
    assert len(rig.records) + s["queue_overflow_packets"] == len(sent)
    assert s["packets_dropped"] == s["queue_overflow_packets"]
    delivered = [r.device_sample_index for r in rig.records]
    assert set(delivered) <= {p.first_sample_index for p in sent}


def test_packets_whose_volts_would_not_be_finite_are_rejected_and_counted(tmp_path):
    with Rig(PtyTransport(str(tmp_path / "fingertip"))) as rig:
        rig.wait_connected()
        rig.run(0.2)
        huge = Packet(np.full((4, 64), 1000, np.int16), 10_000_000, 3e38, pre_trigger=8)
        rig.runner.call(rig.device.inject_frame, huge, now_ns())
        rig.run(10.0, until=lambda: rig.link.stats()["packets_rejected_nonfinite"] >= 1)
        rig.run(10.0, until=lambda: rig.device.finished(time.monotonic_ns()))
        rig.run(0.3)
        s = rig.link.stats()
        assert s["packets_rejected_nonfinite"] == 1 and s["internal_errors"] == 0
        assert all(
            np.isfinite(r.samples_v).all() and np.isfinite(r.noise_rms_v) for r in rig.records
        )
        assert len(rig.records) == len(rig.sent_packets())


def test_tcp_server_serves_several_clients_refuses_extra_ones_and_drops_stuck_ones():
    transport = TcpTransport(max_clients=2, idle_timeout_s=3.0, client_sndbuf=4096)
    assert transport.listener.getsockname()[0] == "127.0.0.1"
    host, port = transport.host, int(transport.port.rsplit(":", 1)[1])
    stuck = socket.create_connection((host, port))  # connects, never reads
    stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    with Rig(transport) as rig:
        rig.wait_connected(timeout=20.0)
        assert rig.link.stats()["state"] == "connected"
        extra = socket.create_connection((host, port))  # a third one: refused cleanly
        extra.settimeout(10.0)
        assert extra.recv(10) == b""  # closed by the server
        extra.close()
        rig.runner.call(rig.device.inject_garbage, bytes(300_000))  # fills the stuck one
        rig.run(30.0, until=lambda: transport.timed_out + transport.overflowed >= 1)
        assert transport.timed_out == 1 and transport.refused == 1
        assert len(transport.clients) == 1  # the link is still served
        assert rig.link.stats()["disconnects"] == 0
        rig.run(20.0, until=lambda: rig.device.finished(time.monotonic_ns()))
        sent = rig.sent_packets()
        rig.run(10.0, until=lambda: len(rig.records) >= len(sent))
        assert [r.device_sample_index for r in rig.records] == [p.first_sample_index for p in sent]
        assert rig.link.stats()["disconnects"] == 0
    stuck.close()


def test_tcp_server_counts_a_dropped_client_only_once_it_is_gone():
    """The link's thread serves the clients while another reads the counters (stats, the
    test above): a client is counted as timed out or overflowed only after it has left
    the list. Seen from the drop's own log line (the last moment it is listed), the count
    is still the old one; after it, the count is one more and the client is gone."""
    import logging

    seen = []

    class Snapshot(logging.Handler):
        def emit(self, record):
            if "disconnected" in record.getMessage():
                seen.append((t.timed_out, t.overflowed, len(t.clients)))

    log = logging.getLogger("ae_tactile.virtual_device")
    handler, level = Snapshot(), log.level
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    t = TcpTransport(max_clients=2, idle_timeout_s=0.05, client_sndbuf=4096)
    host, port = t.host, int(t.port.rsplit(":", 1)[1])
    stuck = socket.create_connection((host, port))  # connects, never reads
    stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    try:
        deadline = time.monotonic() + 30.0
        while not t.clients and time.monotonic() < deadline:
            t.read()  # accepts it
            time.sleep(0.001)
        assert len(t.clients) == 1
        t.write(memoryview(bytes(200_000)))  # more than its buffers take: it stalls
        while t.timed_out + t.overflowed == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
            t.service()
        assert t.timed_out + t.overflowed == 1
        assert seen == [(0, 0, 1)]
        assert t.clients == []
    finally:
        log.removeHandler(handler)
        log.setLevel(level)
        stuck.close()
        t.close()


def test_tcp_transport_parameters_are_checked():
    with pytest.raises(ValueError):
        TcpTransport(max_clients=0)
    with pytest.raises(ValueError):
        TcpTransport(idle_timeout_s=0)


def test_link_stall_report_parameter_is_checked():
    with pytest.raises(ValueError, match="stall_report_s"):
        LinkConfig(port="loop://", stall_report_s=0)
    with pytest.raises(ValueError, match="stall_report_s"):
        LinkConfig(port="loop://", stall_report_s=float("nan"))


def test_link_survives_a_consumer_and_a_device_that_never_answer(tmp_path):
    """A pty with nobody behind it (a device that never speaks): connecting, timeouts,
    reconnects; never an exception, never 'connected'."""
    master, slave = os.openpty()
    path = os.ttyname(slave)
    link = FingertipLink(
        LinkConfig(
            port=path,
            link_timeout_s=0.3,
            command_timeout_s=0.05,
            command_retries=1,
            sync_max_pings=2,
            reconnect_initial_s=0.05,
            reconnect_max_s=0.1,
        )
    )
    link.start()
    try:
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline and link.stats()["link_timeouts"] < 2:
            assert link.stats()["state"] != "connected"
            time.sleep(0.01)
        s = link.stats()
    finally:
        link.stop()
        os.close(master)
        os.close(slave)
    assert s["link_timeouts"] >= 2 and s["connects"] >= 2 and s["internal_errors"] == 0
    assert s["frames_ok"] == 0 and s["state"] != "connected"


def test_hostile_but_crc_valid_frames_never_stop_the_link(tmp_path):
    """Frames that pass every protocol check but carry extreme values (1 Hz and 4.29 GHz
    sample rates, 1-sample packets, a STREAM block in triggered mode, ACKs nobody asked
    for, clock jumps): each is used or counted, the reader never stops, packets keep
    flowing. Packets at a rate the device does not run at are counted rejections."""
    from ae_tactile.protocol import Ack, AckResult, StreamBlock

    with Rig(PtyTransport(str(tmp_path / "fingertip")), scene=LONG) as rig:
        rig.wait_connected()
        rig.run(0.3)
        one = np.ones((4, 1), np.int16)
        hostile = [
            Packet(one, 1, 1e-6),
            Packet(
                np.full((4, 8), 32767, np.int16),
                4_294_967_295,
                1e-30,
                pre_trigger=7,
                onset_index=7,
            ),
            StreamBlock(np.zeros((4, 16), np.int16), 1, 1e-6),
            Ack(65535, 200, AckResult.INTERNAL_ERROR, 7),
        ]
        for body in hostile:
            rig.runner.call(rig.device.inject_frame, body, now_ns())

        def n_rejected():
            return rig.link.stats()["packets_rejected_sample_rate"]

        rig.run(30.0, until=lambda: n_rejected() >= 3)
        n = len(rig.records)
        rig.run(30.0, until=lambda: len(rig.records) > n + 3)  # still delivering after them
        s = rig.link.stats()
        assert s["internal_errors"] == 0 and s["disconnects"] == 0 and s["state"] == "connected"
        assert s["frames_ok"] >= 4 and s["crc_errors"] == 0
        assert s["packets_rejected_sample_rate"] == 3  # two packets and the STREAM block
        fs = s["device_sample_rate_hz"]
        assert all(r.sample_rate_hz == fs for r in rig.records)
        assert all(
            np.isfinite(r.noise_rms_v) and 0 <= r.onset_index < r.samples_v.shape[1]
            for r in rig.records
        )
        assert len(rig.records) > n + 3  # still delivering


@pytest.mark.parametrize("relabel_hz", [5_000_000, 1])
def test_packet_relabelled_mid_stream_costs_only_itself(tmp_path, relabel_hz):
    """A packet of the device's own samples whose sample-rate field says 5 MHz (or 1 Hz)
    while the device runs at 10 MHz: read at that rate its delays, so its point, would be
    off by 2x (or its 400 samples would span 400 s and move the clock mapping). It is a
    counted rejection; its neighbours arrive, stamped within 3 ms of the true host time."""
    from test_faults_clock import true_stamps

    with Rig(PtyTransport(str(tmp_path / "fingertip")), scene=LONG) as rig:
        rig.wait_connected()
        rig.run(60.0, until=lambda: len(rig.records) >= 20)
        fs = rig.link.stats()["device_sample_rate_hz"]
        assert relabel_hz != fs
        real = rig.sent_packets()[-1]
        fake = Packet(real.samples, relabel_hz, real.v_per_count,
                      pre_trigger=real.pre_trigger, first_sample_index=real.first_sample_index)
        n_before = rig.runner.call(
            lambda: (rig.device.inject_frame(fake, now_ns()), len(rig.records))[1])
        rig.run(60.0, until=lambda: len(rig.records) >= n_before + 30)
        s = rig.link.stats()
    assert s["packets_rejected_sample_rate"] == 1
    assert all(r.sample_rate_hz == fs for r in rig.records)
    stamps = np.array([r.stamp_ns for r in rig.records], dtype=np.int64)
    assert np.all(np.diff(stamps) > 0)
    err_ms = (stamps - true_stamps(rig, rig.records)) / 1e6
    assert np.abs(err_ms).max() < 3.0, err_ms
    assert s["clock_steps"] == 0 and s["internal_errors"] == 0


@pytest.mark.parametrize("then", ["rest_of_the_frame", "a_new_frame"])
def test_partial_frame_then_silence_is_reported_and_kept(then):
    """A device that sends part of a frame and then pauses: the stall is reported once
    (``stalled_frames``) after stall_report_s without a byte, and the partial frame is kept.
    If the device then finishes it, the frame is delivered whole (a pause loses no valid
    frame); if it sends a new frame instead (it was reset), the new one is delivered and
    the cut one is counted (truncated, its sequence number dropped)."""
    from ae_tactile.protocol import DeviceState, FrameEncoder, Status

    master, slave = os.openpty()
    import tty

    tty.setraw(slave)
    path = os.ttyname(slave)
    enc = FrameEncoder()
    status = Status(
        1500, DeviceState.IDLE, 10_000_000, 1e-6, 200, 400, 100, 0, 0, (1, 0, 0), "AE-IDLE"
    )
    first = enc.encode(status, 1500)
    big = enc.encode(Packet(np.ones((4, 4000), np.int16), 10_000_000, 1e-6), 2000)
    link = FingertipLink(
        LinkConfig(
            port=path,
            link_timeout_s=60.0,
            stall_report_s=0.2,
            command_timeout_s=0.05,
            command_retries=1,
            sync_max_pings=1,
        )
    )
    link.start()
    try:
        deadline = time.monotonic() + 30.0
        while link.stats()["connects"] < 1 and time.monotonic() < deadline:
            time.sleep(0.01)  # the port is open (opening it empties its input)
        os.write(master, first)
        os.write(master, big[:5000])  # then silence
        while time.monotonic() < deadline and link.stats()["stalled_frames"] < 1:
            time.sleep(0.01)
        time.sleep(0.3)  # silence goes on: reported once, nothing given up
        s = link.stats()
        assert s["stalled_frames"] == 1 and s["truncated_frames"] == 0
        assert s["pending_bytes"] == 5000 and s["frames_ok"] == 1
        if then == "rest_of_the_frame":
            os.write(master, big[5000:])
        else:
            os.write(master, enc.encode(status, 2500))
        while time.monotonic() < deadline and link.stats()["frames_ok"] < 2:
            time.sleep(0.01)
        s = link.stats()
        assert s["frames_ok"] == 2 and s["state"] == "connected"
        assert s["pending_bytes"] == 0 and s["stalled_frames"] == 1
        if then == "rest_of_the_frame":
            assert s["truncated_frames"] == 0 and s["dropped_frames"] == 0
            assert s["bytes_decoded"] == len(first) + len(big)
        else:
            assert s["truncated_frames"] == 1
            assert s["dropped_frames"] == 1  # the cut frame's sequence number
        assert s["bytes_received"] == s["bytes_decoded"] + s["bytes_discarded"]
    finally:
        link.stop()
        os.close(master)
        os.close(slave)


# ------------------------------------------------------------------ property: any frames
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from test_protocol_stream import device_bodies  # noqa: E402


@settings(
    max_examples=30,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(
    st.lists(
        st.tuples(
            device_bodies,
            st.integers(0, 2**32 - 1),
            st.sampled_from(["frame", "repeat", "cut", "garbage"]),
        ),
        min_size=1,
        max_size=12,
    ),
    st.sampled_from(["triggered", "stream"]),
)
def test_any_sequence_of_valid_frames_and_damage_is_used_or_counted(items, mode):
    """The link's frame handling (the reader thread's code, without a port) on any
    sequence of CRC-valid frames with arbitrary field values, repeats, cut frames and
    garbage: no exception, no non-finite value delivered, every packet accounted for."""
    from ae_tactile.protocol import Ack, AckResult, FrameEncoder, Opcode, Packet, Status

    out = []
    link = FingertipLink(
        LinkConfig(port="loop://", mode=mode),
        clock_ns=time.monotonic_ns,
        sink=lambda b: out.extend(b.packets),
    )
    enc = FrameEncoder()
    n_packets = 0
    device_fs = 0  # the device's rate as its STATUS / SET_SAMPLE_RATE ACK say (0: unknown)
    rng = np.random.default_rng(len(items))
    for body, ts, kind in items:
        wire = enc.encode(body, ts)
        if kind != "cut" and isinstance(body, Status):
            device_fs = body.sample_rate_hz
        elif kind != "cut" and isinstance(body, Ack) and body.result == AckResult.OK:
            device_fs = body.value if body.opcode == Opcode.SET_SAMPLE_RATE else device_fs
        n_packets += (
            isinstance(body, Packet)
            and kind != "cut"
            and float(body.v_per_count) * 32768.0 <= float(np.finfo(np.float32).max)
            and device_fs in (0, body.sample_rate_hz)  # else: packets_rejected_sample_rate
        )
        if kind == "repeat":
            wire += wire
        elif kind == "cut":
            wire = wire[: max(24, len(wire) // 2)]
        elif kind == "garbage":
            wire = rng.bytes(int(rng.integers(1, 100))) + wire
        link._handle_bytes(wire)
    link._handle_frames(link.decoder.flush())
    s = link.stats()
    assert s["internal_errors"] == 0 and s["sink_errors"] == 0
    assert s["bytes_received"] == s["bytes_decoded"] + s["bytes_discarded"]
    for r in out:
        assert np.isfinite(r.samples_v).all() and np.isfinite(r.noise_rms_v)
        assert 0 <= r.onset_index < r.samples_v.shape[1]
    if mode == "triggered":
        assert len(out) == n_packets  # once each; those that would overflow: counted


def test_simulated_fingertip_refuses_a_hostile_scene_file_with_a_clear_error(tmp_path):
    """Deeply nested YAML, a list instead of a mapping, bad YAML: SceneError, no traceback."""
    from ae_tactile.sim.scene import SceneError
    from ae_tactile.virtual_device import VirtualFingertip

    cases = {
        "nested.yaml": "a: " + "[" * 5000 + "]" * 5000,
        "list.yaml": "- 1\n- 2\n",
        "bad.yaml": "generator: [unclosed\n",
    }
    for name, text in cases.items():
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(SceneError):
            VirtualFingertip(str(path))


def test_a_reader_that_falls_behind_says_so_and_when_it_is_back_in_step(tmp_path, caplog):
    """The consumer of the reader thread takes 35 ms a packet while the fingertip sends
    40 a second: bytes wait on the port after every batch. The link says once in the log
    and in its stats that it is behind (bytes waiting after every batch for 0.5 s), with
    the read lag growing; once the consumer is fast again it catches up and says that
    too. Every packet sent is delivered once, in order."""
    import logging

    from test_faults_clock import STEADY

    from ae_tactile.virtual_device import DeviceRunner, VirtualFingertip

    slow = {"on": True}
    got = []

    def sink(batch):
        got.extend(batch.packets)
        if slow["on"]:
            time.sleep(0.035 * len(batch.packets))  # [s] per packet: the device sends one in 25 ms

    transport = PtyTransport(str(tmp_path / "fingertip"))
    device = VirtualFingertip(STEADY, record=True)
    runner = DeviceRunner(device, transport)
    link = FingertipLink(LinkConfig(port=transport.port), clock_ns=time.monotonic_ns, sink=sink)
    caplog.set_level(logging.INFO, logger="ae_tactile.link")
    runner.start()
    link.start()
    try:
        deadline = time.monotonic() + 60.0
        while not link.stats()["behind"] and time.monotonic() < deadline:
            time.sleep(0.05)
        behind = link.stats()
        slow["on"] = False
        deadline = time.monotonic() + 60.0
        while link.stats()["behind"] and time.monotonic() < deadline:
            time.sleep(0.05)
        after = link.stats()
        deadline = time.monotonic() + 60.0
        while not device.finished(time.monotonic_ns()) and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)  # the last packets in flight
    finally:
        link.stop()
        runner.stop()
    assert behind["behind"] == 1 and behind["behind_episodes"] == 1, behind
    assert behind["read_lag_max_ms"] > 50.0  # packets read long after they were taken
    assert after["behind"] == 0 and after["behind_episodes"] == 1, after
    said = [r.getMessage() for r in caplog.records]
    assert sum("behind the fingertip" in m for m in said) == 1, said
    assert any("back in step" in m for m in said), said
    sent = [b.first_sample_index for k, _, b, f in device.sent_log
            if k == "packet" and f == "sent"]
    assert [p.device_sample_index for p in got] == sent  # each once, in order: none lost
