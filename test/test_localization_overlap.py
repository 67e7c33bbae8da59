# SPDX-License-Identifier: Apache-2.0
"""Overlapping emissions (`ae_tactile.localization.overlap`): two or three emissions in one
window, each localized; single emissions stay single; wrong answers are rejected, not
accepted; the stated covariances match the actual errors; bad input gives clear errors.

Packets come from the simulator: `simulate_overlaps` (single emissions rendered by
`render_triggered` and summed with exact sub-sample delays: linear acoustics) and, for
an independent path, the simulator's stream renderer, which places several emissions on
one timeline. Every random draw is seeded; thresholds leave margins over the measured
rates (docs/localization.md) so that the tests do not flake.
"""

import numpy as np
import pytest

from ae_eval.crlb import joint_crlb
from ae_eval.overlap_trials import simulate_overlaps
from ae_tactile.dsp import PacketDetector
from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import localize
from ae_tactile.localization import overlap as overlap_mod
from ae_tactile.localization.common import Reason, make_plan
from ae_tactile.localization.overlap import (
    OverlapReason,
    PulseModel,
    calibrate_pulse,
    localize_with_overlaps,
    resolve_overlaps,
    suspect_overlap,
)
from ae_tactile.localization.overlap.model import _Model
from ae_tactile.localization.overlap.search import _grid_search, _segments, _surface_grid
from ae_tactile.localization.segments import prepare
from ae_tactile.sim import SimConfig, noise_rms_for_snr, render_triggered, signal_power_v2
from ae_tactile.sim.frontend import quantize
from ae_tactile.sim.stream import EmissionList, StreamRenderer

WATER = SimConfig(reflections=True)
SILICONE = SimConfig.for_medium("silicone", reflections=True)
FS = WATER.sample_rate_hz
CHI2_2_683 = 2.2957  # 68.3 % quantile of chi^2 with 2 degrees of freedom


def per_truth_errors(truth, sources):
    """For each true point, the distance to the nearest reported source (inf if none)."""
    if not sources:
        return np.full(len(truth), np.inf)
    pts = np.array([s.point_m for s in sources])
    return np.linalg.norm(pts[:, None, :] - truth[None], axis=2).min(axis=0)


def run(d, cfg, **kw):
    return resolve_overlaps(
        d["samples_v"], d["sample_rate_hz"], d["onset_index"], geometry=cfg.geometry, **kw
    )


