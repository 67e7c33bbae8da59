# SPDX-License-Identifier: Apache-2.0
"""Driver link <-> virtual fingertip over a real pty (and TCP): exactness and faults.

No ROS here: these exercise ae_tactile.link and ae_tactile.virtual_device directly;
test_driver_node.py repeats the end-to-end check through the ROS nodes.
"""

import os
import time

import numpy as np
import pytest
import yaml

from ae_tactile.link import FingertipLink, LinkConfig
from ae_tactile.protocol import FRAME_OVERHEAD, PACKET_PREFIX_LEN
from ae_tactile.virtual_device import DeviceRunner, PtyTransport, TcpTransport, VirtualFingertip

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENE = os.path.join(ROOT, "config", "scenes", "random_touches.yaml")


class Rig:
    """A virtual fingertip on a transport and a link reading it, clocks shared."""

    def __init__(self, transport, scene=SCENE, **link_kw):
        self.device = VirtualFingertip(scene, record=True)
        self.transport = transport
        self.runner = DeviceRunner(self.device, transport)
        self.link = FingertipLink(
            LinkConfig(port=transport.port, **link_kw), clock_ns=time.monotonic_ns
        )
        self.records = []
        self.receive_ns = []  # host time each record's batch was read [ns]
        self.truth = []

    def __enter__(self):
        self.runner.start()
        self.link.start()
        return self

    def run(self, seconds, until=None):
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end and not (until and until()):
            for b in self.link.poll():
                self.records.extend(b.packets)
                self.receive_ns.extend([b.receive_ns] * len(b.packets))
            self.truth.extend(self.device.pop_truth())
            time.sleep(0.005)

    def wait_connected(self, timeout=30.0):
        self.run(
            timeout,
            until=lambda: (
                self.link.stats()["state"] == "connected" and self.device.scene_t0_ns is not None
            ),
        )

    def sent_packets(self, fate="sent"):
        return [
            body for kind, _, body, f in self.device.sent_log if kind == "packet" and f == fate
        ]

    def __exit__(self, *exc):
        self.link.stop()
        self.runner.stop()


@pytest.mark.parametrize("kind", ["pty", "tcp"])
def test_every_packet_arrives_once_in_order_exact_and_well_stamped(tmp_path, kind):
    transport = PtyTransport(str(tmp_path / "fingertip")) if kind == "pty" else TcpTransport()
    with Rig(transport) as rig:
        rig.wait_connected()
        rig.run(60.0, until=lambda: rig.device.finished(time.monotonic_ns()))
        rig.run(20.0, until=lambda: len(rig.records) >= len(rig.sent_packets()))  # in flight
        rig.run(0.3)
        sent = rig.sent_packets()
        captured = [t for t in rig.truth if t.captured]
        assert len(sent) >= 30 and len(captured) == len(sent)
        assert len(rig.records) == len(sent)  # exactly once
        idx = [r.device_sample_index for r in rig.records]
        assert idx == [p.first_sample_index for p in sent]  # in order, none missing
        assert [r.sequence_id for r in rig.records] == list(range(len(sent)))
        for r, p in zip(rig.records, sent):  # samples exact after scaling
            expect = (p.samples.astype(np.float32) * np.float32(p.v_per_count)).astype(np.float32)
            assert np.array_equal(r.samples_v, expect)
        # Stamp of the first sample + onset vs the emission's ground-truth time: < 1 ms.
        err_ms = [
            (r.stamp_ns + r.onset_index * 1e9 / r.sample_rate_hz - t.device_time_ns) / 1e6
            for r, t in zip(rig.records, captured)
        ]
        assert max(abs(e) for e in err_ms) < 1.0, err_ms
        s = rig.link.stats()
        assert s["crc_errors"] == s["dropped_frames"] == s["bytes_discarded"] == 0
        assert s["device_serial"] == "AE-SIM-0001"


def test_a_device_stopped_before_it_started_closes_its_port(tmp_path):
    """A simulated fingertip stopped while its node was still being built (Ctrl-C during
    the start-up) never started its loop: stopping it closes the port, raises nothing."""
    transport = PtyTransport(str(tmp_path / "fingertip"))
    runner = DeviceRunner(VirtualFingertip(SCENE), transport)
    assert os.path.islink(tmp_path / "fingertip")
    runner.stop()
    assert not transport.connected() and not os.path.lexists(tmp_path / "fingertip")


