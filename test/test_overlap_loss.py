# SPDX-License-Identifier: Apache-2.0
"""The medium's power-law loss in the overlap pulse: the filter gives the stated loss,
the learner finds a lossy body's loss from its own single touches, and the device file
keeps it (older files without it load as lossless)."""

import math

import numpy as np

from ae_eval.overlap_trials import _single_touches
from ae_eval.zoo import LOSSY_DB_PER_M, ZOO
from ae_tactile.localization import localize
from ae_tactile.localization.overlap import PulseLearner
from ae_tactile.localization.overlap.pulse import PulseModel, power_law_filter


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


def test_the_learner_finds_a_lossy_bodys_loss_and_the_file_keeps_it():
    cfg = ZOO["lossy"].config("water_skin", 10e6, reflections=True)
    pk = _single_touches(cfg, 24, np.random.default_rng(3))
    learner = PulseLearner(cfg.geometry)
    res = localize(pk.samples_v, cfg.sample_rate_hz, pk.onset_index, geometry=cfg.geometry)
    learner.offer(pk.samples_v, cfg.sample_rate_hz, pk.onset_index, res)
    learner.wait()
    assert learner.converged, learner.state()
    loss = learner.pulse.attenuation_db_per_m_at_1mhz
    assert 0.7 * LOSSY_DB_PER_M < loss < 1.3 * LOSSY_DB_PER_M
    assert 1.0 < learner.pulse.attenuation_exponent < 2.0  # the body's y is 1.5
    state = learner.calibration_state()
    again = PulseLearner(cfg.geometry)
    again.load_calibration(state)
    assert again.pulse.attenuation_db_per_m_at_1mhz == loss
    old = {k: v for k, v in state.items() if not k.startswith("attenuation")}
    again.load_calibration(old)  # a file written before the loss was learnt
    assert again.pulse.attenuation_db_per_m_at_1mhz == 0.0
