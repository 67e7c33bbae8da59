# SPDX-License-Identifier: Apache-2.0
"""Packet detector against ground truth: analytic streams (ae_eval.synth, exact
onsets) and the simulator's streaming source (ae_tactile.sim). No ROS."""

import math

import numpy as np
import pytest

import ae_tactile.sim as sim
from ae_eval.synth import SynthEvent, random_delays, snr_amplitude, synth_stream
from ae_tactile.dsp import DetectorConfig, PacketBatch, PacketDetector, analyze_window
from ae_tactile.sim.scene import reference_noise_rms
from ae_tactile.sim.stream import (
    EmissionList,
    StaticEmissions,
    StreamingSource,
    sample_index_of_ns,
)

FS = 10e6
SIGMA = 2e-3


def run(det, x, chunk=8192, start=0):
    out = [det.process(x[:, i : i + chunk], start + i) for i in range(0, x.shape[1], chunk)]
    out.append(det.flush())
    return PacketBatch.concatenate(out, det.sample_rate_hz, det.window_samples)


def onsets(b):
    return b.start_index + b.onset_index


def match(found, truth, tol):
    """Index into found of the nearest detection within tol of each truth, or -1."""
    out = np.full(len(truth), -1)
    for i, t in enumerate(truth):
        if len(found):
            j = int(np.argmin(np.abs(found - t)))
            if abs(found[j] - t) <= tol:
                out[i] = j
    return out


def random_events(rng, n, snr_db, t0=0.5e-3, gap=(150e-6, 400e-6), fs=FS):
    amp = snr_amplitude(snr_db, SIGMA, fs)
    times = t0 + np.cumsum(rng.uniform(*gap, n))
    return [
        SynthEvent(float(t), amp * float(rng.choice([-1, 1])), random_delays(rng)) for t in times
    ]


# ---------------------------------------------------------------- detection accuracy
@pytest.mark.parametrize("snr_db", [20.0, 30.0])
def test_detects_every_emission_with_exact_onsets(snr_db):
    rng = np.random.default_rng(int(snr_db))
    evs = random_events(rng, 40, snr_db)
    n = int((evs[-1].time_s + 0.2e-3) * FS)
    x = synth_stream(n, FS, evs, noise_rms_v=SIGMA, dc_v=[0.01, -0.02, 0.0, 0.05], seed=1)
    det = PacketDetector()
    b = run(det, x)
    truth = np.array([e.onset_index(FS) for e in evs])
    m = match(onsets(b), truth, 1)
    assert (m >= 0).all(), "recall < 1"
    assert len(b) == len(evs), "precision < 1"
    err = onsets(b)[m] - truth
    assert np.abs(err).max() <= 1 and np.mean(err == 0) >= 0.9
    # windows: 10 us before and the whole first 30 us after the onset, original samples
    assert b.samples.shape == (40, 4, 400) and (b.onset_index == 100).all()
    for i, s in enumerate(b.start_index[:5]):
        assert np.array_equal(b.samples[i], x[:, s : s + 400])
    assert np.array_equal(b.polarity[m], np.sign([e.amplitude_v for e in evs]).astype(np.int8))
    # pre-onset noise within 10 % of the truth (on average; each within 25 %)
    r = b.noise_rms_v / SIGMA
    assert abs(r.mean() - 1) < 0.05 and np.all(np.abs(r - 1) < 0.25)
    assert not b.overlap.any() and not b.in_hit.any() and not b.saturated.any()
    assert (b.clear_after == 300).all()
    st = det.stats
    assert (st.hits, st.packets, st.in_hit_emissions, st.dropped_invalid) == (40, 40, 0, 0)
    assert np.all(np.isfinite(b.snr_db)) and abs(np.median(b.snr_db) - snr_db) < 1.5


