# SPDX-License-Identifier: Apache-2.0
"""Slip figures of one zoo device: scenes' emissions rendered through the device's own
front end, noise, mismatch and medium, then through the driver's in-process path.

Each emission of a scene (its ground truth: time, point, polarity, Eq. 10 parameters) is
rendered as one triggered packet with the DEVICE's `SimConfig` (`render_triggered`: the
only renderer with every zoo effect; emissions closer than a packet are not overlapped
here, `bench_zoo`'s overlap figure covers those), stamped at its true time and fed in
1 ms read cycles to a `ContactPipeline` with its `SlipStage` (defaults), ticked every
20 ms as the driver's timer does.

Scenes and what is scored:

- ``incipient_slip`` (a plane loaded to gross slip, micro-slips in the Cattaneo-Mindlin
  annulus): a SLIP_PRECURSOR before gross slip; no SLIP before q = 0.9; the first SLIP's
  delay after gross slip;
- ``three_pins`` (the paper's Fig. 8), ``touch_hold_release``, ``paper_positions`` (Fig. 7's
  sequence): no SLIP_PRECURSOR / SLIP / TEXTURE at all.
"""

from __future__ import annotations

import math
import os

import numpy as np

from ae_tactile.pipeline import ContactPipeline, PacketLocalizer, SlipStage
from ae_tactile.records import EventType, PacketView
from ae_tactile.sim import render_triggered
from ae_tactile.sim.scene import load_scene, reference_noise_rms

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCENES = os.path.join(ROOT, "config", "scenes")
#: scenes without any slip: every slip output is false
TOUCH_SCENES = ("three_pins", "touch_hold_release", "paper_positions")
READ_CYCLE_NS = 1_000_000  # [ns] the driver's read cycle
TICK_NS = 20_000_000  # [ns] the driver's slip timer
ALARMS = (int(EventType.SLIP_PRECURSOR), int(EventType.SLIP), int(EventType.TEXTURE))


def scene_emissions(name: str, seed: int):
    """The scene's emissions (an `EmissionList`), its config, SNR [dB] and the scene."""
    sc = load_scene(os.path.join(SCENES, name + ".yaml"), {"seed": int(seed)})
    em = sc.process.advance(int(round(sc.duration_s * 1e9)))
    snr = (sc.spec.get("noise") or {}).get("snr_db", 30.0)
    return em, sc, float(snr)


def run_on_device(dev, name: str, seed: int, sample_rate_hz: float = 10e6):
    """Slip records of one scene played on one device through the driver's path.

    Parameters
    ----------
    dev : ae_eval.zoo.Device
    name : str
        A scene file of config/scenes (without .yaml).
    seed : int
    sample_rate_hz : float

    Returns
    -------
    dict
        ``slip``: list of (event type, time [ns]); ``n_emissions``, ``n_contacts``
        (localized emissions), the scene's ``truth`` and the ``scene``.
    """
    em, sc, snr = scene_emissions(name, seed)
    cfg = dev.config(sc.config.medium, sample_rate_hz)
    g = np.random.default_rng([seed, 7])
    n = len(em)
    alpha = em.alpha_1_s if "emission_alpha_1_s" not in dev.fields else None
    pk = render_triggered(em.point_m, cfg, noise_rms_v=reference_noise_rms(cfg, snr),
                          polarity=em.polarity.astype(int), speed_m_s=em.speed_m_s,
                          curvature_1_m=em.curvature_1_m, alpha_1_s=alpha, rng=g)
    fs = cfg.sample_rate_hz
    start = em.time_ns - np.rint(pk.emission_time_s * 1e9).astype(np.int64)  # first sample
    views = [PacketView(pk.samples_v[i], fs, int(pk.onset_index[i]), int(start[i]), i)
             for i in range(n)]
    pipe = ContactPipeline(PacketLocalizer("ml", geometry=cfg.geometry), SlipStage())
    slips, contacts = [], []
    t_end = int(em.time_ns.max(initial=0)) + 10**9
    next_tick = TICK_NS
    i = 0
    for t in range(0, t_end, READ_CYCLE_NS):
        j = i
        while j < n and em.time_ns[j] < t:
            j += 1
        if j > i:
            pipe.process(views[i:j], contacts.extend, slips.extend)
            pipe.run_idle_work()
            i = j
        if t >= next_tick:
            pipe.tick(t)
            next_tick += TICK_NS
    pipe.run_idle_work()
    pipe.tick(t_end + 10**9)
    return dict(slip=[(int(s.event_type), int(s.time_ns)) for s in slips], n_emissions=n,
                n_contacts=len(contacts), truth=sc.truth, scene=sc)


def _q_time_ns(sc, q: float) -> float:
    """When the incipient-slip scene's load fraction reaches q [ns] (inf: never)."""
    proc = sc.process
    return float(proc._time_of_q(q, proc.loads[0][1]))


def device_slip_figures(dev, seeds) -> dict:
    """The slip figures of one device over the scenes and seeds.

    Parameters
    ----------
    dev : ae_eval.zoo.Device
    seeds : sequence of int

    Returns
    -------
    dict
        ``precursor_before_gross`` (share of incipient-slip runs), ``slip_before_q09``
        (share), ``slip_delay_ms`` (median first SLIP after gross slip, NaN if none),
        ``slip_found`` (share), ``false_alarm_runs`` (share of touch-scene runs with any
        slip output), ``kept`` (localized share of emissions over all runs).
    """
    prec = early = found = 0
    delays, false_runs, runs = [], 0, 0
    kept = total = 0
    for seed in seeds:
        r = run_on_device(dev, "incipient_slip", seed)
        kept, total = kept + r["n_contacts"], total + r["n_emissions"]
        gross = r["truth"]["gross_slip_time_ns"]
        t09 = _q_time_ns(r["scene"], 0.9)
        pre = [t for k, t in r["slip"] if k == EventType.SLIP_PRECURSOR]
        sl = [t for k, t in r["slip"] if k == EventType.SLIP]
        prec += gross is not None and any(t < gross for t in pre)
        early += any(t < t09 for t in sl)
        late = [t for t in sl if t >= t09]
        if late and gross is not None:
            found += 1
            delays.append((late[0] - gross) / 1e6)
        for name in TOUCH_SCENES:
            t = run_on_device(dev, name, seed)
            kept, total = kept + t["n_contacts"], total + t["n_emissions"]
            runs += 1
            false_runs += any(k in ALARMS for k, _ in t["slip"])
    m = len(seeds)
    return dict(precursor_before_gross=prec / m, slip_before_q09=early / m, slip_found=found / m,
                slip_delay_ms=float(np.median(delays)) if delays else math.nan,
                false_alarm_runs=false_runs / max(runs, 1), kept=kept / max(total, 1),
                seeds=len(seeds))
