# SPDX-License-Identifier: Apache-2.0
"""Streaming behaviour of the packet detector: identical output however the stream is
cut, gaps, bad samples, bad calls. No ROS."""

import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ae_eval.synth import SynthEvent, random_delays, snr_amplitude, synth_stream
from ae_tactile.dsp import PacketBatch, PacketDetector

FS = 10e6
SIGMA = 2e-3


def _stream():
    """30k samples: isolated and overlapping emissions, an echo-like repeat, a clipped
    packet, a burst of NaN/inf inside one packet and one outside, a DC offset."""
    rng = np.random.default_rng(42)
    amp = snr_amplitude(22.0, SIGMA, FS)
    t = [
        0.45e-3,
        0.62e-3,
        0.62e-3 + 6e-6,
        0.8e-3,
        0.8e-3 + 13.5e-6,
        1.0e-3,
        1.15e-3,
        1.3e-3,
        1.3e-3 + 22e-6,
        1.31e-3 + 40e-6,
        1.55e-3,
        1.75e-3,
        2.3e-3,
        2.6e-3,
    ]
    a = [1, -1, 0.6, 1, -0.5, 9.0, 1, 1, -1, 0.7, 1, -1, 1, 1]
    evs = [SynthEvent(ti, ai * amp, random_delays(rng)) for ti, ai in zip(t, a)]
    x = synth_stream(30000, FS, evs, noise_rms_v=SIGMA, dc_v=0.3, seed=7, full_scale_v=1.0)
    x[2, 15520:15530] = np.nan  # inside the packet at 1.55 ms: window dropped
    x[1, 21000:21004] = np.inf  # in the quiet between packets
    return x, evs


STREAM, EVENTS = _stream()


def _run(x, chunks, **kw):
    det = PacketDetector(**kw)
    out, i = [], 0
    for c in chunks:
        out.append(det.process(x[:, i : i + c], i))
        i += c
    out.append(det.flush())
    return PacketBatch.concatenate(out, det.sample_rate_hz, det.window_samples), det.stats


def _same_stats(a, b):
    da, db = dataclasses.asdict(a), dataclasses.asdict(b)
    for k in ("chunks", "chunks_with_invalid"):  # these count calls
        da.pop(k), db.pop(k)
    return da == db


REF, REF_STATS = _run(STREAM, [STREAM.shape[1]])


def test_reference_stream_is_interesting():
    """The fixture exercises overlaps, saturation and invalid samples."""
    assert len(REF) >= 11
    assert REF.overlap.sum() >= 4 and REF.saturated.sum() == 1
    assert REF_STATS.invalid_samples == 14 and REF_STATS.dropped_invalid == 1
    assert np.all(np.isfinite(REF.samples))


@pytest.mark.parametrize("size", [1, 7, 399, 400, 401, 8192])
@pytest.mark.parametrize("min_batch_s", [0.0, 1e-3])
def test_fixed_chunk_sizes_give_identical_output(size, min_batch_s):
    """min_batch_s=0 processes every chunk as it comes (arbitrary internal boundaries)."""
    n = STREAM.shape[1]
    b, stats = _run(
        STREAM, [size] * (n // size) + ([n % size] if n % size else []), min_batch_s=min_batch_s
    )
    assert b.equals(REF) and _same_stats(stats, REF_STATS)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.lists(
        st.sampled_from([1, 3, 7, 64, 399, 400, 401, 1000, 4096, 20000]), min_size=1, max_size=60
    ),
    st.sampled_from([0.0, 0.3e-3, 1e-3]),
)
def test_random_chunkings_give_identical_output(sizes, min_batch_s):
    n = STREAM.shape[1]
    chunks, total = [], 0
    while total < n:
        for s in sizes:
            s = min(s, n - total)
            if s <= 0:
                break
            chunks.append(s)
            total += s
    b, stats = _run(STREAM, chunks, min_batch_s=min_batch_s)
    assert b.equals(REF) and _same_stats(stats, REF_STATS)


