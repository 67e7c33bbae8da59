# SPDX-License-Identifier: Apache-2.0
"""Device-clock mapping: drift, heavy-tailed latency, restarts, monotonic output."""

import numpy as np
import pytest

from ae_tactile.timesync import DeviceClockMapper

MS = 1_000_000


def simulate(mapper, true_ns, device_ns, latency_ns):
    """Feed frames; return mapped host times of each frame's device time."""
    out = []
    for t, d, lat in zip(true_ns, device_ns, latency_ns):
        mapper.update(int(d), int(t + lat))
        out.append(mapper.to_host_ns(int(d)))
    return np.array(out, dtype=np.int64)


def link(rng, n, rate_hz=200.0):
    true_ns = (np.arange(n) * (1e9 / rate_hz)).astype(np.int64) + 1_000_000_000_000
    latency = (0.3 * MS + rng.exponential(1.0 * MS, n)).astype(np.int64)
    spikes = rng.random(n) < 0.02
    latency[spikes] += rng.integers(5 * MS, 40 * MS, spikes.sum())
    return true_ns, latency


def test_drifting_clock_with_jitter_is_mapped_within_1ms_and_beats_arrival_time():
    rng = np.random.default_rng(0)
    true_ns, latency = link(rng, 6000)  # 30 s at 200 frames/s
    skew = 80e-6  # 80 ppm fast device crystal
    device_ns = ((true_ns - true_ns[0]) * (1 + skew)).astype(np.int64) + 123_456_789
    mapper = DeviceClockMapper()
    mapped = simulate(mapper, true_ns, device_ns, latency)
    settled = slice(600, None)  # after 3 s
    err = mapped[settled] - true_ns[settled]
    naive = latency[settled]  # stamping with the arrival time
    assert np.percentile(np.abs(err), 99) < 1 * MS
    assert np.percentile(naive, 99) > 3 * MS  # what the estimator removes
    assert abs(mapper.device_rate_error - skew) < 20e-6
    assert np.all(np.diff(mapped) > 0)  # strictly monotonic


def test_device_restart_resyncs_and_stays_monotonic():
    rng = np.random.default_rng(1)
    true_ns, latency = link(rng, 4000)
    device_ns = (true_ns - true_ns[0]).astype(np.int64) + 5_000_000_000
    restart = 2000
    device_ns[restart:] = true_ns[restart:] - true_ns[restart]  # device clock back to 0
    mapper = DeviceClockMapper()
    mapped = simulate(mapper, true_ns, device_ns, latency)
    assert mapper.resyncs == 1
    assert np.all(np.diff(mapped) > 0)
    err = mapped[restart + 400 :] - true_ns[restart + 400 :]
    assert np.percentile(np.abs(err), 99) < 1 * MS


def test_host_clock_jump_back_resyncs():
    rng = np.random.default_rng(2)
    true_ns, latency = link(rng, 2000)
    device_ns = true_ns - true_ns[0]
    host_shift = np.where(np.arange(2000) >= 1000, -2_000 * MS, 0)  # host clock set back 2 s
    mapper = DeviceClockMapper()
    mapped = simulate(mapper, true_ns + host_shift, device_ns, latency)
    assert mapper.resyncs == 1
    err = mapped[1400:] - (true_ns + host_shift)[1400:]
    assert np.percentile(np.abs(err), 99) < 1 * MS


def test_mapping_before_update_and_bad_parameters_are_errors():
    with pytest.raises(RuntimeError, match="before any update"):
        DeviceClockMapper().to_host_ns(0)
    with pytest.raises(ValueError, match="bucket_s"):
        DeviceClockMapper(window_s=1.0, bucket_s=2.0)
    with pytest.raises(ValueError):
        DeviceClockMapper(max_skew=0.5)


@pytest.mark.parametrize("step_s", [-5.0, -1000.0, -0.5, 1000.0])
def test_device_clock_step_without_restart_is_detected_and_output_stays_monotonic(step_s):
    """The device clock steps (no BOOT: the link's mapper ignores device time going back,
    max_backstep_s = 3600): a step back shows as frames later than the model, frame after
    frame; a step forward as a frame earlier than it. Either way the model is rebuilt
    within a few frames and the output never goes back."""
    rng = np.random.default_rng(3)
    true_ns, latency = link(rng, 4000)
    device_ns = (true_ns - true_ns[0]).astype(np.int64) + 5_000_000_000
    at = 2000
    device_ns[at:] += int(step_s * 1e9)
    mapper = DeviceClockMapper(max_backstep_s=3600.0)
    mapped = simulate(mapper, true_ns, device_ns, latency)
    assert mapper.resyncs == 1 and mapper.steps == (1 if step_s < 0 else 0)
    assert np.all(np.diff(mapped) > 0)
    err = np.abs(mapped - true_ns)
    late = np.flatnonzero(err[at:] > 2 * MS)
    # back within 2 ms after step_span_s (50 ms, 10 frames here) and a few frames
    assert late.size == 0 or late.max() < 14
    assert np.percentile(err[at + 400 :], 99) < 1 * MS


def test_delayed_buckets_do_not_pull_the_envelope_late():
    """A backlog (frames queued behind a burst of garbage on a slow line, a loaded host):
    for 3 s every frame is late, by up to 20 ms; the buckets of those seconds are left out
    of the fitted line, so the stamps stay on the true time."""
    rng = np.random.default_rng(4)
    true_ns, latency = link(rng, 8000)  # 40 s
    device_ns = ((true_ns - true_ns[0]) * (1 + 50e-6)).astype(np.int64)
    a, b = 3000, 3600  # 15 s to 18 s
    latency[a:b] += np.linspace(0, 20 * MS, b - a).astype(np.int64)
    mapper = DeviceClockMapper()
    mapped = simulate(mapper, true_ns, device_ns, latency)
    err = np.abs(mapped - true_ns)
    assert np.max(err[a:]) < 1 * MS
    assert mapper.resyncs == 0 and mapper.steps == 0


