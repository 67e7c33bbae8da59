# SPDX-License-Identifier: Apache-2.0
"""The channel delays and delay noise a driver has learnt after a while in use: ordinary
touches of a device through a `PacketLocalizer` (its `ChannelDelayLearner`), for
benchmarks that measure the driver as it runs after its first minutes, not only on a fresh
pipeline."""

from __future__ import annotations

import math

import numpy as np

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


def learnt_channel_model(cfg, g, n=DELAY_WARM_TOUCHES):
    """(channel delay offsets [s] (4,) or None (none applied), delay noise (scale, timing
    sd [s]) or None (the model's)): what a driver's PacketLocalizer has in use after ``n``
    ordinary touches of the device of simulator config ``cfg`` (polar 0-70 deg, 25-40 dB,
    one every 25 ms)."""
    fs = cfg.sample_rate_hz
    pl = PacketLocalizer("ml", geometry=cfg.geometry, reject_interference=False,
                         resolve_overlaps=False)
    for k in range(0, n, 200):
        m = min(200, n - k)
        pk = render_triggered(cap_points(cfg.geometry, m, g, 70.0), cfg,
                              snr_db=g.uniform(25.0, 40.0, m), rng=g)
        # a touch every 25 ms: under the learning's rate limit (DELAY_LEARN_MAX_RATE_HZ)
        views = [PacketView(pk.samples_v[i], fs, int(pk.onset_index[i]), (k + i) * 25 * 10**6,
                            k + i) for i in range(m)]
        for i in range(0, m, 8):
            pl.process(views[i : i + 8])
    return pl.localizer.channel_delays_s, pl.localizer.delay_noise
