# SPDX-License-Identifier: Apache-2.0
"""The compiled per-packet path (`fast.py`, `Localizer.localize_one`) against the numpy
path: same points (to a tiny fraction of the Cramer-Rao bound), same decisions and
reasons, on clean and damaged packets; the light result; argument errors; the emission
offset against the simulator's emission instant. No timing here (bench/)."""

import os
import subprocess
import sys

import numpy as np
import pytest

from ae_eval.crlb import simulated_crlb
from ae_tactile.localization import NUMBA_AVAILABLE, Localizer, PacketLocation, Reason, localize
from ae_tactile.sim import SimConfig, render_triggered

CFG = SimConfig()
GEO = CFG.geometry
FS = CFG.sample_rate_hz
needs_numba = pytest.mark.skipif(not NUMBA_AVAILABLE, reason="numba not importable here")


def cap_points(rng, n, max_deg=70.0):
    ct = rng.uniform(np.cos(np.deg2rad(max_deg)), 1, n)
    return GEO.surface_point_from_angles(np.arccos(ct), rng.uniform(0, 2 * np.pi, n))


def damaged_batch(rng, fs, n=120, snr_db=20.0):
    """Clean packets plus every kind of damage the localizer must reject (or survive)."""
    cfg = CFG.replace(sample_rate_hz=fs)
    pts = cap_points(rng, n)
    pk = render_triggered(pts, cfg, snr_db=snr_db, rng=rng)
    x = pk.samples_v.astype(float).copy()
    on = pk.onset_index.copy()
    x[0, 1, 50] = np.nan  # NONFINITE
    x[1] = 0.0  # NO_SIGNAL
    x[2, 3] = 0.01  # dead (constant) channel
    on[3] = x.shape[2] + 5  # WINDOW
    on[4] = -3
    lim = 0.15 * np.abs(x[5]).max()
    x[5] = np.clip(x[5], -lim, lim)  # clipped: flat top
    x[6] *= 1e-3  # LOW_SNR after adding noise below
    x[6] += 0.5 * np.std(pk.samples_v[6, :, : on[6] - 20]) * rng.standard_normal(x[6].shape)
    far = GEO.surface_point_from_angles(np.deg2rad(50), np.arctan2(pts[7, 1], pts[7, 0]) + np.pi)
    other = render_triggered(far[None], cfg, snr_db=40, subsample_offset=0.3, rng=rng)
    d = int(on[7] - other.onset_index[0] + round(2e-6 * fs))  # a second packet 2 us later
    x[7, :, d:] += 2 * other.clean_v[0, :, : x.shape[2] - d]  # OVERLAP
    x[8] = x[8, ::-1]  # time-reversed: not a packet after its onset
    x[9, 2] = np.roll(x[9, 2], 60)  # impossible delay on one channel
    x[10, :, :] = np.inf
    x[11] *= 1e6  # huge but finite
    x[12] += 3.0  # DC offset
    return pts, x, on, pk


@needs_numba
@pytest.mark.parametrize("fs", [2e6, 5e6, 10e6, 20e6])
def test_numba_and_numpy_agree(fs):
    rng = np.random.default_rng(int(fs) % 1000 + 3)
    pts, x, on, pk = damaged_batch(rng, fs)
    a = localize(x, fs, on, engine="numpy")
    b = localize(x, fs, on, engine="numba")
    assert np.array_equal(a.reason, b.reason), (a.reason_names, b.reason_names)
    assert np.array_equal(a.reason_flags, b.reason_flags)
    assert np.array_equal(a.accepted, b.accepted)
    assert np.array_equal(a.polarity, b.polarity)
    assert np.array_equal(a.clamped, b.clamped)
    cfg = CFG.replace(sample_rate_hz=fs)
    bound = simulated_crlb(pts[:5], cfg, snr_db=20.0)["rms_m"].min()
    # same points to 1e-4 of the bound (rounding; Newton's stopping test at 1e-4 sample)
    assert np.abs(a.point_m - b.point_m).max() < 1e-4 * bound
    for f in ("tau_x_s", "tau_y_s", "twist_s", "polar_rad", "azimuth_rad", "emission_offset_s"):
        np.testing.assert_allclose(getattr(b, f), getattr(a, f), rtol=1e-5, atol=1e-12, err_msg=f)
    for f in ("snr_db_est", "confidence", "residual", "overlap_excess"):
        np.testing.assert_allclose(getattr(b, f), getattr(a, f), rtol=1e-5, atol=1e-8, err_msg=f)
    for f in ("noise_rms_v_est", "amplitude_v"):
        scale = np.abs(getattr(a, f)).max()
        np.testing.assert_allclose(
            getattr(b, f), getattr(a, f), rtol=1e-5, atol=1e-8 * scale, err_msg=f
        )
    np.testing.assert_allclose(
        b.covariance_m2,
        a.covariance_m2,
        rtol=1e-5,
        atol=1e-6 * np.abs(a.covariance_m2[a.accepted]).max(),
    )
    # the damage is rejected for the documented reasons
    r = b.reason
    assert r[0] == Reason.NONFINITE and r[10] == Reason.NONFINITE
    assert r[1] == Reason.NO_SIGNAL and r[2] == Reason.NO_SIGNAL
    assert r[3] == Reason.WINDOW and r[4] == Reason.WINDOW
    assert r[5] == Reason.SATURATED
    assert r[6] == Reason.LOW_SNR
    assert r[7] == Reason.OVERLAP
    assert not b.accepted[9]
    clean = np.arange(len(r)) >= 11
    assert b.accepted[clean].mean() > 0.97
    for name in ("point_m", "covariance_m2", "confidence", "snr_db_est", "emission_offset_s"):
        assert np.all(np.isfinite(getattr(b, name))), name


