# SPDX-License-Identifier: Apache-2.0
"""The simulator's device parameters (issue 37's zoo axes) against independent
expectations: front-end families against scipy.signal.freqs, amplifier noise against
|F(f)|^2, power-law loss against exp(-a f^y d), channel mismatch, and the default device
unchanged."""
import math

import numpy as np
import pytest
from scipy import signal

from ae_tactile.sim import SimConfig, render_triggered
from ae_tactile.sim.propagation import apply_power_law, power_law_transfer
from ae_tactile.sim.renderer import StreamRenderer

W = 2 * math.pi


def _points(cfg, xy=((0.0, 0.0), (2e-3, 1e-3), (-4e-3, 3e-3), (6e-3, -5e-3))):
    return np.array([cfg.geometry.surface_point_from_xy(x, y) for x, y in xy])


def _freqs(b_a_list, f_hz):
    h = np.ones(len(f_hz), complex)
    for b, a in b_a_list:
        h *= signal.freqs(b, a, worN=W * np.asarray(f_hz))[1]
    return h


F_TEST = np.array([20e3, 60e3, 100e3, 300e3, 1e6, 2.5e6])


def test_rc_highpass_bessel_lowpass_against_freqs():
    cfg = SimConfig(highpass_rc_hz=(60e3, 69e3), lowpass_family="bessel", lowpass_order=6,
                    lowpass_hz=1e6)
    expect = _freqs([([1, 0], [1, W * 60e3]), ([1, 0], [1, W * 69e3]),
                     signal.bessel(6, W * 1e6, analog=True, norm="mag")], F_TEST)
    got = cfg.frontend.frequency_response(F_TEST) / cfg.sensitivity_v_per_pa
    np.testing.assert_allclose(got, expect, rtol=1e-9)


def test_cheby_lowpass_and_amplifier_pole_against_freqs():
    cfg = SimConfig(highpass_hz=50e3, highpass_order=1, lowpass_family="cheby1",
                    lowpass_ripple_db=1.0, lowpass_order=5, lowpass_hz=800e3,
                    amplifier_pole_hz=2e6)
    expect = _freqs([signal.butter(1, W * 50e3, "highpass", analog=True),
                     signal.cheby1(5, 1.0, W * 800e3, analog=True),
                     ([W * 2e6], [1, W * 2e6])], F_TEST)
    got = cfg.frontend.frequency_response(F_TEST) / cfg.sensitivity_v_per_pa
    np.testing.assert_allclose(got, expect, rtol=1e-9)


def test_default_front_end_is_the_butterworth_pair():
    cfg = SimConfig()
    expect = _freqs([signal.butter(2, W * 100e3, "highpass", analog=True),
                     signal.butter(4, W * 1e6, analog=True)], F_TEST)
    np.testing.assert_allclose(cfg.frontend.frequency_response(F_TEST) / 0.01, expect,
                               rtol=1e-12)


def test_default_device_renders_as_before():
    """Values of a default render recorded before the device fields existed."""
    cfg = SimConfig()
    pk = render_triggered(_points(cfg), cfg, snr_db=25, rng=3)
    assert float(np.sum(pk.samples_v)) == pytest.approx(-0.232421875, abs=1e-12)
    assert float(np.sum(np.abs(pk.clean_v))) == pytest.approx(21.674233630836817, rel=1e-12)
    assert float(pk.clean_v[1, 2, 150]) == pytest.approx(-0.0074247581785521505, rel=1e-12)
    explicit = SimConfig(highpass_rc_hz=None, lowpass_family="butter", amplifier_pole_hz=None,
                         attenuation_law="pole", channel_gain=(1, 1, 1, 1),
                         channel_delay_s=(0, 0, 0, 0), amplifier_noise_share=0.0)
    again = render_triggered(_points(cfg), explicit, snr_db=25, rng=3)
    assert np.array_equal(again.samples_v, pk.samples_v)


def test_amplifier_noise_spectrum_is_the_chain_squared():
    cfg = SimConfig(amplifier_noise_share=1.0)
    fe = cfg.frontend
    x = fe.amplifier_noise.draw((48, 4096), np.random.default_rng(1))
    assert np.var(x) == pytest.approx(1.0, rel=0.05)
    f, pxx = signal.welch(x, fs=cfg.sample_rate_hz, nperseg=512, axis=-1)
    pxx = pxx.mean(axis=0)
    grid = np.linspace(0.0, 40e6, 400001)
    total = np.trapezoid(np.abs(fe.frequency_response(grid)) ** 2, grid)
    for f0 in (150e3, 400e3, 1e6, 2e6):
        i = int(np.argmin(np.abs(f - f0)))
        expect = np.abs(fe.frequency_response(f[i])) ** 2 / total
        assert pxx[i] == pytest.approx(expect, rel=0.12), f0
    r = fe.amplifier_noise.autocorrelation(4)
    emp = [np.mean(x[:, :x.shape[1] - m] * x[:, m:]) / np.var(x) for m in range(4)]
    np.testing.assert_allclose(r, emp, atol=0.03)


