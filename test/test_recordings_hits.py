# SPDX-License-Identifier: Apache-2.0
"""Hit definition in AE terms on recordings the tests write: a ringing 20 ms hit is one hit
with the default DDT, the first hit of a file is found (no blind start), onsets sit on
the known emission, rearm / maximum duration / PDT act as AE systems define them, features
(amplitude, counts, energy) match their definitions, and a threshold in the noise warns."""

import math

import numpy as np
import pytest
from scipy.io import wavfile

from ae_tactile.recordings import (
    HitDefinition,
    Recording,
    db_ae_to_v,
    detect,
    find_hits,
    noise_floor_v,
    v_to_db_ae,
)

FS = 2_000_000.0
NOISE_V = 5e-6  # 14 dB_AE rms, a good AE preamp's floor


def _noise(n, seed=0, sigma=NOISE_V, channels=1):
    return np.random.default_rng(seed).normal(0.0, sigma, (channels, n))


def _burst(n, onset_s, amp_v, f_hz=150e3, rise_s=2e-6, decay_s=30e-6, gaps_every_s=0.0):
    """A burst starting at onset_s: amp (1 - e^{-t/rise}) e^{-t/decay} sin(2 pi f t); with
    gaps_every_s > 0 the ringing drops out for 60 us every gaps_every_s (mode beating)."""
    t = np.arange(n) / FS - onset_s
    on = t >= 0
    tt = np.where(on, t, 0.0)
    env = amp_v * (1 - np.exp(-tt / rise_s)) * np.exp(-tt / decay_s)
    if gaps_every_s:
        env = env * (np.mod(tt, gaps_every_s) < gaps_every_s - 60e-6)
    return np.where(on, env * np.sin(2 * np.pi * f_hz * tt), 0.0)


def test_db_ae_scale():
    assert db_ae_to_v(0) == pytest.approx(1e-6) and db_ae_to_v(40) == pytest.approx(1e-4)
    assert v_to_db_ae(1e-4) == pytest.approx(40) and v_to_db_ae(0.0) == -math.inf
    assert HitDefinition(threshold_db_ae=40, preamp_gain_db=34).threshold_v() == \
        pytest.approx(1e-4 * 10 ** (34 / 20))


def test_a_ringing_20_ms_hit_is_one_hit_with_the_default_ddt(tmp_path):
    """20 ms of ringing that drops out for 60 us every 2 ms (mode beating), written as a
    WAV: one hit lasting ~20 ms with the default DDT; a DDT shorter than the drop-outs
    splits it, as it must."""
    n = int(30e-3 * FS)
    x = _noise(n)[0] + _burst(n, 1e-3, 20e-3, decay_s=4e-3, gaps_every_s=2e-3)
    wavfile.write(tmp_path / "ring.wav", int(FS), x.astype(np.float32))
    det = detect(tmp_path / "ring.wav")
    assert len(det.hits) == 1, [(h.crossing_time_s, h.duration_s) for h in det.hits]
    h = det.hits[0]
    assert 18e-3 < h.duration_s < 24e-3 and h.truncated == ""
    assert h.counts > 2500  # one count per cycle of 150 kHz over ~20 ms
    assert abs(h.onset_time_s - 1e-3) <= 3 / FS
    short = detect(tmp_path / "ring.wav", ddt_us=20.0)
    assert len(short.hits) >= 10


def test_the_first_hit_of_a_file_is_found_no_blind_start(tmp_path):
    """A burst 20 us after the first sample of a continuous file: found, onset on it; a
    file that starts inside a hit reports it as truncated at the start."""
    n = int(5e-3 * FS)
    x = _noise(n, seed=1)[0] + _burst(n, 20e-6, 2e-3) + _burst(n, 3e-3, 1e-3)
    np.save(tmp_path / "early.npy", x)
    det = detect(tmp_path / "early.npy", sample_rate_hz=FS)
    assert [round(h.onset_time_s * 1e6) for h in det.hits] == [20, 3000]
    assert abs(det.hits[0].onset_time_s - 20e-6) <= 2 / FS
    assert det.hits[0].truncated == ""
    late = Recording(x[int(30e-6 * FS):], FS)
    (first, _) = find_hits(late)
    assert first.crossing_index <= 2 and first.truncated == "start"


@pytest.mark.parametrize("snr_db_ae", [30.0, 50.0])
def test_onsets_sit_on_the_known_emission_times(snr_db_ae):
    rng = np.random.default_rng(7)
    n = int(20e-3 * FS)
    onsets = np.sort(rng.uniform(0.5e-3, 19e-3, 8))
    onsets = onsets[np.concatenate(([True], np.diff(onsets) > 0.6e-3))]
    amp = NOISE_V * 10 ** (snr_db_ae / 20) * 3
    x = _noise(n, seed=2)[0] + sum(_burst(n, t, amp) for t in onsets)
    hits = find_hits(Recording(x, FS), HitDefinition(threshold_db_ae=v_to_db_ae(8 * NOISE_V)))
    assert len(hits) == len(onsets)
    err = np.array([h.onset_time_s for h in hits]) - onsets
    assert np.abs(err).max() <= 3 / FS, err * FS


