# SPDX-License-Identifier: Apache-2.0
"""Building blocks of ae_tactile.dsp: streaming filter, noise tracker, AIC picker,
window features, configuration. Pure numpy/scipy, no ROS."""

import math

import numpy as np
import pytest
from scipy import signal

from ae_eval.synth import SynthEvent, hp_step, random_delays, snr_amplitude, synth_stream
from ae_tactile.dsp import (
    BlockNoiseTracker,
    DetectorConfig,
    StreamingSOS,
    aic_pick,
    design_bandpass_sos,
    noise_power_gain,
    window_features,
)
from ae_tactile.dsp.features import window_features_fixed
from ae_tactile.dsp.filters import diff_noise_ratio

FS = 10e6


# ---------------------------------------------------------------- filters
def test_bandpass_design_corners_and_low_rate_clipping():
    sos = design_bandpass_sos(10e6, 100e3, 1.5e6)
    assert sos.shape == (2, 6)  # HP2 + LP2
    w, h = signal.sosfreqz(sos, worN=[50e3, 100e3, 500e3, 1.5e6, 4e6], fs=10e6)
    g = np.abs(h)
    assert g[1] == pytest.approx(1 / math.sqrt(2), rel=0.05)  # -3 dB at both corners
    assert g[3] == pytest.approx(1 / math.sqrt(2), rel=0.05)
    assert g[2] > 0.95 and g[0] < 0.3 and g[4] < 0.2
    # at low rates the low-pass is clipped to 0.36 fs (Nyquist), dropped at 1 MS/s where
    # that would leave less than a factor 4 above the high-pass: a pure high-pass remains
    w, h = signal.sosfreqz(design_bandpass_sos(10e6 / 3, 100e3, 1.5e6), worN=[1.2e6], fs=10e6 / 3)
    assert abs(h[0]) == pytest.approx(1 / math.sqrt(2), rel=0.05)
    assert design_bandpass_sos(1e6, 100e3, 1.5e6).shape == (1, 6)
    with pytest.raises(ValueError, match="highpass_hz"):
        design_bandpass_sos(1e6, 450e3, None)
    with pytest.raises(ValueError, match="lowpass_hz"):
        design_bandpass_sos(10e6, 100e3, 50e3)


def test_streaming_filter_is_bit_identical_to_one_shot_and_has_no_dc_transient():
    sos = design_bandpass_sos(5e6, 100e3, 1.5e6)
    rng = np.random.default_rng(0)
    x = rng.normal(size=(4, 5000)) + 0.7  # with a DC offset
    one = StreamingSOS(sos, 4).process(x.copy())
    f = StreamingSOS(sos, 4)
    cuts = [0, 1, 8, 333, 334, 4000, 5000]
    parts = [f.process(x[:, a:b].copy()) for a, b in zip(cuts[:-1], cuts[1:])]
    assert np.array_equal(np.concatenate(parts, axis=1), one)
    # reference: scipy with the same steady-state start
    zi = signal.sosfilt_zi(sos)[:, None, :] * x[None, :, 0, None]
    ref, _ = signal.sosfilt(sos, x, axis=-1, zi=zi)
    assert np.allclose(one, ref, rtol=0, atol=1e-12)
    # a constant input (any DC) gives a zero output from the first sample on
    c = StreamingSOS(sos, 4).process(np.full((4, 300), -0.3))
    assert np.max(np.abs(c)) < 1e-12


def test_noise_gains_of_the_trigger_filter():
    sos = design_bandpass_sos(5e6, 100e3, 1.5e6)
    g = noise_power_gain(sos)
    rng = np.random.default_rng(1)
    y = signal.sosfilt(sos, rng.normal(size=400_000))
    assert np.var(y[1000:]) == pytest.approx(g, rel=0.02)
    assert np.var(np.diff(y[1000:])) / np.var(y[1000:]) == pytest.approx(
        diff_noise_ratio(sos), rel=0.03
    )


# ---------------------------------------------------------------- noise tracker
def _blocks(x, b):
    y2 = (x * x).reshape(x.shape[0], -1, b)
    return y2.mean(-1), y2.max(-1)


