# SPDX-License-Identifier: Apache-2.0
"""Incipient slip: a Cattaneo-Mindlin ramp of the tangential load on a Hertz contact,
randomised per seed (``INCIPIENT_RANGES``), optionally announced by a touch at the
contact centre. ``incipient_slip_trial``: precursor before gross slip, lead time, load
fraction q = Q/(mu P) at detection, SLIP delay; ``closed_loop_trial``: the grip reflex
raising P once SLIP_PRECURSOR arrives."""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.localization.weak_release import WeakReleaseGate
from ae_tactile.records import EventType
from ae_tactile.sim.generators import hertz_contact_radius_m
from ae_tactile.sim.scene import load_scene
from ae_tactile.sim.stream import EmissionList
from ae_tactile.slip import SlipConfig, SlipDetector

from .common import NS, WithTouch, cap_point_xy, draw, first_output, n_before
from .pipelines import (
    DETECTOR_OPTIONS,
    localized_events,
    run_detector,
    scene_events,
    triggered_source,
)

# Randomised parameter ranges (SI units); "log" = log-uniform.
INCIPIENT_RANGES = {
    "max_polar_deg": 50.0,  # contact centre, uniform by area over this cap
    "normal_load_n": (0.5, 2.0, "log"),
    "youngs_modulus_pa": (0.7e6, 2.0e6, "log"),  # a_H = 1.1 .. 2.5 mm
    "friction_coefficient": (0.5, 1.2, "uniform"),
    "time_to_gross_slip_s": (0.25, 2.5, "log"),  # mu P / (dQ/dt): sets dQ/dt
    "snr_db": (25.0, 35.0, "uniform"),
}


def incipient_slip_scene(
    seed: int,
    *,
    announce_touch: bool = False,
    post_s: float = 0.25,
    ranges: dict | None = None,
    overload: float | None = None,
    polarity: str = "random",
    micro_slip_count=None,
    slip_rate_hz=None,
    hold_s=None,
):
    """(scene, process wrapper or None, drawn parameters) for one randomised trial.

    ``polarity``: 'random', 'compression', 'rarefaction' or 'mixed' (one of the three
    drawn per trial); ``micro_slip_count``: None (the simulator's density: dense
    emitters) or (lo, hi): a mean count drawn uniformly, no background emissions (sparse
    emitters); ``slip_rate_hz``: None (500 Hz) or (lo, hi) log-uniform gross-slip rate;
    ``hold_s``: with ``announce_touch``, None (the load starts 80 ms after the touch) or
    (lo, hi): the touch held a log-uniform time first (a grasp held, then loaded)."""
    r = dict(INCIPIENT_RANGES, **(ranges or {}))
    rng = np.random.default_rng([7001, int(seed)])
    R = 0.01
    x, y = cap_point_xy(rng, R, r["max_polar_deg"])
    P = draw(rng, r["normal_load_n"])
    E = draw(rng, r["youngs_modulus_pa"])
    mu = draw(rng, r["friction_coefficient"])
    T = draw(rng, r["time_to_gross_slip_s"])
    snr = draw(rng, r["snr_db"])
    extra, polarity = _emitter_options(seed, polarity, micro_slip_count, slip_rate_hz)
    start_s = _load_start_s(seed, announce_touch, hold_s)
    qdot = mu * P / T
    spec = {
        "generator": "incipient_slip",
        "duration_s": start_s + T + post_s,
        "seed": int(seed) + 1000,
        "sensor": {"medium": "silicone"},
        "effects": {"attenuation": True},
        "noise": {"snr_db": snr},
        "params": {
            "x_m": x,
            "y_m": y,
            "normal_load_n": P,
            "youngs_modulus_pa": E,
            "friction_coefficient": mu,
            "start_s": start_s,
            "tangential_load_rate_n_per_s": qdot,
            "tangential_load_max_n": None if overload is None else overload * mu * P,
            **extra,
        },
    }
    scene = load_scene(spec)
    params = {
        "seed": int(seed), "x_m": x, "y_m": y, "normal_load_n": P, "youngs_modulus_pa": E,
        "friction_coefficient": mu, "tangential_load_rate_n_per_s": qdot,
        "time_to_gross_slip_s": T, "snr_db": snr,
        "hertz_radius_m": float(hertz_contact_radius_m(P, R, E, 0.5)),
        "announce_touch": bool(announce_touch),
        "hold_before_load_s": start_s - 0.02 if announce_touch else None,
        "polarity": polarity,
        "micro_slip_count": extra.get("micro_slip_count"),
        "slip_rate_hz": extra.get("slip_rate_hz", 500.0),
    }
    source = _announced(scene) if announce_touch else None
    return scene, source, params