def test_rearm_and_maximum_duration_as_ae_systems_define_them():
    n = int(5e-3 * FS)
    x = _noise(n, seed=3)[0] + _burst(n, 0.5e-3, 2e-3) + _burst(n, 0.9e-3, 2e-3)
    rec = Recording(x, FS)
    assert len(find_hits(rec)) == 2  # 400 us apart, ~100 us long: DDT 250 us ends the first
    locked = find_hits(rec, HitDefinition(rearm_us=500.0))
    assert len(locked) == 1  # the second starts within the rearm time
    assert len(find_hits(rec, HitDefinition(ddt_us=400.0))) == 1  # bridged by the DDT
    long = _noise(int(30e-3 * FS), seed=4)[0] + _burst(int(30e-3 * FS), 1e-3, 20e-3,
                                                       decay_s=5e-3)
    cut = find_hits(Recording(long, FS), HitDefinition(max_duration_us=5000.0))
    assert len(cut) >= 3 and all(h.duration_s <= 5e-3 + 1 / FS for h in cut)


def test_tone_burst_features_follow_their_definitions():
    """A 100-cycle 100 kHz tone burst of 10 mV: amplitude 80 dB_AE, 100 counts, energy
    A^2/2 x duration, rise time to the largest peak; with a 34 dB preamplifier the same
    sensor levels come out."""
    a, f, cycles = 10e-3, 100e3, 100
    n = int(3e-3 * FS)
    t = np.arange(n) / FS
    on = (t >= 1e-3) & (t < 1e-3 + cycles / f)
    tone = np.where(on, a * np.sin(2 * np.pi * f * (t - 1e-3)), 0.0)
    for gain_db in (0.0, 34.0):
        g = 10 ** (gain_db / 20)
        rec = Recording((tone + _noise(n, seed=5)[0]) * g, FS)
        (h,) = find_hits(rec, HitDefinition(preamp_gain_db=gain_db))
        assert h.amplitude_db_ae == pytest.approx(80.0, abs=0.05)
        assert h.peak_v == pytest.approx(a * g, rel=0.01)
        assert h.counts == cycles
        assert h.duration_s == pytest.approx(cycles / f, abs=6 / FS)
        assert h.energy_v2s == pytest.approx(a * a / 2 * cycles / f, rel=0.02)
        assert h.energy_eu == pytest.approx(h.energy_v2s / 1e-14)
        assert h.rise_time_s < cycles / f


def test_peak_definition_time_takes_the_first_peak_not_exceeded_within_it():
    n = int(3e-3 * FS)
    x = _noise(n, seed=6)[0] + _burst(n, 0.5e-3, 1e-3, decay_s=20e-6) \
        + _burst(n, 0.7e-3, 3e-3, decay_s=20e-6)
    rec = Recording(x, FS)
    (whole,) = find_hits(rec)
    (early,) = find_hits(rec, HitDefinition(pdt_us=100.0))
    assert whole.rise_time_s > 190e-6 and whole.peak_v > 2e-3
    assert early.rise_time_s < 50e-6 and early.peak_v < 1.1e-3


def test_noise_floor_from_pretrigger_or_quiet_stretches_and_a_threshold_in_the_noise_warns(
        tmp_path):
    n = int(10e-3 * FS)
    loud = 1e-3  # 60 dB_AE rms: a 40 dB_AE threshold fires on noise
    x = _noise(n, seed=8, sigma=loud)[0] + _burst(n, 2e-3, 50e-3, decay_s=1e-3)
    np.save(tmp_path / "loud.npy", x)
    assert noise_floor_v(Recording(x, FS))[0] == pytest.approx(loud, rel=0.1)
    det = detect(tmp_path / "loud.npy", sample_rate_hz=FS)
    assert det.warnings and "within 12 dB of the noise" in det.warnings[0]
    fl = detect(tmp_path / "loud.npy", sample_rate_hz=FS, floating_db=20.0)
    assert not fl.warnings and len(fl.hits) == 1
    assert abs(fl.hits[0].onset_time_s - 2e-3) <= 3 / FS
    pre = Recording(np.concatenate([_noise(400, seed=9, sigma=3e-6)[0], x[:2000]]), FS,
                    pretrigger_samples=400)
    assert noise_floor_v(pre)[0] == pytest.approx(3e-6, rel=0.15)


def test_bad_hit_definitions_are_refused():
    for kw in ({"ddt_us": -1}, {"threshold_db_ae": float("nan")}, {"rearm_us": "x"},
               {"floating_db": -3}, {"threshold_db_ae": 300}):
        with pytest.raises(ValueError):
            HitDefinition(**kw)
    with pytest.raises(ValueError, match="either a HitDefinition or its keywords"):
        detect("x.wav", definition=HitDefinition(), ddt_us=3.0)


def test_a_threshold_in_the_noise_is_warned_and_the_hits_per_channel_bounded(tmp_path):
    """Threshold at half the noise rms and DDT 0: a hit every few samples; the channel
    stops at MAX_HITS_PER_CHANNEL with a warning rather than growing without bound."""
    from ae_tactile.recordings.hits import MAX_HITS_PER_CHANNEL

    x = _noise(1_000_000, seed=10, sigma=1e-3)[0]
    np.save(tmp_path / "noise.npy", x)
    det = detect(tmp_path / "noise.npy", sample_rate_hz=1e6, threshold_db_ae=54.0, ddt_us=0.0)
    assert len(det.hits) == MAX_HITS_PER_CHANNEL
    assert any("within 12 dB of the noise" in w for w in det.warnings)
    assert any(f"stopped at {MAX_HITS_PER_CHANNEL} hits" in w for w in det.warnings)
