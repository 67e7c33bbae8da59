# SPDX-License-Identifier: Apache-2.0
"""Common-mode interference: the renderer (ae_tactile.sim.interference) and the packet
discriminator (ae_tactile.dsp.interference) against acoustic packets at and near the apex
rendered by the acoustic simulator. Seeded; thresholds leave margins to the measured rates
(bench/bench_slip.py, docs/slip.md)."""

import numpy as np
import pytest

from ae_eval.slip import apex_touch_packets
from ae_tactile.dsp.burst_train import BurstTrain
from ae_tactile.dsp.interference import (
    EchoLearner,
    common_mode_interference,
    common_mode_share,
    echo_ratio,
    packet_common_share,
)
from ae_tactile.localization import localize
from ae_tactile.pipeline import COMMON_SUSPECT
from ae_tactile.sim.config import SimConfig
from ae_tactile.sim.interference import (
    InterferenceSource,
    burst_times_s,
    render_interference,
    shared_clock_burst_times_ns,
)
from ae_tactile.sim.scene import load_scene, reference_noise_rms
from ae_tactile.sim.triggered import render_triggered


def apex_packets(cfg, n, noise, rng, radius_m=1e-3):
    return apex_touch_packets(cfg, n, noise, rng, radius_m=radius_m)


def rates(cfg, snr_db, coupling, seed, echo_min=None, n=120):
    rng = np.random.default_rng(seed)
    g = cfg.geometry
    noise = reference_noise_rms(cfg, snr_db)
    kw = dict(
        noise_rms_v=noise,
        geometry=g,
        lowpass_hz=cfg.lowpass_hz,
        lowpass_order=cfg.lowpass_order,
        echo_min=echo_min,
    )
    pk = apex_packets(cfg, n, noise, rng)
    kept = (
        1.0
        - common_mode_interference(pk.samples_v, cfg.sample_rate_hz, pk.onset_index, **kw)[
            0
        ].mean()
    )
    ip = render_interference(n, cfg, coupling=coupling, noise_rms_v=noise, rng=rng)
    rej = common_mode_interference(ip.samples_v, cfg.sample_rate_hz, ip.onset_index, **kw)[
        0
    ].mean()
    return kept, rej


@pytest.mark.parametrize("medium", ["water_skin", "silicone"])
@pytest.mark.parametrize("fs", [2e6, 10e6])
@pytest.mark.parametrize("snr_db", [20.0, 40.0])
def test_adc_coupled_interference_rejected_apex_touches_kept(medium, fs, snr_db):
    cfg = SimConfig.for_medium(medium, sample_rate_hz=fs)
    kept, rej = rates(cfg, snr_db, "adc", seed=int(fs) % 97 + int(snr_db))
    assert kept >= 0.97
    assert rej >= 0.8


@pytest.mark.parametrize("fs", [2e6, 5e6, 10e6])
@pytest.mark.parametrize("kind", ["spike", "edge", "ringing"])
def test_every_adc_coupled_waveform_rejected_by_its_shape(fs, kind):
    """Spikes (one or two samples at 2 MS/s), edges and ringing aliased into the band
    coupled after the front end: whatever the out-of-band tests leave, the shape test
    rejects (the best step-response template per channel leaves more than an acoustic
    packet's mismatch and more than the noise), while apex touches up to 1.5 mm off the
    apex (arrivals a few samples apart in silicone at 10 MS/s), weak (SNR 20 dB) and
    strong (40 dB, noise below the ADC's step), are kept."""
    cfg = SimConfig.for_medium("silicone", sample_rate_hz=fs)
    rng = np.random.default_rng([int(fs), len(kind)])
    kw = dict(geometry=cfg.geometry, lowpass_hz=cfg.lowpass_hz, lowpass_order=cfg.lowpass_order)
    noise = reference_noise_rms(cfg, 25.0)
    ip = render_interference(300, cfg, kind=kind, coupling="adc", noise_rms_v=noise, rng=rng)
    rej = common_mode_interference(ip.samples_v, fs, ip.onset_index, noise_rms_v=noise, **kw)
    assert rej[0].mean() >= 0.97
    for snr_db in (20.0, 40.0):
        noise = reference_noise_rms(cfg, snr_db)
        pk = apex_packets(cfg, 300, noise, rng, radius_m=1.5e-3)
        m, score = common_mode_interference(
            pk.samples_v, fs, pk.onset_index, noise_rms_v=noise, **kw
        )
        assert 1.0 - m.mean() >= 0.99
        if snr_db == 40.0:  # strong touches: far from the threshold (score 1)
            assert np.nanmax(score) < 0.5


