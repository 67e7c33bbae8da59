# SPDX-License-Identifier: Apache-2.0
"""Streaming renderer: chunk invariance (bit-exact), noise statistics, truth per chunk,
triggered windows cut from the stream, agreement with the batch triggered renderer."""
import numpy as np
import pytest

from ae_tactile.sim import SimConfig, render_triggered
from ae_tactile.sim.stream import (
    EmissionList,
    StreamingSource,
    StreamRenderer,
    TriggeredSource,
    sample_index_of_ns,
    time_ns_of_sample,
)


def _emissions(cfg, n=60, span_ns=50_000_000, seed=0, release_every=3):
    rng = np.random.default_rng(seed)
    pts = cfg.geometry.surface_point_from_angles(np.arccos(rng.uniform(0.1, 1, n)),
                                                 rng.uniform(0, 2 * np.pi, n))
    t = np.sort(rng.integers(0, span_ns, n))
    if n > 5:
        t[5] = t[4] + 3_000      # two emissions 3 us apart: overlapping responses
    pol = np.where(np.arange(n) % release_every == 0, -1, 1)
    return EmissionList.create(t, pts, "touch", polarity=pol, speed_m_s=rng.uniform(0.1, 0.5, n),
                               curvature_1_m=1000.0, alpha_1_s=rng.choice([2000.0, 3000.0], n),
                               density_kg_m3=cfg.density, event_id=np.arange(n))


@pytest.mark.parametrize("cfg", [SimConfig(),
                                 SimConfig(reflections=True, attenuation=True, quantization=True),
                                 SimConfig.for_medium("silicone", attenuation=True,
                                                      quantization=False)],
                         ids=["default", "all-effects", "silicone"])
def test_chunk_invariance_bit_exact(cfg):
    """Any window [n0, n1) equals the same samples of a full render, bit for bit (signal,
    noise and quantization), and so does a stream read in irregular chunks."""
    em = _emissions(cfg)
    n_total = 500_000
    r = StreamRenderer(cfg, noise_rms_v=2e-3, seed=11)
    full, _ = r.render(em, 0, n_total)
    rng = np.random.default_rng(1)
    for _ in range(25):
        a = int(rng.integers(0, n_total - 1))
        b = int(rng.integers(a + 1, min(n_total, a + 40_000) + 1))
        w, _ = StreamRenderer(cfg, noise_rms_v=2e-3, seed=11).render(em, a, b)
        assert np.array_equal(w, full[:, a:b])
    src = StreamingSource(em, cfg, noise_rms_v=2e-3, seed=11)
    parts, pos = [], 0
    while pos < n_total:
        n = min(int(rng.integers(1, 60_000)), n_total - pos)
        parts.append(src.next_chunk(n).samples_v.copy())
        pos += n
    assert np.array_equal(np.concatenate(parts, axis=1), full)


def test_signal_is_sum_of_single_emissions():
    """Linearity: the clean stream is the sum of the emissions rendered one by one."""
    cfg = SimConfig(quantization=False)
    em = _emissions(cfg, n=12, span_ns=2_000_000)
    r = StreamRenderer(cfg)
    total = r.render_clean(em, 0, 25_000)
    parts = sum(r.render_clean(em.take([i]), 0, 25_000) for i in range(len(em)))
    np.testing.assert_allclose(total, parts, rtol=0, atol=1e-15)


def test_stream_matches_batch_triggered_renderer():
    """The streaming path (tables, truncation) and the batch path (BLAS, untruncated) agree."""
    cfg = SimConfig(quantization=False, reflections=True)
    em = EmissionList.create([1_234_567], cfg.geometry.surface_point_from_xy(2.5e-3, -1e-3),
                             "touch", speed_m_s=0.3, curvature_1_m=1000.0, alpha_1_s=3000.0,
                             density_kg_m3=cfg.density, event_id=0)
    ts = TriggeredSource(em, cfg, keep_clean=True, window_s=60e-6)
    sp = ts.next_packets(5)
    assert len(sp) == 1
    u = (sp.arrival_times_s[0].min() * cfg.sample_rate_hz) - (sp.onset_index[0] - 1)
    pk = render_triggered(em.point_m, cfg, window_s=60e-6,
                          pretrigger_s=(sp.onset_index[0] - 1) / 1e7,
                          subsample_offset=float(u))
    np.testing.assert_allclose(sp.clean_v[0], pk.clean_v[0], atol=1e-6 * np.abs(pk.clean_v).max())
    np.testing.assert_allclose(sp.arrival_times_s[0], pk.arrival_times_s[0], atol=1e-12)
    np.testing.assert_allclose(sp.delays_s[0], pk.delays_s[0], atol=1e-18)