@pytest.mark.parametrize("snr_db", [20.0, 30.0])
def test_simulator_stream_ground_truth(snr_db):

    cfg = sim.SimConfig()
    rng = np.random.default_rng(11)
    n_em = 80
    times = 0.5e-3 + np.cumsum(rng.uniform(100e-6, 300e-6, n_em))
    th = np.arccos(rng.uniform(np.cos(np.radians(70)), 1.0, n_em))
    pts = cfg.geometry.surface_point_from_angles(th, rng.uniform(0, 2 * np.pi, n_em))
    pol = rng.choice([-1, 1], n_em)
    em = EmissionList.create(
        (times * 1e9).astype(np.int64),
        pts,
        "touch",
        polarity=pol,
        speed_m_s=0.3,
        curvature_1_m=1000.0,
        alpha_1_s=3000.0,
        density_kg_m3=1000.0,
        event_id=np.arange(n_em),
    )
    sigma = reference_noise_rms(cfg, snr_db)
    src = StreamingSource(StaticEmissions(em), cfg, noise_rms_v=sigma, seed=2)
    det = PacketDetector(DetectorConfig(full_scale_v=cfg.adc_full_scale_v, adc_bits=cfg.adc_bits))
    out = []
    while src.position < int((times[-1] + 0.2e-3) * FS):
        ch = src.next_chunk(8192)
        out.append(det.process(ch.samples_v, ch.start_index))
    out.append(det.flush())
    b = PacketBatch.concatenate(out)
    ne, frac = sample_index_of_ns(em.time_ns, FS)
    first = frac + cfg.geometry.arrival_times_s(em.point_m).min(axis=1)
    truth = ne + np.ceil(first * FS - 1e-9).astype(np.int64)
    m = match(onsets(b), truth, 6)
    assert (m >= 0).all() and len(b) == n_em
    err = onsets(b)[m] - truth
    # the simulated front end's 1 MHz 4th-order low-pass delays the visible rise by
    # ~0.2 us: the pick is 1-3 samples after the geometric arrival, tightly
    assert err.min() >= 0 and err.max() <= 4
    assert np.mean(np.abs(err - np.median(err)) <= 1) >= 0.95
    assert np.array_equal(b.polarity[m], pol.astype(np.int8))
    # noise: the simulator's white noise plus the ADC's quantization noise (LSB^2 / 12)
    true_rms = math.sqrt(sigma**2 + cfg.lsb_v**2 / 12)
    assert abs(np.mean(b.noise_rms_v) / true_rms - 1) < 0.05
    assert abs(np.median(b.snr_db) - snr_db) < 1.5


# ---------------------------------------------------------------- overlapping emissions
@pytest.mark.parametrize(
    "dt_us, ratio",
    [(5, 1.0), (8, 1.0), (15, 1.0), (30, 1.0), (6, 0.5), (15, 0.5), (5, 2.0), (20, 2.0)],
)
def test_overlapping_emissions_each_get_a_flagged_window(dt_us, ratio):
    rng = np.random.default_rng(dt_us * 10 + int(ratio * 4))
    amp = snr_amplitude(25.0, SIGMA, FS)
    evs, truth = [], []
    for i in range(20):
        t0 = 0.6e-3 + i * 300e-6 + rng.uniform(0, 1e-6)
        a = SynthEvent(t0, amp * rng.choice([-1, 1]), random_delays(rng))
        c = SynthEvent(t0 + dt_us * 1e-6, ratio * amp * rng.choice([-1, 1]), random_delays(rng))
        evs += [a, c]
        truth.append((a.onset_index(FS), c.onset_index(FS)))
    x = synth_stream(int(6.9e-3 * FS), FS, evs, noise_rms_v=SIGMA, seed=dt_us)
    det = PacketDetector()
    b = run(det, x)
    on = onsets(b)
    ok = 0
    for a, c in truth:
        i, j = match(on, [a, c], 2)
        if i < 0 or j < 0:
            continue
        assert b.overlap[i] and b.overlap[j]
        assert b.overlap_next_id[i] == b.packet_id[j] and b.overlap_prev_id[j] == b.packet_id[i]
        assert b.clear_after[i] == on[j] - on[i]
        # inside the first packet (HDT 10 us after its last active sample) it is an
        # emission within the same AE hit
        assert b.in_hit[j] == (b.hit_id[i] == b.hit_id[j])
        if dt_us <= 8:
            assert b.in_hit[j]
        ok += 1
    assert ok >= 19, f"only {ok}/20 pairs resolved"
    assert len(b) <= 41  # no spurious extra windows