@pytest.mark.parametrize(
    "medium, fs, radius_m",
    [("water_skin", 1e6, None), ("water_skin", 3e6, 5e-3), ("water_skin", 5e6, 3e-3)],
)
def test_apex_touches_kept_when_the_echo_comes_a_few_samples_after_the_onset(
    medium, fs, radius_m
):
    """A slow ADC or a small sphere leaves only 10 .. 20 samples before the wall echo: the
    shape test's templates run to the end of that span (the packet's own tail is explained,
    not counted), and without a noise level (a pretrigger too short to estimate it) there
    is no shape test: apex touches are kept; 'adc' spikes with a given noise still go."""
    kw = {} if radius_m is None else {"radius_m": radius_m}
    cfg = SimConfig.for_medium(medium, sample_rate_hz=fs, **kw)
    rng = np.random.default_rng(4)
    noise = reference_noise_rms(cfg, 25.0)
    pk = apex_packets(cfg, 200, noise, rng, radius_m=1.5e-3)
    common = dict(
        geometry=cfg.geometry, lowpass_hz=cfg.lowpass_hz, lowpass_order=cfg.lowpass_order
    )
    for given in (noise, None):
        m, _ = common_mode_interference(pk.samples_v, fs, pk.onset_index, noise_rms_v=given,
                                        **common)
        assert 1.0 - m.mean() >= 0.99
    ip = render_interference(200, cfg, kind="spike", coupling="adc", noise_rms_v=noise, rng=rng)
    m, _ = common_mode_interference(ip.samples_v, fs, ip.onset_index, noise_rms_v=noise, **common)
    assert m.mean() >= 0.97


def test_a_packet_is_judged_alone_whatever_its_batch():
    """Scores do not depend on the other packets of a call (the ADC step is read per
    packet), nor on where the onset lies in a longer window."""
    cfg = SimConfig.for_medium("silicone", sample_rate_hz=10e6)
    rng = np.random.default_rng(8)
    noise = reference_noise_rms(cfg, 30.0)
    pk = apex_packets(cfg, 40, noise, rng)
    ip = render_interference(40, cfg, coupling="adc", noise_rms_v=noise, rng=rng)
    x = np.concatenate([pk.samples_v, ip.samples_v])
    on = np.concatenate([pk.onset_index, ip.onset_index])
    kw = dict(geometry=cfg.geometry, noise_rms_v=noise)
    _, alone = common_mode_interference(x, cfg.sample_rate_hz, on, **kw)
    _, mixed = common_mode_interference(
        np.concatenate([x, 1.37 * x[:1]]), cfg.sample_rate_hz, np.append(on, on[0]), **kw
    )
    np.testing.assert_allclose(mixed[:-1], alone, rtol=1e-9, atol=1e-12)
    pad = rng.normal(0.0, noise, (x.shape[0], 4, 220))  # the onset 220 samples later
    m, _ = common_mode_interference(np.concatenate([pad, x], axis=2)[:, :, :400],
                                    cfg.sample_rate_hz, on + 220, **kw)
    assert 1.0 - m[:40].mean() >= 0.97 and m[40:].mean() >= 0.9


def test_front_end_shaped_interference_needs_the_wall_echo():
    """Interference entering at the amplifier's input has an acoustic packet's band; its
    spikes and ringing differ in shape (rejected), its edges do not (a step through the
    front end *is* an apex touch's packet): only the wall echo tells them apart."""
    cfg = SimConfig.for_medium("water_skin")
    kept, rej = rates(cfg, 30.0, "input", seed=5)
    assert kept >= 0.97 and 0.4 <= rej <= 0.85
    cfg = SimConfig.for_medium("water_skin", reflections=True)
    kept, rej = rates(cfg, 30.0, "input", seed=6, echo_min=0.25)
    assert kept >= 0.97 and rej >= 0.97


