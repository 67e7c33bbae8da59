# SPDX-License-Identifier: Apache-2.0
"""Simulator core: emission (Eqs. 10-11), front end, exact delays, polarity, SNR, validation."""
import math

import numpy as np
import pytest
from scipy import signal

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.sim import (
    SimConfig,
    collision_pressure_pa,
    noise_rms_for_snr,
    peak_pressure_pa,
    render_triggered,
    signal_power_v2,
)
from ae_tactile.sim.propagation import attenuation_pole_rad_s
from ae_tactile.sim.response import arrival_coefficients, evaluate


def _single_response(cfg, amplitude=9.0, alpha=3000.0, att=None, offset=0.0, n=None):
    co = arrival_coefficients([amplitude], [alpha], None if att is None else [att],
                              [0], [offset], cfg)
    return co, evaluate(co, cfg, n_samples=int(co.length[0]) if n is None else n)[0]


# ----------------------------------------------------------------- emission, Eq. 10-11
def test_eq11_nine_pascal():
    # rho = 1000 kg/m^3, v0 = 30 cm/s, l = 10 mm, a = 1/mm  ->  rho v0^2/(a l) = 9 Pa
    assert peak_pressure_pa(0.30, 1000.0, 10e-3, 1000.0) == pytest.approx(9.0, rel=1e-12)
    dist, c = 10e-3, 1480.0
    t0 = dist / c
    p = collision_pressure_pa([t0 - 1e-9, t0 + 1e-12], dist, c, speed_m_s=0.3,
                              curvature_1_m=1000.0,
                              density_kg_m3=1000.0)
    assert p[0] == 0.0
    assert p[1] == pytest.approx(9.0, rel=1e-6)


def test_eq10_pulse_integrates_to_zero_and_recovers():
    dist, c, alpha = 10e-3, 1480.0, 3000.0
    t = dist / c + 1e-12 + np.linspace(0, 40 / alpha, 400001)
    p = collision_pressure_pa(t, dist, c, alpha_1_s=alpha)
    assert np.trapezoid(p, t) == pytest.approx(0.0, abs=1e-5 * 9.0 / alpha)
    # zero crossing at tau = ln 2 / alpha, minimum -p0/8
    # (2x^2 - x, x = e^{-alpha tau}: min at x = 1/4)
    assert p.min() == pytest.approx(-9.0 / 8.0, rel=1e-4)


def test_highpassed_jump_is_eq11():
    """After an (ideal-gain) high-pass only, the output just after the arrival is 9 Pa."""
    cfg = SimConfig(lowpass_hz=None, sensitivity_v_per_pa=1.0)
    _, y = _single_response(cfg, amplitude=peak_pressure_pa(0.3, 1000.0, 10e-3, 1000.0))
    assert y[0] == pytest.approx(9.0, rel=1e-9)


@pytest.mark.parametrize("kw,att", [({}, None), ({"lowpass_hz": None}, None),
                                    ({"highpass_order": 3, "lowpass_order": 5}, None),
                                    ({}, 2 * math.pi * 3e6)])
def test_closed_form_matches_scipy_impulse(kw, att):
    """Independent check of the partial-fraction evaluation against scipy's LTI solver."""
    cfg = SimConfig(max_support_s=150e-6, support_rel_tol=1e-9, **kw)
    fe = cfg.frontend
    A, alpha, off = 9.0, 4000.0, 0.37e-7
    co, y = _single_response(cfg, A, alpha, att, off)
    zeros = np.r_[fe.zeros, 0.0]
    poles = np.r_[fe.poles, -alpha, -2 * alpha]
    gain = fe.gain * A
    if att is not None:
        poles = np.r_[poles, -att]
        gain = gain * att
    tau = co.eps_s[0] + np.arange(len(y)) / cfg.sample_rate_hz
    _, ref = signal.impulse(signal.ZerosPolesGain(zeros, poles, gain), T=tau)
    assert np.max(np.abs(y - ref)) < 1e-6 * np.max(np.abs(ref))


def test_pulse_duration_about_one_over_omega0():
    """Paper: after high-pass filtering at omega_0 the pulse lasts T ~ 1/omega_0 ('10 us at
    100 kHz'). Measure the time the pulse stays above 10 % of its peak: between 1/omega_0
    (1.6 us) and 1/f_0 (10 us) at 100 kHz, and inversely proportional to the cut-off."""
    def duration(hp):
        cfg = SimConfig(highpass_hz=hp)
        _, y = _single_response(cfg, n=1000)
        above = np.nonzero(np.abs(y) > 0.1 * np.abs(y).max())[0]
        return above.max() / cfg.sample_rate_hz

    d100 = duration(100e3)
    assert 1.0 / (2 * math.pi * 100e3) < d100 < 1.0 / 100e3
    ratio = duration(50e3) / duration(200e3)
    assert 3.0 < ratio < 5.0