def test_stream_noise_level_and_whiteness():
    cfg = SimConfig(quantization=False)
    r = StreamRenderer(cfg, noise_rms_v=1e-3, seed=2)
    nz = r.noise(12_345, 12_345 + 200_000)
    assert nz.std() == pytest.approx(1e-3, rel=0.01)
    assert abs(nz.mean()) < 3e-3 / np.sqrt(nz.size) * 3
    # white: lag-1 autocorrelation ~ 0, channels independent
    x = nz[0]
    assert abs(np.dot(x[:-1], x[1:]) / np.dot(x, x)) < 0.01
    assert abs(np.corrcoef(nz[0], nz[1])[0, 1]) < 0.01
    # block-seeded: any sub-window gives the same numbers
    np.testing.assert_array_equal(r.noise(20_000, 20_100), nz[:, 20_000 - 12_345:20_100 - 12_345])
    # another seed gives other noise
    other = StreamRenderer(cfg, noise_rms_v=1e-3, seed=3).noise(0, 100)
    assert not np.array_equal(other, r.noise(0, 100))


def test_chunks_carry_their_ground_truth():
    cfg = SimConfig()
    em = _emissions(cfg, n=40, span_ns=20_000_000)
    src = StreamingSource(em, cfg)
    got = []
    for _ in range(20):
        c = src.next_chunk(10_000)
        t0 = c.start_time_ns
        t1 = int(time_ns_of_sample(c.start_index + 10_000, cfg.sample_rate_hz))
        assert np.all((c.emissions.time_ns >= t0) & (c.emissions.time_ns < t1))
        got.extend(c.emissions.event_id.tolist())
    assert sorted(got) == sorted(em.event_id.tolist())


def test_silent_stream_costs_no_emissions_and_is_noise_only():
    cfg = SimConfig(quantization=False)
    src = StreamingSource(EmissionList.empty(), cfg, noise_rms_v=5e-4, seed=4)
    c = src.next_chunk(50_000)
    assert len(c.emissions) == 0
    assert c.samples_v.std() == pytest.approx(5e-4, rel=0.02)


def test_streaming_source_buffer_is_bounded():
    """A long scene streamed in chunks keeps only the emissions that can still reach
    future samples."""
    cfg = SimConfig()
    em = _emissions(cfg, n=400, span_ns=400_000_000)
    src = StreamingSource(em, cfg)
    for _ in range(40):
        src.next_chunk(100_000)
        assert len(src._buffer) < 40


def test_triggered_source_windows_match_stream_and_align_onset():
    cfg = SimConfig(reflections=True)
    em = _emissions(cfg, n=30, span_ns=30_000_000)
    full, _ = StreamRenderer(cfg, noise_rms_v=1e-3, seed=5).render(em, 0, 320_000)
    ts = TriggeredSource(em, cfg, noise_rms_v=1e-3, seed=5, pretrigger_s=8e-6, window_s=40e-6)
    pk = ts.next_packets(100)
    assert len(pk) == 30
    for i in range(len(pk)):
        s = pk.start_index[i]
        assert np.array_equal(pk.samples_v[i], full[:, s:s + 400])
    assert np.all(pk.onset_index == 80)
    # onset = first sample at or after the earliest direct arrival
    first = pk.arrival_times_s.min(axis=1) * cfg.sample_rate_hz
    assert np.all((pk.onset_index - first >= -1e-6) & (pk.onset_index - first < 1))
    assert pk.n_overlapping[np.nonzero(pk.emissions.event_id == 5)[0][0]] >= 1


def test_sample_index_arithmetic_is_exact():
    t = np.array([0, 99, 100, 101, 59_999_999_950, 3_600_000_000_123], dtype=np.int64)
    n, frac = sample_index_of_ns(t, 10e6)
    np.testing.assert_array_equal(n, t // 100)
    np.testing.assert_allclose(frac, (t % 100) * 1e-9, atol=1e-18)
    np.testing.assert_array_equal(time_ns_of_sample(n, 10e6), (t // 100) * 100)