@pytest.mark.parametrize("medium", ["water_skin", "silicone"])
@pytest.mark.parametrize("fs", [1e6, 2e6, 10e6])
def test_echo_ratio_of_touches_is_the_walls_reflection_coefficient(medium, fs):
    """The echo a touch anywhere on the cap brings back (the concave wall refocuses it on
    the array: its ratio to the direct wave is the wall's reflection coefficient), measured
    at the localized point; about 0 without echoes, NaN for a window too short to hold
    the echo, and the learner's threshold follows."""

    for r_wall in (-0.5, 0.3, None):
        cfg = SimConfig.for_medium(medium, sample_rate_hz=fs, reflections=r_wall is not None,
                                   reflection_coefficient=r_wall or -0.5)
        rng = np.random.default_rng(int(fs) + 7)
        g = cfg.geometry
        th = np.radians(rng.uniform(5, 50, 60))
        ph = rng.uniform(0, 2 * np.pi, 60)
        pk = render_triggered(g.surface_point_from_angles(th, ph), cfg, snr_db=30.0, rng=rng)
        res = localize(pk.samples_v, fs, pk.onset_index, geometry=g)
        ok = np.flatnonzero(res.accepted)
        beta = echo_ratio(pk.samples_v[ok], fs, pk.onset_index[ok], res.point_m[ok], g)
        assert np.isfinite(beta).mean() >= 0.5  # the rest too weak for a clean ratio
        learner = EchoLearner()
        learner.add(beta)
        if r_wall is None:
            assert np.nanmax(np.abs(beta)) < 0.05 and learner.echo_min is None
        else:
            assert np.nanmedian(beta) == pytest.approx(r_wall, abs=0.03)
            assert learner.echo_min == pytest.approx(0.5 * abs(r_wall), abs=0.02)
        short = echo_ratio(pk.samples_v[ok, :, :20], fs, pk.onset_index[ok], res.point_m[ok], g)
        assert np.isnan(short).all()
    with pytest.raises(ValueError):
        echo_ratio(np.zeros((2, 4, 50)), fs, [0, 0], np.zeros((3, 3)), g)


def test_off_apex_touches_are_not_common_mode():
    cfg = SimConfig.for_medium("water_skin")
    rng = np.random.default_rng(3)
    g = cfg.geometry
    th = np.radians(rng.uniform(10, 60, 100))
    ph = rng.uniform(0, 2 * np.pi, 100)
    pk = render_triggered(g.surface_point_from_angles(th, ph), cfg, snr_db=30.0, rng=rng)
    mask, score = common_mode_interference(
        pk.samples_v, cfg.sample_rate_hz, pk.onset_index, noise_rms_v=pk.noise_rms_v, geometry=g
    )
    assert not mask.any()


def test_identical_channels_and_bad_input():
    x = np.zeros((3, 4, 400))
    x[:, :, 100] = 1.0  # one-sample spike, identical everywhere
    x[2] = np.nan
    mask, score = common_mode_interference(x, 10e6, np.array([99, 99, 99]))
    assert mask.tolist() == [True, True, False] and np.isnan(score[2])
    with pytest.raises(ValueError):
        common_mode_interference(np.zeros((2, 3, 50)), 10e6, [0, 0])
    with pytest.raises(ValueError):
        common_mode_interference(np.zeros((2, 4, 50)), 10e6, [0, 0, 0])
    with pytest.raises(ValueError):
        common_mode_interference(np.zeros((2, 4, 50)), -1.0, [0, 0])
    m, s = common_mode_interference(np.zeros((0, 4, 50)), 10e6, np.zeros(0, int))
    assert m.shape == (0,) and s.shape == (0,)


def test_renderer_format_and_burst_times():
    cfg = SimConfig()
    pk = render_interference(5, cfg, kind="spike", noise_rms_v=1e-3, rng=1)
    assert pk.samples_v.shape == (5, 4, 400) and np.all(np.isnan(pk.points_m))
    assert np.all(pk.onset_index == 81)
    # identical waveform on the four channels up to the 1 % gain mismatch
    c = pk.clean_v
    corr = [np.corrcoef(c[i])[0, 1:].min() for i in range(5)]
    assert min(corr) > 0.999
    # quantized to the ADC's LSB
    assert np.allclose(pk.samples_v / cfg.lsb_v, np.rint(pk.samples_v / cfg.lsb_v))
    t = burst_times_s(1.0, 1000.0, rng=2)
    assert 999 <= t.size <= 1001 and np.allclose(np.diff(t), 1e-3)
    t = burst_times_s(2.0, 50.0, periodic=False, rng=3)
    assert 60 <= t.size <= 140 and np.all(np.diff(t) > 0)
    with pytest.raises(ValueError):
        render_interference(2, cfg, coupling="magic")