@pytest.fixture(scope="module")
def pairs():
    """Seeded two-emission windows, 2-10 us apart, strength ratio 1-4, SNR of the weaker
    emission 20-30 dB, water and silicone; and their results."""
    out = {}
    rng = np.random.default_rng(11)
    for name, cfg in (("water", WATER), ("silicone", SILICONE)):
        n = 48
        sep = rng.choice([2e-6, 3.5e-6, 5e-6, 8e-6], n)
        ds = [
            simulate_overlaps(
                n // 3,
                cfg,
                separation_s=sep[i::3],
                amplitude_ratio=r,
                snr_db=rng.uniform(20, 30, n // 3),
                rng=rng,
            )
            for i, r in enumerate((1.0, 2.0, 4.0))
        ]
        res = sum((run(d, cfg) for d in ds), [])
        truth = np.concatenate([d["points_m"] for d in ds])
        out[name] = (ds, res, truth)
    return out


@pytest.mark.parametrize("medium", ["water", "silicone"])
def test_both_points_within_0p1_mm_in_most_pairs(pairs, medium):
    # Target: both points within 0.1 mm in >= 90 % of pairs at separations >= 2 us
    # (measured ~99 %, docs/localization.md); asserted with margin at 85 %.
    ds, res, truth = pairs[medium]
    ok = [
        r.accepted and len(r.sources) == 2 and np.all(per_truth_errors(t, r.sources) <= 0.1e-3)
        for r, t in zip(res, truth)
    ]
    assert np.mean(ok) >= 0.85, np.mean(ok)


@pytest.mark.parametrize("medium", ["water", "silicone"])
def test_sources_carry_polarity_time_and_order(pairs, medium):
    ds, res, truth = pairs[medium]
    pol = np.concatenate([d["polarity"] for d in ds])
    t_emit = np.concatenate([d["emission_time_s"] for d in ds])
    t_arr = np.concatenate([d["arrival_times_s"] for d in ds])
    checked = 0
    for i, r in enumerate(res):
        if not (r.accepted and len(r.sources) == 2):
            continue
        times = [s.emission_time_s for s in r.sources]
        assert times == sorted(times)  # earliest first
        for s in r.sources:
            j = int(np.argmin(np.linalg.norm(truth[i] - s.point_m, axis=1)))
            if np.linalg.norm(truth[i][j] - s.point_m) > 0.1e-3:
                continue
            assert s.polarity == pol[i, j]
            assert abs(s.emission_time_s - t_emit[i, j]) < 50e-9  # 0.5 sample
            np.testing.assert_allclose(s.arrival_times_s, t_arr[i, j], atol=50e-9)
            assert 0.0 < s.confidence <= 1.0
            assert np.all(np.linalg.eigvalsh(s.covariance_m2) >= -1e-18)
            checked += 1
    assert checked >= 0.85 * 2 * len(res)


def test_covariance_is_calibrated(pairs):
    # e^T C^-1 e ~ chi^2(2) for right in-plane covariances: 68.3 % inside 1.515 sigma, mean 2.
    q = []
    for medium in ("water", "silicone"):
        ds, res, truth = pairs[medium]
        for r, t in zip(res, truth):
            for s in r.sources if r.accepted else []:
                e = s.point_m - t[np.argmin(np.linalg.norm(t - s.point_m, axis=1))]
                q.append(e[:2] @ np.linalg.solve(s.covariance_m2[:2, :2], e[:2]))
    q = np.array(q)
    assert len(q) >= 150
    inside = np.mean(q <= CHI2_2_683)
    assert 0.55 <= inside <= 0.85, inside
    assert 1.3 <= np.median(q) / 1.386 * 1.386 <= 2.0 * 1.386, np.median(q)  # chi2(2) median 1.386
    assert 0.9 <= np.median(q) <= 2.1, np.median(q)


def test_no_wrong_accept_with_small_uncertainty_over_a_sweep():
    # Separations 0.3-10 us (below 1.5 us the packet is rejected, not guessed), ratios to 1:4,
    # SNR of the weaker emission 10-30 dB: no reported point 0.5 mm off with sigma < 0.1 mm.
    rng = np.random.default_rng(5)
    bad = []
    for cfg in (WATER, SILICONE):
        for ratio in (1.0, 4.0):
            n = 30
            d = simulate_overlaps(
                n,
                cfg,
                separation_s=rng.uniform(0.3e-6, 10e-6, n),
                amplitude_ratio=ratio,
                snr_db=rng.uniform(10, 30, n),
                rng=rng,
            )
            for r, t in zip(run(d, cfg), d["points_m"]):
                for s in r.sources if r.accepted else []:
                    e = np.linalg.norm(t - s.point_m, axis=1).min()
                    if e > 0.5e-3 and s.sigma_m < 0.1e-3:
                        bad.append((e, s.sigma_m))
                    # and no point is off by more than 6 of its stated sigmas plus 50 um
                    assert e < 6 * s.sigma_m + 50e-6, (e, s.sigma_m)
    assert not bad


def test_single_emissions_stay_single_and_accurate():
    rng = np.random.default_rng(3)
    for cfg in (WATER, SILICONE):
        n = 40
        pts = cfg.geometry.surface_point_from_angles(
            np.arccos(rng.uniform(0.5, 1, n)), rng.uniform(0, 2 * np.pi, n)
        )
        pk = render_triggered(pts, cfg, snr_db=rng.uniform(20, 30, n), rng=rng)
        res = resolve_overlaps(pk.samples_v, FS, pk.onset_index, geometry=cfg.geometry)
        one = [r.accepted and len(r.sources) == 1 for r in res]
        assert np.mean(one) >= 0.95
        assert not any(r.accepted and len(r.sources) > 1 for r in res)
        err = [np.linalg.norm(r.sources[0].point_m - p) for r, p in zip(res, pts) if r.accepted]
        assert np.max(err) < 0.1e-3


def test_three_emissions():
    rng = np.random.default_rng(8)
    d = simulate_overlaps(
        16,
        WATER,
        n_sources=3,
        separation_s=3e-6,
        amplitude_ratio=2.0,
        snr_db=rng.uniform(20, 30, 16),
        rng=rng,
    )
    res = run(d, WATER)
    ok = [
        r.accepted and len(r.sources) == 3 and np.all(per_truth_errors(t, r.sources) <= 0.1e-3)
        for r, t in zip(res, d["points_m"])
    ]
    assert np.mean(ok) >= 0.75
    # with max_sources=2 a three-emission window is not explained: rejected, not guessed
    res2 = run(d, WATER, max_sources=2)
    for r, t in zip(res2, d["points_m"]):
        for s in r.sources if r.accepted else []:
            assert np.linalg.norm(t - s.point_m, axis=1).min() < 6 * s.sigma_m + 50e-6


def test_stream_rendered_pairs_independent_path():
    # The simulator's stream renderer puts two emissions on one timeline (its own
    # superposition, truncation and sample placement); windows cut around the first.
    rng = np.random.default_rng(21)
    geo = WATER.geometry
    ok = 0
    n = 12
    for _ in range(n):
        p = geo.surface_point_from_angles(
            np.arccos(rng.uniform(0.5, 1, 2)), rng.uniform(0, 2 * np.pi, 2)
        )
        if np.linalg.norm(p[0] - p[1]) < 2e-3:
            p[1] = geo.surface_point_from_xy([-p[0, 0]], [-p[0, 1]])[0]
        t0 = 100_000 + int(rng.integers(0, 100))
        sep_ns = int(rng.integers(2000, 9000))
        em = EmissionList.create(
            [t0, t0 + sep_ns],
            p,
            "touch",
            polarity=[1, -1],
            speed_m_s=[0.3, 0.2],
            curvature_1_m=1000.0,
            alpha_1_s=3000.0,
            density_kg_m3=1000.0,
            event_id=[0, 1],
        )
        first = (t0 * 1e-9 + geo.arrival_times_s(p[:1]).min()) * FS
        onset_abs = int(np.ceil(first))
        n0 = onset_abs - 80
        clean = StreamRenderer(WATER).render_clean(em, n0, n0 + 400)[None]
        p_sig = signal_power_v2(clean, np.array([80]), FS)
        sigma = noise_rms_for_snr(p_sig, 25.0)
        x, _ = quantize(clean + sigma[:, None, None] * rng.standard_normal(clean.shape), WATER)
        r = resolve_overlaps(x, FS, 80)[0]
        ok += (
            r.accepted and len(r.sources) == 2 and np.all(per_truth_errors(p, r.sources) <= 0.1e-3)
        )
        if r.accepted:
            times = sorted(s.emission_time_s for s in r.sources)
            assert abs((times[1] - times[0]) - sep_ns * 1e-9) < 50e-9
    assert ok >= n - 1


def test_detector_windows_end_to_end():
    # A stream (the simulator's renderer) with single touches and pairs 2-9 us apart, cut
    # by the packet detector (ae_tactile.dsp), then localize_with_overlaps: singles stay
    # on the fast path, pairs are resolved.

    geo = WATER.geometry
    rng = np.random.default_rng(31)
    times, pts, pol, spd, truth = [], [], [], [], []
    t = 2_000_000  # ns: the detector's noise floor settles first
    for i in range(16):
        p = geo.surface_point_from_angles(
            np.arccos(rng.uniform(0.5, 1, 2)), rng.uniform(0, 2 * np.pi, 2)
        )
        if np.linalg.norm(p[0] - p[1]) < 2e-3:
            p[1] = geo.surface_point_from_xy([-p[0, 0]], [-p[0, 1]])[0]
        k = 2 if i % 2 == 0 else 1
        sep = int(rng.integers(2000, 9000))
        times += [t, t + sep][:k]
        pts += [p[0], p[1]][:k]
        pol += [1, -1][:k]
        spd += [0.3, 0.3 * np.sqrt(rng.uniform(0.25, 1))][:k]
        truth.append((t, p[:k]))
        t += 1_000_000
    em = EmissionList.create(
        np.array(times),
        np.array(pts),
        "touch",
        polarity=pol,
        speed_m_s=spd,
        curvature_1_m=1000.0,
        alpha_1_s=3000.0,
        density_kg_m3=1000.0,
        event_id=np.arange(len(times)),
    )
    x, _ = StreamRenderer(WATER, noise_rms_v=0.7e-3, seed=1).render(em, 0, int(t * 1e-2) + 1000)
    det = PacketDetector()
    batch = det.process(x, 0)
    keep = ~batch.in_hit
    single, overlap = localize_with_overlaps(
        batch.samples[keep],
        batch.sample_rate_hz,
        batch.onset_index[keep],
        saturated=batch.saturated[keep],
    )
    start_ns = batch.start_index[keep] * 100
    hits = {"pair": 0, "single": 0}
    for w in range(int(keep.sum())):
        tp = truth[int(np.argmin([abs(tt - start_ns[w]) for tt, _ in truth]))][1]
        srcs = overlap[w].sources if w in overlap and overlap[w].accepted else []
        for s_ in srcs:
            assert np.linalg.norm(tp - s_.point_m, axis=1).min() < 6 * s_.sigma_m + 50e-6
        if len(tp) == 2:
            assert not single.accepted[w]
            hits["pair"] += len(srcs) == 2 and np.all(per_truth_errors(tp, srcs) <= 0.1e-3)
        elif single.accepted[w] and w not in overlap:
            hits["single"] += np.linalg.norm(tp[0] - single.point_m[w]) <= 0.1e-3
    assert hits["pair"] >= 7 and hits["single"] >= 7, hits


def test_model_reproduces_the_simulator_and_bound_is_below_single_packet_bound():
    # The known-pulse model (front end + Eq. 9 pulse, 1/l spreading, first wall echo)
    # describes the simulator's noise-free windows at the true parameters; the joint
    # bound is never below the bound of each emission alone and tends to it when far apart.
    rng = np.random.default_rng(2)
    for cfg in (WATER, SILICONE):
        for sep in (1e-6, 8e-6):
            d = simulate_overlaps(10, cfg, separation_s=sep, amplitude_ratio=2, snr_db=25, rng=rng)
            b = joint_crlb(
                d["clean_v"],
                FS,
                d["onset_index"],
                d["points_m"],
                d["emission_time_s"],
                d["noise_rms_v"] ** 2,
                geometry=cfg.geometry,
            )
            assert b["model_mismatch"].max() < 1e-5
            assert np.all(b["rms_m"] >= b["single_rms_m"] * (1 - 1e-9))
            if sep == 8e-6:
                assert np.all(b["rms_m"] <= 1.1 * b["single_rms_m"])
            assert np.all((b["rms_m"] > 1e-6) & (b["rms_m"] < 60e-6))


def test_suspect_overlap_flags_late_second_emission_not_singles():
    """Both engines (with numba, "auto" is one compiled call per packet) flag the packets
    whose second emission `localize` missed, almost never a single one, and agree packet
    by packet."""
    rng = np.random.default_rng(4)
    # a second emission 8.5 us later lands at the end of the single-source echo-free segment
    d = simulate_overlaps(
        40, WATER, separation_s=8.5e-6, amplitude_ratio=2, snr_db=rng.uniform(20, 30, 40), rng=rng
    )
    ml = localize(d["samples_v"], FS, d["onset_index"])
    sus = {e: suspect_overlap(d["samples_v"], FS, d["onset_index"], ml, engine=e)
           for e in ("auto", "numpy")}
    np.testing.assert_array_equal(sus["auto"], sus["numpy"])
    assert not np.any(sus["auto"] & ~ml.accepted)
    assert np.all(sus["auto"][ml.accepted])
    # single packets accepted by ml are (almost) never flagged
    n = 100
    pts = WATER.geometry.surface_point_from_angles(
        np.arccos(rng.uniform(0.5, 1, n)), rng.uniform(0, 2 * np.pi, n)
    )
    pk = render_triggered(pts, WATER, snr_db=rng.uniform(15, 30, n), rng=rng)
    ml = localize(pk.samples_v, FS, pk.onset_index)
    sus = {e: suspect_overlap(pk.samples_v, FS, pk.onset_index, ml, engine=e)
           for e in ("auto", "numpy")}
    np.testing.assert_array_equal(sus["auto"], sus["numpy"])
    assert ml.accepted.mean() > 0.95
    assert sus["auto"].mean() <= 0.03
    # and with a given noise sigma (then the limit has no pre-onset term)
    nr = np.full(n, np.nan)
    nr[: n // 2] = pk.noise_rms_v[: n // 2] if np.ndim(pk.noise_rms_v) else pk.noise_rms_v
    sus = {e: suspect_overlap(pk.samples_v, FS, pk.onset_index, ml, noise_rms_v=nr, engine=e)
           for e in ("auto", "numpy")}
    np.testing.assert_array_equal(sus["auto"], sus["numpy"])
    assert sus["auto"].mean() <= 0.03


def test_pulse_mismatch_is_rejected_not_guessed():
    # Data whose front end differs from the model (high-pass 90 kHz, model 100 kHz): the
    # residual test rejects rather than report wrong points.
    rng = np.random.default_rng(6)
    cfg = WATER.replace(highpass_hz=80e3)
    d = simulate_overlaps(20, cfg, separation_s=4e-6, amplitude_ratio=2, snr_db=25, rng=rng)
    for r, t in zip(run(d, cfg, pulse=PulseModel()), d["points_m"]):
        for s in r.sources if r.accepted else []:
            assert np.linalg.norm(t - s.point_m, axis=1).min() < 6 * s.sigma_m + 50e-6


def test_lossy_medium_needs_and_takes_its_loss_in_the_model():
    # Silicone with attenuation: each path's pulse depends on its length. With the medium's
    # loss in the model (PulseModel.from_config) the pairs resolve; without it they are
    # rejected by the residual test, never reported wrong.
    cfg = SimConfig.for_medium("silicone", reflections=True, attenuation=True)
    rng = np.random.default_rng(14)
    d = simulate_overlaps(
        16, cfg, separation_s=rng.uniform(2e-6, 10e-6, 16), amplitude_ratio=2, snr_db=25, rng=rng
    )
    lossy = PulseModel.from_config(cfg)
    assert lossy.attenuation_db_per_m_at_1mhz == pytest.approx(200.0)
    b = joint_crlb(
        d["clean_v"],
        FS,
        d["onset_index"],
        d["points_m"],
        d["emission_time_s"],
        d["noise_rms_v"] ** 2,
        geometry=cfg.geometry,
        pulse=lossy,
    )
    assert b["model_mismatch"].max() < 1e-5
    ok = [
        r.accepted and len(r.sources) == 2 and np.all(per_truth_errors(t, r.sources) <= 0.1e-3)
        for r, t in zip(run(d, cfg, pulse=lossy), d["points_m"])
    ]
    assert np.mean(ok) >= 0.85
    for r, t in zip(run(d, cfg), d["points_m"]):
        for s in r.sources if r.accepted else []:
            assert np.linalg.norm(t - s.point_m, axis=1).min() < 6 * s.sigma_m + 50e-6


def test_calibrate_pulse_recovers_the_front_end_from_single_touches():
    # The data's high-pass corner is 90 kHz, the default model's 100 kHz: calibration on
    # single touches finds the corners, and overlapping pairs then resolve.

    cfg = WATER.replace(highpass_hz=90e3)
    rng = np.random.default_rng(15)
    n = 30
    pts = cfg.geometry.surface_point_from_angles(
        np.arccos(rng.uniform(0.5, 1, n)), rng.uniform(0, 2 * np.pi, n)
    )
    pk = render_triggered(pts, cfg, snr_db=30, rng=rng)
    pm = calibrate_pulse(pk.samples_v, FS, pk.onset_index)
    assert pm.highpass_hz == pytest.approx(90e3, rel=0.02)
    assert pm.lowpass_hz == pytest.approx(1e6, rel=0.03)
    d = simulate_overlaps(8, cfg, separation_s=4e-6, amplitude_ratio=2, snr_db=25, rng=rng)
    ok = [
        r.accepted and len(r.sources) == 2 and np.all(per_truth_errors(t, r.sources) <= 0.1e-3)
        for r, t in zip(run(d, cfg, pulse=pm), d["points_m"])
    ]
    assert np.mean(ok) >= 0.75
    with pytest.raises(ValueError, match="single-emission"):
        calibrate_pulse(np.zeros((2, 4, 400)), FS, [80, 80])


@pytest.mark.parametrize("fs", [2e6, 5e6])
def test_other_sample_rate(fs):
    # The default pulse model follows the sample rate like the front end does (at 2 MS/s
    # its anti-alias filter): measured 19 / 20 pairs resolved at 2 MS/s, 20 / 20 at 5 MS/s;
    # a 1 MHz model at 2 MS/s rejects every pair (safe, but none resolved).
    cfg = SimConfig(reflections=True, sample_rate_hz=fs)
    rng = np.random.default_rng(16)
    d = simulate_overlaps(20, cfg, separation_s=4e-6, amplitude_ratio=2, snr_db=25, rng=rng)
    res = resolve_overlaps(d["samples_v"], fs, d["onset_index"])
    ok = [
        r.accepted and len(r.sources) == 2 and np.all(per_truth_errors(t, r.sources) <= 0.1e-3)
        for r, t in zip(res, d["points_m"])
    ]
    wrong = [
        r.accepted and np.any(per_truth_errors(t, r.sources) > 0.5e-3)
        for r, t in zip(res, d["points_m"])
    ]
    assert np.mean(ok) >= 0.8 and not any(wrong)
    assert PulseModel.for_sample_rate(fs) == PulseModel.from_config(cfg)


def test_input_problems_are_rejections_with_reasons():
    rng = np.random.default_rng(9)
    d = simulate_overlaps(6, WATER, separation_s=4e-6, snr_db=25, rng=rng)
    x = d["samples_v"].copy()
    on = d["onset_index"].copy()
    x[0, 1, 100] = np.nan  # non-finite sample
    x[1] = 0.0  # all-zero window
    x[2, 3] = 0.25  # dead (constant) channel
    on[3] = 10_000  # onset outside the window
    noise = np.random.default_rng(1).normal(0, 1e-3, (1, 4, 400))
    res = resolve_overlaps(x, FS, on)
    assert res[0].reason == OverlapReason.NONFINITE and not res[0].accepted
    assert res[1].reason == OverlapReason.NO_SIGNAL
    assert res[2].reason == OverlapReason.NO_SIGNAL
    assert res[3].reason == OverlapReason.WINDOW
    assert res[4].accepted and res[5].accepted
    sat = resolve_overlaps(x[4:5], FS, on[4:5], saturated=[True])[0]
    assert sat.reason == OverlapReason.SATURATED and sat.reason_name == "SATURATED"
    # noise only: nothing to report
    r = resolve_overlaps(noise, FS, 80)[0]
    assert not r.accepted and r.sources == []
    assert resolve_overlaps(np.zeros((0, 4, 400)), FS, np.zeros(0, int)) == []


def test_bad_parameters_raise_clear_errors():
    x = np.zeros((2, 4, 400))
    with pytest.raises(ValueError, match="shape"):
        resolve_overlaps(np.zeros((2, 3, 400)), FS, [80, 80])
    with pytest.raises(ValueError, match="onset_index"):
        resolve_overlaps(x, FS, [80, 80, 80])
    with pytest.raises(ValueError, match="sample_rate_hz"):
        resolve_overlaps(x, -1.0, [80, 80])
    with pytest.raises(ValueError, match="max_sources"):
        resolve_overlaps(x, FS, [80, 80], max_sources=4)
    with pytest.raises(ValueError, match="max_sigma_m"):
        resolve_overlaps(x, FS, [80, 80], max_sigma_m=0.0)
    with pytest.raises(TypeError, match="geometry"):
        resolve_overlaps(x, FS, [80, 80], geometry="tip")
    with pytest.raises(TypeError, match="pulse"):
        resolve_overlaps(x, FS, [80, 80], pulse=(100e3, 1e6))
    with pytest.raises(ValueError, match="engine"):
        resolve_overlaps(x, FS, [80, 80], engine="fortran")
    with pytest.raises(TypeError):
        resolve_overlaps(np.full((1, 4, 400), "a"), FS, [80])
    with pytest.raises(ValueError, match="single_source_result"):
        ml = localize(np.random.default_rng(0).normal(size=(3, 4, 400)), FS, [80, 80, 80])
        suspect_overlap(x, FS, [80, 80], ml)


def test_localize_with_overlaps_routes_only_what_needs_it():

    rng = np.random.default_rng(12)
    n = 20
    pts = WATER.geometry.surface_point_from_angles(
        np.arccos(rng.uniform(0.5, 1, n)), rng.uniform(0, 2 * np.pi, n)
    )
    singles = render_triggered(pts, WATER, snr_db=25, rng=rng)
    d = simulate_overlaps(6, WATER, separation_s=4e-6, amplitude_ratio=2, snr_db=25, rng=rng)
    x = np.concatenate([singles.samples_v, d["samples_v"]])
    on = np.concatenate([singles.onset_index, d["onset_index"]])
    single, overlap = localize_with_overlaps(x, FS, on)
    assert single.accepted[:n].all() and not single.accepted[n:].any()
    assert set(overlap) == set(range(n, n + 6))  # only the pairs took the slow path
    assert np.all(single.reason[n:] == 6)  # OVERLAP
    err = np.linalg.norm(single.point_m[:n] - pts, axis=1)
    assert err.max() < 0.1e-3
    for i, r in overlap.items():
        assert r.accepted and len(r.sources) == 2
        assert np.all(per_truth_errors(d["points_m"][i - n], r.sources) <= 0.1e-3)


needs_numba = pytest.mark.skipif(
    not overlap_mod._kernels.NUMBA_AVAILABLE,
    reason="numba absent (or AE_TACTILE_NO_NUMBA=1): only the numpy path exists to test",
)


@needs_numba
def test_compiled_and_numpy_fits_agree():
    """The compiled kernels (`overlap_kernels`) and the numpy path give the same answer on
    two- and three-emission windows, down to separations where several optima compete
    (1-2 us), at low and high SNR, with the same decisions (accepted, reason, order)."""
    rng = np.random.default_rng(5)
    ds = [
        simulate_overlaps(
            24, WATER, separation_s=rng.uniform(1e-6, 9e-6, 24), amplitude_ratio=3.0,
            snr_db=rng.uniform(12, 35, 24), rng=rng,
        ),
        simulate_overlaps(
            6, SILICONE, n_sources=3, separation_s=3e-6, amplitude_ratio=2.0, snr_db=30.0,
            rng=rng,
        ),
    ]
    n_two = 0
    for d, cfg in zip(ds, (WATER, SILICONE)):
        a = run(d, cfg, engine="numpy")
        b = run(d, cfg, engine="auto")
        for ra, rb in zip(a, b):
            assert (ra.accepted, ra.reason, ra.n_fitted, ra.n_dropped) == (
                rb.accepted, rb.reason, rb.n_fitted, rb.n_dropped
            )
            assert rb.chi2_ratio == pytest.approx(ra.chi2_ratio, rel=1e-6)
            assert len(ra.sources) == len(rb.sources)
            n_two += len(rb.sources) >= 2
            for sa, sb in zip(ra.sources, rb.sources):
                np.testing.assert_allclose(sb.point_m, sa.point_m, rtol=0, atol=1e-9)
                np.testing.assert_allclose(sb.emission_time_s, sa.emission_time_s, atol=1e-13)
                np.testing.assert_allclose(
                    sb.covariance_m2, sa.covariance_m2, rtol=1e-5, atol=1e-18
                )
                assert sb.polarity == sa.polarity
    assert n_two >= 20  # the comparison covers real two-emission answers


@needs_numba
def test_compiled_quick_answer_is_the_numpy_quick_answer():
    """The driver's quick answer (exhaustive=False) is computed by compiled kernels from
    the raw window on (preparation, segment, search); the numpy engine computes it step by
    step. Same decisions and reasons (DEFERRED included), points and covariances to
    rounding, on one, two and three emissions (deferred), on windows every check must reject
    (non-finite, flagged saturation, clipped at a given full scale, flat, onset at the
    end), with measured and with given noise; the same errors for bad arguments."""
    rng = np.random.default_rng(21)
    two = simulate_overlaps(
        12, WATER, separation_s=rng.uniform(1e-6, 8e-6, 12), amplitude_ratio=2.0,
        snr_db=rng.uniform(15, 35, 12), rng=rng,
    )
    three = simulate_overlaps(4, WATER, n_sources=3, separation_s=3e-6, snr_db=30.0, rng=rng)
    geo = WATER.geometry
    n = two["samples_v"].shape[2]
    pts = geo.surface_point_from_angles(rng.uniform(0.1, 1.0, 4), rng.uniform(0, 6.28, 4))
    one = [_window_from_model(geo, [p], [0.0], [1e-2], 1e-4, rng, n) for p in pts]
    x = np.concatenate([two["samples_v"], three["samples_v"], [w for w, _ in one]])
    on = np.concatenate([two["onset_index"], three["onset_index"], [o for _, o in one]])
    n_good = len(x)
    bad = x[:5].copy()
    bad[0, 2, 150] = np.nan
    bad[2, :, :] = 0.25  # flat: no signal
    bad_on = on[:5].copy()
    bad_on[3] = x.shape[2] - 2  # onset at the window's end
    x = np.concatenate([x, bad])
    on = np.concatenate([on, bad_on])
    sat = np.zeros(len(x), bool)
    sat[n_good + 1] = True  # flagged upstream
    cases = [
        {"saturated": sat},
        {"noise_rms_v": np.concatenate([two["noise_rms_v"], three["noise_rms_v"],
                                        np.full(4, 1e-4), np.full(5, np.nan)])},
        {"full_scale_v": float(np.abs(x[n_good + 4]).max()) * 0.5},
    ]
    decided = set()
    for kw in cases:
        a = resolve_overlaps(x, FS, on, geometry=WATER.geometry, exhaustive=False,
                             engine="numpy", **kw)
        b = resolve_overlaps(x, FS, on, geometry=WATER.geometry, exhaustive=False, **kw)
        for ra, rb in zip(a, b):
            assert (ra.accepted, ra.reason, ra.n_fitted, ra.n_dropped) == (
                rb.accepted, rb.reason, rb.n_fitted, rb.n_dropped
            )
            decided.add((rb.accepted, int(rb.reason), rb.n_fitted))
            assert rb.noise_rms_v == pytest.approx(ra.noise_rms_v, rel=1e-9)
            if np.isfinite(ra.chi2_ratio):
                assert rb.chi2_ratio == pytest.approx(ra.chi2_ratio, rel=1e-6)
            assert len(ra.sources) == len(rb.sources)
            for sa, sb in zip(ra.sources, rb.sources):
                np.testing.assert_allclose(sb.point_m, sa.point_m, rtol=0, atol=1e-9)
                np.testing.assert_allclose(sb.emission_time_s, sa.emission_time_s, atol=1e-13)
                np.testing.assert_allclose(
                    sb.covariance_m2, sa.covariance_m2, rtol=1e-5, atol=1e-18
                )
                assert (sb.polarity, sb.snr_db) == pytest.approx((sa.polarity, sa.snr_db))
        # the bad windows are rejected for what is wrong with them
        reasons = [int(r.reason) for r in b[n_good:]]
        assert reasons[0] == Reason.NONFINITE and reasons[2] == Reason.NO_SIGNAL
        assert reasons[3] == Reason.WINDOW
        if "saturated" in kw:
            assert reasons[1] == Reason.SATURATED
        if "full_scale_v" in kw:
            assert reasons[4] == Reason.SATURATED
    # the comparison covered accepted one- and two-emission answers and deferrals (three
    # emissions leave more than noise after the joint fit of two: the worker's to search)
    assert {(True, 0, 1), (True, 0, 2)} <= decided
    assert any(r == OverlapReason.DEFERRED for _, r, _ in decided)
    for kw in ({"full_scale_v": -1.0}, {"saturated": np.zeros(3, bool)},
               {"noise_rms_v": np.ones(2)}):
        for engine in ("numpy", "auto"):
            with pytest.raises(ValueError):
                resolve_overlaps(x, FS, on, exhaustive=False, engine=engine, **kw)


@needs_numba
def test_compiled_grid_search_is_the_numpy_grid_search():
    """The matched-filter grid (float32, same order of operations) picks the same points
    and times, with the same statistic, as the numpy path."""
    d = simulate_overlaps(8, WATER, separation_s=4e-6, snr_db=25.0, rng=2)
    geo = WATER.geometry

    plan = make_plan(FS, geo, d["samples_v"].shape[2], (100e3, 1e6))
    prep = prepare(d["samples_v"], d["onset_index"], plan)
    seg, start, length, inside = _segments(prep, plan, geo, FS, None)
    pulse = PulseModel.for_sample_rate(FS)
    grid = _surface_grid(geo, 1e-3)
    out = {}
    for engine in ("numpy", "auto"):
        model = _Model(geo, FS, start, length, pulse, True, inside, engine)
        out[engine] = _grid_search(model, seg, grid, n_peaks=3)
    np.testing.assert_array_equal(out["auto"][0], out["numpy"][0])
    np.testing.assert_array_equal(out["auto"][1], out["numpy"][1])
    # and it finds an emission: the best point is within 1.5 mm of one of the true points
    best = out["auto"][0][:, 0, :2]
    dist = np.linalg.norm(d["points_m"][:, :, :2] - best[:, None, :], axis=2).min(axis=1)
    assert np.median(dist) < 1.5e-3


def test_warm_up_resolves_its_two_emissions():
    """The driver's warm-up window (two emissions 4 us apart) takes the two-emission path
    the first real overlap takes, and its points come out where they were put."""

    geo = FingertipGeometry()
    res = overlap_mod.warm_up(geo, FS, 400)
    truth = geo.surface_point_from_angles(np.array([0.35, 0.3]), np.array([0.4, 3.5]))
    assert res.accepted and res.n_fitted == 2
    assert per_truth_errors(truth, res.sources).max() < 0.05e-3
    assert [s.polarity for s in res.sources] == [1, -1]


def _window_from_model(geo, points_m, delays_s, amplitudes_v, noise_v, rng, n=400):
    """A window of direct waves A (R / d) h(t - T - d / c) (the resolver's own pulse model)
    plus white noise; the earliest arrival at sample n // 4."""
    pulse = PulseModel.for_sample_rate(FS)
    tt = geo.arrival_times_s(np.asarray(points_m, float))
    gain = geo.radius_m / (tt * geo.sound_speed_m_s)
    on = n // 4
    t0 = on / FS - (tt + np.asarray(delays_s)[:, None]).min()
    t = np.arange(n) / FS
    x = rng.normal(0.0, noise_v, (4, n))
    for j in range(len(points_m)):
        x += amplitudes_v[j] * gain[j][:, None] * pulse.waveform(
            t[None, :] - t0 - delays_s[j] - tt[j][:, None]
        )
    return x, on


def test_joint_fit_is_stable_on_degenerate_windows():
    """Hard cases for the joint fit (nearly singular normal equations, huge dynamic range,
    no second emission, a point at the cap's edge): no exception, no non-finite output, the
    physically right answer, and (with numba) the same decision and points from both
    paths."""

    geo = FingertipGeometry()
    rng = np.random.default_rng(8)
    apex = geo.surface_point_from_angles(np.array([0.2]), np.array([1.0]))[0]
    edge = geo.surface_point_from_angles(np.array([np.radians(80.0)]), np.array([2.0]))[0]
    other = geo.surface_point_from_angles(np.array([0.4]), np.array([4.0]))[0]
    cases = {
        "same point 0.3 us apart": ([apex, apex], [0.0, 0.3e-6], [1e-2, 1e-2]),
        "same time, two points": ([apex, other], [0.0, 0.0], [1e-2, -1e-2]),
        "ratio 1:1000": ([apex, other], [0.0, 3e-6], [1e-2, 1e-5]),
        "one emission at the edge": ([edge], [0.0], [1e-2]),
        "edge and apex": ([edge, apex], [0.0, 2e-6], [1e-2, 5e-3]),
    }
    for name, (pts, dt, amp) in cases.items():
        x, on = _window_from_model(geo, pts, dt, amp, 1e-4, rng)
        a = resolve_overlaps(x, FS, [on], geometry=geo, engine="numpy")[0]
        b = resolve_overlaps(x, FS, [on], geometry=geo, engine="auto")[0]
        assert (a.accepted, a.reason, a.n_fitted) == (b.accepted, b.reason, b.n_fitted), name
        assert np.isfinite(a.chi2_ratio), name
        assert np.isfinite(b.chi2_ratio), name
        for sa, sb in zip(a.sources, b.sources):
            assert np.all(np.isfinite(sb.point_m)) and np.all(np.isfinite(sb.covariance_m2))
            np.testing.assert_allclose(sb.point_m, sa.point_m, rtol=0, atol=1e-8, err_msg=name)
        # what the physics allows: emissions that cannot be told apart are rejected, not
        # guessed; one 60 dB below the noise is not there; the others come out right
        if name in ("same point 0.3 us apart", "same time, two points"):
            assert not b.accepted and b.reason == OverlapReason.UNRESOLVED, name
        else:
            expect = [pts[0]] if name == "ratio 1:1000" else pts
            assert b.accepted and len(b.sources) == len(expect), name
            assert per_truth_errors(np.array(expect), b.sources).max() < 0.1e-3, name


def test_quick_search_answers_or_defers_never_differs():
    """exhaustive=False (the driver resolver's quick answer): a window whose first joint
    fit leaves more than noise is DEFERRED, every other answer is the exhaustive one (to
    rounding: with numba the quick path prepares the window with the compiled kernel)."""
    d = simulate_overlaps(
        24, WATER, separation_s=np.array([1e-6, 1.5e-6, 2e-6] * 8), amplitude_ratio=1.0,
        snr_db=30.0, rng=4,
    )
    full = run(d, WATER)
    quick = run(d, WATER, exhaustive=False)
    deferred = 0
    for f, q in zip(full, quick):
        if q.reason == OverlapReason.DEFERRED:
            deferred += 1
            assert not q.accepted and not q.sources
            continue
        assert (q.accepted, q.reason, q.n_fitted) == (f.accepted, f.reason, f.n_fitted)
        for a, b in zip(f.sources, q.sources):
            np.testing.assert_allclose(b.point_m, a.point_m, rtol=0, atol=1e-12)
    assert 0 < deferred < len(quick) // 2  # hard windows only