def test_a_packet_out_of_order_keeps_its_own_stamp_and_a_step_back_is_held():
    """A window that started 2 ms before a packet mapped earlier (within reorder_s) is
    stamped at its own time, exactly as in order; one 1 s behind (a clock step not detected
    yet) is held after the last stamp instead of going back."""
    m = DeviceClockMapper(reorder_s=0.05)
    d0, h0 = 10**12, 5 * 10**12
    for k in range(20):
        m.update(d0 + k * 10 * MS, h0 + k * 10 * MS + MS // 2)
    in_order = m.to_host_ns(d0 + 150 * MS)
    late_packet = m.to_host_ns(d0 + 148 * MS)
    assert late_packet == in_order - 2 * MS  # its true time, not clamped
    assert m.clamped == 0
    later = m.to_host_ns(d0 + 160 * MS)
    assert later == in_order + 10 * MS
    stepped = m.to_host_ns(d0 + 160 * MS - 10**9)
    assert stepped == later + 1 and m.clamped == 1


@pytest.mark.parametrize("drain", ["one_read", "read_at_3x"])
def test_a_host_stall_is_no_clock_step(drain):
    """The host stops reading for 0.6 s (a loaded machine): the frames of that time queue
    in the kernel and are read late, by up to 0.6 s, at once or three times faster than
    they came. Their latency falls as their device time advances, where a clock step's
    would stay: no step, no re-sync, stamps on the true time throughout."""
    rng = np.random.default_rng(5)
    true_ns, latency = link(rng, 4000)
    device_ns = (true_ns - true_ns[0]).astype(np.int64) + 5_000_000_000
    a, b = 2000, 2120  # 0.6 s at 200 frames/s
    t_read = true_ns[b] + 1 * MS
    for i in range(a, b):
        if drain == "one_read":
            got = t_read
        else:  # read back at 3x the rate they came, starting at the end of the stall
            got = t_read + (true_ns[i] - true_ns[a]) // 3
        latency[i] = max(got - true_ns[i], latency[i])
    mapper = DeviceClockMapper(max_backstep_s=3600.0)
    mapped = simulate(mapper, true_ns, device_ns, latency)
    assert mapper.steps == 0 and mapper.resyncs == 0
    assert np.all(np.diff(mapped) > 0)
    assert np.abs(mapped - true_ns)[400:].max() < 1 * MS  # once the mapping has settled


@pytest.mark.parametrize("lag_ms", [300, 900])
def test_a_reader_that_stays_behind_is_no_clock_step(lag_ms):
    """A starved reader (a busy host): it falls behind by lag_ms over 0.2 s, then reads at
    the rate the frames come, that far behind, for 2 s, then catches up. Its latency does
    not fall while it stays behind, as a clock step's would not; but the device time never
    goes back, and only a device clock that steps back moves the frames late at once:
    no step, no re-sync, every stamp on the true time."""
    rng = np.random.default_rng(6)
    true_ns, latency = link(rng, 4000)
    device_ns = (true_ns - true_ns[0]).astype(np.int64) + 5_000_000_000
    a = 2000
    ramp, hold, drain = 40, 400, 60  # frames at 200/s: 0.2 s, 2 s, 0.3 s
    lag = np.concatenate([np.linspace(0, lag_ms * MS, ramp), np.full(hold, lag_ms * MS),
                          np.linspace(lag_ms * MS, 0, drain)]).astype(np.int64)
    latency[a : a + lag.size] += lag
    mapper = DeviceClockMapper(max_backstep_s=3600.0)
    mapped = simulate(mapper, true_ns, device_ns, latency)
    assert mapper.steps == 0 and mapper.resyncs == 0
    assert np.all(np.diff(mapped) > 0)
    assert np.abs(mapped - true_ns)[400:].max() < 1 * MS


def test_a_host_clock_step_moves_the_mapping_with_it():
    """The host clock (the system clock ROS stamps with) is stepped forward by 2 s (NTP at
    start-up) or back by 2 s: the link sees it against the monotonic clock and moves the
    mapping by the step at once, so stamps are the host's new time from the next frame
    (held monotonic after a step back), with no re-sync and no learning again."""
    for shift_ms in (2000, -2000):
        rng = np.random.default_rng(7)
        true_ns, latency = link(rng, 3000)
        device_ns = (true_ns - true_ns[0]).astype(np.int64) + 5_000_000_000
        at = 1500
        mapper = DeviceClockMapper(max_backstep_s=3600.0)
        out = []
        for k, (t, d, lat) in enumerate(zip(true_ns, device_ns, latency)):
            host = int(t + (shift_ms * MS if k >= at else 0))
            if k == at:
                mapper.shift_host(shift_ms * MS)
            mapper.update(int(d), host + int(lat))
            out.append(mapper.to_host_ns(int(d)))
        mapped = np.array(out, dtype=np.int64)
        truth = true_ns + np.where(np.arange(true_ns.size) >= at, shift_ms * MS, 0)
        assert mapper.resyncs == 0 and mapper.steps == 0 and mapper.host_steps == 1
        assert np.all(np.diff(mapped) > 0)
        err = np.abs(mapped - truth)
        settled = slice(at + (0 if shift_ms > 0 else 410), None)  # a step back: held 2 s
        assert err[400:at].max() < 1 * MS and err[settled].max() < 1 * MS, shift_ms