def test_the_sink_sees_waiting_bytes_and_gets_an_idle_call_after_the_last_packet(tmp_path):
    """What the in-process pipeline relies on: `bytes_waiting` is true while frames sit on
    the port (the reader is held in the sink, so it cannot have taken them), the frames
    that waited come as one batch (more than the tty's 4 KiB per read), and the link
    calls `on_idle` once the packets stop. Every packet still arrives once."""
    transport = PtyTransport(str(tmp_path / "fingertip"))
    device = VirtualFingertip(SCENE, record=True)
    runner = DeviceRunner(device, transport)
    calls, seen = [], {}

    def packets_sent():
        return [b for kind, _, b, f in device.sent_log if kind == "packet" and f == "sent"]

    def sink(batch):
        calls.append(("batch", len(batch.packets)))
        if "waiting" not in seen:  # hold the reader until the device sent 3 more packets
            n0 = len(packets_sent())
            t_end = time.monotonic() + 30.0
            while len(packets_sent()) < n0 + 3 and time.monotonic() < t_end:
                time.sleep(0.001)
            time.sleep(0.05)  # the last one's bytes are on the port
            seen["waiting"] = link.bytes_waiting()

    link = FingertipLink(
        LinkConfig(port=transport.port),
        clock_ns=time.monotonic_ns,
        sink=sink,
        on_idle=lambda: calls.append(("idle", 0)),
    )
    assert not link.bytes_waiting()  # no port open yet
    runner.start()
    link.start()
    try:
        t_end = time.monotonic() + 90.0
        while time.monotonic() < t_end and not device.finished(time.monotonic_ns()):
            time.sleep(0.01)
        sent = packets_sent()
        while time.monotonic() < t_end and sum(n for k, n in calls if k == "batch") < len(sent):
            time.sleep(0.01)
        time.sleep(0.1)  # > read_timeout_s: the cycles after the last packet
    finally:
        link.stop()
        runner.stop()
    assert seen["waiting"] is True
    # what waited while the reader was held comes as one batch (a backlog is batched)
    assert max(n for k, n in calls if k == "batch") >= 3
    assert len(sent) >= 30 and sum(n for k, n in calls if k == "batch") == len(sent)
    last_batch = max(i for i, c in enumerate(calls) if c[0] == "batch")
    assert ("idle", 0) in calls[last_batch + 1 :]
    assert link.stats()["sink_errors"] == 0


def test_garbage_and_crc_faults_are_counted_exactly_and_lose_nothing_valid(tmp_path):
    rng = np.random.default_rng(3)
    garbage = bytes(rng.integers(0, 256, 5000, dtype=np.uint8))
    with Rig(PtyTransport(str(tmp_path / "fingertip"))) as rig:
        rig.wait_connected()
        rig.run(0.2)
        rig.device.inject_garbage(garbage)  # between two frames
        rig.device.corrupt_next(3)  # three PACKET frames with one bad bit each
        rig.run(60.0, until=lambda: rig.device.finished(time.monotonic_ns()))
        rig.run(20.0, until=lambda: len(rig.records) >= len(rig.sent_packets()))  # in flight
        rig.run(0.3)
        sent, corrupted = rig.sent_packets(), rig.sent_packets("corrupted")
        assert len(corrupted) == 3
        assert [r.device_sample_index for r in rig.records] == [p.first_sample_index for p in sent]
        s = rig.link.stats()
        assert s["crc_errors"] == 3
        assert (
            s["dropped_frames"] == 3 and s["packets_dropped"] == 3
        )  # their sequence numbers are gone
        corrupt_bytes = sum(
            FRAME_OVERHEAD + PACKET_PREFIX_LEN + 8 * p.n_samples for p in corrupted
        )
        assert s["bytes_discarded"] == len(garbage) + corrupt_bytes
        assert (
            s["bytes_received"] == s["bytes_decoded"] + s["bytes_discarded"] + s["pending_bytes"]
        )


def test_unplug_for_one_second_reconnects_and_resumes(tmp_path):
    with open(SCENE) as fh:
        scene = dict(yaml.safe_load(fh), duration_s=6.0, name="long_random_touches")
    with Rig(
        PtyTransport(str(tmp_path / "fingertip")),
        scene=scene,
        reconnect_initial_s=0.1,
        reconnect_max_s=0.4,
    ) as rig:
        rig.wait_connected()
        rig.run(0.3)
        rig.run(20.0, until=lambda: len(rig.records) >= len(rig.sent_packets()) > 0)

        def unplug():  # under the device loop's lock: nothing is sent in between
            log_at_unplug = len(rig.device.sent_log)
            rig.runner.unplug(1.0)
            return log_at_unplug, len(rig.sent_packets())

        link_path = str(tmp_path / "fingertip")
        assert os.path.islink(link_path)
        log_at_unplug, n_sent = rig.runner.call(unplug)
        # like a udev rule: nothing at the stable name while unplugged (the driver cannot
        # open another program's pty that took the closed one's number)
        assert not os.path.lexists(link_path)
        rig.run(0.2)
        before = len(rig.records)
        assert before <= n_sent  # those in flight at the unplug are lost with it
        rig.run(20.0, until=lambda: rig.link.stats()["state"] != "connected")
        assert rig.link.stats()["state"] != "connected"
        rig.run(
            30.0, until=lambda: rig.link.stats()["connects"] == 2 and len(rig.records) > before + 3
        )
        s = rig.link.stats()
        assert s["disconnects"] == 1 and s["connects"] == 2 and s["state"] == "connected"
        assert os.path.islink(link_path)  # back, on the new pty
        assert rig.device.boots == 1  # re-plug rebooted the device
        assert s["clock_resyncs"] >= 2  # time mapping rebuilt
        after = [r.device_sample_index for r in rig.records[before:]]
        stamps = [r.stamp_ns for r in rig.records]
        assert all(b > a for a, b in zip(stamps, stamps[1:]))  # monotonic across the outage
        # Everything the rebooted device sent arrived once, in order (the newest one or two
        # may still be in flight when we look).
        resent = [
            p.first_sample_index
            for kind, _, p, f in rig.device.sent_log[log_at_unplug:]
            if kind == "packet" and f == "sent"
        ]
        rig.run(30.0, until=lambda: len(rig.records) - before >= len(resent))  # in flight: arrive
        after = [r.device_sample_index for r in rig.records[before:]]
        assert len(after) > 3 and after[: len(resent)] == resent


