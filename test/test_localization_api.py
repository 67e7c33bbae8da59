# SPDX-License-Identifier: Apache-2.0
"""The localization interface: parameters, registry, rejection reasons, invariances."""

import numpy as np
import pytest

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import (
    ESTIMATORS,
    LocalizationResult,
    Localizer,
    Reason,
    available_methods,
    default_band_hz,
    get_estimator,
    localize,
    register_estimator,
)
from ae_tactile.sim import SimConfig, render_triggered

CFG = SimConfig()
GEO = CFG.geometry
FS = CFG.sample_rate_hz
METHODS = ["ml", "gradient", "gcc_phat", "xcorr_farfield"]


@pytest.fixture(scope="module")
def packets():
    rng = np.random.default_rng(11)
    ct = rng.uniform(np.cos(np.deg2rad(60)), 1, 24)
    pts = GEO.surface_point_from_angles(np.arccos(ct), rng.uniform(0, 2 * np.pi, 24))
    return render_triggered(pts, CFG, snr_db=25, rng=rng)


def assert_finite(r: LocalizationResult):
    for name in (
        "tau_x_s",
        "tau_y_s",
        "twist_s",
        "point_m",
        "covariance_m2",
        "delay_covariance_s2",
        "polar_rad",
        "azimuth_rad",
        "residual",
        "overlap_excess",
        "pair_residual_s",
        "snr_db_est",
        "noise_rms_v_est",
        "amplitude_v",
        "confidence",
    ):
        assert np.all(np.isfinite(getattr(r, name))), name
    assert np.all((r.confidence >= 0) & (r.confidence <= 1))
    np.testing.assert_allclose(np.linalg.norm(r.point_m, axis=1), GEO.radius_m, rtol=1e-6)
    assert np.all(r.point_m[:, 2] >= 0)
    assert np.all(np.isin(r.polarity, (-1, 0, 1)))
    assert np.all(r.accepted == (r.reason == 0))
    assert set(np.unique(r.reason)) <= {int(c) for c in Reason}


def test_registry_and_result_fields(packets):
    assert available_methods() == sorted(METHODS)
    assert set(METHODS) <= set(ESTIMATORS)
    with pytest.raises(ValueError, match="unknown localization method"):
        get_estimator("music")
    for m in METHODS:
        r = localize(packets.samples_v, FS, packets.onset_index, method=m)
        assert r.method == m and len(r) == 24
        assert r.point_m.shape == (24, 3) and r.covariance_m2.shape == (24, 3, 3)
        assert r.delay_covariance_s2.shape == (24, 2, 2)
        assert (
            r.reason.dtype == np.uint8 and r.accepted.dtype == bool and r.polarity.dtype == np.int8
        )
        assert_finite(r)
        assert r.accepted.all()
        assert r.packet(0)["reason_name"] == "OK"
        # covariance is symmetric positive semi-definite
        np.testing.assert_allclose(
            r.covariance_m2, np.swapaxes(r.covariance_m2, 1, 2), rtol=1e-9, atol=1e-30
        )
        assert np.all(np.linalg.eigvalsh(r.covariance_m2[:, :2, :2]) > 0)
    loc = Localizer("gcc_phat", min_snr_db=3.0)
    r = loc(packets.samples_v, FS, packets.onset_index)
    assert r.method == "gcc_phat" and r.accepted.all()
    assert LocalizationResult.describe_reason(Reason.OVERLAP).startswith("the four channels")


def test_custom_estimator_can_be_registered(packets):
    calls = []

    def wrapped(prep, plan, **kw):
        calls.append(prep.x.shape)
        return ESTIMATORS["gradient"].function(prep, plan, **kw)

    register_estimator("test_wrapped", wrapped, "gradient, counted")
    try:
        r = localize(packets.samples_v[:3], FS, packets.onset_index[:3], method="test_wrapped")
        assert calls == [(3, 4, 400)] and r.accepted.all()
    finally:
        del ESTIMATORS["test_wrapped"]


def test_single_window_empty_batch_and_dtypes(packets):
    one = localize(packets.samples_v[0], FS, packets.onset_index[0])
    assert len(one) == 1 and one.accepted[0]
    empty = localize(np.zeros((0, 4, 400)), FS, np.zeros(0, int))
    assert len(empty) == 0 and empty.point_m.shape == (0, 3)
    r64 = localize(packets.samples_v, FS, packets.onset_index)
    r32 = localize(packets.samples_v.astype(np.float32), FS, packets.onset_index.astype(np.int32))
    assert r32.accepted.all()
    # float32 volts carry ~1e-7 relative rounding: far below the noise
    assert np.abs(r32.point_m - r64.point_m).max() < 1e-7
    codes = np.rint(packets.samples_v / CFG.lsb_v).astype(np.int16)
    rc = localize(codes, FS, packets.onset_index)
    np.testing.assert_allclose(rc.point_m, r64.point_m, atol=1e-9)