def test_noise_tracker_median_estimate_blind_start_and_burst_rejection():
    rng = np.random.default_rng(2)
    sig = np.array([1.0, 2.0, 0.5, 1.5])
    x = rng.normal(size=(4, 64 * 500)) * sig[:, None]
    # packet-like bursts (short, loud) are flagged; a long loud stretch is not flagged
    # (its mean is high too) but cannot move the median either
    for j in (20, 21, 40):
        x[:, j * 500 + 100 : j * 500 + 110] += 50.0 * sig[:, None]
    x[:, 30 * 500 : 30 * 500 + 300] *= 20.0
    ms, pk = _blocks(x, 500)
    t = BlockNoiseTracker(4, history_blocks=16, min_blocks=2, burst_ratio=6.0, epoch_blocks=4)
    var, bursty = t.update(ms, pk, np.zeros(64, bool), first_block=0)
    assert np.isnan(var[:, :2]).all() and np.isfinite(var[:, 2:]).all()
    assert set(np.flatnonzero(bursty)) == {20, 21, 40}
    est = np.sqrt(var[:, 20:])
    assert np.allclose(est, sig[:, None], rtol=0.08)
    # constant between epoch starts (block index multiple of 4) after the warm-up
    assert np.array_equal(var[:, 9], var[:, 11]) and not np.array_equal(var[:, 11], var[:, 12])


def test_noise_tracker_is_invariant_to_how_blocks_are_batched():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(4, 50 * 200)) * np.linspace(1, 3, 50 * 200)
    ms, pk = _blocks(x, 200)
    miss = np.zeros(50, bool)
    miss[[0, 17]] = True
    one = BlockNoiseTracker(4, 8, 2, 6.0, 0.0, 5).update(ms, pk, miss, 0)[0]
    t = BlockNoiseTracker(4, 8, 2, 6.0, 0.0, 5)
    parts, j = [], 0
    for n in (1, 7, 3, 20, 19):
        v, _ = t.update(ms[:, j : j + n], pk[:, j : j + n], miss[j : j + n], j)
        parts.append(v[:, :n])
        j += n
    assert np.array_equal(np.concatenate(parts, axis=1), one[:, :50], equal_nan=True)
    assert np.array_equal(t.variance, one[:, 50], equal_nan=True)


# ---------------------------------------------------------------- AIC
def test_aic_finds_the_earliest_channel_of_a_step_in_noise():
    rng = np.random.default_rng(4)
    hits = 0
    for _ in range(200):
        onset = int(rng.integers(15, 35))
        x = rng.normal(0, 1.0, (1, 4, 50)) + 3.0  # noise + DC
        lags = rng.integers(0, 8, 4)
        lags[rng.integers(4)] = 0  # one channel starts at onset
        for k in range(4):
            t = (np.arange(50) - onset - lags[k]) / FS
            x[0, k] += 15.0 * hp_step(t)
        m, aic = aic_pick(x)
        hits += abs(int(m[0]) - onset) <= 1
        assert np.isfinite(aic[0, 2:-2]).all()
    assert hits >= 195


def test_aic_start_and_degenerate_segments():
    rng = np.random.default_rng(5)
    x = rng.normal(0, 0.01, (2, 4, 60))
    x[:, :, 10:14] += 5.0  # an earlier disturbance
    x[:, :, 40:] += np.sin(np.arange(20) + 1.0)  # the onset we want at 40
    m, _ = aic_pick(x)
    assert (m == 10).all()
    m, _ = aic_pick(x, start=[20, 30])
    assert (m == 40).all()
    # constant and all-zero segments: finite curve, a valid index, no warnings
    with np.errstate(all="raise"):
        m, aic = aic_pick(np.stack([np.zeros((4, 30)), np.full((4, 30), 2.5)]))
    assert ((m >= 2) & (m <= 28)).all() and np.isfinite(aic[:, 1:-2]).all()
    with pytest.raises(ValueError):
        aic_pick(np.zeros((4, 30)))
    with pytest.raises(ValueError):
        aic_pick(np.zeros((1, 4, 30)), weights=np.ones(4))


