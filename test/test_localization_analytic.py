# SPDX-License-Identifier: Apache-2.0
"""Estimators on analytic pulses (independent of the simulator): exact delays from the
geometry, a Gabor pulse evaluated at the sample instants, any sample rate and geometry."""

import numpy as np
import pytest

from ae_eval.crlb import position_crlb
from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import available_methods, localize

GEO = FingertipGeometry()


def gabor_windows(
    geo, points, fs, *, snr_db=None, rng=None, pre_s=8e-6, window_s=40e-6, polarity=1, offset=None
):
    """(K, 4, M) windows of a Gabor pulse starting at each element's exact arrival time.

    Pulse: cos(2 pi f0 tau) exp(-tau^2 / (2 s^2)), tau = t - t_k - 3 s, f0 = min(400 kHz,
    0.2 fs), s = 1 / (2 pi 0.5 f0) (spectrum well inside the band, negligible aliasing).
    Returns (windows, onset_index, arrival_times).
    """
    rng = np.random.default_rng(rng)
    pts = np.atleast_2d(points)
    k = pts.shape[0]
    m = int(round(window_s * fs))
    f0 = min(400e3, 0.2 * fs)
    s = 1.0 / (2 * np.pi * 0.5 * f0)
    travel = geo.arrival_times_s(pts)
    u = rng.random(k) if offset is None else np.full(k, offset)
    first = pre_s + u / fs
    arr = travel - travel.min(axis=1, keepdims=True) + first[:, None]
    t = np.arange(m) / fs
    tau = t[None, None, :] - arr[..., None] - 3 * s
    x = np.cos(2 * np.pi * f0 * tau) * np.exp(-0.5 * (tau / s) ** 2)
    x *= np.asarray(polarity, float).reshape(-1, 1, 1) if np.ndim(polarity) else polarity
    onset = np.ceil(first * fs - 1e-9).astype(np.int64)
    if snr_db is not None:
        w = int(round(30e-6 * fs))
        idx = onset[:, None] + np.arange(w)
        p = np.mean(
            np.take_along_axis(x, np.clip(idx, 0, m - 1)[:, None, :].repeat(4, 1), axis=2) ** 2,
            axis=(1, 2),
        )
        x = x + np.sqrt(p / 10 ** (snr_db / 10))[:, None, None] * rng.standard_normal(x.shape)
    return x, onset, arr


def _pulse(shape, tau):
    """Value and time derivative (1/s) of a unit pulse at tau seconds after its arrival."""
    if shape == "gabor":  # 400 kHz Gabor, sigma 0.4 us
        f0 = 400e3
        s = 1 / (2 * np.pi * 0.5 * f0)
        u = tau - 3 * s
        g = np.exp(-0.5 * (u / s) ** 2)
        x = np.cos(2 * np.pi * f0 * u) * g
        return x, -2 * np.pi * f0 * np.sin(2 * np.pi * f0 * u) * g - u / s**2 * x
    if shape == "gabor_narrow":  # 250 kHz Gabor, sigma 1 us: band-limited for 2 MS/s
        f0, s = 250e3, 1e-6  # sigma_f = 1 / (2 pi s) = 0.16 MHz: 1 MHz is 4.7 sigma_f away
        u = tau - 3 * s
        g = np.exp(-0.5 * (u / s) ** 2)
        x = np.cos(2 * np.pi * f0 * u) * g
        return x, -2 * np.pi * f0 * np.sin(2 * np.pi * f0 * u) * g - u / s**2 * x
    if shape == "ricker":  # Ricker (Mexican hat) peaking at 0.8 MHz
        f = 800e3
        u = tau - 1.5 / f
        a = (np.pi * f * u) ** 2
        e = np.exp(-a)
        return (1 - 2 * a) * e, -2 * np.pi**2 * f**2 * u * e * (3 - 2 * a)
    if shape == "damped":  # causal 0.6 MHz sine, 0.2 us rise, 1.5 us decay
        f, rise, decay = 600e3, 0.2e-6, 1.5e-6
        t = np.maximum(tau, 0.0)
        r = 1 - np.exp(-t / rise)
        env = r * r * np.exp(-t / decay)
        denv = 2 * r * np.exp(-t / rise) / rise * np.exp(-t / decay) - env / decay
        x = env * np.sin(2 * np.pi * f * t)
        dx = denv * np.sin(2 * np.pi * f * t) + env * 2 * np.pi * f * np.cos(2 * np.pi * f * t)
        return np.where(tau > 0, x, 0.0), np.where(tau > 0, dx, 0.0)
    raise ValueError(shape)


