# SPDX-License-Identifier: Apache-2.0
"""Fingertip geometry: exact forward model, its inverse, derivatives, clamping, covariance."""

import numpy as np
import pytest

from ae_tactile.geometry import CHANNEL_XI_ETA, FingertipGeometry

GEO = FingertipGeometry()


def random_points(rng, n, max_polar_deg=90.0, geo=GEO):
    ct = rng.uniform(np.cos(np.deg2rad(max_polar_deg)), 1.0, n)
    return geo.surface_point_from_angles(np.arccos(ct), rng.uniform(0, 2 * np.pi, n))


def test_defaults_and_layout():
    assert (
        GEO.radius_m == 10e-3 and GEO.element_offset_m == 1.5e-3 and GEO.sound_speed_m_s == 1480.0
    )
    e = GEO.element_positions_m
    np.testing.assert_allclose(e[:, :2], 1.5e-3 * CHANNEL_XI_ETA)
    assert GEO.max_delay_s == pytest.approx(1.5e-3 / 1480.0)


@pytest.mark.parametrize(
    "kw",
    [
        dict(radius_m=0),
        dict(element_offset_m=-1e-3),
        dict(sound_speed_m_s=np.nan),
        dict(radius_m=2e-3, element_offset_m=1.5e-3),
    ],
)
def test_invalid_geometry(kw):
    with pytest.raises(ValueError):
        FingertipGeometry(**kw)


def test_surface_point_from_xy_outside_raises():
    with pytest.raises(ValueError):
        GEO.surface_point_from_xy(11e-3, 0.0)
    p = GEO.surface_point_from_xy(10e-3, 0.0)
    np.testing.assert_allclose(p, [10e-3, 0, 0], atol=1e-12)


def test_exact_round_trip_everywhere():
    rng = np.random.default_rng(1)
    pts = np.concatenate(
        [
            random_points(rng, 500),
            GEO.surface_point_from_angles(
                np.array([0.0, np.pi / 2, np.pi / 2 - 1e-6]), np.array([0.0, 0.7, 2.0])
            ),
        ]
    )
    tau = GEO.exact_delays_s(pts)
    back, clamped = GEO.point_from_delays(tau[:, 0], tau[:, 1])
    err = np.linalg.norm(back - pts, axis=1)
    # Round trip good to 1 nm inside; points exactly on the horizon come back on the
    # clamp circle rho = R (1 - 1e-9), i.e. within 0.5 um in z.
    assert err[:-2].max() < 1e-9
    assert err[-2:].max() < 1e-6
    assert np.all(np.abs(np.linalg.norm(back, axis=1) - GEO.radius_m) < 1e-12)
    assert not clamped[:-3].any()


def test_far_field_error_is_tens_of_micrometres_at_30_deg():
    az = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    pts = GEO.surface_point_from_angles(np.full(16, np.deg2rad(30)), az)
    tau = GEO.exact_delays_s(pts)
    ff, _ = GEO.point_from_delays(tau[:, 0], tau[:, 1], exact=False)
    err = np.linalg.norm((ff - pts)[:, :2], axis=1)
    assert 10e-6 < err.max() < 100e-6


def test_delay_sign_convention():
    # Contact at +x: elements at +x hear it first, so tau_x > 0 (conventions.md).
    p = GEO.surface_point_from_xy(5e-3, 0.0)
    t = GEO.arrival_times_s(p)
    assert t[0] < t[2] and t[1] < t[3]
    tx, ty = GEO.exact_delays_s(p)
    assert tx > 0 and abs(ty) < 1e-15


