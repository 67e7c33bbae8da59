# SPDX-License-Identifier: Apache-2.0
"""The channel delays and delay noise a driver has learnt after a while in use, and its
stated front end calibrated: ordinary touches of a device through a `PacketLocalizer` (its
`ChannelDelayLearner`, its `FrontEndLearner`), for benchmarks that measure the driver as it
runs after its first minutes, not only on a fresh pipeline."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ae_tactile.localization.overlap import PulseModel
from ae_tactile.pipeline import PacketLocalizer
from ae_tactile.records import PacketView
from ae_tactile.sim import render_triggered

#: touches a driver has localized before it is measured: what it learns the channel delays
#: from (one in two kept while learning: ~1,000 measured)
DELAY_WARM_TOUCHES = 2000


def cap_points(geo, n, g, max_polar_deg, min_polar_deg=0.0):
    """(n, 3) [m] points uniform by area over the cap between the two polar angles [deg]."""
    cos_t = g.uniform(math.cos(math.radians(max_polar_deg)),
                      math.cos(math.radians(min_polar_deg)), n)
    return geo.surface_point_from_angles(np.arccos(cos_t), g.uniform(0, 2 * math.pi, n))


#: [1] a stated corner's tolerance: components of 5-10 % (`stated_front_end`)
CORNER_TOLERANCE = 0.08


class LearntModel(NamedTuple):
    """What a driver has in use after its warm-up touches (`learnt_channel_model`)."""

    delays_s: np.ndarray | None  # (4,) channel delay offsets [s]; None: none applied
    delay_noise: tuple | None  # (scale, timing sd [s]); None: the model's
    front_end: PulseModel | None  # the calibrated stated front end; None: none trusted


def stated_front_end(cfg, g) -> str:
    """The front end of simulator config ``cfg`` as its maker would state it
    (`PulseModel.from_spec` text): its families and orders, each corner off by up to
    CORNER_TOLERANCE (uniform: the components' tolerance), the emission decay unstated
    (the default 3e3 /s); the body's loss is no part of it (a lossy body's pulse differs
    path by path: its calibration is not trusted and ml's answers stay)."""
    true = PulseModel.from_config(cfg)
    k_hp, k_lp = g.uniform(1 - CORNER_TOLERANCE, 1 + CORNER_TOLERANCE, 2)
    lp = None if true.lowpass_hz is None else true.lowpass_hz * k_lp
    pm = PulseModel(true.highpass_hz * k_hp, true.highpass_order, lp, true.lowpass_order,
                    highpass_rc_hz=tuple(f * k_hp for f in true.highpass_rc_hz),
                    lowpass_family=true.lowpass_family,
                    lowpass_ripple_db=true.lowpass_ripple_db,
                    amplifier_pole_hz=true.amplifier_pole_hz)
    return pm.spec()


def learnt_channel_model(cfg, g, n=DELAY_WARM_TOUCHES, front_end="") -> LearntModel:
    """What a driver's PacketLocalizer has in use after ``n`` ordinary touches of the
    device of simulator config ``cfg`` (polar 0-70 deg, 25-40 dB, one every 25 ms): the
    channel delays and delay noise, and the ``front_end`` it was given (`PulseModel`
    text; '' none) as calibrated on those touches."""
    fs = cfg.sample_rate_hz
    pl = PacketLocalizer("ml", geometry=cfg.geometry, reject_interference=False,
                         resolve_overlaps=False, front_end=front_end)
    for k in range(0, n, 200):
        m = min(200, n - k)
        pk = render_triggered(cap_points(cfg.geometry, m, g, 70.0), cfg,
                              snr_db=g.uniform(25.0, 40.0, m), rng=g)
        # a touch every 25 ms: under the learning's rate limit (DELAY_LEARN_MAX_RATE_HZ)
        views = [PacketView(pk.samples_v[i], fs, int(pk.onset_index[i]), (k + i) * 25 * 10**6,
                            k + i) for i in range(m)]
        for i in range(0, m, 8):
            pl.process(views[i : i + 8])
    lo = pl.localizer
    return LearntModel(lo.channel_delays_s, lo.delay_noise, lo.front_end)