def _emitter_options(seed, polarity, micro_slip_count, slip_rate_hz):
    """(the scene's extra generator parameters, the polarity drawn) of
    `incipient_slip_scene`'s emitter options (their own random stream)."""
    extra = {}
    prng = np.random.default_rng([7011, int(seed)])
    if polarity == "mixed":
        polarity = str(prng.choice(["random", "compression", "rarefaction"]))
    extra["micro_slip_polarity"] = polarity
    if micro_slip_count is not None:
        extra["micro_slip_count"] = float(prng.uniform(*micro_slip_count))
        extra["background_rate_hz"] = 0.0
    if slip_rate_hz is not None:
        lo, hi = slip_rate_hz
        extra["slip_rate_hz"] = float(math.exp(prng.uniform(math.log(lo), math.log(hi))))
    return extra, polarity


def _load_start_s(seed, announce_touch, hold_s):
    """When the tangential load starts [s]: at once, 80 ms after an announcing touch at
    20 ms, or after the touch held a log-uniform time drawn from ``hold_s``."""
    start_s = 0.1 if announce_touch else 0.0
    if announce_touch and hold_s is not None:
        lo, hi = hold_s
        hrng = np.random.default_rng([7012, int(seed)])
        start_s = 0.02 + float(math.exp(hrng.uniform(math.log(lo), math.log(hi))))
    return start_s


def _announced(scene):
    """The scene's process with a touch at the contact centre at 20 ms."""
    c = scene.process.center
    touch = EmissionList.create(
        np.array([int(0.02 * NS)]),
        c[None, :],
        "touch",
        polarity=1,
        speed_m_s=0.3,
        curvature_1_m=1000.0,
        alpha_1_s=3000.0,
        density_kg_m3=scene.config.density,
        event_id=np.array([1 << 40]),
    )
    return WithTouch(scene.process, touch)


def incipient_slip_trial(
    seed: int,
    config: SlipConfig | None = None,
    *,
    announce_touch: bool = False,
    post_s: float = 0.25,
    ranges: dict | None = None,
    pipeline: str = "triggered",
    polarity: str = "random",
    micro_slip_count=None,
    slip_rate_hz=None,
    hold_s=None,
) -> dict:
    """One open-loop incipient-slip trial: precursor, lead time, q at detection, SLIP delay.
    ``pipeline``: 'triggered' (ideal trigger windows) or 'stream' (stream + dsp detector);
    scene options: `incipient_slip_scene`."""
    scene, source, params = incipient_slip_scene(
        seed,
        announce_touch=announce_touch,
        post_s=post_s,
        ranges=ranges,
        polarity=polarity,
        micro_slip_count=micro_slip_count,
        slip_rate_hz=slip_rate_hz,
        hold_s=hold_s,
    )
    end_ns = int(round(scene.duration_s * NS))
    events, n_em = scene_events(scene, source, end_ns, pipeline)
    proc = scene.process
    truth = proc.scene_truth(end_ns)
    t_gross = truth["gross_slip_time_ns"]
    centre = np.asarray(truth["contact_center_m"], dtype=float)
    a_h = float(truth["hertz_radius_m"])
    # the detector's own view of the stick zone at gross slip: its contact's centre (a
    # ring fitted to the micro-slips, or none yet) against the true centre
    at_gross = {"ring_fitted_at_gross": None, "centre_error_at_gross_over_a": None}

    def view_at_gross(det_g):
        if det_g.contacts:
            cg = max(det_g.contacts, key=lambda c: c.valid())
            at_gross["ring_fitted_at_gross"] = bool(cg.fitted)
            at_gross["centre_error_at_gross_over_a"] = (
                float(np.linalg.norm(cg.centre - centre)) / a_h
            )

    det, outs, trace = run_detector(
        events,
        config,
        end_ns,
        snapshot=None if t_gross is None else (t_gross, view_at_gross),
    )
    out = dict(params)
    out["pipeline"] = pipeline
    # load ratio when the 2nd / 3rd micro-slip reached the detector: where a precursor on
    # two / three emissions would come (the bound of sparse emitters)
    micro = [e.time_ns for e in events if t_gross is not None and e.time_ns < t_gross]
    out["q_at_micro_slip_2"] = (
        float(proc.state_at(micro[1])["load_ratio"]) if len(micro) >= 2 else None
    )
    out["q_at_micro_slip_3"] = (
        float(proc.state_at(micro[2])["load_ratio"]) if len(micro) >= 3 else None
    )
    out.update({"n_emissions": n_em, "n_events": len(events)})
    out.update(_gross_window(events, t_gross, centre, a_h))
    out.update(at_gross)
    out.update(_detections(outs, trace, proc, t_gross, params["hertz_radius_m"]))
    return out


