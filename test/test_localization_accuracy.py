# SPDX-License-Identifier: Apache-2.0
"""Localization accuracy on simulated packets: the paper's Fig. 7(d) and Fig. 8(e) cases,
accuracy against the Cramer-Rao bound, covariance calibration, touch vs release."""

import numpy as np
import pytest
from test_localization_analytic import analytic_windows

from ae_eval.crlb import simulated_crlb
from ae_tactile.dsp import DetectorConfig, PacketDetector
from ae_tactile.localization import localize, localize_packets
from ae_tactile.localization.common import adc_noise
from ae_tactile.sim import SimConfig, noise_rms_for_snr, render_triggered, signal_power_v2
from ae_tactile.sim.stream import EmissionList, StreamRenderer

CFG = SimConfig()  # the paper's water-skin tip, 10 MS/s, 12-bit ADC
GEO = CFG.geometry
FS = CFG.sample_rate_hz


def cap_points(rng, n, max_deg=60.0):
    ct = rng.uniform(np.cos(np.deg2rad(max_deg)), 1, n)
    return GEO.surface_point_from_angles(np.arccos(ct), rng.uniform(0, 2 * np.pi, n))


def test_fig7d_touches_at_0_25_5_mm_within_50_um():
    # Fig. 7(d): touches at (x, y) = (0, 0), (2.5, 0), (5, 0) mm, SNR 30 dB, 10 MS/s.
    xs = np.repeat([0.0, 2.5e-3, 5e-3], 25)
    pts = GEO.surface_point_from_xy(xs, np.zeros_like(xs))
    pk = render_triggered(pts, CFG, snr_db=30, rng=70)
    res = localize(pk.samples_v, FS, pk.onset_index, method="ml")
    assert res.accepted.all()
    err = np.linalg.norm(res.point_m - pts, axis=1)
    assert err.max() < 50e-6
    # in-plane x as the paper plots it
    np.testing.assert_allclose(res.point_m[:, 0], xs, atol=50e-6)
    assert np.all(res.polarity == 1)
    # the paper's own processing (Eq. 2 from cross-correlation peaks) is near, not exact
    ff = localize(pk.samples_v, FS, pk.onset_index, method="xcorr_farfield")
    err_ff = np.linalg.norm(ff.point_m - pts, axis=1)
    assert err_ff.max() < 0.3e-3 and np.sqrt(np.mean(err_ff**2)) > 2 * np.sqrt(np.mean(err**2))


def test_fig8e_three_pins_in_one_stream_within_50_um():
    # Fig. 8(e): a plate with three pins; three touches within 2 ms in one stream, with the
    # wall echoes on (the estimators must stop before them). SNR 30 dB for a touch at the apex.
    cfg = CFG.replace(reflections=True)
    xy = np.array([[-3e-3, 2e-3], [3e-3, 2e-3], [0.0, -3e-3]])  # the simulator's three_pins scene
    pts = GEO.surface_point_from_xy(xy[:, 0], xy[:, 1])
    t_ns = np.array([100_000, 800_000, 1_900_000])  # 1.8 ms apart at most
    em = EmissionList.create(
        t_ns,
        pts,
        "touch",
        speed_m_s=0.3,
        curvature_1_m=1000.0,
        alpha_1_s=3000.0,
        density_kg_m3=cfg.density,
        event_id=np.arange(3),
    )
    apex = render_triggered(
        np.array([[0, 0, GEO.radius_m]]), cfg.replace(quantization=False), subsample_offset=0.0
    )
    sigma = float(noise_rms_for_snr(signal_power_v2(apex.clean_v, apex.onset_index, FS), 30.0)[0])
    n_total = int(2.1e-3 * FS)
    for seed in range(5):
        stream, clipped = StreamRenderer(cfg, noise_rms_v=sigma, seed=seed).render(em, 0, n_total)
        assert not clipped
        # windows cut like a detector would: 8 us before the first arrival, 40 us long
        first = t_ns * 1e-9 + GEO.arrival_times_s(pts).min(axis=1)
        onset_abs = np.ceil(first * FS).astype(int)
        starts = onset_abs - 80
        win = np.stack([stream[:, s : s + 400] for s in starts])
        res = localize(win, FS, onset_abs - starts, method="ml")
        assert res.accepted.all(), res.reason_names
        assert np.linalg.norm(res.point_m - pts, axis=1).max() < 50e-6
        assert np.all(res.polarity == 1)