@pytest.mark.parametrize("snr_db", [20.0, 40.0])
@pytest.mark.parametrize("medium", ["water_skin", "silicone"])
def test_noise_estimated_from_the_pretrigger(medium, snr_db):
    """Without noise_rms_v (the driver's call) the noise comes from the samples before the
    onset: weak apex touches are still kept, and so are strong ones whose pretrigger noise
    is below the ADC's step (read as nearly constant)."""
    cfg = SimConfig.for_medium(medium, sample_rate_hz=5e6)
    rng = np.random.default_rng(17)
    noise = reference_noise_rms(cfg, snr_db)
    pk = apex_packets(cfg, 150, noise, rng)
    m1, _ = common_mode_interference(
        pk.samples_v, cfg.sample_rate_hz, pk.onset_index, geometry=cfg.geometry
    )
    ip = render_interference(150, cfg, coupling="adc", noise_rms_v=noise, rng=rng)
    m2, _ = common_mode_interference(
        ip.samples_v, cfg.sample_rate_hz, ip.onset_index, geometry=cfg.geometry
    )
    assert 1.0 - m1.mean() >= 0.97 and m2.mean() >= 0.8


def test_a_crystal_timed_burst_train_is_recognized_and_touches_are_not():
    """Bursts at multiples of one period (to a fraction of a microsecond) join a train from
    the 4th on, whatever the period (1 Hz .. 10 kHz) and with bursts missing; touches,
    whose timing jitters by milliseconds, are not taken for one (two in 10,000 taps at
    random times; at a random phase of a 1 kHz train ~2 tol / T = 0.4 %)."""

    rng = np.random.default_rng(4)
    tol = 1e-6
    for period in (1.0, 1e-2, 1e-3, 1e-4):
        tr = BurstTrain()
        t = 0.37 + period * np.arange(40)
        t = np.delete(t, [5, 6, 17])  # bursts the localizer did not keep
        t = t + rng.normal(0, 0.05e-6, t.size)
        member = []
        for x in t:
            member.append(tr.is_member(x, tol))
            tr.add(x)
        assert not any(member[:3]) and all(member[3:]), (period, member[:8])
    taps = np.cumsum(rng.uniform(0.05, 0.5, 10_000))  # a robot tapping every 50-500 ms
    tr, hits = BurstTrain(), 0
    for x in taps:
        hits += tr.is_member(x, tol)
        tr.add(x)
    assert hits <= 2
    tr, hits = BurstTrain(), 0
    t_train = np.arange(2000) * 1e-3
    touches = rng.uniform(0.01, 2.0, 500)
    events = sorted([(x, False) for x in t_train] + [(x, True) for x in touches])
    for x, touch in events:
        if touch:
            hits += tr.is_member(x, tol)
        tr.add(x)
    assert hits <= 0.02 * touches.size
    # one chance relation t = h_j + h_k - h_i is not a train (it reads the same from j and
    # from k), and apex packets at random times at 1 kHz are hardly ever taken for one
    tr = BurstTrain()
    for x in (0.0, 3.1e-3, 7.3e-3):
        tr.add(x)
    assert not tr.is_member(10.4e-3, tol)
    tr, hits = BurstTrain(), 0
    poisson = np.cumsum(rng.exponential(1e-3, 5000))
    for x in poisson:
        hits += tr.is_member(x, tol)
        tr.add(x)
    assert hits <= 0.005 * poisson.size
    # packets close together (within a packet's length) or stamps that do not advance are
    # no period: a burst of touches at one moment is not a train
    for times in (np.zeros(12), 1.0 + 1e-6 * rng.uniform(0, 5, 12),
                  np.repeat(np.cumsum(rng.uniform(0.05, 0.5, 6)), 2)):
        tr = BurstTrain()
        member = []
        for x in np.sort(times):
            member.append(tr.is_member(x, tol))
            tr.add(x)
        assert not any(member)


def _water_touches_off_apex(seed, n, lo_deg, hi_deg, snr_db):
    """(config, packets, rng): ``n`` touches lo_deg .. hi_deg from the apex, water, snr_db."""
    cfg = SimConfig.for_medium("water_skin")
    rng = np.random.default_rng(seed)
    th = np.radians(rng.uniform(lo_deg, hi_deg, n))
    pk = render_triggered(cfg.geometry.surface_point_from_angles(th, rng.uniform(0, 6.3, n)),
                          cfg, snr_db=snr_db, rng=rng)
    return cfg, pk, rng


