# SPDX-License-Identifier: Apache-2.0
"""Property-based stability of `localize` over random geometry, sample rate, noise, gain,
DC offset, dtype and damage (NaN/inf, zero and constant windows, clipping, overlapping
packets): never an exception, never a non-finite output, bad input rejected with its
reason, estimates invariant to gain and DC offset."""

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import Reason, available_methods, localize
from ae_tactile.sim import SimConfig, render_triggered

SETTINGS = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
DAMAGE = ["none", "nan", "inf", "zeros", "constant", "dead_channel", "clip", "overlap"]


@st.composite
def scenarios(draw):
    r = draw(st.floats(6e-3, 15e-3))
    a = draw(st.floats(0.5e-3, min(2.5e-3, r / 4)))
    c = draw(st.floats(1000.0, 1600.0))
    fs = float(draw(st.integers(1, 20)) * 1_000_000)
    kind = draw(st.sampled_from(["pole", "grazing", "random"]))
    polar = {"pole": 0.0, "grazing": np.pi / 2}.get(kind, draw(st.floats(0.0, np.pi / 2)))
    az = draw(st.floats(-np.pi, np.pi))
    snr = draw(st.one_of(st.none(), st.floats(0.0, 50.0)))
    return dict(
        geo=FingertipGeometry(r, a, c),
        fs=fs,
        polar=polar,
        az=az,
        snr=snr,
        gain=10 ** draw(st.floats(-3.0, 3.0)),
        dc=draw(st.floats(-10.0, 10.0)),
        f32=draw(st.booleans()),
        pol=draw(st.sampled_from([-1, 1])),
        damage=draw(st.sampled_from(DAMAGE)),
        overlap=draw(st.floats(0.0, 1.0)),
        polar2=draw(st.floats(0.0, np.pi / 2)),
        az2=draw(st.floats(-np.pi, np.pi)),
        method=draw(st.sampled_from(available_methods())),
        seed=draw(st.integers(0, 2**16)),
    )


def render(sc):
    geo = sc["geo"]
    fs = sc["fs"]
    cfg = SimConfig(
        geometry=geo,
        medium="custom",
        density_kg_m3=1000.0,
        attenuation_db_per_m_at_1mhz=0.0,
        sample_rate_hz=fs,
        lowpass_hz=min(1e6, 0.4 * fs),
        quantization=False,
    )
    p = geo.surface_point_from_angles(np.array([sc["polar"]]), np.array([sc["az"]]))
    rng = np.random.default_rng(sc["seed"])
    pk = render_triggered(p, cfg, polarity=sc["pol"], window_s=60e-6, rng=rng)
    x = pk.clean_v.copy()
    if sc["damage"] == "overlap":
        # A second packet from elsewhere, overlapping the first's echo-free part by 0-100 %.
        p2 = geo.surface_point_from_angles(np.array([sc["polar2"]]), np.array([sc["az2"]]))
        q = render_triggered(p2, cfg, polarity=1, window_s=60e-6, subsample_offset=0.5, rng=rng)
        d = int(round((1.0 - sc["overlap"]) * geo.echo_free_duration_s * fs))
        d = min(d, x.shape[2] - 1)
        x[:, :, d:] += q.clean_v[:, :, : x.shape[2] - d]
    if sc["snr"] is not None:
        sigma = np.sqrt(pk.signal_power_v2 / 10 ** (sc["snr"] / 10))
        x = x + sigma[:, None, None] * rng.standard_normal(x.shape)
    return x, pk.onset_index, p


def damage(x, sc, rng, offset):
    """Apply the scenario's damage; ``offset`` is the DC level the ADC range is centred on."""
    kind = sc["damage"]
    full_scale = None
    if kind == "nan":
        x[0, rng.integers(4), rng.integers(x.shape[2])] = np.nan
    elif kind == "inf":
        x[0, rng.integers(4), rng.integers(x.shape[2])] = rng.choice([np.inf, -np.inf])
    elif kind == "zeros":
        x[:] = 0.0
    elif kind == "constant":
        x[:] = 0.25
    elif kind == "dead_channel":
        x[0, rng.integers(4)] = 0.0
    elif kind == "clip":
        half = 0.5 * np.abs(x - offset).max()
        np.clip(x, offset - half, offset + half, out=x)
        full_scale = abs(offset) + half  # the clip level the ADC would report
        if offset != 0:
            # an ADC clips at a fixed level: put the DC where the range is symmetric
            x -= offset
            full_scale = half
    return x, full_scale


