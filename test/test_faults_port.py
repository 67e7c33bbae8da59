# SPDX-License-Identifier: Apache-2.0
"""The link's hold on its device over a real pty: one owner per port (a second link on the
same port is refused, naming the owner, and the first keeps everything), and liveness is
data (a device that stops acquiring without a reboot, heartbeats still coming, is
restarted, then reconnected if that does not help).

No wall-clock bounds: waits are on conditions with generous timeouts, the assertions on
counters and on what is delivered.
"""

import os
import time

import yaml
from test_hardware_link import SCENE, Rig

from ae_tactile.link import FingertipLink, LinkConfig
from ae_tactile.protocol import DeviceState
from ae_tactile.virtual_device import PtyTransport

STEADY = dict(yaml.safe_load(open(SCENE)), duration_s=10.0, name="steady_touches")


def sent_indices(rig):
    return [p.first_sample_index for p in rig.sent_packets()]


def test_a_second_link_on_the_same_port_is_refused_and_the_first_keeps_everything(tmp_path):
    with Rig(PtyTransport(str(tmp_path / "fingertip")), scene=STEADY) as rig:
        rig.wait_connected()
        rig.run(60.0, until=lambda: len(rig.records) >= 10)
        for port in (rig.transport.path, rig.transport.port):  # the pty and its symlink
            second = FingertipLink(
                LinkConfig(port=port, reconnect_initial_s=0.05, reconnect_max_s=0.1)
            )
            second.start()
            try:
                deadline = time.monotonic() + 30.0
                while second.stats()["port_busy"] < 3 and time.monotonic() < deadline:
                    rig.run(0.02)
                s2 = second.stats()
            finally:
                second.stop()  # never connected: sends no STOP to the first one's device
            assert s2["port_busy"] >= 3 and s2["connect_failures"] == s2["port_busy"]
            assert s2["state"] == "disconnected" and s2["frames_ok"] == 0
            assert f"in use by pid {os.getpid()}" in s2["last_error"]
            assert rig.transport.path in s2["last_error"] or port in s2["last_error"]
        n = len(rig.records)
        rig.run(60.0, until=lambda: len(rig.records) >= n + 10)  # the first goes on
        rig.run(60.0, until=lambda: rig.device.finished(time.monotonic_ns()))
        rig.run(30.0, until=lambda: len(rig.records) >= len(rig.sent_packets()))
        s = rig.link.stats()
        assert [r.device_sample_index for r in rig.records] == sent_indices(rig)  # all of it
        assert s["disconnects"] == 0 and s["connects"] == 1 and s["port_busy"] == 0
        assert rig.device.state == DeviceState.TRIGGERED  # nobody stopped it


def test_a_lock_left_by_a_closed_link_does_not_block_the_next_one(tmp_path):
    with Rig(PtyTransport(str(tmp_path / "fingertip")), scene=STEADY) as rig:
        rig.wait_connected()
        rig.link.stop()
        rig.link = FingertipLink(LinkConfig(port=rig.transport.port))
        rig.link.start()
        n = len(rig.records)
        rig.run(60.0, until=lambda: len(rig.records) >= n + 5)
        assert rig.link.stats()["port_busy"] == 0 and len(rig.records) >= n + 5


def test_a_device_that_stops_acquiring_is_restarted(tmp_path):
    with Rig(PtyTransport(str(tmp_path / "fingertip")), scene=STEADY) as rig:
        rig.wait_connected()
        rig.run(60.0, until=lambda: len(rig.records) >= 10)
        rig.runner.call(rig.device.halt_acquisition)  # no reboot; heartbeats go on
        rig.run(60.0, until=lambda: rig.link.stats()["acquisition_restarts"] >= 1)
        n = len(rig.records)
        rig.run(60.0, until=lambda: len(rig.records) >= n + 10)
        s = rig.link.stats()
        assert s["acquisition_restarts"] == 1 and s["acquisition_reconnects"] == 0
        assert s["disconnects"] == 0 and s["state"] == "connected"
        assert len(rig.records) >= n + 10 and rig.device.boots == 0


def test_a_device_that_will_not_restart_acquiring_is_reconnected(tmp_path):
    with Rig(PtyTransport(str(tmp_path / "fingertip")), scene=STEADY) as rig:
        rig.wait_connected()
        rig.run(60.0, until=lambda: len(rig.records) >= 10)
        start = rig.device._start

        def broken():
            rig.device._start = lambda mode, now_ns: None  # START acknowledged, ignored
            rig.device.halt_acquisition()

        rig.runner.call(broken)
        # the reconnect is counted, then the port closed (disconnects): wait for both
        rig.run(60.0, until=lambda: rig.link.stats()["acquisition_reconnects"] >= 1
                and rig.link.stats()["disconnects"] >= 1)
        s = rig.link.stats()
        assert s["acquisition_restarts"] >= 1 and s["acquisition_reconnects"] >= 1
        assert s["disconnects"] >= 1
        rig.runner.call(setattr, rig.device, "_start", start)  # the fault clears
        n = len(rig.records)
        rig.run(60.0, until=lambda: len(rig.records) >= n + 10)
        assert len(rig.records) >= n + 10 and rig.link.stats()["state"] == "connected"


def test_heartbeats_of_a_device_acquiring_with_nothing_to_capture_keep_it_alive(tmp_path):
    """Triggered mode with no emission: no packet for longer than acquisition_timeout_s,
    but the heartbeats report the running state: no restart."""
    quiet = dict(STEADY, params=dict(STEADY["params"], rate_hz=0.001), name="quiet")
    with Rig(PtyTransport(str(tmp_path / "fingertip")), scene=quiet) as rig:
        rig.wait_connected()
        t_dev = rig.device.device_us(time.monotonic_ns())
        rig.run(60.0, until=lambda: rig.device.device_us(time.monotonic_ns()) - t_dev > 6e6)
        s = rig.link.stats()
        assert s["acquisition_restarts"] == 0 and s["state"] == "connected"
