# SPDX-License-Identifier: Apache-2.0
"""Everyday scenes on a zoo device: the 'waveform' pipeline beside the 'events' one.

`ae_eval.everyday`'s 'events' pipeline draws each localized emission from a Gaussian error
model. Here every emission of the same truth is rendered as one triggered packet on the
DEVICE (`ae_eval.zoo.Device.config`: its front end, noise colour, mismatch, medium; the
emission's relative amplitude sets its SNR against ``snr_ref_db``) and localized by the
driver's own `PacketLocalizer` with its screens (after the device's warm-up: 300 ordinary
touches it learns the device from), in 1 ms read cycles; what it keeps goes to
the slip detector as the driver's slip stage feeds it. So a device whose front end makes
the screens drop apex touches, or whose covariance is wrong, shows in the slip figures.
Emissions closer than a packet are not overlapped here (bench_zoo's overlap figure).
"""

from __future__ import annotations

import math

import numpy as np

from ae_eval.everyday.score import NS, score_trial
from ae_eval.everyday.summary import TICK_S
from ae_eval.slip import run_detector
from ae_tactile.pipeline import PacketLocalizer
from ae_tactile.records import EventType, PacketView
from ae_tactile.sim import render_triggered
from ae_tactile.sim.scene import reference_noise_rms
from ae_tactile.slip import LocalizedEvent

READ_CYCLE_NS = 1_000_000  # [ns] the driver's read cycle
WARM_TOUCHES = 300  # ordinary touches a device's localizer has seen before a trial
_WARM: dict = {}  # (device, medium, rate) -> its localizer after the warm-up (a device in use)
SNR_REF_DB = 30.0  # [dB] of an emission of relative amplitude 1 (a touch)
MIN_REL_AMP = 1e-3  # relative amplitudes below this are rendered at this level


def warm_localizer(device, cfg, medium):
    """The device's `PacketLocalizer` after WARM_TOUCHES ordinary touches (polar 0-60 deg,
    20-40 dB, both polarities, over 30 s, batches of 10 with the learning the driver does
    when idle): what it has learnt of the device by then. One per device, reused."""
    key = (device.name, medium, cfg.sample_rate_hz)
    if key not in _WARM:
        g = np.random.default_rng([38300, sum(map(ord, device.name))])
        loc = PacketLocalizer("ml", geometry=cfg.geometry)
        cos_t = g.uniform(math.cos(math.radians(60.0)), 1.0, WARM_TOUCHES)
        pts = cfg.geometry.surface_point_from_angles(np.arccos(cos_t),
                                                     g.uniform(0, 2 * math.pi, WARM_TOUCHES))
        pk = render_triggered(pts, cfg, snr_db=g.uniform(20.0, 40.0, WARM_TOUCHES),
                              polarity=g.choice([-1, 1], WARM_TOUCHES), rng=g)
        t_ns = np.sort(g.integers(0, 30 * NS, WARM_TOUCHES))
        fs = cfg.sample_rate_hz
        views = [PacketView(pk.samples_v[i], fs, int(pk.onset_index[i]), int(t_ns[i]),
                            10**6 + i) for i in range(WARM_TOUCHES)]
        for k in range(0, WARM_TOUCHES, 10):
            loc.process(views[k : k + 10])
            loc.learn_echo()
        _WARM[key] = loc
    return _WARM[key]


def device_events(scene, device, rng, *, snr_ref_db=SNR_REF_DB, medium="water_skin",
                  sample_rate_hz=10e6, warm=True):
    """The slip detector's input for one scene on one device.

    Parameters
    ----------
    scene : ae_eval.everyday.truth.Scene
    device : ae_eval.zoo.Device
    rng : numpy.random.Generator
    snr_ref_db : float
        SNR [dB] of a relative amplitude of 1.
    medium : str
    sample_rate_hz : float
    warm : bool
        The device's localizer after its warm-up (`warm_localizer`: a device in use), or
        a fresh one (a device's first touches).

    Returns
    -------
    (list of LocalizedEvent, dict)
        The events in time order (packet_id = the emission's index in the truth) and the
        localizer's counters.
    """
    n = scene.t_s.size
    cfg = device.config(medium, sample_rate_hz)
    loc = warm_localizer(device, cfg, medium) if warm else PacketLocalizer(
        "ml", geometry=cfg.geometry)
    loc.counts.clear()
    if n == 0:
        return [], dict(loc.counts)
    pts = cfg.geometry.surface_point_from_xy(scene.xy_m[:, 0], scene.xy_m[:, 1])
    amp = np.maximum(np.abs(scene.amplitude), MIN_REL_AMP)
    noise = reference_noise_rms(cfg, snr_ref_db) / amp  # the noise is fixed: weaker, lower SNR
    # render at unit amplitude with the noise scaled (same SNR), then scale back to volts
    pk = render_triggered(pts, cfg, noise_rms_v=noise, polarity=scene.polarity, rng=rng)
    fs = cfg.sample_rate_hz
    samples = pk.samples_v * amp[:, None, None]
    t_ns = np.round(scene.t_s * NS).astype(np.int64)
    start = t_ns - np.round(pk.emission_time_s * NS).astype(np.int64)  # first sample
    views = [PacketView(samples[i], fs, int(pk.onset_index[i]), int(start[i]), int(i),
                        noise_rms_v=float(noise[i] * amp[i]))
             for i in range(n)]
    order = np.argsort(t_ns, kind="stable")
    out = []
    i = 0
    while i < n:
        t_cut = (t_ns[order[i]] // READ_CYCLE_NS + 1) * READ_CYCLE_NS
        j = i
        while j < n and t_ns[order[j]] < t_cut:
            j += 1
        for c in loc.process([views[k] for k in order[i:j]]):
            cov = np.asarray(c.covariance_m2, dtype=float)
            out.append(LocalizedEvent(
                int(c.time_ns), np.asarray(c.point_m, dtype=float), 0.5 * (cov + cov.T),
                -1 if c.event_type == EventType.DETOUCH else 1, float(c.amplitude_v),
                min(max(float(c.confidence), 0.0), 1.0) if math.isfinite(c.confidence) else 0.0,
                int(c.packet_ids[0])))
        i = j
    out.sort(key=lambda e: e.time_ns)
    return out, dict(loc.counts)


def run_trial_on_device(generator, seed, device, held_out=False, config=None):
    """`ae_eval.everyday.run_trial` with the waveform pipeline on ``device``.

    Parameters
    ----------
    generator : callable
        A family generator ``(seed, held_out) -> Scene``.
    seed : int
    device : ae_eval.zoo.Device
    held_out : bool
    config : SlipConfig or None

    Returns
    -------
    dict
        `score_trial`'s record plus ``localized`` (share of the emissions the localizer
        kept).
    """
    scene = generator(seed, held_out)
    ev, _ = device_events(scene, device, np.random.default_rng([38200, int(seed),
                                                                  int(held_out)]))
    end_ns = int(round(scene.duration_s * NS))
    _, outs, trace = run_detector(ev, config, end_ns, tick_ns=int(TICK_S * NS))
    rec = score_trial(scene, outs, trace)
    rec["localized"] = len(ev) / max(scene.t_s.size, 1)
    return rec