@needs_numba
def test_localize_one_equals_the_batch_row():
    rng = np.random.default_rng(21)
    pts, x, on, pk = damaged_batch(rng, FS, n=40)
    batch = localize(x, FS, on)
    loc = Localizer("ml").warm_up(GEO, FS, x.shape[2])
    for i in range(len(x)):
        one = loc.localize_one(x[i], FS, int(on[i]), saturated=None)  # as the batch: unknown
        assert isinstance(one, PacketLocation)
        assert one.reason == batch.reason[i] and one.accepted == batch.accepted[i]
        assert one.reason_flags == batch.reason_flags[i]
        np.testing.assert_array_equal(one.point_m, batch.point_m[i])
        np.testing.assert_array_equal(one.covariance_m2, batch.covariance_m2[i])
        assert one.polarity == batch.polarity[i]
        assert one.snr_db == batch.snr_db_est[i]
        assert one.emission_offset_s == batch.emission_offset_s[i]
        assert (one.tau_x_s, one.tau_y_s) == (batch.tau_x_s[i], batch.tau_y_s[i])
        assert (one.polar_rad, one.azimuth_rad) == (batch.polar_rad[i], batch.azimuth_rad[i])
        assert one.amplitude_v == batch.amplitude_v[i] and one.confidence == batch.confidence[i]
    # float32 windows (what the link delivers) give the float32-rounded answer
    x32 = x[20:].astype(np.float32)
    b32 = localize(x32, FS, on[20:], engine="numpy")
    for i in range(len(x32)):
        one = loc.localize_one(x32[i], FS, int(on[20 + i]), saturated=None)
        assert one.reason == b32.reason[i]
        np.testing.assert_allclose(one.point_m, b32.point_m[i], atol=1e-9)


@pytest.mark.parametrize("engine", ["numpy", None])
def test_light_result_and_options_through_localize_one(engine):
    if engine is None and not NUMBA_AVAILABLE:
        pytest.skip("numba not importable here")
    rng = np.random.default_rng(22)
    pts = cap_points(rng, 6)
    pk = render_triggered(pts, CFG, snr_db=30, polarity=np.array([1, -1, 1, -1, 1, -1]), rng=rng)
    g = np.array([1.2, 0.8, 1.0, 1.1])
    loc = Localizer("ml", engine=engine, min_snr_db=3.0)
    for i in range(6):
        r = loc.localize_one(
            pk.samples_v[i] * g[:, None],
            FS,
            pk.onset_index[i],
            channel_gains=g,
            noise_rms_v=pk.noise_rms_v[i],
        )
        assert r.accepted and r.reason == Reason.OK
        assert np.linalg.norm(r.point_m - pts[i]) < 30e-6
        assert r.polarity == (1 if i % 2 == 0 else -1)
        assert np.sign(r.amplitude_v) == r.polarity
        assert r.covariance_m2.shape == (3, 3) and r.point_m.shape == (3,)
        assert 0 < r.confidence <= 1 and 20 < r.snr_db < 40
        # the given noise is in input volts (divided by the rms gain), plus the ADC's q^2/12
        nr = loc.localize_one(
            pk.samples_v[i], FS, pk.onset_index[i], noise_rms_v=pk.noise_rms_v[i]
        )
        np.testing.assert_allclose(
            nr.noise_rms_v_est**2, pk.noise_rms_v[i] ** 2 + CFG.lsb_v**2 / 12, rtol=1e-6
        )
        np.testing.assert_allclose(
            r.noise_rms_v_est**2,
            (pk.noise_rms_v[i] ** 2 / np.mean(g * g) + CFG.lsb_v**2 / 12),
            rtol=0.02,
        )
        assert r.polar_rad == pytest.approx(np.arccos(r.point_m[2] / GEO.radius_m), abs=1e-9)
        assert "OK" in repr(r)
    # an upstream saturation flag rejects
    r = loc.localize_one(pk.samples_v[0], FS, pk.onset_index[0], saturated=True)
    assert not r.accepted and r.reason == Reason.SATURATED


