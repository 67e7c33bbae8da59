# SPDX-License-Identifier: Apache-2.0
"""Device clock faults on a real pty with a real FingertipLink and VirtualFingertip: the
device clock steps back or forward, with or without a reboot. The link's packet stamps
never go back and return to the true host time within a few packets.

No wall-clock bounds: waits are on conditions with generous timeouts, the assertions on
counters, stamps and packet counts.
"""

import os
import time

import numpy as np
import pytest
import yaml
from test_hardware_link import SCENE, Rig

from ae_tactile.pipeline import ContactPipeline, PacketLocalizer, SlipStage
from ae_tactile.records import EventType
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


def floor_ms(rig, truth, start=0):
    """[ms] From record ``start`` on, the least read delay so far of the records with true
    times ``truth`` (the first ones): each record's read time less its last sample's true
    time. No clock mapping can be truer than the least-delayed frame it has seen (its
    envelope): on a busy host every frame may be read late for a while."""
    recs = rig.records[: len(truth)]
    end = truth + np.array([(r.samples_v.shape[1] - 1) * 1e9 / r.sample_rate_hz
                            for r in recs], dtype=np.int64)
    delay_ms = (np.array(rig.receive_ns[: len(truth)], dtype=np.int64) - end) / MS
    return np.minimum.accumulate(delay_ms[start:])


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
        truth = true_stamps(rig, rig.records)
        err_ms = (stamps - truth) / MS
        # After the step the device clock's offset is new: the mapping learns it afresh
        # from the frames read since (`floor_ms`).
        after_floor = floor_ms(rig, truth, n_before)
        off = np.flatnonzero(np.abs(err_ms[n_before:]) > 3.0 + after_floor)
        # back within 3 ms of the true host time, plus that floor, after a few packets
        assert off.size == 0 or off.max() < 8, (off, err_ms[n_before : n_before + 12],
                                                after_floor[:12])
        assert np.all(np.abs(err_ms[:n_before]) < 3.0 + floor_ms(rig, truth)[:n_before])
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


SLIP_SCENE = os.path.join(os.path.dirname(SCENE), "incipient_slip.yaml")


@pytest.mark.parametrize("step_s", [-5.0, 1000.0])
def test_slip_detection_keeps_working_across_a_clock_step(tmp_path, step_s):
    """The incipient-slip scene (micro-slips from the start, gross slip at 1 s of its 1.2 s)
    through the link and the driver's ContactPipeline; the device clock steps while the
    micro-slips come. The slip detector sees monotonic stamps: it rejects nothing as out of
    order, and the gross slip after the step is still reported as SLIP."""
    pipe = ContactPipeline(PacketLocalizer("ml"), SlipStage())
    contacts, slips = [], []
    with Rig(PtyTransport(str(tmp_path / "fingertip")), scene=SLIP_SCENE) as rig:
        rig.wait_connected()
        fed = 0

        def feed():
            nonlocal fed
            new = rig.records[fed:]
            fed = len(rig.records)
            if new:
                pipe.process(new, contacts.extend, slips.extend)
                pipe.run_pending_slip()
            return False

        rig.run(60.0, until=lambda: feed() or len(rig.records) >= 20)
        n_before = rig.runner.call(lambda: (rig.device.step_clock(step_s), len(rig.records))[1])
        # until the scene's end (gross slip and its SLIP) has come through
        rig.run(60.0, until=lambda: feed() or any(
            s.event_type == EventType.SLIP for s in slips[:]) and len(rig.records) > n_before + 40)
        feed()
        pipe.run_pending_slip()
    c = pipe.all_counts()
    stamps = np.array([r.stamp_ns for r in rig.records], dtype=np.int64)
    assert np.all(np.diff(stamps) > 0)
    assert c.get("slip_rejected_out_of_order", 0) == 0, dict(c)
    t_step = rig.records[n_before].stamp_ns
    slip_after = [s for s in slips if s.event_type == EventType.SLIP and s.time_ns > t_step]
    assert slip_after, [(EventType(s.event_type).name, s.time_ns - t_step) for s in slips]
    assert sum(1 for x in contacts if x.time_ns > t_step) >= 20
    assert rig.link.stats()["clock_steps"] >= (1 if step_s < 0 else 0)