def test_overlapping_emissions_in_the_simulator():

    cfg = sim.SimConfig()
    rng = np.random.default_rng(5)
    n = 30
    t1 = 0.6e-3 + np.arange(n) * 300e-6
    dts = np.tile([5e-6, 10e-6, 25e-6], n // 3)
    times = np.concatenate([t1, t1 + dts])
    th = np.arccos(rng.uniform(np.cos(np.radians(60)), 1.0, 2 * n))
    pts = cfg.geometry.surface_point_from_angles(th, rng.uniform(0, 2 * np.pi, 2 * n))
    em = EmissionList.create(
        (times * 1e9).astype(np.int64),
        pts,
        "touch",
        polarity=rng.choice([-1, 1], 2 * n),
        speed_m_s=0.3,
        curvature_1_m=1000.0,
        alpha_1_s=3000.0,
        density_kg_m3=1000.0,
        event_id=np.arange(2 * n),
    )
    src = StreamingSource(
        StaticEmissions(em), cfg, noise_rms_v=reference_noise_rms(cfg, 25.0), seed=4
    )
    det = PacketDetector()
    out = []
    while src.position < int((t1[-1] + 0.3e-3) * FS):
        ch = src.next_chunk(8192)
        out.append(det.process(ch.samples_v, ch.start_index))
    b = PacketBatch.concatenate(out + [det.flush()])
    ne, frac = sample_index_of_ns(em.time_ns, FS)
    truth = ne + np.ceil(
        (frac + cfg.geometry.arrival_times_s(em.point_m).min(axis=1)) * FS - 1e-9
    ).astype(np.int64)
    by_id = dict(zip(em.event_id.tolist(), truth.tolist()))
    on = onsets(b)
    resolved = 0
    for i in range(n):
        a, c = match(on, [by_id[i] + 2, by_id[n + i] + 2], 3)
        resolved += a >= 0 and c >= 0 and b.overlap[a] and b.overlap[c]
    assert resolved >= n - 1 and len(b) <= 2 * n


def test_only_windows_that_intersect_are_flagged():
    amp = snr_amplitude(25.0, SIGMA, FS)
    evs = [
        SynthEvent(0.6e-3, amp),
        SynthEvent(0.6e-3 + 35e-6, amp),  # intersect
        SynthEvent(1.0e-3, amp),
        SynthEvent(1.0e-3 + 45e-6, amp),
    ]  # 45 us > 40 us
    x = synth_stream(int(1.3e-3 * FS), FS, evs, noise_rms_v=SIGMA, seed=3)
    b = run(PacketDetector(), x)
    assert len(b) == 4
    assert b.overlap.tolist() == [True, True, False, False]
    assert b.clear_after.tolist() == [300, 300, 300, 300]  # 35 us > the 30 us post part


# ---------------------------------------------------------------- AE timing rules
def test_hit_definition_time_groups_and_lockout_suppresses():
    amp = snr_amplitude(25.0, SIGMA, FS)
    times = [0.6e-3, 0.6e-3 + 50e-6, 1.2e-3]
    evs = [SynthEvent(t, amp) for t in times]
    x = synth_stream(int(1.5e-3 * FS), FS, evs, noise_rms_v=SIGMA, seed=9)
    # short HDT: three hits
    det = PacketDetector(hit_definition_time_s=10e-6)
    b = run(det, x)
    assert len(b) == 3 and det.stats.hits == 3 and not b.in_hit.any()
    assert len(set(b.hit_id.tolist())) == 3
    # HDT longer than the 50 us gap: the second emission is inside the first hit
    det = PacketDetector(hit_definition_time_s=60e-6)
    b = run(det, x)
    assert len(b) == 3 and det.stats.hits == 2 and det.stats.in_hit_emissions == 1
    assert b.in_hit.tolist() == [False, True, False] and b.hit_id[0] == b.hit_id[1]
    # HLT: no new hit within HLT after the hit ended; the second emission gets no window
    det = PacketDetector(hit_definition_time_s=10e-6, hit_lockout_time_s=100e-6)
    b = run(det, x)
    assert len(b) == 2 and det.stats.locked_out == 1 and det.stats.hits == 2
    assert np.all(np.abs(onsets(b) - [evs[0].onset_index(FS), evs[2].onset_index(FS)]) <= 1)


def test_hysteresis_no_chatter_on_a_slowly_decaying_packet():
    """A long ringing packet whose envelope decays slowly through the threshold region
    and crosses zero every 3.3 us must give exactly one window."""
    rng = np.random.default_rng(1)
    n = int(2e-3 * FS)
    x = rng.normal(0, SIGMA, (4, n))
    t = np.arange(n) / FS
    for t0 in (0.5e-3, 1.2e-3):
        for k, dl in enumerate(random_delays(rng)):
            tt = t - t0 - dl
            x[k] += np.where(
                tt >= 0, 0.05 * np.exp(-tt / 60e-6) * np.cos(2 * np.pi * 150e3 * tt), 0
            )
    det = PacketDetector()
    b = run(det, x)
    assert len(b) == 2 and det.stats.in_hit_emissions == 0
    # without hysteresis (hold of one sample, re-arm just below the threshold) the same
    # packets chatter
    det = PacketDetector(
        envelope_hold_s=0.2e-6,
        rearm_sigma=4.9,
        hit_definition_time_s=0.2e-6,
        min_separation_s=0.2e-6,
    )
    assert len(run(det, x)) > 4


# ---------------------------------------------------------------- echoes, saturation
def test_wall_echo_rejection():
    rng = np.random.default_rng(2)
    evs = random_events(rng, 20, 25.0, gap=(200e-6, 300e-6))
    x = synth_stream(
        int((evs[-1].time_s + 0.2e-3) * FS),
        FS,
        evs,
        noise_rms_v=SIGMA,
        seed=5,
        echo_ratio=-0.5,
        echo_delay_s=13.5e-6,
    )
    truth = np.array([e.onset_index(FS) for e in evs])
    plain = run(PacketDetector(), x)
    assert len(plain) >= 35 and plain.in_hit.sum() >= 15  # echoes windowed as in-hit
    det = PacketDetector(echo_delay_s=13.5e-6)
    b = run(det, x)
    assert len(b) == 20 and (match(onsets(b), truth, 1) >= 0).all()
    assert det.stats.echoes >= 20 and not b.overlap.any()


def test_saturated_packets_are_flagged():
    rng = np.random.default_rng(3)
    amp = snr_amplitude(25.0, SIGMA, FS)
    evs = [
        SynthEvent(0.6e-3, amp, random_delays(rng)),
        SynthEvent(0.9e-3, 4.0, random_delays(rng)),
        SynthEvent(1.2e-3, -4.0, random_delays(rng)),
    ]
    x = synth_stream(int(1.5e-3 * FS), FS, evs, noise_rms_v=SIGMA, seed=6, full_scale_v=1.0)
    det = PacketDetector(full_scale_v=1.0, adc_bits=12)
    b = run(det, x)
    assert len(b) == 3
    assert b.saturated.tolist() == [False, True, True] and det.stats.saturated_packets == 2
    assert b.saturated_channels[1].any()


# ---------------------------------------------------------------- sample rates, dtypes
@pytest.mark.parametrize("fs", [1e6, 2e6, 5e6, 10e6, 20e6])
def test_sample_rates_1_to_20_mhz(fs):
    rng = np.random.default_rng(int(fs // 1e6))
    evs = random_events(rng, 12, 25.0, fs=fs)
    x = synth_stream(int((evs[-1].time_s + 0.2e-3) * fs), fs, evs, noise_rms_v=SIGMA, seed=2)
    det = PacketDetector(sample_rate_hz=fs)
    b = run(det, x, chunk=3000)
    truth = np.array([e.onset_index(fs) for e in evs])
    m = match(onsets(b), truth, 1)
    assert (m >= 0).all() and len(b) == 12
    assert b.n_samples == round(40e-6 * fs) and (b.onset_index == round(10e-6 * fs)).all()
    assert abs(np.mean(b.noise_rms_v) / SIGMA - 1) < 0.1


def test_float32_input_gives_the_same_packets_as_its_float64_values():
    rng = np.random.default_rng(4)
    evs = random_events(rng, 10, 20.0)
    x32 = synth_stream(
        int((evs[-1].time_s + 0.2e-3) * FS), FS, evs, noise_rms_v=SIGMA, seed=3, dtype=np.float32
    )
    b32 = run(PacketDetector(), x32)
    b64 = run(PacketDetector(), x32.astype(np.float64))
    assert len(b32) == 10 and b32.equals(b64)
    assert b32.samples.dtype == np.float64
    s = b32.start_index[0]
    assert np.array_equal(b32.samples[0], x32[:, s : s + 400].astype(np.float64))
    # int16 ADC counts are accepted too (no exception, same windows up to the scale)
    counts = np.round(x32 / 1e-4).astype(np.int16)
    bi = run(PacketDetector(full_scale_v=3.2767), counts)
    assert len(bi) == 10


# ---------------------------------------------------------------- analyze_window
def test_analyze_window_reproduces_the_stream_fields():
    rng = np.random.default_rng(6)
    evs = random_events(rng, 15, 25.0)
    x = synth_stream(int((evs[-1].time_s + 0.2e-3) * FS), FS, evs, noise_rms_v=SIGMA, seed=4)
    b = run(PacketDetector(), x)
    a = analyze_window(b.samples, FS, start_index=b.start_index)
    assert len(a) == len(b) and a.valid.all()
    assert np.all(np.abs(a.onset_index - b.onset_index) <= 1)
    assert np.allclose(a.noise_rms_v, b.noise_rms_v, rtol=0.05)
    assert np.array_equal(a.polarity, b.polarity) and np.array_equal(a.start_index, b.start_index)
    # a device onset hint is honoured as the search centre
    h = analyze_window(b.samples, FS, onset_hint=np.full(len(b), 100))
    assert np.all(np.abs(h.onset_index - 100) <= 1)
    # single window, NaN window: no exception, valid flag, finite fields
    one = analyze_window(b.samples[0], FS)
    assert len(one) == 1
    bad = b.samples[:2].copy()
    bad[1, 2, 50:60] = np.nan
    r = analyze_window(bad, FS)
    assert r.valid.tolist() == [True, False]
    for f in ("noise_rms_v", "peak_amplitude_v", "snr_db"):
        assert np.all(np.isfinite(getattr(r, f)))
    for w in (
        np.zeros((2, 3, 400)),
        np.zeros((4,)),
        np.zeros((1, 4, 8)),
        np.zeros((1, 4, 400), complex),
    ):
        with pytest.raises(ValueError):
            analyze_window(w, FS)