def test_default_spectrum_band():
    """The sensed band: the emission is ~1/f above 2 alpha/2pi ~ 1 kHz and the front end
    passes 0.1-1 MHz, so the output spectrum peaks near 100 kHz, is 20 dB down at 1 MHz,
    >15 dB down at 10 kHz, and > 40 dB down at Nyquist (little aliasing at 10 MS/s)."""
    fe = SimConfig().frontend
    alpha = 3000.0
    f = np.geomspace(1e3, 5e6, 2000)
    s = 2j * np.pi * f
    db = 20 * np.log10(np.abs(fe.transfer(s) * (2 / (s + 2 * alpha) - 1 / (s + alpha))))
    db -= db.max()
    assert 50e3 < f[np.argmax(db)] < 200e3
    assert np.interp(1e6, f, db) == pytest.approx(-20.0, abs=1.0)
    assert np.interp(1e4, f, db) < -15.0
    assert db[-1] < -40.0


# ----------------------------------------------------------------- delays
def _xy_points(geo, xs_mm):
    return geo.surface_point_from_xy(np.asarray(xs_mm) * 1e-3, np.zeros(len(xs_mm)))


def _measured_delay(x, y, up=64):
    """Delay of y relative to x (seconds * fs) by upsampled cross-correlation + parabola."""
    n = x.shape[-1]
    nfft = 4 * n
    X = np.fft.rfft(x, nfft)
    Y = np.fft.rfft(y, nfft)
    cc = np.fft.irfft(Y * np.conj(X), nfft * up)
    cc = np.roll(cc, nfft * up // 2)
    k = int(np.argmax(cc))
    a, b, c = cc[k - 1], cc[k], cc[k + 1]
    frac = 0.5 * (a - c) / (a - 2 * b + c)
    return (k + frac - nfft * up // 2) / up


def test_paper_positions_delays_match_geometry_and_waveforms():
    """Contacts at x = 0, 2.5, 5 mm (paper Fig. 7): ground-truth delays equal geometry.py's,
    and the delays measured from the rendered waveforms agree with them to < 1 ns."""
    cfg = SimConfig(quantization=False)
    geo = cfg.geometry
    pts = _xy_points(geo, [0.0, 2.5, 5.0])
    pk = render_triggered(pts, cfg, window_s=100e-6, pretrigger_s=20e-6, rng=3)
    np.testing.assert_allclose(pk.delays_s, geo.exact_delays_s(pts), rtol=0, atol=1e-18)
    np.testing.assert_allclose(pk.arrival_times_s - pk.arrival_times_s[:, :1],
                               geo.arrival_times_s(pts) - geo.arrival_times_s(pts)[:, :1],
                               atol=1e-15)
    fs = cfg.sample_rate_hz
    for i in range(3):
        t_meas = np.array([_measured_delay(pk.clean_v[i, 0], pk.clean_v[i, k])
                           for k in range(4)]) / fs
        t_true = pk.arrival_times_s[i] - pk.arrival_times_s[i, 0]
        np.testing.assert_allclose(t_meas, t_true, atol=1e-9)
        d_meas = geo.delays_from_arrival_times(t_meas)[:2]
        np.testing.assert_allclose(d_meas, pk.delays_s[i], atol=1e-9)
    # x = 0: no delay; tau_x grows with x (paper Fig. 7: p11 + p1-1 leads p-11 + p-1-1)
    assert abs(pk.delays_s[0, 0]) < 1e-15
    assert 0 < pk.delays_s[1, 0] < pk.delays_s[2, 0]
    assert np.all(np.abs(pk.delays_s[:, 1]) < 1e-15)
    # far field (Eq. 2): tau_x = (a/c) x / R  -> 0.253 us and 0.507 us; the exact geometry
    # differs at order (a/R)^2 = 2.25 % for a = 1.5 mm, R = 10 mm
    np.testing.assert_allclose(pk.delays_s[1:, 0], [1.5e-3 / 1480 * 0.25, 1.5e-3 / 1480 * 0.5],
                               rtol=0.03)


def test_far_field_agrees_with_exact_to_first_order():
    """Eq. 2 vs exact geometry: the error, relative to a/c, shrinks like (a/R)^2."""
    rng = np.random.default_rng(0)
    th = np.arccos(rng.uniform(0.05, 1.0, 500))
    ph = rng.uniform(0, 2 * np.pi, 500)
    errs = []
    for a in (0.5e-3, 1.0e-3, 2.0e-3):
        geo = FingertipGeometry(element_offset_m=a)
        pts = geo.surface_point_from_angles(th, ph)
        err = np.max(np.abs(geo.exact_delays_s(pts) - geo.far_field_delays_s(pts)))
        errs.append(err / (a / geo.sound_speed_m_s))
        assert errs[-1] < (a / geo.radius_m) ** 2
    assert 3.5 < errs[1] / errs[0] < 4.5 and 3.5 < errs[2] / errs[1] < 4.5


# ----------------------------------------------------------------- polarity
def test_touch_and_release_have_opposite_polarity():
    cfg = SimConfig()
    pts = _xy_points(cfg.geometry, [2.5, 2.5])
    pk = render_triggered(pts, cfg, polarity=[1, -1], subsample_offset=0.3)
    np.testing.assert_array_equal(pk.clean_v[0], -pk.clean_v[1])
    # a touch raises the pressure: the first lobe after the onset is positive
    for k in range(4):
        seg = pk.clean_v[0, k]
        first = seg[np.argmax(np.abs(seg) > 0.05 * np.abs(seg).max())]
        assert first > 0


# ----------------------------------------------------------------- SNR, noise, ADC
def test_realised_snr_matches_request():
    cfg = SimConfig(quantization=False)
    rng = np.random.default_rng(5)
    th = np.arccos(rng.uniform(0.3, 1.0, 400))
    pts = cfg.geometry.surface_point_from_angles(th, rng.uniform(0, 2 * np.pi, 400))
    for snr in (10.0, 20.0, 30.0):
        pk = render_triggered(pts, cfg, snr_db=snr, rng=7)
        noise = pk.samples_v - pk.clean_v
        p_sig = signal_power_v2(pk.clean_v, pk.onset_index, cfg.sample_rate_hz)
        np.testing.assert_allclose(p_sig, pk.signal_power_v2)
        realised = 10 * np.log10(p_sig.mean() / noise.var(axis=(1, 2)).mean())
        assert realised == pytest.approx(snr, abs=0.1)
        np.testing.assert_allclose(pk.noise_rms_v, noise_rms_for_snr(p_sig, snr))


def test_snr_window_is_thirty_microseconds_from_earliest_arrival():
    x = np.zeros((1, 4, 1000))
    x[0, :, 100:400] = 2.0          # 300 samples = 30 us at 10 MS/s
    x[0, :, 400:] = 100.0           # outside the window: must not count
    assert signal_power_v2(x, [100], 10e6)[0] == pytest.approx(4.0)
    assert noise_rms_for_snr(4.0, 20.0) == pytest.approx(0.2)


def test_quantization_and_clipping():
    cfg = SimConfig()
    pts = _xy_points(cfg.geometry, [1.0])
    pk = render_triggered(pts, cfg, snr_db=25, rng=1)
    codes = pk.samples_v / cfg.lsb_v
    np.testing.assert_allclose(codes, np.rint(codes), atol=1e-9)
    assert not pk.saturated[0]
    hot = render_triggered(pts, cfg.replace(sensitivity_v_per_pa=1.0), rng=1)
    assert hot.saturated[0]
    assert hot.samples_v.max() == pytest.approx(cfg.adc_full_scale_v - cfg.lsb_v)
    assert hot.samples_v.min() == pytest.approx(-cfg.adc_full_scale_v)


# ----------------------------------------------------------------- optional effects
def test_first_wall_echo_arrives_two_radii_later():
    base = SimConfig(quantization=False)
    refl = base.replace(reflections=True, n_reflections=1)
    pts = _xy_points(base.geometry, [3.0])
    a = render_triggered(pts, base, window_s=60e-6, subsample_offset=0.0)
    b = render_triggered(pts, refl, window_s=60e-6, subsample_offset=0.0)
    diff = np.abs(b.clean_v - a.clean_v)[0]
    geo = base.geometry
    t_echo = (b.emission_time_s[0]
              + (2 * geo.radius_m + geo.path_lengths_m(-pts)[0]) / geo.sound_speed_m_s)
    fs = base.sample_rate_hz
    for k in range(4):
        first = np.argmax(diff[k] > 0) / fs
        assert t_echo[k] <= first < t_echo[k] + 1.0 / fs
    lag = t_echo - b.arrival_times_s[0]
    np.testing.assert_allclose(lag, 2 * geo.radius_m / geo.sound_speed_m_s, rtol=0.05)   # ~13.5 us


def test_attenuation_pole_gives_configured_loss():
    for att_db_m, path_m in ((200.0, 0.01), (200.0, 0.013), (50.0, 0.009)):
        w = attenuation_pole_rad_s(path_m, att_db_m)
        loss = 10 * np.log10(1 + (2 * np.pi * 1e6 / w) ** 2)
        assert loss == pytest.approx(att_db_m * path_m, rel=1e-9)
    assert np.isinf(attenuation_pole_rad_s(0.01, 0.0))


def test_silicone_attenuation_lowers_and_delays_pulse():
    lossless = SimConfig.for_medium("silicone", quantization=False)
    lossy = lossless.replace(attenuation=True)
    pts = _xy_points(lossless.geometry, [0.0])
    a = render_triggered(pts, lossless, subsample_offset=0.0)
    b = render_triggered(pts, lossy, subsample_offset=0.0)
    assert np.abs(b.clean_v).max() < np.abs(a.clean_v).max()
    # same geometric ground truth, waveforms differ
    np.testing.assert_array_equal(a.delays_s, b.delays_s)


# ----------------------------------------------------------------- validation
@pytest.mark.parametrize("kw,msg", [
    ({"sample_rate_hz": -1.0}, "sample_rate_hz"),
    ({"sample_rate_hz": 10.5e6 + 0.5}, "integer number of Hz"),
    ({"highpass_hz": 6e6}, "Nyquist"),
    ({"lowpass_hz": 50e3}, "above highpass_hz"),
    ({"lowpass_hz": "1 MHz"}, 'a number or "auto"'),
    ({"lowpass_order": "steep"}, 'a number or "auto"'),
    ({"adc_bits": 0}, "adc_bits"),
    ({"adc_bits": 12.0}, "adc_bits"),
    ({"medium": "honey"}, "unknown medium"),
    ({"medium": "silicone"}, "does not match medium"),
    ({"medium": "custom"}, "needs density_kg_m3"),
    ({"reflection_coefficient": 1.5}, "|r| < 1"),
    ({"sensitivity_v_per_pa": float("nan")}, "sensitivity_v_per_pa"),
    ({"quantization": "yes"}, "true or false"),
])
def test_config_validation_messages(kw, msg):
    with pytest.raises(ValueError, match=msg.replace("|", r"\|")):
        SimConfig(**kw)


def test_front_end_low_pass_follows_the_sample_rate():
    # "auto": the 1 MHz PVDF band (order 4) where the ADC is fast enough; below 3.33 MS/s an
    # anti-alias filter at 0.3 fs (order 8); a Butterworth is 10 log10(1 + (f/fc)^2n) dB
    # down: >= 30 dB at fs/2 wherever "auto" is used (36 dB at 2 MS/s, 32 dB at 5 MS/s).
    for fs, lp, order in [(10e6, 1e6, 4), (5e6, 1e6, 4), (2e6, 0.6e6, 8), (1e6, 0.3e6, 8)]:
        cfg = SimConfig(sample_rate_hz=fs)
        assert (cfg.lowpass_hz, cfg.lowpass_order) == (pytest.approx(lp), order)
        assert 10 * np.log10(1 + (0.5 * fs / cfg.lowpass_hz) ** (2 * order)) > 30.0
        assert cfg.replace(sample_rate_hz=10e6).lowpass_hz == 1e6  # re-resolved
        assert SimConfig().replace(sample_rate_hz=fs).lowpass_hz == pytest.approx(lp)
    fixed = SimConfig(lowpass_hz=0.8e6, lowpass_order=6).replace(sample_rate_hz=2e6)
    assert (fixed.lowpass_hz, fixed.lowpass_order) == (0.8e6, 6)  # numbers stay
    assert SimConfig(lowpass_hz=None).replace(sample_rate_hz=2e6).lowpass_hz is None
    assert SimConfig(sample_rate_hz=2e6, lowpass_order=4).lowpass_order == 4
    # the frequency response the renderer uses: 0.5 fs is where aliasing starts
    h = SimConfig(sample_rate_hz=2e6).frontend
    f = np.array([0.2e6, 1e6])
    mag = np.abs(h.gain * np.prod(2j * np.pi * f[:, None] - h.zeros, 1)
                 / np.prod(2j * np.pi * f[:, None] - h.poles, 1))
    assert 20 * np.log10(mag[1] / mag[0]) < -35.0


def test_render_triggered_validation_messages():
    cfg = SimConfig()
    good = _xy_points(cfg.geometry, [1.0])
    with pytest.raises(ValueError, match="off the sensing surface"):
        render_triggered([[0.0, 0.0, 0.011]], cfg)
    with pytest.raises(ValueError, match="below the sensing hemisphere"):
        render_triggered([[0.0, 0.0, -0.01]], cfg)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        render_triggered(np.zeros((2, 2)), cfg)
    with pytest.raises(ValueError, match="not both"):
        render_triggered(good, cfg, snr_db=20, noise_rms_v=1e-3)
    with pytest.raises(ValueError, match="polarity"):
        render_triggered(good, cfg, polarity=0)
    with pytest.raises(ValueError, match="SNR window"):
        render_triggered(good, cfg, snr_db=20, window_s=20e-6)
    with pytest.raises(ValueError, match="speed_m_s"):
        render_triggered(good, cfg, speed_m_s=-0.1)