def check_finite(r, geo):
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
    np.testing.assert_allclose(np.linalg.norm(r.point_m, axis=1), geo.radius_m, rtol=1e-6)
    assert np.all(r.point_m[:, 2] >= 0)
    assert np.all(r.accepted == (r.reason == 0))
    assert set(np.unique(r.reason)) <= {int(c) for c in Reason}


@settings(max_examples=200, **SETTINGS)
@given(scenarios())
def test_never_raises_never_nan_and_rejects_bad_input(sc):
    geo = sc["geo"]
    x, onset, p = render(sc)
    rng = np.random.default_rng(sc["seed"] + 1)
    offset = sc["dc"] * sc["gain"]
    x = sc["gain"] * x + offset
    x, full_scale = damage(x, sc, rng, offset)
    x = x.astype(np.float32 if sc["f32"] else np.float64)
    r = localize(x, sc["fs"], onset, method=sc["method"], geometry=geo, full_scale_v=full_scale)
    check_finite(r, geo)
    kind = sc["damage"]
    if kind in ("nan", "inf"):
        assert r.reason[0] == Reason.NONFINITE
    elif kind in ("zeros", "constant", "dead_channel"):
        assert r.reason[0] == Reason.NO_SIGNAL
    elif kind == "clip":
        assert r.reason[0] == Reason.SATURATED
    elif (
        kind == "none"
        and sc["snr"] is not None
        and sc["snr"] >= 25
        and sc["fs"] >= 5e6
        and sc["polar"] <= np.deg2rad(80)
        and sc["method"] != "xcorr_farfield"
    ):
        assert r.accepted[0], r.reason_names
        assert np.linalg.norm(r.point_m[0] - p[0]) < 0.2e-3
        assert r.polarity[0] == sc["pol"]


@settings(max_examples=80, **SETTINGS)
@given(scenarios())
def test_invariant_to_gain_and_dc_offset(sc):
    geo = sc["geo"]
    x, onset, _ = render(sc)
    base = localize(x, sc["fs"], onset, method=sc["method"], geometry=geo)
    rng = np.random.default_rng(sc["seed"])
    dc = sc["gain"] * rng.uniform(-10, 10, (1, 4, 1))
    r = localize(sc["gain"] * x + dc, sc["fs"], onset, method=sc["method"], geometry=geo)
    check_finite(r, geo)
    assert np.array_equal(r.reason, base.reason)
    # Equal up to float rounding of the offset (10 V against micro-volt noise at worst);
    # in-plane, since z = sqrt(R^2 - rho^2) amplifies rounding without bound at the horizon.
    assert np.linalg.norm(r.point_m[:, :2] - base.point_m[:, :2]) < 1e-7 * geo.radius_m
    assert np.linalg.norm(r.point_m - base.point_m) < 1e-5 * geo.radius_m
    np.testing.assert_allclose(
        r.amplitude_v, sc["gain"] * base.amplitude_v, rtol=1e-5, atol=1e-12 * sc["gain"]
    )


@settings(max_examples=40, **SETTINGS)
@given(st.integers(1, 6), st.integers(0, 2**16), st.sampled_from(available_methods()))
def test_batches_of_mixed_damage(k, seed, method):
    # Damaged packets do not disturb their neighbours in the same batch.
    rng = np.random.default_rng(seed)
    cfg = SimConfig()
    geo = cfg.geometry
    ct = rng.uniform(np.cos(np.deg2rad(60)), 1, k)
    pts = geo.surface_point_from_angles(np.arccos(ct), rng.uniform(0, 2 * np.pi, k))
    pk = render_triggered(pts, cfg, snr_db=30, rng=rng)
    x = pk.samples_v.copy()
    bad = rng.random(k) < 0.5
    for i in np.nonzero(bad)[0]:
        x[i, rng.integers(4), rng.integers(400)] = np.nan
    r = localize(x, cfg.sample_rate_hz, pk.onset_index, method=method)
    check_finite(r, geo)
    assert np.all(r.reason[bad] == Reason.NONFINITE)
    good = localize(pk.samples_v[~bad], cfg.sample_rate_hz, pk.onset_index[~bad], method=method)
    np.testing.assert_allclose(r.point_m[~bad], good.point_m, atol=1e-12)