def _gross_window(events, t_gross, centre, a_h):
    """What a SLIP within 50 ms can rest on: the emissions received in the 50 ms after
    gross slip, and whether one lies inside the stick zone at q = 0.9 (c = (1 - q)^(1/3)
    a_H = 0.46 a_H round the centre), where no micro-slip at q < 0.9 can come from."""
    gross = []
    if t_gross is not None:
        gross = [e for e in events if t_gross <= e.time_ns <= t_gross + 50 * 10**6]
    stick_r = (1.0 - 0.9) ** (1.0 / 3.0) * a_h
    return {
        "n_micro_slip_events": n_before(events, t_gross),
        "n_gross_events_50ms": len(gross),
        "gross_event_in_stick_zone_50ms": any(
            float(np.linalg.norm(np.asarray(e.point_m) - centre)) <= stick_r for e in gross
        ),
    }


def _detections(outs, trace, proc, t_gross, hertz_radius_m):
    """The detector's decisions of an incipient-slip trial against the truth: times,
    lead, load ratios, the precursor's distance to the contact's ring [m], counts and the
    state trace."""
    pre = first_output(outs, EventType.SLIP_PRECURSOR)
    slip = first_output(outs, EventType.SLIP)
    ring_error = None
    if pre is not None:
        c = np.asarray(proc.center)
        ring_error = float(abs(np.linalg.norm(pre.position_m - c) - hertz_radius_m))
    return {
        "gross_slip_time_ns": t_gross,
        "precursor_time_ns": None if pre is None else pre.time_ns,
        "slip_time_ns": None if slip is None else slip.time_ns,
        "precursor_before_gross": bool(
            pre is not None and t_gross is not None and pre.time_ns < t_gross
        ),
        "lead_ms": None if pre is None or t_gross is None else (t_gross - pre.time_ns) / 1e6,
        "q_at_precursor": None
        if pre is None
        else float(proc.state_at(pre.time_ns)["load_ratio"]),
        "slip_delay_ms": None
        if slip is None or t_gross is None
        else (slip.time_ns - t_gross) / 1e6,
        "q_at_slip": None if slip is None else float(proc.state_at(slip.time_ns)["load_ratio"]),
        "precursor_error_to_ring_m": ring_error,
        "n_precursor_events": sum(o.kind == EventType.SLIP_PRECURSOR for o in outs),
        "n_slip_events": sum(o.kind == EventType.SLIP for o in outs),
        "n_texture_events": sum(o.kind == EventType.TEXTURE for o in outs),
        "states": [[t, int(s)] for t, s in trace],
    }


def closed_loop_trial(
    seed: int,
    config: SlipConfig | None = None,
    *,
    latency_s: float = 0.05,
    load_factor: float = 1.5,
    overload: float = 1.2,
    chunk_s: float = 0.005,
    margin_s: float = 0.2,
    announce_touch: bool = False,
    ranges: dict | None = None,
) -> dict:
    """Grip reflex: the tangential load ramps to ``overload`` x mu P (open loop: gross slip
    at mu P / Qdot) and stays there; when the first SLIP_PRECURSOR arrives, P is raised by
    ``load_factor`` at ``latency_s`` after its emission time (or as soon as the stream
    allows), so that q stays below overload / load_factor < 1 if the reflex comes before
    q reaches 1. The scene runs ``margin_s`` past the end of the ramp. Averted = no gross
    slip in the whole scene."""
    scene, source, params = incipient_slip_scene(
        seed,
        announce_touch=announce_touch,
        post_s=(overload - 1.0) * INCIPIENT_RANGES["time_to_gross_slip_s"][1] + margin_s,
        ranges=ranges,
        overload=overload,
    )
    proc = scene.process
    src = triggered_source(scene, source)
    geo = scene.config.geometry
    det = SlipDetector(config, **DETECTOR_OPTIONS)
    end_ns = int(round(scene.duration_s * NS))
    step = int(round(chunk_s * NS))
    t_reflex = None
    t_pre = None
    h = 0
    n_id = 0
    gate = WeakReleaseGate()
    while h < end_ns:
        h = min(end_ns, h + step)
        pk = src.next_packets(1 << 30, horizon_ns=h)
        evs = localized_events(pk, geo, id_offset=n_id, weak_release_gate=gate)
        n_id += len(pk.emissions)
        for ev in evs:
            for o in det.process(ev):
                if t_pre is None and o.kind == EventType.SLIP_PRECURSOR:
                    t_pre = o.time_ns
        det.advance(h)
        if t_pre is not None and t_reflex is None:
            t_reflex = max(t_pre + int(round(latency_s * NS)), proc.horizon_ns, h)
            proc.set_normal_load(params["normal_load_n"] * load_factor, t_reflex)
    truth = proc.scene_truth(end_ns)
    out = dict(params)
    out.update(
        {
            "latency_s": latency_s,
            "load_factor": load_factor,
            "overload": overload,
            "precursor_time_ns": t_pre,
            "reflex_time_ns": t_reflex,
            "gross_slip_intervals_ns": truth["gross_slip_intervals_ns"],
            "averted": not truth["gross_slip_intervals_ns"],
            "q_at_reflex": None
            if t_reflex is None
            else float(proc.state_at(t_reflex - 1)["load_ratio"]),
        }
    )
    return out