@pytest.mark.parametrize(
    "bad, exc",
    [
        (dict(windows=np.zeros((3, 3, 100))), ValueError),
        (dict(windows=np.zeros((3, 4))), ValueError),
        (dict(windows=np.zeros((2, 4, 2))), ValueError),
        (dict(windows=np.array([[["a"] * 10] * 4])), TypeError),
        (dict(onset_index=np.zeros(5, int)), ValueError),
        (dict(onset_index=np.full(2, 1.5)), ValueError),
        (dict(sample_rate_hz=0.0), ValueError),
        (dict(sample_rate_hz=np.nan), ValueError),
        (dict(band_hz=(2e6, 1e6)), ValueError),
        (dict(band_hz=(6e6, 7e6)), ValueError),
        (dict(band_hz="wide"), ValueError),
        (dict(method="nope"), ValueError),
        (dict(geometry="default"), TypeError),
        (dict(noise_rms_v=np.ones(3)), ValueError),
        (dict(channel_gains=[1, 1, 0, 1]), ValueError),
        (dict(full_scale_v=-1.0), ValueError),
        (dict(overlap_threshold=0.0), ValueError),
        (dict(min_snr_db=np.nan), ValueError),
        (dict(iterations=0), ValueError),
        (dict(echo_guard_s=1.0), ValueError),
    ],
)
def test_parameter_errors(bad, exc):
    kw = dict(
        windows=np.random.default_rng(0).standard_normal((2, 4, 400)),
        sample_rate_hz=FS,
        onset_index=np.array([80, 80]),
    )
    kw.update(bad)
    w, fs, on = kw.pop("windows"), kw.pop("sample_rate_hz"), kw.pop("onset_index")
    with pytest.raises(exc):
        localize(w, fs, on, **kw)


def test_default_band():
    assert default_band_hz(10e6) == (100e3, 1e6)
    assert default_band_hz(2e6) == (100e3, 0.5e6)


def test_rejection_reasons(packets):
    x = packets.samples_v.copy()
    on = packets.onset_index.copy()
    x[0, 1, 100] = np.nan
    x[1, 2, 5] = np.inf
    x[2] = 0.0  # all-zero window
    x[3] = 0.37  # constant window
    x[4, 3] = 0.0  # dead channel
    on[5] = 500  # onset outside the window
    on[6] = 395  # packet starts at the end of the window
    x[7] *= 1e-4 * 0 + 1.0
    x[7] += (
        30 * np.random.default_rng(1).standard_normal(x[7].shape) * packets.noise_rms_v[7]
    )  # ~ -5 dB
    big = np.abs(packets.clean_v[8]).max()
    x[8] = np.clip(packets.clean_v[8], -0.5 * big, 0.5 * big)  # hard clip, no noise
    for m in METHODS:
        r = localize(x, FS, on, method=m)
        assert_finite(r)
        assert r.reason[0] == Reason.NONFINITE and r.reason[1] == Reason.NONFINITE
        assert r.reason[2] == Reason.NO_SIGNAL and r.reason[3] == Reason.NO_SIGNAL
        assert r.reason[4] == Reason.NO_SIGNAL
        assert r.reason[5] == Reason.WINDOW and r.reason[6] == Reason.WINDOW
        assert r.reason[7] == Reason.LOW_SNR
        assert r.reason[8] == Reason.SATURATED
        assert r.accepted[9:].all()
        assert np.all(r.confidence[:9] == 0)
        assert np.all(r.polarity[:5] == 0)
        # the reason bit of every primary reason is set
        assert np.all(r.reason_flags[:9] & (1 << r.reason[:9].astype(int)))


def test_saturation_from_flags_and_full_scale(packets):
    sat = np.zeros(24, bool)
    sat[3] = True
    r = localize(packets.samples_v, FS, packets.onset_index, saturated=sat)
    assert r.reason[3] == Reason.SATURATED and r.accepted.sum() == 23
    peak = np.abs(packets.samples_v).max(axis=(1, 2))
    r = localize(packets.samples_v, FS, packets.onset_index, full_scale_v=float(np.median(peak)))
    assert np.all((r.reason == Reason.SATURATED) == (peak >= np.median(peak) * (1 - 1e-3)))