def test_fig8e_three_pins_through_the_packet_detector():
    # The same three pins, 2 ms of stream with wall echoes, cut by ae_tactile.dsp's detector
    # (AIC onsets, its own windows): the direct packets localize within 50 um; the
    # detector's in-hit re-triggers on the echoes are not accepted.

    cfg = CFG.replace(reflections=True)
    xy = np.array([[-3e-3, 2e-3], [3e-3, 2e-3], [0.0, -3e-3]])
    pts = GEO.surface_point_from_xy(xy[:, 0], xy[:, 1])
    t_ns = np.array([400_000, 1_100_000, 2_200_000])
    em = EmissionList.create(
        t_ns,
        pts,
        "touch",
        speed_m_s=0.3,
        curvature_1_m=1000.0,
        alpha_1_s=3000.0,
        density_kg_m3=cfg.density,
        event_id=np.arange(3),
    )
    apex = render_triggered(
        np.array([[0, 0, GEO.radius_m]]), cfg.replace(quantization=False), subsample_offset=0.0
    )
    sigma = float(noise_rms_for_snr(signal_power_v2(apex.clean_v, apex.onset_index, FS), 30.0)[0])
    stream, _ = StreamRenderer(cfg, noise_rms_v=sigma, seed=3).render(em, 0, int(2.5e-3 * FS))
    det = PacketDetector(DetectorConfig(sample_rate_hz=FS))
    batches = [det.process(stream, 0), det.flush()]
    found = []
    for b in batches:
        if len(b.onset_index) == 0:
            continue
        res = localize_packets(b)
        for i in range(len(res)):
            if b.in_hit[i]:
                assert not res.accepted[i]
            else:
                assert res.accepted[i], res.reason_names
                found.append(res.point_m[i])
    found = np.array(found)
    assert found.shape == (3, 3)
    assert np.linalg.norm(found - pts, axis=1).max() < 50e-6


@pytest.mark.parametrize("snr_db", [20.0, 30.0])
def test_accuracy_against_crlb(snr_db):
    rng = np.random.default_rng(int(snr_db))
    pts = cap_points(rng, 300)
    u = rng.uniform(0.01, 0.99, 300)
    pk = render_triggered(pts, CFG, snr_db=snr_db, subsample_offset=u, rng=rng)
    bound = simulated_crlb(pts, CFG, snr_db=snr_db, subsample_offset=u)
    crlb = np.sqrt(np.mean(bound["rms_m"] ** 2))
    assert 5e-6 < crlb < 30e-6  # tens of micrometres at 20 dB, a few at 30 dB
    rms = {}
    for m in ("ml", "gradient", "gcc_phat", "xcorr_farfield"):
        r = localize(pk.samples_v, FS, pk.onset_index, method=m)
        assert r.accepted.mean() > 0.98
        e = (r.point_m - pts)[r.accepted, :2]
        rms[m] = np.sqrt(np.mean(np.sum(e**2, axis=1)))
    assert rms["ml"] < 1.3 * crlb
    assert rms["gradient"] < 1.3 * crlb
    assert rms["gcc_phat"] < 2.0 * crlb
    assert rms["xcorr_farfield"] > 2.0 * rms["ml"]


def _calibration(err, cov):
    """Fractions of 2-D errors within Mahalanobis 1 and 1.515, and within 1 sigma along
    each principal axis of the reported covariance."""
    d2 = np.einsum("ki,kij,kj->k", err, np.linalg.inv(cov), err)
    lam, vec = np.linalg.eigh(cov)
    proj = np.einsum("kij,ki->kj", vec, err) / np.sqrt(lam)
    return np.mean(d2 < 1.0), np.mean(d2 < 1.515**2), np.mean(np.abs(proj) < 1.0, axis=0)


@pytest.mark.parametrize("method", ["ml", "gradient"])
@pytest.mark.parametrize("where", ["pole", "off_axis", "random"])
def test_covariance_is_calibrated(method, where):
    # Reading of "the 1-sigma ellipse holds about 68 %": the reported 2x2 in-plane
    # covariance C is right when the errors e satisfy e^T C^-1 e ~ chi^2(2): 39.3 % within
    # the 1-sigma ellipse, 68.3 % within 1.515 sigma, and 68.3 % of the errors projected
    # on each principal axis within that axis' sigma.
    rng = np.random.default_rng({"pole": 1, "off_axis": 2, "random": 3}[where])
    n = 2000
    if where == "pole":
        pts = np.tile([0.0, 0.0, GEO.radius_m], (n, 1))
    elif where == "off_axis":
        pts = np.tile(GEO.surface_point_from_angles(np.deg2rad(45.0), 0.5), (n, 1))
    else:
        pts = cap_points(rng, n)
    snr = rng.choice([20.0, 30.0], n)
    pk = render_triggered(pts, CFG, snr_db=snr, rng=rng)
    r = localize(pk.samples_v, FS, pk.onset_index, method=method)
    assert r.accepted.all()
    err = (r.point_m - pts)[:, :2]
    in1, in1515, axes = _calibration(err, r.covariance_m2[:, :2, :2])
    assert 0.34 < in1 < 0.45, in1
    assert 0.62 < in1515 < 0.74, in1515
    assert np.all((axes > 0.62) & (axes < 0.75)), axes