def test_jacobian_and_time_derivatives_match_finite_differences():
    rng = np.random.default_rng(2)
    pts = random_points(rng, 20, 85)
    h = 1e-8
    t, dt, d2t = GEO.arrival_time_derivatives(pts[:, 0], pts[:, 1])
    np.testing.assert_allclose(t, GEO.arrival_times_s(pts), rtol=1e-12)
    for i, (ex, ey) in enumerate([(h, 0), (0, h)]):
        tp = GEO.arrival_time_derivatives(pts[:, 0] + ex, pts[:, 1] + ey)[0]
        tm = GEO.arrival_time_derivatives(pts[:, 0] - ex, pts[:, 1] - ey)[0]
        np.testing.assert_allclose(dt[..., i], (tp - tm) / (2 * h), rtol=1e-5, atol=1e-12)
        gp = GEO.arrival_time_derivatives(pts[:, 0] + ex, pts[:, 1] + ey)[1]
        gm = GEO.arrival_time_derivatives(pts[:, 0] - ex, pts[:, 1] - ey)[1]
        np.testing.assert_allclose(d2t[..., i], (gp - gm) / (2 * h), rtol=1e-4, atol=1e-12)
        # delay_jacobian is the (tau_x, tau_y) contrast of dt
        taup = GEO.delays_from_arrival_times(tp)[:, :2]
        taum = GEO.delays_from_arrival_times(tm)[:, :2]
        np.testing.assert_allclose(
            GEO.delay_jacobian(pts[:, 0], pts[:, 1])[..., i], (taup - taum) / (2 * h), rtol=1e-5
        )


def test_clamp_when_noise_pushes_sin_theta_past_one():
    phi = np.array([0.0, 0.4, 2.0, -2.5])
    h = GEO.exact_delays_s(GEO.surface_point_from_angles(np.full(4, np.pi / 2), phi))
    tau = h * 1.2  # |sin theta| > 1 implied
    p, clamped = GEO.point_from_delays(tau[:, 0], tau[:, 1])
    assert clamped.all() and np.all(np.isfinite(p))
    np.testing.assert_allclose(np.linalg.norm(p, axis=1), GEO.radius_m, rtol=1e-9)
    assert np.all(p[:, 2] >= 0) and np.all(
        p[:, 2] < 1e-4 * GEO.radius_m
    )  # clamp circle R (1 - 1e-9)
    # Exact mode: the Newton iterate is projected on the horizon, near the true azimuth.
    np.testing.assert_allclose(np.arctan2(p[:, 1], p[:, 0]), phi, atol=0.01)
    pf, cf = GEO.point_from_delays(tau[:, 0], tau[:, 1], exact=False)
    assert cf.all() and np.all(np.isfinite(pf))
    # Far-field mode clamps along the measured delay direction exactly.
    np.testing.assert_allclose(
        np.arctan2(pf[:, 1], pf[:, 0]), np.arctan2(tau[:, 1], tau[:, 0]), atol=1e-12
    )


def test_non_finite_delays_flagged():
    with np.errstate(invalid="ignore"):
        p, clamped = GEO.point_from_delays(np.array([np.nan, 0.0]), np.array([0.0, np.inf]))
    assert clamped.all() and np.isnan(p).all()


def test_echo_free_duration_is_a_lower_bound_of_the_echo_lag():
    rng = np.random.default_rng(3)
    pts = random_points(rng, 5000)
    direct = GEO.path_lengths_m(pts)
    echo = 2 * GEO.radius_m + GEO.path_lengths_m(-pts)  # first (antipodal) wall echo
    lag = (echo - direct) / GEO.sound_speed_m_s
    assert lag.min() >= GEO.echo_free_duration_s - 1e-15
    assert lag.min() < GEO.echo_free_duration_s * 1.02  # and it is nearly reached
    assert 2 * GEO.radius_m / GEO.sound_speed_m_s == pytest.approx(13.5e-6, rel=0.01)


def test_point_covariance_matches_monte_carlo():
    rng = np.random.default_rng(4)
    p = GEO.surface_point_from_angles(np.deg2rad(40.0), 0.6)
    tau = GEO.exact_delays_s(p)
    c_tau = np.array([[4.0, 1.0], [1.0, 2.0]]) * 1e-18  # (ns)^2 scale
    cov = GEO.point_covariance(p, c_tau)
    d = rng.multivariate_normal(np.zeros(2), c_tau, size=20000)
    pts, _ = GEO.point_from_delays(tau[0] + d[:, 0], tau[1] + d[:, 1])
    emp = np.cov((pts - p).T)
    np.testing.assert_allclose(emp, cov, rtol=0.05, atol=1e-3 * np.abs(cov).max())