def analytic_windows(shape, points, fs, snr_db, rng, *, geo=GEO, pre_s=8e-6, window_s=40e-6):
    """(K, 4, M) noisy windows of an analytic pulse at the exact arrival times, the onsets,
    and the Cramer-Rao bound (RMS, m) for those packets (white noise at ``snr_db`` per
    docs/conventions.md, echo-free samples; `crlb.position_crlb` with the exact derivative)."""

    pts = np.atleast_2d(points)
    k, m = len(pts), int(round(window_s * fs))
    travel = geo.arrival_times_s(pts)
    first = pre_s + rng.random(k) / fs
    arr = travel - travel.min(axis=1, keepdims=True) + first[:, None]
    x, dx = _pulse(shape, np.arange(m)[None, None, :] / fs - arr[..., None])
    onset = np.ceil(first * fs - 1e-9).astype(np.int64)
    idx = onset[:, None] + np.arange(int(round(30e-6 * fs)))
    seg = np.take_along_axis(x, np.repeat(idx[:, None, :], 4, axis=1), axis=2)
    p = np.mean(seg**2, axis=(1, 2))
    var = p / 10 ** (snr_db / 10)
    y = x + np.sqrt(var)[:, None, None] * rng.standard_normal(x.shape)
    bound = position_crlb(x, dx, fs, var, pts, arr, geo)["rms_m"]
    return y, onset, float(np.sqrt(np.mean(bound**2)))


def test_analytic_pulse_derivatives():
    # the CRLB of the accuracy tests needs d pulse / dt: check it against a central difference
    tau = np.linspace(-1e-6, 8e-6, 2001)
    for shape in ("gabor", "gabor_narrow", "ricker", "damped"):
        x, dx = _pulse(shape, tau)
        h = 1e-11
        num = (_pulse(shape, tau + h)[0] - _pulse(shape, tau - h)[0]) / (2 * h)
        np.testing.assert_allclose(dx, num, atol=1e-4 * np.abs(dx).max())


def cap_points(geo, rng, n, max_deg):
    ct = rng.uniform(np.cos(np.deg2rad(max_deg)), 1, n)
    return geo.surface_point_from_angles(np.arccos(ct), rng.uniform(0, 2 * np.pi, n))


@pytest.mark.parametrize("fs", [2e6, 5e6, 10e6, 20e6])
def test_noise_free_exact_recovery(fs):
    rng = np.random.default_rng(int(fs))
    pts = np.concatenate(
        [
            cap_points(GEO, rng, 40, 85),
            GEO.surface_point_from_angles(np.array([0.0, np.deg2rad(89.0)]), np.array([0.0, 0.8])),
        ]
    )
    x, onset, _ = gabor_windows(GEO, pts, fs, rng=rng)
    # the far-field baseline is off by up to ~2 mm near the horizon (Eq. 2 + smeared sum pairs)
    tol = {"ml": 1e-6, "gradient": 1e-6, "gcc_phat": 10e-6, "xcorr_farfield": 2.5e-3}
    for m in available_methods():
        r = localize(x, fs, onset, method=m)
        err = np.linalg.norm(r.point_m - pts, axis=1)
        assert r.accepted.all(), (m, r.reason_names)
        assert err.max() < tol[m], (m, err.max())