@pytest.mark.parametrize("engine", ["numpy", None])
def test_localize_one_argument_errors_and_bad_data(engine):
    if engine is None and not NUMBA_AVAILABLE:
        pytest.skip("numba not importable here")
    pk = render_triggered(
        GEO.surface_point_from_xy(np.array([1e-3]), np.array([2e-3])), CFG, snr_db=25, rng=1
    )
    w, on = pk.samples_v[0], int(pk.onset_index[0])
    loc = Localizer("ml", engine=engine)
    for bad in (w[:3], w[None], w[:, :2], np.zeros(4)):
        with pytest.raises(ValueError):
            loc.localize_one(bad, FS, on)
    for fs in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError):
            loc.localize_one(w, fs, on)
    for nr in (0.0, -1e-3, np.inf):
        with pytest.raises(ValueError, match="noise_rms_v"):
            loc.localize_one(w, FS, on, noise_rms_v=nr)
        with pytest.raises(ValueError, match="noise_rms_v"):
            localize(pk.samples_v, FS, pk.onset_index, noise_rms_v=nr, engine=engine)
    with pytest.raises(ValueError):
        loc.localize_one(w, FS, 10.5)
    with pytest.raises(ValueError):
        loc.localize_one(w, FS, on, channel_gains=[1.0, 0.0, 1.0, 1.0])
    with pytest.raises(TypeError):
        loc.localize_one(w.astype(object), FS, on)
    # NaN noise means "unknown": measured, the same as None
    a = loc.localize_one(w, FS, on, noise_rms_v=np.nan)
    b = loc.localize_one(w, FS, on)
    np.testing.assert_array_equal(a.point_m, b.point_m)
    # data damage is a rejection, never an exception
    for x, reason in (
        (np.full_like(w, np.nan), Reason.NONFINITE),
        (np.zeros_like(w), Reason.NO_SIGNAL),
        (np.clip(w, -0.01, 0.01), Reason.SATURATED),
    ):
        r = loc.localize_one(x, FS, on, saturated=None)
        assert not r.accepted and r.reason == reason
        assert np.all(np.isfinite(r.point_m)) and np.all(np.isfinite(r.covariance_m2))
    r = loc.localize_one(w, FS, w.shape[1] + 10)
    assert r.reason == Reason.WINDOW


def test_emission_offset_matches_the_simulated_emission_instant():
    # emission offset = onset / fs - travel time to the nearest element; the onset is the
    # first sample at/after the arrival, so the estimate lies within one sample after the
    # true instant (plus the position error's travel-time share, < 0.05 us here).
    rng = np.random.default_rng(23)
    pts = cap_points(rng, 200, 80.0)
    pk = render_triggered(pts, CFG, snr_db=30, rng=rng)
    for engine in ("numpy", None) if NUMBA_AVAILABLE else ("numpy",):
        r = localize(pk.samples_v, FS, pk.onset_index, engine=engine)
        err = r.emission_offset_s - pk.emission_time_s
        assert np.all(err > -0.05e-6) and np.all(err < 1.0 / FS + 0.05e-6), (err.min(), err.max())
        assert abs(np.mean(err) - 0.5 / FS) < 0.15 / FS


def test_numpy_path_without_numba():
    # AE_TACTILE_NO_NUMBA=1: the import guard leaves numba out; everything still works.
    code = (
        "import numpy as np\n"
        "from ae_tactile.localization import NUMBA_AVAILABLE, Localizer, localize\n"
        "from ae_tactile.sim import SimConfig, render_triggered\n"
        "assert not NUMBA_AVAILABLE\n"
        "cfg = SimConfig()\n"
        "p = cfg.geometry.surface_point_from_xy(np.array([2e-3]), np.array([1e-3]))\n"
        "pk = render_triggered(p, cfg, snr_db=30, rng=1)\n"
        "r = Localizer().localize_one(pk.samples_v[0], 10e6, int(pk.onset_index[0]))\n"
        "assert r.accepted and np.linalg.norm(r.point_m - p[0]) < 30e-6\n"
        "b = localize(pk.samples_v, 10e6, pk.onset_index)\n"
        "assert b.accepted.all()\n"
        "print('ok')\n"
    )
    env = dict(os.environ, AE_TACTILE_NO_NUMBA="1")
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_engine_argument():
    pk = render_triggered(
        GEO.surface_point_from_xy(np.array([1e-3]), np.array([2e-3])), CFG, snr_db=25, rng=1
    )
    with pytest.raises(ValueError, match="engine"):
        localize(pk.samples_v, FS, pk.onset_index, engine="gpu")
    if NUMBA_AVAILABLE:
        with pytest.raises(ValueError, match="engine"):
            localize(pk.samples_v, FS, pk.onset_index, method="gradient", engine="numba")
    r = localize(pk.samples_v, FS, pk.onset_index, method="gradient")  # numpy, any engine
    assert r.accepted.all() and r.emission_offset_s.shape == (1,)