def test_chunkings_are_identical_at_other_rates_and_with_float32():
    rng = np.random.default_rng(3)
    for fs in (1e6, 20e6):
        evs = [
            SynthEvent(t, snr_amplitude(25, SIGMA, fs) * s, random_delays(rng))
            for t, s in ((0.5e-3, 1), (0.7e-3, -1), (0.7e-3 + 8e-6, 1))
        ]
        x = synth_stream(int(1e-3 * fs), fs, evs, noise_rms_v=SIGMA, seed=1).astype(np.float32)
        a, _ = _run(x, [x.shape[1]], sample_rate_hz=fs)
        b, _ = _run(x, [5] * (x.shape[1] // 5), sample_rate_hz=fs, min_batch_s=0.0)
        c, _ = _run(
            x, [777] * (x.shape[1] // 777) + [x.shape[1] % 777], sample_rate_hz=fs, min_batch_s=0.0
        )
        assert len(a) == 3 and a.equals(b) and a.equals(c)


# ---------------------------------------------------------------- gaps
def test_gap_resets_cleanly_and_no_window_spans_it():
    x = STREAM
    det = PacketDetector()
    out = [det.process(x[:, :17600], 0)]
    # drop 2000 samples (a lost STREAM block): the packet at 1.75 ms loses its tail
    out.append(det.process(x[:, 19600:], 19600))
    out.append(det.flush())
    b = PacketBatch.concatenate(out)
    s = det.stats
    assert (s.gaps, s.gap_samples, s.discontinuities) == (1, 2000, 0)
    assert s.dropped_truncated == 1
    end = b.start_index + b.n_samples
    assert not np.any((b.start_index < 19600) & (end > 17600))
    assert np.array_equal(
        b.start_index[b.start_index < 17000], REF.start_index[REF.start_index < 17000]
    )
    # the detector is blind for the warm-up after the gap, then finds the late packets
    assert np.any(b.start_index > 21500)
    # a repeated / backward index is a discontinuity: same clean restart
    det.process(x[:, :5000], 0)
    det.process(x[:, 2000:9000], 2000)
    assert det.stats.discontinuities == 1


def test_windows_cut_by_the_end_of_the_stream_are_dropped():
    det = PacketDetector()
    b = PacketBatch.concatenate([det.process(STREAM[:, :6220], 0), det.flush()])
    assert det.stats.dropped_truncated == 1 and np.all(b.start_index + b.n_samples <= 6220)
    # after a flush the same detector takes a new stream from any index
    b2 = PacketBatch.concatenate([det.process(STREAM, 10**9), det.flush()])
    assert len(b2) == len(REF) and np.array_equal(b2.start_index - 10**9, REF.start_index)
    assert np.all(np.diff(np.concatenate([b.packet_id, b2.packet_id])) > 0)


# ---------------------------------------------------------------- bad samples
def _finite(b):
    for f in dataclasses.fields(b):
        v = getattr(b, f.name)
        if isinstance(v, np.ndarray) and v.dtype.kind == "f":
            assert np.all(np.isfinite(v)), f.name


@pytest.mark.parametrize(
    "name", ["nan", "inf", "zeros", "constant", "dc", "clipped", "huge", "alternating"]
)
def test_bad_streams_never_raise_and_never_produce_nan(name):
    rng = np.random.default_rng(0)
    n = 40000
    if name == "nan":
        x = rng.normal(0, SIGMA, (4, n))
        x[:, ::3] = np.nan
    elif name == "inf":
        x = rng.normal(0, SIGMA, (4, n))
        x[rng.integers(0, 4, 500), rng.integers(0, n, 500)] = -np.inf
    elif name == "zeros":
        x = np.zeros((4, n))
    elif name == "constant":
        x = np.full((4, n), 0.123)
    elif name == "dc":
        x = rng.normal(0, SIGMA, (4, n)) + np.array([[0.5], [-0.7], [0.0], [0.99]])
    elif name == "clipped":
        x = np.clip(rng.normal(0, 2.0, (4, n)), -1.0, 1.0)
    elif name == "huge":
        x = rng.normal(0, 1e30, (4, n))
    else:
        x = np.tile([[1.0, -1.0]], (4, n // 2))
    for dtype in (np.float64, np.float32):
        det = PacketDetector()
        b = PacketBatch.concatenate(
            [det.process(x[:, i : i + 3000].astype(dtype), i) for i in range(0, n, 3000)]
            + [det.flush()]
        )
        _finite(b)
        s = det.stats
        if name in ("nan", "inf", "huge"):
            assert s.invalid_samples > 0 and s.chunks_with_invalid > 0
            assert len(b) == 0 or s.dropped_invalid >= 0
        if name in ("zeros", "constant", "dc"):
            assert len(b) == 0 and s.invalid_samples == 0
        if name == "clipped":
            assert np.all(b.saturated)


def test_packets_far_from_bad_samples_survive():
    x = STREAM.copy()
    x[:, 25000:25200] = np.nan  # after the last packet's window
    b, s = _run(x, [4096] * 8)
    assert s.invalid_samples == 14 + 200
    assert len(b) == len(REF) and np.array_equal(b.start_index, REF.start_index)


# ---------------------------------------------------------------- API errors
@pytest.mark.parametrize(
    "samples",
    [
        np.zeros((3, 10)),
        np.zeros(10),
        np.zeros((4, 10, 1)),
        np.zeros((4, 10), complex),
        np.zeros((4, 10), bool),
        np.array([["a"] * 10] * 4),
        [[1, 2], [3]],
    ],
)
def test_wrong_shapes_and_types_raise_value_error(samples):
    with pytest.raises(ValueError):
        PacketDetector().process(samples, 0)


@pytest.mark.parametrize("index", [1.5, -1, True, None, "0", 2**63])
def test_bad_indices_raise_value_error(index):
    with pytest.raises(ValueError, match="first_sample_index"):
        PacketDetector().process(np.zeros((4, 10)), index)


def test_empty_chunks_and_overrides():
    det = PacketDetector(threshold_sigma=6.0)
    assert det.config.threshold_sigma == 6.0
    assert len(det.process(np.zeros((4, 0)), 123)) == 0 and det.expected_index is None
    assert len(det.flush()) == 0
    with pytest.raises(TypeError):
        PacketDetector(config={"threshold_sigma": 5})
    with pytest.raises(TypeError):
        PacketDetector(threshold=5)


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.sampled_from([1e6, 2e6, 3e6, 5e6, 7.5e6, 10e6, 12e6, 20e6]),
    st.integers(0, 2**31 - 1),
    st.booleans(),
    st.booleans(),
    st.sampled_from([0.0, 1e-3]),
    st.sampled_from([None, 13.5e-6]),
)
def test_fuzz_never_raises_never_nan(fs, seed, float32, corrupt, min_batch_s, echo):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1000, 30000))
    evs = [
        SynthEvent(
            float(t), float(rng.choice([-1, 1]) * 10 ** rng.uniform(-3, 0.5)), random_delays(rng)
        )
        for t in rng.uniform(0, n / fs, rng.integers(0, 8))
    ]
    x = synth_stream(
        n,
        fs,
        evs,
        noise_rms_v=float(10 ** rng.uniform(-5, -1)),
        dc_v=float(rng.uniform(-0.5, 0.5)),
        seed=seed % 1000,
        full_scale_v=1.0 if rng.random() < 0.5 else None,
    )
    if float32:
        x = x.astype(np.float32)
    if corrupt:
        k = int(rng.integers(1, 20))
        x[rng.integers(0, 4, k), rng.integers(0, n, k)] = rng.choice(
            [np.nan, np.inf, -np.inf, 1e30], k
        )
    det = PacketDetector(sample_rate_hz=fs, min_batch_s=min_batch_s, echo_delay_s=echo)
    out, i, start = [], 0, int(rng.integers(0, 10**9))
    with np.errstate(all="raise"):  # no floating-point warning may escape either
        while i < n:
            c = int(rng.integers(1, 9000))
            if rng.random() < 0.05:
                start += int(rng.integers(1, 5000))  # a dropped block
            out.append(det.process(x[:, i : i + c], start + i))
            i += c
        out.append(det.flush())
    _finite(PacketBatch.concatenate(out, fs, det.window_samples))