def test_amplifier_noise_share_sets_the_variance():
    cfg = SimConfig(amplifier_noise_share=0.5, quantization=False)
    pts = _points(cfg)[:1].repeat(64, axis=0)
    pk = render_triggered(pts, cfg, noise_rms_v=0.01, rng=2)
    noise = pk.samples_v - pk.clean_v
    assert np.std(noise) == pytest.approx(0.01, rel=0.05)


def test_power_law_loss_amplitude_and_delay():
    """A narrow-band burst at f0 loses exp(-a f0^1.5 d) and moves by the group delay of
    the Kramers-Kronig phase."""
    cfg = SimConfig.for_medium("silicone", attenuation=True, attenuation_law="power",
                               attenuation_db_per_m_at_1mhz=300.0)
    fs = cfg.sample_rate_hz
    t = np.arange(8192) / fs
    d = 0.02                                                  # [m]
    a1 = 300.0 * math.log(10) / 20
    for f0 in (300e3, 1e6):
        env = np.exp(-0.5 * ((t - 400e-6) / 40e-6) ** 2)
        x = env * np.cos(W * f0 * t)
        y = apply_power_law(x, np.array(d), cfg)
        ratio = np.abs(signal.hilbert(y)).max() / np.abs(signal.hilbert(x)).max()
        assert ratio == pytest.approx(math.exp(-a1 * (f0 / 1e6) ** 1.5 * d), rel=0.01)
        # group delay -d(phase)/d(omega) of exp(-j b l)
        df = 1.0
        ph = np.angle(power_law_transfer(np.array([f0 - df, f0 + df]), d, 300.0, 1.5, 300e3))
        tg = -(ph[1] - ph[0]) / (W * 2 * df)
        shift = (np.argmax(np.abs(signal.hilbert(y))) - np.argmax(env)) / fs
        assert shift == pytest.approx(tg, abs=1.5 / fs)
    assert np.angle(power_law_transfer(300e3, d, 300.0, 1.5, 300e3)) == pytest.approx(0.0)


def test_power_law_render_with_negligible_loss_is_lossless():
    base = SimConfig.for_medium("silicone", reflections=True)
    lossy = base.replace(attenuation=True, attenuation_law="power",
                         attenuation_db_per_m_at_1mhz=1e-9)
    pts = _points(base)
    a = render_triggered(pts, base, subsample_offset=0.3).clean_v
    b = render_triggered(pts, lossy, subsample_offset=0.3).clean_v
    np.testing.assert_allclose(b, a, atol=1e-9 * np.abs(a).max())
    c = render_triggered(pts, lossy.replace(attenuation_db_per_m_at_1mhz=300.0),
                         subsample_offset=0.3).clean_v
    assert 0.3 < np.abs(c).max() / np.abs(a).max() < 0.99