def test_clock_round_trips_during_acquisition_lose_nothing_and_keep_stamps(tmp_path):
    """A status round trip every 0.05 s while packets flow (the clock mapping's fresh
    round-trip samples): every one is answered, no packet is lost or doubled, and the
    stamps stay within 1 ms of the emissions' ground truth."""
    with Rig(PtyTransport(str(tmp_path / "fingertip")), sync_period_s=0.05) as rig:
        rig.wait_connected()
        rig.run(60.0, until=lambda: rig.device.finished(time.monotonic_ns()))
        rig.run(20.0, until=lambda: len(rig.records) >= len(rig.sent_packets()))
        sent = rig.sent_packets()
        captured = [t for t in rig.truth if t.captured]
        s = rig.link.stats()
        duration_s = (captured[-1].device_time_ns - captured[0].device_time_ns) / 1e9
        assert duration_s > 0.5
        # one round trip per 0.05 s at least while acquiring (the reader may be late, never
        # early), all of them answered
        assert s["clock_pings"] >= s["sync_good_pings"] + int(duration_s / 0.05) // 2
        assert s["commands_unacked"] == s["commands_failed"] == 0
        assert [r.device_sample_index for r in rig.records] == [
            p.first_sample_index for p in sent
        ]
        err_ms = [
            (r.stamp_ns + r.onset_index * 1e9 / r.sample_rate_hz - t.device_time_ns) / 1e6
            for r, t in zip(rig.records, captured)
        ]
        assert max(abs(e) for e in err_ms) < 1.0, err_ms


def test_bad_link_parameters_are_rejected_with_the_reason():
    with pytest.raises(ValueError, match="mode"):
        LinkConfig(port="/dev/null", mode="burst")
    with pytest.raises(ValueError, match="port"):
        LinkConfig(port="")
    with pytest.raises(ValueError, match="sync_period_s"):
        LinkConfig(port="loop://", sync_period_s=float("nan"))
    with pytest.raises(ValueError, match="pre_trigger"):
        LinkConfig(port="loop://", packet_samples=100, pre_trigger_samples=100)
    with pytest.raises(ValueError, match="speed"):
        VirtualFingertip(SCENE, speed=0)


def test_missing_port_retries_without_crashing():
    """A port that is not there: retried with back-off, and every snapshot in between says
    disconnected, with the failure counted together with its reason."""
    link = FingertipLink(
        LinkConfig(port="/nonexistent/ttyACM9", reconnect_initial_s=0.05, reconnect_max_s=0.1)
    )
    link.start()
    snaps, deadline = [], time.monotonic() + 30.0
    try:
        while (not snaps or snaps[-1]["connect_failures"] < 3) and time.monotonic() < deadline:
            snaps.append(link.stats())
            time.sleep(0.001)
    finally:
        link.stop()
    assert snaps[-1]["connect_failures"] >= 3
    assert all(s["state"] == "disconnected" for s in snaps)
    assert all("open failed" in s["last_error"] for s in snaps if s["connect_failures"])


def test_stream_mode_cuts_each_emission_on_the_host(tmp_path):
    """STREAM blocks (played at 1/20 real time: 10 MS/s through Python) -> host detector."""
    from ae_tactile.geometry import FingertipGeometry

    with open(os.path.join(ROOT, "config", "scenes", "paper_positions.yaml")) as fh:
        spec = yaml.safe_load(fh)
    rig = Rig(PtyTransport(str(tmp_path / "fingertip")), mode="stream")
    rig.device = VirtualFingertip(spec, record=True, speed=0.05, stream_block_samples=4000)
    rig.runner = DeviceRunner(rig.device, rig.transport)
    with rig:
        rig.wait_connected()
        rig.run(120.0, until=lambda: rig.device.finished(time.monotonic_ns()))
        rig.run(0.3)
        truth = [t for t in rig.truth if t.kind == "touch"]
        assert len(truth) == 3 and len(rig.records) == 3
        fs = rig.records[0].sample_rate_hz
        geo = FingertipGeometry()
        for r, t in zip(rig.records, truth):
            first_arrival_s = t.scene_time_ns * 1e-9 + geo.arrival_times_s(t.point_m).min()
            expect = first_arrival_s * fs - rig.device.index_offset
            assert abs(r.device_sample_index + r.onset_index - expect) <= 3
            assert not r.saturated and r.noise_rms_v > 0
        s = rig.link.stats()
        assert s["stream_gaps"] == 0 and s["crc_errors"] == 0 and s["dropped_frames"] == 0
        assert rig.device.frames_sent["stream"] >= 50
