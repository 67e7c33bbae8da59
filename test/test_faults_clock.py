# SPDX-License-Identifier: Apache-2.0
"""Device clock faults on a real pty with a real FingertipLink and VirtualFingertip: the
device clock steps back or forward, with or without a reboot. The link's packet stamps
never go back and return to the true host time within a few packets.

No wall-clock bounds: waits are on conditions with generous timeouts, the assertions on
counters, stamps and packet counts.
"""

import numpy as np
import pytest
import yaml
from test_hardware_link import SCENE, Rig

from ae_tactile.virtual_device import PtyTransport

#: 40 emissions/s for 12 s: packets keep coming long after the step.
STEADY = dict(yaml.safe_load(open(SCENE)), duration_s=12.0, name="steady_touches")
MS = 1_000_000


def true_stamps(rig, records):
    """Host time [ns] of each record's first sample, from the device's own log (matched in
    order by sample index: a reboot may lose the packets it had queued)."""
    sent = [
        (body.first_sample_index, t)
        for (kind, _, body, fate), t in zip(rig.device.sent_log, rig.device.sent_host_ns)
        if kind == "packet" and fate == "sent"
    ]
    out, j = [], 0
    for r in records:
        while sent[j][0] != r.device_sample_index:
            j += 1
        out.append(sent[j][1])
        j += 1
    return np.array(out, dtype=np.int64)


@pytest.mark.parametrize("reboot", [False, True], ids=["no_reboot", "reboot"])
@pytest.mark.parametrize("step_s", [-5.0, -1000.0, 1000.0])
def test_device_clock_step_keeps_stamps_monotonic_and_true(tmp_path, step_s, reboot):
    with Rig(PtyTransport(str(tmp_path / "fingertip")), scene=STEADY) as rig:
        rig.wait_connected()
        rig.run(60.0, until=lambda: len(rig.records) >= 30)

        def step():
            if reboot:
                rig.device.boot()  # clock from 0, BOOT flag, acquisition stopped
            rig.device.step_clock(step_s)
            return len(rig.records)

        n_before = rig.runner.call(step)
        rig.run(60.0, until=lambda: len(rig.records) >= n_before + 60)
        s = rig.link.stats()
        stamps = np.array([r.stamp_ns for r in rig.records], dtype=np.int64)
        assert np.all(np.diff(stamps) > 0)  # never back, never twice the same
        err_ms = (stamps - true_stamps(rig, rig.records)) / MS
        after = np.abs(err_ms[n_before:])
        off = np.flatnonzero(after > 3.0)
        # back within 3 ms of the true host time after a few packets, and staying there
        assert off.size == 0 or off.max() < 8, (off, err_ms[n_before : n_before + 12])
        assert np.abs(err_ms[:n_before]).max() < 3.0
        assert s["internal_errors"] == 0 and s["disconnects"] == 0
        if reboot:
            assert s["device_restarts_handled"] == 1
        elif step_s < 0:
            assert s["clock_steps"] >= 1  # detected from the packets' latency
        assert s["clock_resyncs"] >= 2
        print(
            f"step {step_s:+g} s reboot={reboot}: {off.size} packets off by > 3 ms,"
            f" first ones {np.round(err_ms[n_before : n_before + 6], 2)} ms"
        )