def test_channel_gain_and_delay_mismatch():
    cfg = SimConfig()
    pts = _points(cfg)
    a = render_triggered(pts, cfg, subsample_offset=0.2).clean_v
    g = render_triggered(pts, cfg.replace(channel_gain=(1.0, 1.05, 1.0, 0.97)),
                         subsample_offset=0.2).clean_v
    np.testing.assert_allclose(g[:, 1], 1.05 * a[:, 1], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(g[:, 3], 0.97 * a[:, 3], rtol=1e-12, atol=1e-15)
    assert np.array_equal(g[:, 0], a[:, 0])
    d = render_triggered(pts, cfg.replace(channel_delay_s=(0.0, 0.0, 0.3 / 10e6, 0.0)),
                         subsample_offset=0.2).clean_v
    shifted = render_triggered(pts, cfg, subsample_offset=0.5).clean_v
    np.testing.assert_allclose(d[:, 2], shifted[:, 2], atol=1e-12 * np.abs(a).max())
    np.testing.assert_array_equal(d[:, 0], a[:, 0])


def test_device_fields_are_validated_and_streaming_refuses_what_it_cannot_render():
    with pytest.raises(ValueError, match="distinct"):
        SimConfig(highpass_rc_hz=(60e3, 60e3))
    with pytest.raises(ValueError, match="lowpass_family"):
        SimConfig(lowpass_family="elliptic")
    with pytest.raises(ValueError, match="channel_gain"):
        SimConfig(channel_gain=(1, 1, 1))
    with pytest.raises(ValueError, match="amplifier_noise_share"):
        SimConfig(amplifier_noise_share=1.5)
    with pytest.raises(ValueError, match="streaming"):
        StreamRenderer(SimConfig(channel_gain=(1, 1.02, 1, 1)))
    assert SimConfig().streamable


def test_zoo_members_build_and_hold_the_issue_examples():
    from ae_eval.zoo import ZOO, held_out

    assert 12 <= len(ZOO) <= 20
    a = ZOO["rc2_bessel6"].config()
    assert a.highpass_rc_hz == (60e3, 69e3) and a.lowpass_family == "bessel"
    assert a.lowpass_order == 6
    b = ZOO["hp1_50k_lp2_800k"].config()
    assert (b.highpass_hz, b.highpass_order, b.lowpass_hz, b.lowpass_order) == (50e3, 1, 800e3, 2)
    c = ZOO["alpha_1e6"].config()
    assert c.emission_alpha_1_s == 1e6 and c.highpass_hz == 100e3
    for d in ZOO.values():
        for medium in ("water_skin", "silicone"):
            for fs in (2e6, 5e6, 10e6):
                assert d.config(medium, fs).frontend.poles.size >= 2
    drawn = held_out(3, 6)
    assert [d.fields for d in drawn] == [d.fields for d in held_out(3, 6)]
    for d in drawn:
        assert all(d.fields != m.fields for m in ZOO.values())
        cfg = d.config("silicone", 2e6)
        assert 1e3 <= cfg.emission_alpha_1_s <= 1e6
        assert 0.3 * 2e6 * (1 - 1e-9) <= cfg.lowpass_hz <= 1e6 * (1 + 1e-9)


def test_zoo_slip_plays_a_scene_on_a_device_through_the_driver_path():
    """ae_eval.zoo_slip renders every emission of the incipient-slip scene on a device
    and feeds it to the pipeline at its true time: on the nominal device every emission
    is localized, the micro-slips give a precursor before the scene's gross slip and no
    SLIP comes before q = 0.9 (the paper's physics, the scene's truth); on a textbook front
    end (rc2_bessel6) the same scene still reaches the slip stage."""
    from ae_eval.zoo import ZOO
    from ae_eval.zoo_slip import _q_time_ns, run_on_device

    r = run_on_device(ZOO["nominal"], "incipient_slip", 1)
    gross = r["truth"]["gross_slip_time_ns"]
    assert r["n_contacts"] == r["n_emissions"] > 100
    pre = [t for k, t in r["slip"] if k == 3]
    assert pre and min(pre) < gross
    assert all(t >= _q_time_ns(r["scene"], 0.9) for k, t in r["slip"] if k == 4)
    other = run_on_device(ZOO["rc2_bessel6"], "incipient_slip", 1)
    assert other["n_emissions"] == r["n_emissions"] and other["n_contacts"] > 0


def test_everyday_scene_on_a_device_is_localized_where_the_truth_says():
    """ae_eval.everyday_zoo renders a multi-point touch's emissions on a device and
    localizes them with the driver's PacketLocalizer: on the nominal device and on a
    textbook front end every touch and release is kept, at its true time, within 0.2 mm of
    its true point, with its polarity."""
    from ae_eval.everyday import multi_point
    from ae_eval.everyday_zoo import device_events
    from ae_eval.zoo import ZOO
    from ae_tactile.geometry import FingertipGeometry

    scene = multi_point(3)
    truth = FingertipGeometry().surface_point_from_xy(scene.xy_m[:, 0], scene.xy_m[:, 1])
    for name in ("nominal", "hp2_150k"):
        ev, counts = device_events(scene, ZOO[name], np.random.default_rng(1))
        assert sorted(e.packet_id for e in ev) == list(range(scene.t_s.size)), (name, counts)
        for e in ev:
            i = e.packet_id
            assert abs(e.time_ns - scene.t_s[i] * 1e9) < 1e3  # [ns]
            assert np.linalg.norm(e.point_m - truth[i]) < 0.2e-3, name
            assert e.polarity == scene.polarity[i]