@pytest.mark.parametrize("factor", [1.3, 3.0])
def test_out_of_range_delays(factor):
    # Synthetic channels whose delays imply a point beyond the horizon (|sin theta| > 1).
    fs = 10e6
    t = np.arange(400) / fs
    big = factor * GEO.max_delay_s
    arr = 9e-6 + np.array([-big, -big, big, big])  # tau_x = factor a / c
    tau = t[None, :] - arr[:, None] - 1e-6
    x = np.cos(2 * np.pi * 4e5 * tau) * np.exp(-0.5 * (tau / 0.5e-6) ** 2)
    x = x[None] + 1e-3 * np.random.default_rng(0).standard_normal((1, 4, 400))
    onset = np.array([int(np.ceil((9e-6 - big) * fs))])
    for m in METHODS:
        r = localize(x, fs, onset, method=m)
        assert_finite(r)
        assert not r.accepted[0]
        if factor < 2:
            # just beyond: the pair lags run into the edge of the physical range
            assert r.reason_flags[0] & (1 << Reason.OUT_OF_RANGE), (m, r.reason_names)
        # far beyond, the exact-sphere fit cannot align the channels either (OVERLAP)
        assert r.reason[0] in (Reason.OVERLAP, Reason.OUT_OF_RANGE), (m, r.reason_names)


@pytest.mark.parametrize("method", METHODS)
def test_gain_and_dc_invariance(packets, method):
    base = localize(packets.samples_v, FS, packets.onset_index, method=method)
    rng = np.random.default_rng(3)
    for gain in (1e-3, 7.5, 1e3):
        dc = rng.uniform(-5, 5, (24, 4, 1)) * gain
        r = localize(gain * packets.samples_v + dc, FS, packets.onset_index, method=method)
        np.testing.assert_allclose(r.point_m, base.point_m, atol=1e-10)
        np.testing.assert_allclose(r.tau_x_s, base.tau_x_s, atol=1e-15)
        np.testing.assert_allclose(r.covariance_m2, base.covariance_m2, rtol=1e-6, atol=1e-18)
        np.testing.assert_allclose(r.snr_db_est, base.snr_db_est, atol=1e-6)
        np.testing.assert_allclose(r.amplitude_v, gain * base.amplitude_v, rtol=1e-6)
        np.testing.assert_allclose(r.confidence, base.confidence, atol=1e-9)
        assert np.array_equal(r.reason, base.reason) and np.array_equal(r.polarity, base.polarity)


def test_channel_gains_are_divided_out(packets):
    g = np.array([1.2, 0.8, 1.0, 1.1])
    base = localize(packets.samples_v, FS, packets.onset_index)
    r = localize(packets.samples_v * g[None, :, None], FS, packets.onset_index, channel_gains=g)
    np.testing.assert_allclose(r.point_m, base.point_m, atol=1e-10)


def test_batched_equals_one_at_a_time(packets):
    for m in METHODS:
        batch = localize(packets.samples_v, FS, packets.onset_index, method=m)
        for i in (0, 7, 23):
            one = localize(
                packets.samples_v[i : i + 1], FS, packets.onset_index[i : i + 1], method=m
            )
            np.testing.assert_allclose(one.point_m[0], batch.point_m[i], atol=1e-12)
            np.testing.assert_allclose(
                one.covariance_m2[0], batch.covariance_m2[i], rtol=1e-9, atol=1e-30
            )


def test_noise_from_residual_without_pre_onset_samples(packets):
    # Onset at the very start of the window: no pre-onset samples; the noise comes from the
    # fit residual (or from noise_rms_v when given).
    x = packets.samples_v[:, :, 78:]
    on = packets.onset_index - 78
    r = localize(x, FS, on)
    assert_finite(r)
    assert r.accepted.mean() > 0.9
    r2 = localize(x, FS, on, noise_rms_v=packets.noise_rms_v)
    np.testing.assert_allclose(
        r2.noise_rms_v_est,
        np.sqrt(packets.noise_rms_v**2 + r2.noise_rms_v_est**2 - packets.noise_rms_v**2),
        rtol=1e-9,
    )
    assert np.abs(np.log(r2.noise_rms_v_est / packets.noise_rms_v)).max() < 0.2


def test_other_geometry_is_used():
    geo = FingertipGeometry(radius_m=8e-3, element_offset_m=1.2e-3, sound_speed_m_s=1000.0)
    cfg = SimConfig.for_medium("silicone", radius_m=8e-3, element_offset_m=1.2e-3)
    pts = geo.surface_point_from_xy(np.array([0.0, 2e-3, -3e-3]), np.array([0.0, 1e-3, 2e-3]))
    pk = render_triggered(pts, cfg, snr_db=30, rng=2)
    r = localize(pk.samples_v, cfg.sample_rate_hz, pk.onset_index, geometry=geo)
    assert r.accepted.all() and np.linalg.norm(r.point_m - pts, axis=1).max() < 50e-6