def test_touch_and_release_polarity_and_amplitude():
    rng = np.random.default_rng(5)
    n = 600
    pts = cap_points(rng, n, 80.0)
    pol = rng.choice([-1, 1], n)
    snr = rng.choice([10.0, 20.0, 30.0, 40.0], n)
    pk = render_triggered(pts, CFG, snr_db=snr, polarity=pol, rng=rng)
    for m in ("ml", "gcc_phat", "xcorr_farfield"):
        r = localize(pk.samples_v, FS, pk.onset_index, method=m)
        assert np.all(r.polarity == pol), m
        assert np.all(np.sign(r.amplitude_v) == pol)
    # amplitude: the first-lobe peak of the aligned channel mean = the mean of the clean
    # channels' peaks (up to noise and sub-sample peak position)
    r = localize(pk.samples_v, FS, pk.onset_index, method="ml")
    clean_peak = np.abs(pk.clean_v).max(axis=2).mean(axis=1)
    hi = snr >= 30
    np.testing.assert_allclose(np.abs(r.amplitude_v[hi]), clean_peak[hi], rtol=0.05)
    assert np.all((r.confidence > 0) & (r.confidence <= 1))
    # confidence grows with SNR
    assert np.median(r.confidence[snr == 40]) > np.median(r.confidence[snr == 10])


def test_snr_estimate_follows_the_package_definition():
    rng = np.random.default_rng(6)
    pts = cap_points(rng, 400)
    for snr in (10.0, 20.0):
        pk = render_triggered(pts, CFG.replace(quantization=False), snr_db=snr, rng=rng)
        r = localize(pk.samples_v, FS, pk.onset_index)
        assert abs(np.median(r.snr_db_est) - snr) < 0.3
        np.testing.assert_allclose(np.median(r.noise_rms_v_est / pk.noise_rms_v), 1.0, atol=0.03)


def test_false_rejections_of_clean_single_packets_are_rare():
    # Overlap thresholds are calibrated on single packets at the lowest accepted SNR.
    rng = np.random.default_rng(8)
    n = 1000
    pts = cap_points(rng, n, 90.0)
    for fs in (5e6, 10e6):
        cfg = CFG.replace(sample_rate_hz=fs)
        pk = render_triggered(pts, cfg, snr_db=8.0, rng=rng)
        for m in ("ml", "gradient", "gcc_phat", "xcorr_farfield"):
            r = localize(pk.samples_v, fs, pk.onset_index, method=m)
            assert np.mean(r.reason == 6) < 0.01, (fs, m)  # OVERLAP
            assert np.mean(~r.accepted) < 0.02, (fs, m, np.bincount(r.reason))


def test_overlapping_packets_are_rejected():
    rng = np.random.default_rng(9)
    n = 300
    p1, p2 = cap_points(rng, n), cap_points(rng, n)
    cfg = CFG.replace(quantization=False)
    a = render_triggered(p1, cfg, subsample_offset=0.3, window_s=60e-6)
    b = render_triggered(p2, cfg, subsample_offset=0.3, window_s=60e-6)
    sigma = np.sqrt(a.signal_power_v2 / 10**2.0)  # 20 dB
    far = np.linalg.norm(p1 - p2, axis=1) > 3e-3
    for delay_us in (1.0, 3.0, 6.0):
        d = int(delay_us * 10)
        x = a.clean_v.copy()
        x[:, :, d:] += rng.uniform(0.5, 2.0, (n, 1, 1)) * b.clean_v[:, :, : x.shape[2] - d]
        x += sigma[:, None, None] * rng.standard_normal(x.shape)
        r = localize(x, FS, a.onset_index, method="ml")
        assert np.mean(r.reason[far] == 6) > 0.9, delay_us
    # a second packet after the echo-free segment does not disturb the first
    x = a.clean_v.copy()
    x[:, :, 150:] += b.clean_v[:, :, : x.shape[2] - 150]
    x += sigma[:, None, None] * rng.standard_normal(x.shape)
    r = localize(x, FS, a.onset_index, method="ml")
    assert r.accepted.mean() > 0.97
    assert np.sqrt(np.mean(np.sum((r.point_m - p1)[r.accepted] ** 2, axis=1))) < 40e-6


