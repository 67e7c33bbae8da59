# SPDX-License-Identifier: Apache-2.0
"""Refinement with the device's stated front end (issue 37 point 3: ml within 1.15x the
Cramer-Rao bound on every device): behind an anti-alias filter that lets the pulse alias
the band-limited estimator locks to the samples; the one-emission fit with the front end's
own pulse models the aliasing and reaches the bound. The expectations are the bound (the
simulator's Fisher information) and the true points, never the estimator's own output."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from ae_eval.crlb import simulated_crlb
from ae_eval.zoo import ZOO
from ae_tactile.localization import Localizer, localize
from ae_tactile.localization.front_end import calibrate_front_end
from ae_tactile.localization.overlap import PulseModel
from ae_tactile.localization.refine import refine_points, refine_result
from ae_tactile.pipeline import LocalizationConfig, PacketLocalizer
from ae_tactile.records import PacketView
from ae_tactile.sim import render_triggered

FS = 2e6  # [Hz] below the 800 kHz low-pass's Nyquist rate: the pulse aliases
ALIASING = "highpass_hz=50e3 highpass_order=1 lowpass_hz=800e3 lowpass_order=2"
CHI2_2D_68 = -2.0 * math.log(1.0 - 0.68)  # [1] the 68 % ellipse of a 2-D Gaussian


def _points(geo, n, g, max_polar_deg=40.0):
    cos_t = g.uniform(math.cos(math.radians(max_polar_deg)), 1.0, n)
    return geo.surface_point_from_angles(np.arccos(cos_t), g.uniform(0, 2 * math.pi, n))


def _packets(name, n, seed, snr_db=40.0):
    """n packets of zoo device ``name`` at FS, 40 dB, and the bound [m] at each point."""
    g = np.random.default_rng(seed)
    cfg = ZOO[name].config("water_skin", FS)
    pts = _points(cfg.geometry, n, g)
    u = g.uniform(0.05, 0.95, n)
    pk = render_triggered(pts, cfg, snr_db=snr_db, subsample_offset=u, rng=g)
    bound = simulated_crlb(pts, cfg, snr_db=snr_db, subsample_offset=u)["rms_m"]
    return cfg, pk, bound


def _rms(points, truth):
    e = (points - truth)[:, :2]
    return math.sqrt(np.mean(np.sum(e**2, axis=1)))


def test_the_stated_front_end_is_the_aliasing_devices_own_pulse():
    """The zoo's aliasing device stated as text is the simulator's chain (the same
    stages, `geometry.front_end_stages`): the fit of its noise-free packets with that pulse
    lands on the true points to a micrometre, where ml is tens of micrometres off."""
    g = np.random.default_rng(1)
    cfg = ZOO["hp1_50k_lp2_800k"].config("water_skin", FS)
    pts = _points(cfg.geometry, 12, g)
    pk = render_triggered(pts, cfg, subsample_offset=g.uniform(0.05, 0.95, 12), rng=g)
    stated = PulseModel.from_spec(ALIASING)
    assert stated == PulseModel.from_config(cfg)
    clean = pk.clean_v if pk.clean_v is not None else pk.samples_v
    ml = localize(clean, FS, pk.onset_index, geometry=cfg.geometry, noise_rms_v=1e-6)
    got = refine_points(clean, FS, pk.onset_index, ml.point_m, ml.emission_offset_s, stated,
                        geometry=cfg.geometry, noise_rms_v=1e-6)
    assert got.refined.all()
    assert np.abs(got.point_m - pk.points_m).max() < 1e-6
    assert _rms(ml.point_m, pk.points_m) > 10e-6


def test_refinement_reaches_the_bound_where_ml_locks_to_the_samples():
    """hp1_50k_lp2_800k at 2 MS/s, 40 dB: ml is several times the bound; the refined points
    are within 1.3x of it (the issue's 1.15 with 60 points' sampling spread) and their 68 %
    ellipses hold 68 +- 15 % of the true points."""
    cfg, pk, bound = _packets("hp1_50k_lp2_800k", 60, 2)
    crb = math.sqrt(np.mean(bound**2))
    ml = localize(pk.samples_v, FS, pk.onset_index, geometry=cfg.geometry)
    assert ml.accepted.all()
    assert _rms(ml.point_m, pk.points_m) > 4.0 * crb
    res, got = refine_result(ml, pk.samples_v, FS, pk.onset_index,
                             PulseModel.from_spec(ALIASING), geometry=cfg.geometry)
    assert got.refined.mean() >= 0.95 and np.array_equal(res.refined, got.refined)
    m = res.refined
    assert _rms(res.point_m[m], pk.points_m[m]) <= 1.3 * crb
    e = (res.point_m - pk.points_m)[m, :2]
    d2 = [v @ np.linalg.solve(c[:2, :2], v) for v, c in zip(e, res.covariance_m2[m])]
    assert 0.53 <= np.mean(np.array(d2) <= CHI2_2D_68) <= 0.83
    # the directions and delays follow the refined points
    polar = np.arccos(res.point_m[m, 2] / cfg.geometry.radius_m)
    np.testing.assert_allclose(res.polar_rad[m], polar, atol=1e-9)
    tau = cfg.geometry.exact_delays_s(res.point_m[m])
    np.testing.assert_allclose(res.tau_x_s[m], tau[:, 0], atol=1e-15)


def test_a_wrong_front_end_fails_its_residual_test_and_keeps_the_estimate():
    """The nominal front end (2nd-order 100 kHz high-pass, 8th-order 600 kHz low-pass) is
    not this device's: at 40 dB its fits leave more than noise, so the packets keep ml's
    answer, unchanged, rather than a point of the wrong model."""
    cfg, pk, _ = _packets("hp1_50k_lp2_800k", 30, 3)
    ml = localize(pk.samples_v, FS, pk.onset_index, geometry=cfg.geometry)
    res, got = refine_result(ml, pk.samples_v, FS, pk.onset_index,
                             PulseModel.for_sample_rate(FS), geometry=cfg.geometry)
    assert got.refined.mean() <= 0.2
    assert np.all(got.chi2_ratio[~got.refined] > 1.2)
    keep = ~res.refined
    np.testing.assert_array_equal(res.point_m[keep], ml.point_m[keep])
    np.testing.assert_array_equal(res.covariance_m2[keep], ml.covariance_m2[keep])


def test_the_per_packet_path_refines_as_the_batch_does():
    """`Localizer.set_front_end`: `localize_one` (the driver's hot path) gives the batch
    call's refined points; `set_front_end(None)` restores the estimator's."""
    cfg, pk, _ = _packets("hp1_50k_lp2_800k", 10, 4)
    loc = Localizer("ml", geometry=cfg.geometry)
    loc.set_front_end(PulseModel.from_spec(ALIASING))
    batch = loc(pk.samples_v, FS, pk.onset_index)
    for i in range(10):
        one = loc.localize_one(np.ascontiguousarray(pk.samples_v[i]), FS,
                               int(pk.onset_index[i]))
        assert one.refined == bool(batch.refined[i])
        np.testing.assert_allclose(one.point_m, batch.point_m[i], atol=1e-9)
    loc.set_front_end(None)
    plain = loc(pk.samples_v, FS, pk.onset_index)
    assert plain.refined is None
    np.testing.assert_array_equal(
        plain.point_m, localize(pk.samples_v, FS, pk.onset_index,
                                geometry=cfg.geometry).point_m)
    with pytest.raises(TypeError):
        loc.set_front_end(ALIASING)


def _stream(name, n, seed, snr_lo=25.0, snr_hi=40.0, max_polar_deg=60.0):
    """n touches of zoo device ``name`` at FS (SNR drawn in [snr_lo, snr_hi] dB) as the
    driver's packets, 0.1 s apart."""
    g = np.random.default_rng(seed)
    cfg = ZOO[name].config("water_skin", FS)
    pts = _points(cfg.geometry, n, g, max_polar_deg)
    pk = render_triggered(pts, cfg, snr_db=g.uniform(snr_lo, snr_hi, n), rng=g,
                          polarity=np.ones(n))
    views = [PacketView(pk.samples_v[i], FS, int(pk.onset_index[i]), 10**9 + i * 10**8, i)
             for i in range(n)]
    return cfg, pk, views


def _errors(pl, views, pk):
    return [float(np.linalg.norm(np.asarray(r.point_m) - pk.points_m[r.packet_ids[0]]))
            for r in pl.process(views)]


def test_the_stated_corners_are_calibrated_from_the_devices_own_touches():
    """A front end stated with its components' tolerance (high-pass corner 8 % high,
    low-pass 7 % low, the decay unknown): the calibration finds the factors back to 1 %
    and the decay to 10 %, and the calibrated pulse refines to the bound where the stated
    one fails its residual test at 40 dB."""
    cfg, pk, _ = _stream("hp1_50k_lp2_800k", 40, 6)
    true = PulseModel.from_config(cfg)
    stated = replace(true, highpass_hz=true.highpass_hz * 1.08,
                     lowpass_hz=true.lowpass_hz * 0.93, alpha_1_s=1e4)
    fit = calibrate_front_end(pk.samples_v, FS, pk.onset_index, stated, geometry=cfg.geometry)
    assert fit.converged and fit.n_inliers >= 0.9 * fit.n_candidates
    assert fit.highpass_factor == pytest.approx(1 / 1.08, rel=0.01)
    assert fit.lowpass_factor == pytest.approx(1 / 0.93, rel=0.01)
    assert fit.alpha_1_s == pytest.approx(true.alpha_1_s, rel=0.1)
    cfg, pk, bound = _packets("hp1_50k_lp2_800k", 40, 7)
    ml = localize(pk.samples_v, FS, pk.onset_index, geometry=cfg.geometry)
    res, got = refine_result(ml, pk.samples_v, FS, pk.onset_index, fit.pulse,
                             geometry=cfg.geometry)
    assert got.refined.mean() >= 0.95
    assert _rms(res.point_m, pk.points_m) <= 1.3 * math.sqrt(np.mean(bound**2))
    _, as_stated = refine_result(ml, pk.samples_v, FS, pk.onset_index, stated,
                                 geometry=cfg.geometry)
    assert as_stated.refined.mean() <= 0.2


def test_a_statement_of_another_filter_is_not_trusted_and_refines_nothing():
    """A 6th-order Bessel low-pass stated for a 2nd-order Butterworth: no corners make it
    the device's pulse, the calibration is not trusted (three tries, then the learner stops),
    the status says so and the driver keeps ml's answers (counted neither refined nor
    failed: no refinement runs)."""
    cfg, pk, views = _stream("hp1_50k_lp2_800k", 240, 8)
    spec = "highpass_hz=50e3 highpass_order=1 lowpass_hz=800e3 lowpass_order=6 " \
           "lowpass_family=bessel"
    fit = calibrate_front_end(pk.samples_v[:40], FS, pk.onset_index[:40],
                              PulseModel.from_spec(spec), geometry=cfg.geometry)
    assert not fit.converged and fit.n_inliers < 0.9 * fit.n_candidates
    pl = PacketLocalizer("ml", geometry=cfg.geometry, front_end=spec)
    for k in range(0, 240, 10):
        pl.process(views[k:k + 10])
    # 240 touches keep some 110 for learning: enough for 4 calibrations, 3 are tried
    assert pl.front_end_learner.attempts == 3 and pl.localizer.front_end is None
    assert "does not describe this device" in pl.front_end_status()
    assert pl.counts["refined"] == pl.counts["refine_failed"] == 0


def test_the_driver_calibrates_its_stated_front_end_then_refines_and_keeps_it():
    """PacketLocalizer(front_end=...) (the driver's localization.front_end, stated with
    tolerance): ml's answers while it calibrates on the kept touches, the refined points
    after (each accepted packet counted refined or refine_failed), 4x smaller errors; the
    calibration is saved and loaded for the same statement (refining at once), refused
    for another; the setting changes at run time, a bad one refused with nothing changed."""
    stated = "highpass_hz=54e3 highpass_order=1 lowpass_hz=760e3 lowpass_order=2"
    cfg, pk, views = _stream("hp1_50k_lp2_800k", 160, 9)
    pl = PacketLocalizer("ml", geometry=cfg.geometry, front_end=stated)
    before = []
    k = 0
    while pl.localizer.front_end is None and k < 120:
        before += _errors(pl, views[k:k + 10], pk)
        k += 10
    assert pl.localizer.front_end is not None, pl.front_end_status()
    assert pl.front_end_status().startswith("calibrated")
    refined0 = pl.counts["refined"]
    assert refined0 == pl.counts["refine_failed"] == 0  # nothing refined while calibrating
    after = _errors(pl, views[k:k + 1], pk) + _errors(pl, views[k + 1:k + 40], pk)
    assert pl.counts["refined"] + pl.counts["refine_failed"] == len(after)
    assert pl.counts["refined"] >= 0.9 * len(after)
    assert np.sqrt(np.mean(np.square(after))) < 0.25 * np.sqrt(np.mean(np.square(before)))
    state = pl.calibration_learners()["front_end"].calibration_state()
    again = PacketLocalizer("ml", geometry=cfg.geometry, front_end=stated)
    again.calibration_learners()["front_end"].load_calibration(state)
    assert again.localizer.front_end == pl.localizer.front_end
    other = PacketLocalizer("ml", geometry=cfg.geometry, front_end="lowpass_hz=600e3")
    with pytest.raises(ValueError, match="another statement"):
        other.calibration_learners()["front_end"].load_calibration(state)
    assert other.localizer.front_end is None
    pl.update(front_end="")
    assert pl.localizer.front_end is None and pl.front_end_status().startswith("none")
    with pytest.raises(ValueError, match="lowpass_family"):
        pl.update(front_end="lowpass_family=elliptic")
    assert pl.config.front_end == ""


@pytest.mark.parametrize("spec, problem", [
    ("lowpass_hz=800e3 lowpass_order", "expected name=value"),
    ("highpass_hz=0", "positive"),
    ("lowpass_order=13", "order"),
    ("highpass_rc_hz=60e3/-1", "positive"),
    ("alpha_1_s=3e3 alpha_1_s=1e4", "twice"),
    ("gain=2", "expected name=value"),
])
def test_a_front_end_that_cannot_be_read_is_refused_by_name(spec, problem):
    with pytest.raises(ValueError, match=problem):
        PulseModel.from_spec(spec)
    with pytest.raises(ValueError):
        LocalizationConfig(front_end=spec)


def test_a_stated_front_end_reads_back_as_itself():
    """`spec()` is `from_spec`'s text: a front end written to a parameter file and read
    again is the same pulse; RC stages and the low-pass families are part of it."""
    for text in (ALIASING, "highpass_rc_hz=60e3/69e3 lowpass_hz=600e3 lowpass_order=6 "
                 "lowpass_family=bessel", "lowpass_hz=none alpha_1_s=1e4",
                 "lowpass_family=cheby1 lowpass_ripple_db=1 amplifier_pole_hz=3e6"):
        pm = PulseModel.from_spec(text)
        assert PulseModel.from_spec(pm.spec()) == pm
    assert PulseModel.from_spec("") == PulseModel()


def test_the_pipeline_calibrates_beside_the_reader_and_refines_what_it_publishes():
    """ContactPipeline (the driver's in-process path): the calibration runs in the
    learning thread beside the reader and is used from the next hand-off on; the contact
    records it publishes after that are the refined points, and its calibration file
    section holds the factors (`calibration_learners`)."""
    from ae_tactile.pipeline import ContactPipeline

    stated = "highpass_hz=47e3 highpass_order=1 lowpass_hz=840e3 lowpass_order=2"
    cfg, pk, views = _stream("hp1_50k_lp2_800k", 240, 10)
    pipe = ContactPipeline(PacketLocalizer("ml", geometry=cfg.geometry, front_end=stated),
                           None)
    out: list = []
    try:
        k = 0
        while pipe.localizer.localizer.front_end is None and k < 200:
            pipe.process(views[k:k + 8], out.extend)
            k += 8
        assert pipe.localizer.localizer.front_end is not None, pipe.localizer.front_end_status()
        n0 = len(out)
        pipe.process(views[k:k + 40], out.extend)
    finally:
        pipe.close()
    late = out[n0:]
    assert len(late) >= 30
    err = [np.linalg.norm(np.asarray(r.point_m) - pk.points_m[r.packet_ids[0]]) for r in late]
    early = [np.linalg.norm(np.asarray(r.point_m) - pk.points_m[r.packet_ids[0]])
             for r in out[:n0]]
    assert np.sqrt(np.mean(np.square(err))) < 0.25 * np.sqrt(np.mean(np.square(early)))
    state = pipe.calibration_learners()["front_end"].calibration_state()
    assert state["stated"] == PulseModel.from_spec(stated).spec()
    assert state["highpass_factor"] == pytest.approx(50 / 47, rel=0.02)
    assert state["lowpass_factor"] == pytest.approx(800 / 840, rel=0.02)


@pytest.mark.parametrize("name", ["nominal", "alpha_1e6"])
def test_channel_delays_taken_out_keep_the_adcs_rounding_in_the_noise(name):
    """At 40 dB the 12-bit ADC's rounding is a good part of the noise; taking the channels'
    own delays out shifts the samples off the ADC's grid, where the quantum cannot be
    seen: the noise (its level and its colour) is measured before the shift, so the
    residual test and the covariance judge the fit as without the shift (the test failed
    100 % of the nominal device's packets, chi^2 3x)."""
    g = np.random.default_rng(12)
    cfg = ZOO[name].config("water_skin", 10e6)
    pts = _points(cfg.geometry, 30, g)
    pk = render_triggered(pts, cfg, snr_db=40.0, rng=g)
    ml = localize(pk.samples_v, 10e6, pk.onset_index, geometry=cfg.geometry)
    pm = PulseModel.from_config(cfg)
    plain = refine_points(pk.samples_v, 10e6, pk.onset_index, ml.point_m, ml.emission_offset_s,
                          pm, geometry=cfg.geometry)
    shifted = refine_points(pk.samples_v, 10e6, pk.onset_index, ml.point_m,
                            ml.emission_offset_s, pm, geometry=cfg.geometry,
                            channel_delays_s=(1e-9, -1e-9, 0.5e-9, -0.5e-9))
    assert plain.refined.mean() >= 0.9 and shifted.refined.mean() >= 0.9
    assert np.median(shifted.chi2_ratio) == pytest.approx(np.median(plain.chi2_ratio), rel=0.2)
    # and the noise's colour is read before the shift too (its rounding read as colour
    # made the claimed sigma 5x too small: 2 % of the points inside the 68 % ellipse)
    both = plain.refined & shifted.refined
    sd = [np.sqrt(np.trace(r.covariance_m2[both][:, :2, :2], axis1=1, axis2=2))
          for r in (plain, shifted)]
    assert np.median(sd[1]) == pytest.approx(np.median(sd[0]), rel=0.2)


def test_under_amplifier_noise_the_ellipses_hold_what_they_claim():
    """Amplifier noise through the front end (zoo `amp_noise`, 10 MS/s, 20 dB) is coloured;
    the fit weighs the samples alike, and the white-noise inverse Fisher matrix claimed
    ellipses that held 30-45 % of the true points. The covariance of the fit under the
    colour measured before the onset holds 68 +- 15 %."""
    g = np.random.default_rng(13)
    cfg = ZOO["amp_noise"].config("water_skin", 10e6)
    pts = _points(cfg.geometry, 80, g)
    pk = render_triggered(pts, cfg, snr_db=20.0, rng=g)
    ml = localize(pk.samples_v, 10e6, pk.onset_index, geometry=cfg.geometry)
    res, got = refine_result(ml, pk.samples_v, 10e6, pk.onset_index,
                             PulseModel.from_config(cfg), geometry=cfg.geometry)
    m = res.refined
    assert m.mean() >= 0.8
    e = (res.point_m - pk.points_m)[m, :2]
    d2 = np.array([v @ np.linalg.solve(c[:2, :2], v) for v, c in zip(e, res.covariance_m2[m])])
    assert 0.53 <= np.mean(d2 <= CHI2_2D_68) <= 0.83