def test_one_mhz_sampling_still_localizes():
    rng = np.random.default_rng(7)
    pts = cap_points(GEO, rng, 40, 60)
    x, onset, _ = gabor_windows(GEO, pts, 1e6, rng=rng)
    r = localize(x, 1e6, onset, method="ml")
    err = np.linalg.norm(r.point_m - pts, axis=1)
    assert r.accepted.mean() > 0.9 and np.median(err) < 20e-6


def test_far_field_baseline_error_grows_with_polar_angle():
    fs = 10e6
    az = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    errs = []
    for deg in (10.0, 30.0, 60.0):
        pts = GEO.surface_point_from_angles(np.full(12, np.deg2rad(deg)), az)
        x, onset, _ = gabor_windows(GEO, pts, fs, rng=1)
        e_ff = np.linalg.norm(
            localize(x, fs, onset, method="xcorr_farfield").point_m - pts, axis=1
        )
        e_ml = np.linalg.norm(localize(x, fs, onset, method="ml").point_m - pts, axis=1)
        assert e_ml.max() < 1e-6
        errs.append(np.sqrt(np.mean(e_ff**2)))
    # tens of micrometres at 30 deg (Eq. 2 alone), more towards the horizon
    assert errs[0] < errs[1] < errs[2]
    assert 10e-6 < errs[1] < 200e-6


@pytest.mark.parametrize(
    "geo",
    [
        FingertipGeometry(radius_m=7e-3, element_offset_m=1.0e-3, sound_speed_m_s=1000.0),
        FingertipGeometry(radius_m=15e-3, element_offset_m=2.5e-3, sound_speed_m_s=1550.0),
    ],
)
def test_other_geometries(geo):
    rng = np.random.default_rng(3)
    pts = cap_points(geo, rng, 30, 75)
    x, onset, _ = gabor_windows(geo, pts, 10e6, rng=rng)
    for m in ("ml", "gradient", "gcc_phat"):
        r = localize(x, 10e6, onset, method=m, geometry=geo)
        assert r.accepted.all()
        assert np.linalg.norm(r.point_m - pts, axis=1).max() < 20e-6, m


def test_delays_of_many_samples_at_20_mss_grazing():
    fs = 20e6
    pts = GEO.surface_point_from_angles(
        np.full(8, np.deg2rad(88.0)), np.linspace(0, 2 * np.pi, 8, endpoint=False)
    )
    x, onset, arr = gabor_windows(GEO, pts, fs, rng=0)
    assert (arr.max(axis=1) - arr.min(axis=1)).max() * fs > 40  # > 40 samples across the array
    r = localize(x, fs, onset, method="ml")
    assert r.accepted.all()
    assert np.linalg.norm(r.point_m - pts, axis=1).max() < 1e-6
    tau = GEO.exact_delays_s(pts)
    np.testing.assert_allclose(r.tau_x_s, tau[:, 0], atol=1e-12)
    np.testing.assert_allclose(r.tau_y_s, tau[:, 1], atol=1e-12)


def test_one_shot_gradient_collapses_off_axis_iterated_does_not():
    # The paper's one-shot LS step tau = <d, m'> / <m', m'> is only valid for w tau << 1
    # (2 pi f a / c ~ 6 at 1 MHz here): fine near the pole, useless tens of degrees off.
    fs = 10e6
    az = np.linspace(0, 2 * np.pi, 6, endpoint=False)
    err = {}
    for deg in (3.0, 45.0):
        pts = GEO.surface_point_from_angles(np.full(6, np.deg2rad(deg)), az)
        x, onset, _ = gabor_windows(GEO, pts, fs, rng=2)
        one = localize(x, fs, onset, method="gradient", start="zero", iterations=1)
        it = localize(x, fs, onset, method="gradient")
        err[deg] = (
            np.linalg.norm(one.point_m - pts, axis=1).max(),
            np.linalg.norm(it.point_m - pts, axis=1).max(),
        )
    assert err[3.0][0] < 50e-6
    assert err[45.0][0] > 1e-3
    assert err[3.0][1] < 1e-6 and err[45.0][1] < 1e-6