# ----------------------------------------------------------------------------- the bound
def _ratio_and_calibration(r, pts, crlb_rms):
    """RMS in-plane error over the CRLB, and the fraction of errors inside the reported
    1.515-sigma ellipse (68.3 % for a right covariance)."""
    assert r.accepted.mean() > 0.98
    e = (r.point_m - pts)[r.accepted, :2]
    rms = np.sqrt(np.mean(np.sum(e**2, axis=1)))
    _, in1515, _ = _calibration(e, r.covariance_m2[r.accepted, :2, :2])
    return rms / crlb_rms, in1515


def _grid_points(n, max_deg=60.0):
    i = np.arange(n) + 0.5
    ct = 1.0 - (1.0 - np.cos(np.deg2rad(max_deg))) * i / n
    return GEO.surface_point_from_angles(np.arccos(ct), np.pi * (1 + 5**0.5) * i)


@pytest.mark.parametrize("case", ["water_10", "silicone_10", "water_2"])
def test_ml_at_the_bound_from_10_to_40_db(case):
    # The data-driven band (each packet's spectrum against its noise) keeps `ml` at the
    # Cramer-Rao bound at every SNR: <= 1.1x at 10 MS/s, <= 1.2x at 2 MS/s behind the
    # simulator's default anti-alias filter (min(1 MHz, 0.3 fs) = 0.6 MHz, 8th order), with the
    # covariance calibrated (68 +- 5 % inside 1.515 sigma). Margins for 300 packets: the
    # ratio's sampling spread is ~4 %, the fraction's ~2.7 %.
    cfg = {
        "water_10": CFG,
        "silicone_10": SimConfig.for_medium("silicone"),
        "water_2": CFG.replace(sample_rate_hz=2e6),
    }[case]
    cfg = cfg.replace(reflections=True)
    fs = cfg.sample_rate_hz
    assert cfg.lowpass_hz == min(1e6, 0.3 * fs) and cfg.lowpass_order == (8 if fs < 3e6 else 4)
    limit = 1.2 if case == "water_2" else 1.1
    rng = np.random.default_rng(40)
    pts = _grid_points(300)
    for snr in (10.0, 20.0, 30.0, 40.0):
        u = rng.uniform(0.01, 0.99, len(pts))
        pk = render_triggered(pts, cfg, snr_db=snr, subsample_offset=u, rng=rng)
        bound = simulated_crlb(pts, cfg, snr_db=snr, subsample_offset=u)
        crlb = np.sqrt(np.mean(bound["rms_m"] ** 2))
        r = localize(pk.samples_v, fs, pk.onset_index, geometry=cfg.geometry)
        ratio, in1515 = _ratio_and_calibration(r, pts, crlb)
        assert ratio < limit + 0.06, (case, snr, ratio)
        assert 0.60 < in1515 < 0.76, (case, snr, in1515)


def test_ml_at_the_bound_on_analytic_pulses():
    # Three pulse shapes independent of the simulator (exact delays, white noise): a Gabor
    # well inside 1 MHz, a Ricker peaking at 0.8 MHz (much of its energy above 1 MHz) and a
    # causal damped 0.6 MHz sine. The data-driven band reaches the bound for all three; the
    # old fixed 100 kHz - 1 MHz band loses a third on the Ricker. 500 packets per cell: the
    # fraction inside 1.515 sigma has a sampling spread of ~2 %.

    rng = np.random.default_rng(41)
    pts = _grid_points(500)
    for shape in ("gabor", "ricker", "damped"):
        for snr in (10.0, 40.0):
            x, onset, crlb = analytic_windows(shape, pts, FS, snr, rng)
            ratio, in1515 = _ratio_and_calibration(localize(x, FS, onset), pts, crlb)
            assert ratio < 1.16, (shape, snr, ratio)
            assert 0.60 < in1515 < 0.76, (shape, snr, in1515)
    x, onset, crlb = analytic_windows("ricker", pts, FS, 30.0, rng)
    fixed, _ = _ratio_and_calibration(localize(x, FS, onset, band_hz=(100e3, 1e6)), pts, crlb)
    auto, _ = _ratio_and_calibration(localize(x, FS, onset), pts, crlb)
    assert fixed > 1.2 and auto < 1.1, (fixed, auto)