def test_common_mode_share_screen_compiled_and_numpy_agree():
    """The driver's cheap screen: one waveform on the four channels scores ~1, touches
    beyond ~12 deg from the apex less than its bar of 0.9; the compiled and the numpy paths
    agree."""

    cfg, pk, rng = _water_touches_off_apex(8, 50, 12.0, 50.0, 30.0)
    noise = float(pk.noise_rms_v[0])
    bursts = render_interference(50, cfg, kind="mixed", coupling="adc", noise_rms_v=noise,
                                 rng=rng, amplitude_v=30 * noise)
    touch = common_mode_share(pk.samples_v, noise)
    burst = common_mode_share(bursts.samples_v, noise)
    assert touch.max() < COMMON_SUSPECT and np.median(burst) > COMMON_SUSPECT
    for x, ref in ((pk.samples_v, touch), (bursts.samples_v, burst)):
        for dtype in (np.float32, np.float64):
            got = [packet_common_share(w.astype(dtype), noise) for w in x]
            np.testing.assert_allclose(got, ref, atol=1e-4)
    assert packet_common_share(np.full((4, 16), np.nan), 0.0) == 0.0
    assert packet_common_share(np.zeros((4, 16)), 0.0) == 0.0
    with pytest.raises(ValueError):
        common_mode_share(np.zeros((2, 3, 8)))


def test_an_adc_offset_does_not_make_a_touch_common_mode():
    """An ADC offset common to the four channels (a quarter of the packet's peak) is
    removed before the screen measures the common-mode share: off-apex touches keep their
    low share, the same as without the offset."""

    _, pk, _ = _water_touches_off_apex(9, 40, 15.0, 45.0, 10.0)
    x = pk.samples_v
    offset = 0.25 * np.abs(x).max(axis=(1, 2))[:, None, None]
    clean = common_mode_share(x, pk.noise_rms_v, pk.onset_index)
    shifted = common_mode_share(x + offset, pk.noise_rms_v, pk.onset_index)
    np.testing.assert_allclose(shifted, clean, atol=1e-9)
    assert common_mode_share(x + offset, pk.noise_rms_v).mean() > clean.mean() + 0.2  # raw
    got = [packet_common_share((x[i] + offset[i]).astype(np.float32), float(pk.noise_rms_v[i]),
                               int(pk.onset_index[i])) for i in range(40)]
    np.testing.assert_allclose(got, clean, atol=1e-4)


@pytest.mark.parametrize("periodic", [True, False])
def test_shared_clock_bursts_are_one_source_for_every_simulated_fingertip(periodic):
    """Bursts on the host's clock ('shared_clock'): two fingertips whose scenes start
    0.37 s apart render one source's bursts at the same host instants, however their
    renders are cut into chunks; the count is the rate's (Poisson: within 4 sigma)."""

    spec = {"generator": "interference", "duration_s": 3.0, "seed": 1,
            "noise": {"snr_db": 30.0},
            "params": {"rate_hz": 200.0, "periodic": periodic, "coupling": "input",
                       "kind": "edge", "shared_clock": True, "shared_seed": 9}}
    host = []
    t0s = (10**12 + 123_456_789, 10**12 + 493_456_789)
    for k, t0 in enumerate(t0s):
        src = InterferenceSource(load_scene(dict(spec, seed=k)), host_t0_ns=t0)
        times = [src.next_packets(h)[0] for h in np.linspace(0, 3e9, 7 + 5 * k)[1:]]
        host.append(np.concatenate(times) + t0)
    lo, hi = max(t0s), min(t0s) + 3 * 10**9
    a, b = (h[(h >= lo) & (h < hi)] for h in host)
    assert a.size > 0 and np.array_equal(a, b)
    one = shared_clock_burst_times_ns(lo, hi, 200.0, periodic=periodic, seed=9)
    assert np.array_equal(one, a)
    n_expect = 200.0 * (hi - lo) * 1e-9
    if periodic:
        assert abs(a.size - n_expect) <= 1 and np.ptp(np.diff(a)) <= 2  # 5 ms apart (ns)
    else:
        assert abs(a.size - n_expect) <= 4 * np.sqrt(n_expect)
    # another seed: another source
    assert not np.array_equal(one, shared_clock_burst_times_ns(lo, hi, 200.0,
                                                               periodic=periodic, seed=10))
