# SPDX-License-Identifier: Apache-2.0
"""Per-channel delay offsets learnt from the device's own touches (issue 37 points 2-3):
`ChannelDelayLearner` recovers a front end's channel delays from packets of unknown
position, the localizer takes them out of the arrivals, and the accuracy returns to the
Cramer-Rao bound where the device has no other mismatch."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from ae_eval.crlb import simulated_crlb
from ae_eval.zoo import ZOO, held_out
from ae_tactile.localization import ChannelDelayLearner, Localizer, localize
from ae_tactile.localization.channel_delays import CONTRASTS, residual_normals
from ae_tactile.pipeline import PacketLocalizer
from ae_tactile.records import PacketView
from ae_tactile.sim import render_triggered

FS = 10e6


def _points(geo, n, g, max_polar_deg):
    cos_t = g.uniform(math.cos(math.radians(max_polar_deg)), 1.0, n)
    return geo.surface_point_from_angles(np.arccos(cos_t), g.uniform(0, 2 * math.pi, n))


def _true_offsets(dev):
    """The device's channel delays less their mean [s] (only differences are defined)."""
    d = np.array(dev.fields.get("channel_delay_s", (0.0, 0.0, 0.0, 0.0)), float)
    return d - d.mean()


def _learn(dev, n, seed, snr_db=(25.0, 40.0)):
    """A learner taught n touches (polar <= 70 deg, SNR uniform in ``snr_db``)."""
    g = np.random.default_rng(seed)
    cfg = dev.config("water_skin", FS)
    learner = ChannelDelayLearner()
    for _ in range(n // 64):
        pk = render_triggered(_points(cfg.geometry, 64, g, 70.0), cfg,
                              snr_db=g.uniform(*snr_db, 64),
                              subsample_offset=g.uniform(0.1, 0.9, 64), rng=g)
        learner.add(pk.samples_v, FS, pk.onset_index, cfg.geometry)
    return learner


def _ratio(dev, delays_s, seed, snr_db=40.0, n=150):
    """rms in-plane error / rms CRLB (the simulator's true noise covariance, as
    test_localization_zoo) of the ml localizer with these channel delays taken out."""
    g = np.random.default_rng(seed)
    cfg = dev.config("water_skin", FS)
    pts = _points(cfg.geometry, n, g, 40.0)
    u = g.uniform(0.1, 0.9, n)
    pk = render_triggered(pts, cfg, snr_db=snr_db, subsample_offset=u, rng=g)
    loc = Localizer("ml", geometry=cfg.geometry)
    loc.set_channel_delays(delays_s)
    res = loc(pk.samples_v, FS, pk.onset_index)
    acc = res.accepted
    assert acc.mean() > 0.97
    e = (res.point_m - pk.points_m)[acc, :2]
    bound = simulated_crlb(pts, cfg, snr_db=snr_db, subsample_offset=u)["rms_m"][acc]
    return math.sqrt(np.mean(np.sum(e**2, axis=1))) / math.sqrt(np.mean(bound**2))


def test_residual_direction_is_orthogonal_to_what_a_fit_absorbs():
    """n(s) is a unit vector orthogonal to the common shift and to d t / d(s_x, s_y): the
    one combination of arrivals a point fit leaves; it is the xy contrast tilted towards
    x and y by the point's position (zero tilt at the apex, by symmetry)."""
    geo = ZOO["nominal"].config("water_skin", FS).geometry
    g = np.random.default_rng(1)
    pts = np.concatenate([_points(geo, 50, g, 70.0), [[0.0, 0.0, geo.radius_m]]])
    n = residual_normals(geo, pts)
    _, dt, _ = geo.arrival_time_derivatives(pts[:, 0], pts[:, 1])
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    assert np.abs(n.sum(axis=1)).max() < 1e-9
    assert np.abs(np.einsum("ka,kai->ki", n, dt)).max() < 1e-9 * np.abs(dt).max()
    comp = n @ CONTRASTS.T
    np.testing.assert_allclose(comp[-1], [0.0, 0.0, 1.0], atol=1e-9)
    assert 0.02 < np.abs(comp[:-1, :2]).max() < 0.2  # tilt: the x, y information


def test_learns_delay_mismatch_and_returns_to_the_bound():
    """Zoo 'delay_mismatch' (0 / 30 / 10 / 50 ns): 2,048 touches at unknown points give
    every offset difference within 1.5 ns, all three contrasts applied; at 40 dB the ml
    error drops from ~55x the bound to <= 1.2x (1.0x with the true offsets)."""
    dev = ZOO["delay_mismatch"]
    learner = _learn(dev, 2048, 3)
    assert learner.all_converged
    err = learner.delays_s - _true_offsets(dev)
    assert np.abs(err).max() < 1.5e-9, err * 1e9
    np.testing.assert_allclose(learner.applied_delays_s, learner.delays_s)
    before = _ratio(dev, None, 4)
    after = _ratio(dev, learner.applied_delays_s, 4)
    assert before > 20.0, before
    assert after <= 1.2, after


def test_learns_a_held_out_device():
    """A held-out device (random front end, amplifier noise share, gain and delay
    mismatch): the offsets within 1.5 ns after 2,048 touches, and the error at 40 dB
    within 10 % of the error with the true offsets (what its other mismatch leaves),
    from >= 10x that before."""
    dev = held_out(0, 3)[1]
    truth = _true_offsets(dev)
    assert np.ptp(truth) > 20e-9  # the draw has a delay mismatch worth learning
    learner = _learn(dev, 2048, 5)
    err = learner.delays_s - truth
    assert np.abs(err).max() < 1.5e-9, err * 1e9
    before = _ratio(dev, None, 6)
    after = _ratio(dev, learner.applied_delays_s, 6)
    oracle = _ratio(dev, truth, 6)
    assert before > 10.0 * oracle, (before, oracle)
    assert after <= 1.1 * oracle, (after, oracle)


def test_nominal_device_learns_nothing_and_keeps_its_accuracy():
    """Equal channels: every offset within 1 ns of zero, and the accuracy at 40 dB as
    without the learner (within 3 %)."""
    dev = ZOO["nominal"]
    learner = _learn(dev, 1024, 7)
    assert np.abs(learner.delays_s).max() < 1e-9, learner.delays_s
    before = _ratio(dev, None, 8)
    after = _ratio(dev, learner.applied_delays_s, 8)
    assert after <= 1.03 * before, (before, after)


def test_nothing_applied_before_enough_packets():
    learner = _learn(ZOO["delay_mismatch"], 0, 9)
    assert learner.applied_delays_s is None and learner.delays_s is None
    few = ChannelDelayLearner(min_count=64)
    g = np.random.default_rng(9)
    cfg = ZOO["delay_mismatch"].config("water_skin", FS)
    pk = render_triggered(_points(cfg.geometry, 32, g, 70.0), cfg, snr_db=40.0, rng=g)
    assert few.add(pk.samples_v, FS, pk.onset_index, cfg.geometry) == 32
    assert few.applied_delays_s is None and not few.converged.any()
    assert "learning" in few.status()


def test_zero_offsets_change_nothing_and_both_engines_agree():
    """set_channel_delays(zeros) is no correction (bit for bit); with offsets the compiled
    and numpy paths give the same points, and localize_one is row i of the batch."""
    dev = ZOO["delay_mismatch"]
    cfg = dev.config("water_skin", FS)
    g = np.random.default_rng(10)
    pk = render_triggered(_points(cfg.geometry, 12, g, 50.0), cfg, snr_db=30.0, rng=g)
    plain = Localizer("ml", geometry=cfg.geometry)(pk.samples_v, FS, pk.onset_index)
    loc = Localizer("ml", geometry=cfg.geometry)
    loc.set_channel_delays(np.zeros(4))
    assert loc.channel_delays_s is None
    np.testing.assert_array_equal(loc(pk.samples_v, FS, pk.onset_index).point_m, plain.point_m)
    d = _true_offsets(dev)
    fast_res = None
    for engine in ("numba", "numpy"):
        loc = Localizer("ml", geometry=cfg.geometry, engine=engine)
        loc.set_channel_delays(d)
        res = loc(pk.samples_v, FS, pk.onset_index)
        one = loc.localize_one(pk.samples_v[3], FS, int(pk.onset_index[3]))
        np.testing.assert_allclose(one.point_m, res.point_m[3], atol=1e-12)
        np.testing.assert_allclose(one.emission_offset_s, res.emission_offset_s[3], atol=1e-15)
        if fast_res is None:
            fast_res = res
        else:
            np.testing.assert_allclose(res.point_m, fast_res.point_m, atol=1e-9)
            np.testing.assert_array_equal(res.accepted, fast_res.accepted)
            np.testing.assert_allclose(res.emission_offset_s, fast_res.emission_offset_s,
                                       atol=1e-12)
    # `localize` called with the delays places the emission instant as the localizer does:
    # the earliest arrival is t_k(s) + d_k
    direct = localize(pk.samples_v, FS, pk.onset_index, geometry=cfg.geometry,
                      channel_delays_s=d)
    np.testing.assert_allclose(direct.point_m, fast_res.point_m, atol=1e-9)
    t_first = (cfg.geometry.arrival_times_s(direct.point_m) + d).min(axis=1)
    np.testing.assert_allclose(direct.emission_offset_s,
                               pk.onset_index / FS - t_first, atol=1e-15)
    np.testing.assert_allclose(direct.emission_offset_s, fast_res.emission_offset_s,
                               atol=1e-12)
    # with the true offsets the points move onto the truth (the bias was ~0.1-0.2 mm)
    err_plain = np.linalg.norm(plain.point_m - pk.points_m, axis=1).mean()
    err_fixed = np.linalg.norm(fast_res.point_m - pk.points_m, axis=1).mean()
    assert err_fixed < 0.2 * err_plain, (err_plain, err_fixed)
    with pytest.raises(ValueError):
        loc.set_channel_delays([0.0, 1e-9, np.nan, 0.0])
    with pytest.raises(ValueError):
        loc.set_channel_delays([0.0, 2e-6, 0.0, 0.0])
    with pytest.raises(ValueError):
        loc.set_channel_delays([0.0, 1e-9, 0.0])


def test_state_round_trip_and_bad_states_rejected():
    learner = _learn(ZOO["delay_mismatch"], 256, 11)
    state = json.loads(json.dumps(learner.calibration_state()))
    other = ChannelDelayLearner()
    other.load_calibration_state(state)
    np.testing.assert_allclose(other.delays_s, learner.delays_s, rtol=1e-12, atol=1e-18)
    np.testing.assert_array_equal(other.converged, learner.converged)
    assert other.n_packets == learner.n_packets
    assert ChannelDelayLearner().calibration_state() is None
    bad = [
        None,
        {"format": 2, "u": state["u"], "y_s": state["y_s"], "var_s2": state["var_s2"]},
        {k: v for k, v in state.items() if k != "y_s"},
        dict(state, y_s=state["y_s"][:-1]),
        dict(state, y_s=[float("nan")] + state["y_s"][1:]),
        dict(state, var_s2=[-1.0] + state["var_s2"][1:]),
        dict(state, u=[[1.0, 1.0, 1.0]] + state["u"][1:]),  # not a unit vector
        dict(state, y_s=[1e-3] + state["y_s"][1:]),  # a millisecond is no channel delay
        dict(state, u="abc"),
    ]
    for s in bad:
        with pytest.raises(ValueError):
            other.load_calibration(s)
        np.testing.assert_allclose(other.delays_s, learner.delays_s, rtol=1e-12, atol=1e-18)
    other.reset()
    assert other.delays_s is None and other.n_packets == 0


def test_packet_localizer_learns_persists_and_applies():
    """Through the driver's `PacketLocalizer`: the touches it accepts teach the learner
    (kept now and then, measured between calls), the offsets reach its localizer once
    converged, survive a change of method, and the learner is the calibration section
    ``channel_delays``; a new body forgets them."""
    dev = ZOO["delay_mismatch"]
    cfg = dev.config("water_skin", FS)
    pl = PacketLocalizer("ml", geometry=cfg.geometry, reject_interference=False,
                         resolve_overlaps=False)
    assert pl.calibration_learners()["channel_delays"] is pl.delay_learner
    assert pl.localizer.channel_delays_s is None
    g = np.random.default_rng(12)
    seq = 0
    for _ in range(24):
        pk = render_triggered(_points(cfg.geometry, 64, g, 70.0), cfg,
                              snr_db=g.uniform(25.0, 40.0, 64), rng=g)
        views = []
        for i in range(64):
            # a touch every 25 ms: under the learning's rate limit (DELAY_LEARN_MAX_RATE_HZ)
            views.append(PacketView(pk.samples_v[i], FS, int(pk.onset_index[i]),
                                    seq * 25 * 10**6, seq))
            seq += 1
        for i in range(0, 64, 8):
            pl.process(views[i:i + 8])
    learner = pl.delay_learner
    assert learner.n_packets >= 600
    assert learner.all_converged
    assert np.abs(learner.delays_s - _true_offsets(dev)).max() < 2e-9
    # in use: what the learning call before the last learnt (taken up at the last hand-off)
    assert np.abs(pl.localizer.channel_delays_s - _true_offsets(dev)).max() < 2e-9
    pl.update(min_snr_db=6.0)  # a new localizer: the offsets stay
    np.testing.assert_allclose(pl.localizer.channel_delays_s, learner.applied_delays_s)
    state = learner.calibration_state()
    fresh = PacketLocalizer("ml", geometry=cfg.geometry)
    fresh.calibration_learners()["channel_delays"].load_calibration(state)
    np.testing.assert_allclose(fresh.localizer.channel_delays_s, learner.applied_delays_s)
    geo2 = ZOO["nominal"].config("silicone", FS).geometry
    assert geo2 != cfg.geometry
    pl.update(geometry=geo2)
    assert pl.localizer.channel_delays_s is None and learner.n_packets == 0


def test_a_fast_stream_is_measured_at_the_learning_rate_limit():
    """Emissions at 1,000/s (a grasp's micro-slips) are measured for the channel delays at
    most DELAY_LEARN_MAX_RATE_HZ per second of their stamps, whatever the stride: the
    learning thread's numpy cannot grow with the emission rate."""
    from ae_tactile.pipeline.config import DELAY_LEARN_MAX_RATE_HZ

    cfg = ZOO["delay_mismatch"].config("water_skin", FS)
    pl = PacketLocalizer("ml", geometry=cfg.geometry, reject_interference=False,
                         resolve_overlaps=False)
    g = np.random.default_rng(13)
    pk = render_triggered(_points(cfg.geometry, 400, g, 70.0), cfg, snr_db=35.0, rng=g)
    views = [PacketView(pk.samples_v[i], FS, int(pk.onset_index[i]), i * 10**6, i)
             for i in range(400)]  # 1 ms apart: 0.4 s
    accepted = sum(len(pl.process(views[i:i + 8])) for i in range(0, 400, 8))
    assert accepted > 300, dict(pl.counts)
    limit = 0.4 * DELAY_LEARN_MAX_RATE_HZ + 1
    assert 0.5 * limit <= pl.delay_learner.n_packets <= limit, pl.delay_learner.n_packets