def test_stamps_stay_true_after_a_burst_of_garbage(tmp_path):
    """A burst of garbage on the line (noise on the wire) delays the frames behind it by
    the time the host takes to scan it: those packets arrive late, but their stamps come
    from the device clock, and the late arrivals do not pull the mapping; every packet
    after the burst is stamped within 3 ms of the true host time (plus the least delay of
    any frame read: the most any mapping can know)."""
    rng = np.random.default_rng(5)
    with Rig(PtyTransport(str(tmp_path / "fingertip")), scene=STEADY) as rig:
        rig.wait_connected()
        rig.run(60.0, until=lambda: len(rig.records) >= 30)
        for _ in range(5):  # bursts of noise, each as long as ~100 packets
            n = rig.runner.call(
                lambda: (rig.device.inject_garbage(rng.bytes(400_000)), len(rig.records))[1])
            rig.run(60.0, until=lambda n=n: len(rig.records) >= n + 15)
        n_before = n
        rig.run(60.0, until=lambda: len(rig.records) >= n_before + 60)
        s = rig.link.stats()
    assert s["bytes_discarded"] >= 5 * 300_000  # the bursts went through the decoder
    stamps = np.array([r.stamp_ns for r in rig.records], dtype=np.int64)
    assert np.all(np.diff(stamps) > 0)
    truth = true_stamps(rig, rig.records)
    err_ms = (stamps - truth) / MS
    # the bursts' late frames do not pull the mapping: within 3 ms plus the least delay
    # of any frame read (`floor_ms`: 0.1-0.5 ms on an idle host)
    off = np.abs(err_ms) >= 3.0 + floor_ms(rig, truth)
    assert not off.any(), np.round(err_ms[off], 2)
    print(f"after garbage bursts: |error| p50 {np.median(np.abs(err_ms)):.2f} ms,"
          f" max {np.abs(err_ms).max():.2f} ms over {len(err_ms)} packets")


@pytest.mark.parametrize("step_s", [2.0, -2.0])
def test_a_host_clock_step_moves_the_stamps_with_it(tmp_path, step_s):
    """The host clock the link stamps with (the system clock under ROS) is stepped by 2 s
    while packets come (NTP setting it): the link sees the step against the monotonic
    clock, the mapping moves with it, and the packets after it are stamped in the host's
    new time, with no device clock step, no re-sync and stamps that never go back."""
    shift = [0]
    with Rig(PtyTransport(str(tmp_path / "fingertip")), scene=STEADY) as rig:
        rig.link.clock_ns = lambda: time.monotonic_ns() + shift[0]
        rig.wait_connected()
        rig.run(60.0, until=lambda: len(rig.records) >= 30)
        n_before = len(rig.records)
        shift[0] = int(step_s * 1e9)
        rig.run(60.0, until=lambda: len(rig.records) >= n_before + 200)
        s = rig.link.stats()
    stamps = np.array([r.stamp_ns for r in rig.records], dtype=np.int64)
    assert np.all(np.diff(stamps) > 0)
    truth = true_stamps(rig, rig.records)
    err_ms = (stamps - truth - np.where(np.arange(truth.size) >= n_before, shift[0], 0)) / MS
    bound = 3.0 + floor_ms(rig, truth[:n_before])  # before the step, in one host time
    assert np.all(np.abs(err_ms[:n_before]) < bound)
    # a step forward: true at once; a step back: held after the last stamp for 2 s (40/s);
    # the mapping is kept (no new floor to learn): within the bound at the step
    settle = n_before + (5 if step_s > 0 else 100)
    assert np.all(np.abs(err_ms[settle:]) < bound[-1]), np.round(
        err_ms[n_before:settle + 5], 2)
    assert s["clock_host_steps"] == 1 and s["clock_steps"] == 0 and s["clock_resyncs"] == 1