# ---------------------------------------------------------------- features
def test_window_features_definitions():
    rng = np.random.default_rng(6)
    k, m, on = 6, 400, 100
    sigma = np.array([1e-3, 2e-3, 3e-3, 4e-3])
    w = rng.normal(size=(k, 4, m)) * sigma[None, :, None] + 0.2  # DC offset
    t = (np.arange(m) - on) / FS
    pol = np.array([1, -1, 1, -1, 1, -1])
    w += pol[:, None, None] * 0.05 * hp_step(t)[None, None, :]
    w[5, 2, 300] = 0.99999  # one rail sample
    kw = dict(
        noise_guard=3,
        peak_window=50,
        polarity_window=10,
        snr_window=300,
        sat_lo=-1 + 2**-12,
        sat_hi=1 - 1.5 * 2**-11,
        var_floor=1e-18,
    )
    f = window_features(w, np.full(k, on), **kw)
    g = window_features_fixed(w, on, **kw)
    for name in f:
        assert np.allclose(f[name], g[name], rtol=1e-12, atol=0), name
    assert np.allclose(f["noise_rms_channel_v"], sigma[None, :], rtol=0.25)
    assert np.allclose(f["noise_rms_v"], math.sqrt(np.mean(sigma**2)), rtol=0.15)
    assert np.array_equal(f["polarity"], pol)
    assert np.allclose(f["peak_amplitude_v"], 0.05, rtol=0.2)
    assert f["saturated"].tolist() == [False] * 5 + [True]
    assert f["saturated_channels"][5].tolist() == [False, False, True, False]
    p_sig = np.mean((0.05 * hp_step(t[on : on + 300])) ** 2)
    assert np.allclose(f["snr_db"][:5], 10 * np.log10(p_sig / np.mean(sigma**2)), atol=1.0)
    # onset too early for a pre-onset estimate: the MAD fallback, still finite
    h = window_features(w, np.array([2, 100, 100, 100, 100, 100]), **kw)
    assert np.isfinite(h["noise_rms_v"]).all() and h["noise_rms_v"][0] > 0


# ---------------------------------------------------------------- synthetic streams
def test_synth_stream_onsets_and_snr():
    rng = np.random.default_rng(7)
    ev = SynthEvent(12.34e-6, 0.1, random_delays(rng))
    x = synth_stream(400, FS, [ev])
    first_nonzero = min(int(np.flatnonzero(x[k])[0]) for k in range(4))
    assert first_nonzero == ev.onset_index(FS)
    spread = max(ev.delays_s) - min(ev.delays_s)
    assert spread <= 2 * math.sqrt(2) * 1e-6 + 1e-12
    a = snr_amplitude(20.0, 1e-3, FS)
    y = synth_stream(700, FS, [SynthEvent(10e-6, a)])
    p = np.mean(y[:, 100:400] ** 2)
    assert 10 * np.log10(p / 1e-6) == pytest.approx(20.0, abs=0.05)


# ---------------------------------------------------------------- configuration
@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(sample_rate_hz=0), "sample_rate_hz"),
        (dict(sample_rate_hz=float("nan")), "sample_rate_hz"),
        (dict(sample_rate_hz="fast"), "sample_rate_hz"),
        (dict(highpass_hz=2e6), "highpass_hz"),
        (dict(lowpass_hz=50e3), "lowpass_hz"),
        (dict(threshold_sigma=3.0, rearm_sigma=3.0), "rearm_sigma"),
        (dict(threshold_sigma=-1), "threshold_sigma"),
        (dict(jump_ratio=1.0), "jump_ratio"),
        (dict(hit_definition_time_s=0), "hit_definition_time_s"),
        (dict(hit_lockout_time_s=-1e-6), "hit_lockout_time_s"),
        (dict(pretrigger_s=-1e-6), "pretrigger_s"),
        (dict(posttrigger_s=0), "posttrigger_s"),
        (dict(filter_order=0), "filter_order"),
        (dict(filter_order=2.5), "filter_order"),
        (dict(noise_history_blocks=4, noise_min_blocks=5), "noise_min_blocks"),
        (dict(adc_bits=True), "adc_bits"),
        (dict(full_scale_v=0), "full_scale_v"),
        (dict(max_abs_v=0.5), "max_abs_v"),
        (dict(echo_delay_s=-1e-6), "echo_delay_s"),
        (dict(posttrigger_s=0.9, pretrigger_s=0.9), "window"),
    ],
)
def test_bad_parameters_raise_clear_value_errors(kw, match):
    with pytest.raises(ValueError, match=match):
        DetectorConfig(**kw)


def test_config_samples_and_dict_round_trip():
    c = DetectorConfig()
    sp = c.samples()
    assert (sp.decim, sp.trigger_rate_hz) == (3, 10e6 / 3)
    assert (sp.pretrigger, sp.posttrigger, sp.window) == (100, 300, 400)
    assert DetectorConfig.from_dict(c.as_dict()) == c
    with pytest.raises(ValueError, match="unknown"):
        DetectorConfig.from_dict({"threshold": 5})
    assert DetectorConfig(sample_rate_hz=20e6).samples().decim == 6
    assert DetectorConfig(sample_rate_hz=5e6).samples().decim == 1
    assert DetectorConfig(sample_rate_hz=1e6).samples().decim == 1
    lo, hi = c.saturation_levels_v
    lsb = 2.0 / 4096
    assert lo == pytest.approx(-1 + lsb / 2) and hi == pytest.approx(1 - 1.5 * lsb)
