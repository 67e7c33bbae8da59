# SPDX-License-Identifier: Apache-2.0
"""The medium's power-law loss in the overlap pulse: the filter gives the stated loss,
the learner finds a lossy body's loss from its own single touches, and the device file
keeps it (older files without it load as lossless)."""

import math

import numpy as np
import pytest

from ae_eval.overlap_trials import _single_touches, simulate_overlaps
from ae_eval.zoo import LOSSY_DB_PER_M, ZOO
from ae_tactile.localization import localize
from ae_tactile.localization.overlap import PulseLearner, resolve_overlaps
from ae_tactile.localization.overlap.decide import _source_energy
from ae_tactile.localization.overlap.loss import _keep_loss
from ae_tactile.localization.overlap.model import _lm, _Model
from ae_tactile.localization.overlap.pulse import PulseModel, power_law_filter
from ae_tactile.localization.overlap.search import _Fit


def test_power_law_filter_gives_the_stated_loss_at_1_mhz():
    fs, n = 20e6, 4000
    t = np.arange(n) / fs
    tone = np.sin(2 * math.pi * 1e6 * t)  # 200 whole periods in the window
    for y in (1.2, 1.5, 1.8):
        pulse = PulseModel(attenuation_db_per_m_at_1mhz=300.0, attenuation_exponent=y)
        out = power_law_filter(tone, np.asarray(0.02), fs, pulse)
        mid = slice(n // 4, n // 2)  # away from the window's start (the filter's onset)
        loss_db = 20 * math.log10(np.std(tone[mid]) / np.std(out[mid]))
        assert abs(loss_db - 300.0 * 0.02) < 0.05  # att l at 1 MHz, whatever y


@pytest.fixture(scope="module")
def lossy_learner():
    """A pulse learner fed 24 single touches of the lossy zoo device (30 dB)."""
    cfg = ZOO["lossy"].config("water_skin", 10e6, reflections=True)
    pk = _single_touches(cfg, 24, np.random.default_rng(3))
    learner = PulseLearner(cfg.geometry)
    res = localize(pk.samples_v, cfg.sample_rate_hz, pk.onset_index, geometry=cfg.geometry)
    learner.offer(pk.samples_v, cfg.sample_rate_hz, pk.onset_index, res)
    learner.wait()
    return cfg, learner


def test_the_learner_finds_a_lossy_bodys_loss_and_the_file_keeps_it(lossy_learner):
    cfg, learner = lossy_learner
    assert learner.converged, learner.state()
    loss = learner.pulse.attenuation_db_per_m_at_1mhz
    assert 0.7 * LOSSY_DB_PER_M < loss < 1.3 * LOSSY_DB_PER_M
    assert 1.0 < learner.pulse.attenuation_exponent < 2.0  # the body's y is 1.5
    state = learner.calibration_state()
    again = PulseLearner(cfg.geometry)
    again.load_calibration(state)
    assert again.pulse.attenuation_db_per_m_at_1mhz == loss
    assert again.pulse.misfit_share == learner.pulse.misfit_share > 0
    old = {k: v for k, v in state.items()
           if not k.startswith(("attenuation", "misfit"))}
    again.load_calibration(old)  # a file written before the loss was learnt
    assert again.pulse.attenuation_db_per_m_at_1mhz == 0.0
    assert again.pulse.misfit_share == 0.0


def _lossy_pairs(lossy_learner, n, seed):
    """(`simulate_overlaps` record, `resolve_overlaps` answers) of ``n`` pairs on the lossy
    body (2-10 us apart, 1:2, 25 dB on the weaker) with its learnt pulse."""
    cfg, learner = lossy_learner
    rng = np.random.default_rng(seed)
    d = simulate_overlaps(n, cfg, separation_s=rng.uniform(2e-6, 10e-6, n),
                          amplitude_ratio=2.0, snr_db=25.0, rng=rng)
    return d, resolve_overlaps(d["samples_v"], cfg.sample_rate_hz, d["onset_index"],
                               geometry=cfg.geometry, pulse=learner.pulse, exhaustive=True)


def test_no_wrong_point_on_a_lossy_body_once_its_pulse_is_learnt(lossy_learner):
    """Pairs on the lossy body (2-10 us apart, 1:2, 25 dB on the weaker), resolved with its
    learnt pulse: no point handed out lies farther than 0.5 mm from both true emissions
    (the simulator's truth), and a window giving fewer than two points says why (a
    rejection, or emissions dropped or refused, counted)."""
    d, out = _lossy_pairs(lossy_learner, 10, 21)
    for i, r in enumerate(out):
        pts = np.array([s.point_m for s in r.sources]).reshape(-1, 3)
        err = np.linalg.norm(pts[:, None, :] - d["points_m"][i][None], axis=2)
        assert (err.min(axis=1) <= 0.5e-3).all(), (i, err.min(axis=1))
        if len(pts) < 2:
            assert not r.accepted or r.n_dropped or r.n_refused, i


def test_pairs_on_a_lossy_body_resolved_within_the_pulses_own_misfit(lossy_learner):
    """The same kind of pairs resolved: both emissions within 0.1 mm of the truth in >= 90 %
    of 20 (issue 37's target). A learnt pulse leaves its own misfit on every emission
    (the body's loss and dispersion are learnt approximately), 2-15x a single touch's
    share on an overlapping pair: the residual test allows it (the allowance the model
    order grants a spurious emission); with the noise's chi^2 limit alone ~30 % of such
    pairs were rejected."""
    d, out = _lossy_pairs(lossy_learner, 20, 37)
    ok = 0
    for i, r in enumerate(out):
        pts = np.array([s.point_m for s in r.sources]).reshape(-1, 3)
        if len(pts) >= 2:
            err = np.linalg.norm(pts[:, None, :] - d["points_m"][i][None], axis=2)
            ok += bool((err.min(axis=0) <= 0.1e-3).all() and (err.min(axis=1) <= 0.1e-3).all())
    assert ok >= 18, ok


def test_the_loss_is_kept_only_where_it_clearly_lowers_the_misfit():
    """Model selection (`loss._keep_loss`): chi^2 ratios of the candidates under the
    lossless pulse and under the pulse with a loss, limit 1.2 each."""
    lim = np.full(24, 1.2)
    body = np.full(24, 2.6)  # a lossy body: no common pulse explains the packets
    assert _keep_loss(body, lim, np.full(24, 1.05), lim)
    front = np.full(24, 1.10)  # a front-end error the loss could stand in for
    assert not _keep_loss(front, lim, np.full(24, 1.07), lim)  # 30 % of the excess: no
    assert _keep_loss(front, lim, np.full(24, 1.04), lim)  # 60 % of it: a clear drop
    lossless = np.where(np.arange(24) < 4, 1.5, 1.1)  # 20 pass the residual test
    fewer = np.where(np.arange(24) < 7, 1.5, 1.0)  # no excess left, but only 17 pass
    assert not _keep_loss(lossless, lim, fewer, lim)
    bad = np.full(24, 1.01)
    bad[0] = np.nan
    assert not _keep_loss(body, lim, bad, lim)  # a failed fit is never kept


def test_source_energy_is_each_emissions_waves_alone():
    """`decide._source_energy` (the amplitude block of the fit's Gram matrix) is the energy
    of each emission's direct wave and echo rendered alone by the model."""
    cfg = ZOO["nominal"].config("water_skin", 10e6, reflections=True)
    geo, fs, L = cfg.geometry, cfg.sample_rate_hz, 240
    pulse = PulseModel.for_sample_rate(fs)
    model = _Model(geo, fs, np.zeros(1), L, pulse, True)
    theta = np.array([[[1.0e-3, -2.0e-3, 2e-6], [-3.0e-3, 1.0e-3, 6e-6]]])
    amp = np.array([[0.8, 0.3, -0.5, 0.2]])
    y = model.evaluate(theta)[0][0].T @ amp[0] + 1e-3 * np.sin(np.arange(4 * L))
    th, a, rss, gram = _lm(model, y[None], theta.copy(), iterations=0)
    fit = _Fit(th, a, rss, gram)
    phi = model.evaluate(th)[0][0]  # (4, 4L): direct, echo of each emission
    for q in range(2):
        wave = a[0, 2 * q] * phi[2 * q] + a[0, 2 * q + 1] * phi[2 * q + 1]
        assert math.isclose(_source_energy(fit, 2)[0, q], float(wave @ wave), rel_tol=1e-9)