def test_ml_at_the_bound_at_2_ms_on_a_band_limited_analytic_pulse():
    # 2 MS/s with a pulse the simulator did not make: a 250 kHz Gabor whose spectrum is
    # ~-100 dB by the 1 MHz Nyquist frequency (what an anti-alias filter guarantees). The
    # data-driven band must reach the bound (<= 1.2x) and stay calibrated; measured
    # 0.99-1.01x and 66-71 % over 500 packets per SNR. (Broadband pulses alias at 2 MS/s
    # and are not at the bound there: the causal damped sine is 4.5-67x.)

    fs = 2e6
    rng = np.random.default_rng(43)
    pts = _grid_points(500)
    for snr in (10.0, 20.0, 30.0, 40.0):
        x, onset, crlb = analytic_windows("gabor_narrow", pts, fs, snr, rng)
        ratio, in1515 = _ratio_and_calibration(localize(x, fs, onset), pts, crlb)
        assert ratio < 1.2, (snr, ratio)
        assert 0.60 < in1515 < 0.76, (snr, in1515)


# ----------------------------------------------------------------- the ADC's rounding noise
def test_adc_noise_inverts_the_quantized_quiet_baseline():
    # A quiet baseline quantized by a mid-tread ADC (baseline on a level) under-reads the
    # analog noise once sigma < q/2 (most samples sit on one level), while on the signal
    # samples the noise is sigma^2 + q^2/12 (the signal crosses levels: uniform rounding
    # error). adc_noise must return that total from the quantized baseline's variance;
    # the earlier linear rule read 6 % low at sigma = 0.27 q and 21 % low at 0.15 q.

    rng = np.random.default_rng(50)
    q = 1.0
    for s in (0.15, 0.2, 0.27, 0.35, 0.5, 1.0, 3.0):
        x = np.round(s * rng.standard_normal(400_000) / q) * q
        total = adc_noise(np.array([x.var()]), np.array([q * q / 12]), np.array([False]))[0]
        expected = s * s + q * q / 12
        assert abs(total / expected - 1.0) < 0.03, (s, total, expected)
        given = adc_noise(np.array([s * s]), np.array([q * q / 12]), np.array([True]))[0]
        assert given == pytest.approx(expected, rel=1e-12)
    # no quantum known: the variance as measured
    assert adc_noise(np.array([0.3]), np.array([0.0]), np.array([False]))[0] == 0.3


@pytest.mark.parametrize("case", ["water_10", "silicone_10", "water_2"])
def test_covariance_calibrated_at_40_db_with_a_12_bit_adc(case):
    # At 40 dB the simulator's analog noise is ~0.27 LSB of its 12-bit ADC: the rounding
    # noise dominates and the quiet baseline under-reads the analog part. Without the
    # quantizer the covariance is calibrated (mean e^T C^-1 e = 2.01); with it, the old
    # noise rule left it optimistic (mean 2.13-2.20, 62-66 % inside 1.515 sigma). With
    # the mid-tread inversion it must hold: 3000 packets, spread of the fraction ~0.9 %,
    # of the mean of chi^2(2) ~0.037; both engines (the compiled one is the default).
    cfg = {
        "water_10": CFG,
        "silicone_10": SimConfig.for_medium("silicone"),
        "water_2": CFG.replace(sample_rate_hz=2e6),
    }[case].replace(reflections=True)
    rng = np.random.default_rng(42)
    pts = _grid_points(3000)
    u = rng.uniform(0.01, 0.99, len(pts))
    pk = render_triggered(pts, cfg, snr_db=40.0, subsample_offset=u, rng=rng)
    for engine in (None, "numpy"):
        r = localize(
            pk.samples_v, cfg.sample_rate_hz, pk.onset_index, geometry=cfg.geometry, engine=engine
        )
        assert r.accepted.mean() > 0.99
        e = (r.point_m - pts)[r.accepted, :2]
        C = r.covariance_m2[r.accepted, :2, :2]
        d2 = np.einsum("ki,kij,kj->k", e, np.linalg.inv(C), e)
        assert 0.655 < np.mean(d2 < 1.515**2) < 0.71, (case, engine, np.mean(d2 < 1.515**2))
        assert 1.89 < np.mean(d2) < 2.11, (case, engine, np.mean(d2))
