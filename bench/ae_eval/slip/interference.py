# SPDX-License-Identifier: Apache-2.0
"""Common-mode electrical interference: a held touch under bursts through the waveform
pipeline and the driver's discrimination (the packet tests, `common_mode_interference`,
then the apex packets' timing, `BurstTrain`) to the detector; and per packet, the apex
touches kept and the bursts rejected."""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.dsp.interference import (
    TRAIN_TOL_S,
    TRAIN_TOL_SAMPLES,
    BurstTrain,
    EchoLearner,
    common_mode_interference,
    common_mode_share,
    echo_ratio,
)
from ae_tactile.localization import localize
from ae_tactile.pipeline import (
    APEX_POLAR_RAD,
    ROUTE_ALL,
    ROUTE_SPECTRUM,
    interference_route,
)
from ae_tactile.sim.config import SimConfig
from ae_tactile.sim.interference import KINDS, InterferenceSource, render_interference
from ae_tactile.sim.scene import load_scene, reference_noise_rms
from ae_tactile.sim.triggered import render_triggered
from ae_tactile.slip import LocalizedEvent, SlipConfig

from .common import NS, alarm_summary, cap_xy, state_at
from .pipelines import localized_events, run_detector


def interference_trial(
    seed: int,
    config: SlipConfig | None = None,
    *,
    discriminate: bool = True,
    duration_s: float = 1.0,
    input_without_echoes: bool = False,
) -> dict:
    """A held touch under common-mode interference bursts (1 Hz .. 10 kHz, every waveform,
    ADC coupling; 'input' coupling with wall echoes) through the waveform pipeline:
    acoustic packets + `InterferenceSource` packets -> localize -> (``discriminate``: as
    the driver's `PacketLocalizer`: `common_mode_interference` on the packets localized at
    the apex, fitting poorly or with one waveform on the four channels, its echo test
    learnt as by default from the device's first three touches, `learnt_echo_min`; then
    the apex packets' timing, `BurstTrain`) -> detector. ``input_without_echoes``: every
    burst enters the amplifier's input of a fingertip without wall echoes (no echo test:
    only the timing can tell). Counts:
    interference packets, rejected (by the packet tests, by the timing), localized
    (phantom events), contacts and false alarms; the held touch kept."""
    st = interference_finger(
        seed,
        discriminate=discriminate,
        duration_s=duration_s,
        input_without_echoes=input_without_echoes,
    )
    return interference_outcome(st, config)


def interference_finger(
    seed: int,
    *,
    discriminate: bool,
    duration_s: float,
    input_without_echoes: bool,
    hand: dict | None = None,
) -> dict:
    """One fingertip of `interference_trial` up to its detector: the kept events, the
    phantom events and the apex packets ``apex`` [(onset ns on the scene's clock,
    acoustic?, ref, rejected by the packet tests or the timing)]. ``hand``: what the
    fingertips of one hand share ({'medium', 'sample_rate_hz', 'rate_hz', 'periodic',
    'burst_times_ns'}: one source's bursts on the scene's clock); the fingertip's own draws
    are made and then replaced, so its other draws stay those of the seed."""
    rng = np.random.default_rng([7024, int(seed)])
    spec = _finger_spec(rng, seed, duration_s, input_without_echoes, hand)
    medium, fs = spec["sensor"]["medium"], spec["sensor"]["sample_rate_hz"]
    rate, coupling = spec["params"]["rate_hz"], spec["params"]["coupling"]
    reflections = spec["effects"]["reflections"]
    scene = load_scene(spec)
    geo = scene.config.geometry
    end_ns = int(round(duration_s * NS))
    pk = scene.triggered_source().next_packets(1 << 30, horizon_ns=end_ns)
    source = InterferenceSource(scene)
    if hand is not None:
        source.bursts[0]["times_ns"] = np.asarray(hand["burst_times_ns"], np.int64)
    t_if, ip = source.next_packets(end_ns)
    n_if = int(t_if.size)
    kw = _test_options(scene, rng)

    def masks(x, onset):
        return _masks(x, onset, fs, kw, discriminate, scene.noise_rms_v)

    events = localized_events(pk, geo)
    n_acoustic = len(events)
    # every packet the localizer accepted at the apex or with a poor fit goes through the
    # discriminator; the apex ones (masked or not) make the timing's history, in time order
    cand, ev_keep = _acoustic_apex(events, geo, *masks(pk.samples_v, pk.onset_index))
    n_train = 0
    phantom = []
    train = set()
    if n_if:
        res, mask, onset_ns, burst_cand = _burst_apex(ip, t_if, fs, geo, masks)
        cand += burst_cand
        if discriminate:
            train = _timing_rejects(cand, fs)
        n_train = sum(1 for a, _ in train if not a)
        ev_keep = [e for e in ev_keep if (True, id(e)) not in train]
        phantom = _phantoms(res, mask, train, onset_ns, geo)
    # the apex packets as the hand sees them: (onset ns, acoustic?, ref, rejected here)
    apex = [
        (t_ns, acoustic, ref, masked or (acoustic, id(ref) if acoustic else ref) in train)
        for t_ns, acoustic, ref, masked in cand
    ]
    return {
        "seed": int(seed),
        "duration_s": duration_s,
        "medium": medium,
        "sample_rate_hz": fs,
        "rate_hz": rate,
        "periodic": bool(spec["params"]["periodic"]),
        "coupling": coupling,
        "echoes": bool(reflections),
        "discriminate": discriminate,
        "input_without_echoes": bool(input_without_echoes),
        "n_interference": n_if,
        "n_train": n_train,
        "n_acoustic_packets": int(len(pk.emissions)),
        "n_acoustic_localized": n_acoustic,
        "end_ns": end_ns,
        "ev_keep": ev_keep,
        "phantom": phantom,
        "apex": apex,
    }


def _finger_spec(rng, seed, duration_s, input_without_echoes, hand):
    """The scene spec of `interference_finger`'s fingertip: medium, sample rate, burst
    rate and coupling drawn from ``rng``, then replaced by the hand's when given."""
    medium = "silicone" if rng.uniform() < 0.5 else "water_skin"
    fs = float(rng.choice([2e6, 5e6, 10e6]))
    rate = float(math.exp(rng.uniform(math.log(1.0), math.log(1e4))))
    coupling = "input" if rng.uniform() < 0.25 else "adc"
    if input_without_echoes:
        coupling = "input"
    reflections = coupling == "input" and not input_without_echoes
    x, y = cap_xy(rng)
    spec = {
        "generator": "interference",
        "duration_s": duration_s,
        "seed": int(seed) + 9000,
        "sensor": {"medium": medium, "sample_rate_hz": fs},
        "effects": {"attenuation": medium == "silicone", "reflections": reflections},
        "noise": {"snr_db": float(rng.uniform(20, 40))},
        "params": {
            "rate_hz": rate,
            "periodic": bool(rng.uniform() < 0.7),
            "jitter_s": 0.0,
            "kind": "mixed",
            "coupling": coupling,
            "amplitude_snr_db": float(rng.uniform(25, 45)),
            "x_m": x,
            "y_m": y,
            "touch_time_s": 0.005,
            "hold_s": duration_s - 0.05,
        },
    }
    if hand is not None:
        medium, fs = str(hand["medium"]), float(hand["sample_rate_hz"])
        rate = float(hand["rate_hz"])
        spec["sensor"] = {"medium": medium, "sample_rate_hz": fs}
        spec["effects"]["attenuation"] = medium == "silicone"
        spec["params"].update(rate_hz=rate, periodic=bool(hand["periodic"]))
    return spec


def _test_options(scene, rng):
    """The packet tests' options on the scene's fingertip, as the driver sets them."""
    return dict(
        noise_rms_v=scene.noise_rms_v,
        geometry=scene.config.geometry,
        lowpass_hz=scene.config.lowpass_hz,
        lowpass_order=scene.config.lowpass_order,
        # the driver's default: the echo test learnt from the device's first touches
        echo_min=learnt_echo_min(scene.config, scene.noise_rms_v, rng),
    )


def _masks(x, onset, fs, kw, discriminate, noise_rms_v):
    """(the full tests' mask, the spectrum tests' mask, common-mode share), as the
    driver applies them: the full tests at the apex or a poor fit, the spectrum tests
    on the other packets with one waveform on the four channels."""
    z = np.zeros(x.shape[0], bool)
    if not discriminate or x.shape[0] == 0:
        return z, z, np.zeros(x.shape[0])
    full, _ = common_mode_interference(x, fs, onset, **kw)
    spec_kw = {**kw, "echo_min": None, "shape_min": None}
    spectrum, _ = common_mode_interference(x, fs, onset, **spec_kw)
    return full, spectrum, common_mode_share(x, noise_rms_v, onset)


def _acoustic_apex(events, geo, m_full, m_spec, share_ac):
    """(apex candidates [(onset ns, True, event, masked)], the events the packet tests
    kept) of the acoustic packets' events, routed as the driver routes them."""
    cand, ev_keep = [], []
    for e in events:
        pol = math.acos(min(1.0, e.point_m[2] / float(np.linalg.norm(e.point_m))))
        j = e.packet_id
        route = interference_route(pol, e.confidence, float(share_ac[j]))
        masked = bool(m_full[j] if route == ROUTE_ALL else route == ROUTE_SPECTRUM and m_spec[j])
        if pol < APEX_POLAR_RAD:
            travel = float(geo.arrival_times_s(e.point_m[None])[0].min())
            cand.append((e.time_ns + int(round(travel * 1e9)), True, e, masked))
        if not masked:
            ev_keep.append(e)
    return cand, ev_keep


def _burst_apex(ip, t_if, fs, geo, masks):
    """(localization, rejected by the packet tests, onset ns, apex candidates [(onset ns,
    False, burst index, masked)]) of the interference packets ``ip`` (first samples at
    ``t_if`` ns)."""
    n_if = int(t_if.size)
    res = localize(ip.samples_v, fs, ip.onset_index, geometry=geo)
    f_if, s_if, share_if = masks(ip.samples_v, ip.onset_index)
    pol = np.arccos(np.clip(res.point_m[:, 2] / np.linalg.norm(res.point_m, axis=1), -1, 1))
    route = np.array([interference_route(pol[i], res.confidence[i], share_if[i])
                      for i in range(n_if)])
    mask = np.where(route == ROUTE_ALL, f_if, (route == ROUTE_SPECTRUM) & s_if)
    mask &= res.accepted
    onset_ns = t_if + int(round(1e9 / fs))
    cand = []
    for i in np.flatnonzero(res.accepted & (pol < APEX_POLAR_RAD)):
        cand.append((int(onset_ns[i]), False, int(i), bool(mask[i])))
    return res, mask, onset_ns, cand


def _timing_rejects(cand, fs):
    """The apex candidates the timing rejects (members of a burst train the packet tests
    let through), as refs (acoustic?, the event's id() or the burst's index)."""
    hist = BurstTrain()
    tol = max(TRAIN_TOL_S, TRAIN_TOL_SAMPLES / fs)
    train = set()
    for t_ns, acoustic, ref, masked in sorted(cand, key=lambda c: c[0]):
        if not masked and hist.is_member(t_ns * 1e-9, tol):
            train.add((acoustic, id(ref) if acoustic else ref))
        hist.add(t_ns * 1e-9)
    return train


def _phantoms(res, mask, train, onset_ns, geo):
    """The events the localizer made of bursts no test rejected (packet ids from
    1,000,000 + burst index)."""
    travel = np.round(geo.arrival_times_s(res.point_m).min(axis=1) * 1e9).astype(np.int64)
    phantom = []
    for i in np.flatnonzero(res.accepted & ~mask):
        if (False, int(i)) in train:
            continue
        phantom.append(
            LocalizedEvent(
                int(onset_ns[i]) - int(travel[i]),
                res.point_m[i],
                res.covariance_m2[i],
                int(res.polarity[i]),
                float(res.amplitude_v[i]),
                float(res.confidence[i]),
                1_000_000 + int(i),
            )
        )
    return phantom


def interference_outcome(st: dict, config: SlipConfig | None, coincident=()) -> dict:
    """The detector's outcome of `interference_finger`'s events; ``coincident``: the
    apex packets' refs ((acoustic?, the event's id() or the burst's index)) the hand's
    coincidence rejected."""
    drop = set(coincident)
    ev_keep = [e for e in st["ev_keep"] if (True, id(e)) not in drop]
    phantom = [e for e in st["phantom"] if (False, e.packet_id - 1_000_000) not in drop]
    n_if, n_train, end_ns = st["n_interference"], st["n_train"], st["end_ns"]
    n_rej = n_if - len(phantom)  # rejected by the localizer, the packet tests or the timing
    allev = sorted(ev_keep + phantom, key=lambda e: e.time_ns)
    det, outs, trace = run_detector(allev, config, end_ns, tick_ns=int(0.01 * NS))
    out = {
        k: st[k]
        for k in (
            "seed", "duration_s", "medium", "sample_rate_hz", "rate_hz", "periodic",
            "coupling", "echoes", "discriminate", "input_without_echoes", "n_interference",
        )
    }
    out.update({
        "n_rejected": n_rej,
        "n_rejected_timing": n_train,
        "n_phantom_events": len(phantom),
        "n_acoustic_packets": st["n_acoustic_packets"],
        "n_acoustic_kept": len(ev_keep),
        "n_acoustic_localized": st["n_acoustic_localized"],
        "contacts_created": int(det.counts["contacts_created"]),
        "state_mid": int(state_at(trace, end_ns // 2)),
    })
    out.update(alarm_summary(outs))
    return out


def learnt_echo_min(config, noise_rms_v: float, rng, n: int = 3, n_touches: int = 24):
    """The echo test's threshold the driver learns by default (`EchoLearner`,
    ``interference_echo_min`` -1) from the device's first ``n`` touches away from the apex
    whose echo it could measure (of ``n_touches``: polar 10 .. 45 deg, 0.1 .. 0.5 m/s,
    localized; a weak one is not measured): None on a device without wall echoes (or when
    fewer than ``n`` were measured)."""
    g = config.geometry
    pol = np.radians(rng.uniform(10.0, 45.0, n_touches))
    az = rng.uniform(0, 2 * np.pi, n_touches)
    r = g.radius_m * np.sin(pol)
    pk = render_triggered(
        g.surface_point_from_xy(r * np.cos(az), r * np.sin(az)),
        config,
        noise_rms_v=noise_rms_v,
        rng=rng,
        speed_m_s=rng.uniform(0.1, 0.5, n_touches),
        polarity=rng.choice([-1, 1], n_touches),
    )
    fs = config.sample_rate_hz
    res = localize(pk.samples_v, fs, pk.onset_index, geometry=g)
    ok = np.flatnonzero(res.accepted)
    beta = echo_ratio(pk.samples_v[ok], fs, pk.onset_index[ok], res.point_m[ok], g)
    learner = EchoLearner()
    learner.add(beta[np.isfinite(beta)][:n])
    return learner.echo_min


def apex_touch_packets(config, n: int, noise_rms_v: float, rng, radius_m: float = 1.5e-3):
    """``n`` rendered trigger windows of touches and releases (random polarity, 0.05 ..
    0.5 m/s) uniform over the disc of ``radius_m`` round the apex: near-zero delays and
    nearly equal waveforms, what common-mode interference also gives."""
    g = config.geometry
    r = np.sqrt(rng.uniform(0, 1, n)) * radius_m
    th = rng.uniform(0, 2 * np.pi, n)
    pts = g.surface_point_from_xy(r * np.cos(th), r * np.sin(th))
    return render_triggered(
        pts,
        config,
        noise_rms_v=noise_rms_v,
        rng=rng,
        speed_m_s=rng.uniform(0.05, 0.5, n),
        polarity=rng.choice([-1, 1], n),
    )


def interference_packet_rates(
    medium: str, sample_rate_hz: float, snr_db: float, *, echoes: bool = False, n: int = 300,
    seed: int = 0,
) -> list[dict]:
    """Per packet, with the noise given and estimated from the pretrigger (the driver's
    call): apex touches (<= 1.5 mm) kept, and common-mode interference (each waveform,
    'adc' and 'input' coupling, amplitude 10 .. 300 noise sigmas) rejected, and of those
    passed how many the localizer accepts (phantom events). ``echoes``: a device with wall
    echoes (the echo test on, learnt as the driver does by default from three touches
    away from the apex, `learnt_echo_min`). One row per (noise, coupling, kind)."""
    cfg = SimConfig.for_medium(medium, sample_rate_hz=sample_rate_hz, reflections=echoes)
    rng = np.random.default_rng([int(seed), int(sample_rate_hz), int(snr_db), int(echoes),
                                 len(medium)])
    noise = reference_noise_rms(cfg, snr_db)
    fs = cfg.sample_rate_hz
    apex = apex_touch_packets(cfg, n, noise, rng)
    echo_min = learnt_echo_min(cfg, noise, rng) if echoes else None
    bursts = {
        (c, k): render_interference(n, cfg, kind=k, coupling=c, noise_rms_v=noise, rng=rng)
        for c in ("adc", "input")
        for k in KINDS
    }
    rows = []
    for given in (True, False):
        kw = dict(
            noise_rms_v=noise if given else None,
            geometry=cfg.geometry,
            lowpass_hz=cfg.lowpass_hz,
            lowpass_order=cfg.lowpass_order,
            echo_min=echo_min,
        )
        m_apex, _ = common_mode_interference(apex.samples_v, fs, apex.onset_index, **kw)
        kept = 1.0 - float(m_apex.mean())
        for (coupling, kind), pk in bursts.items():
            mask, _ = common_mode_interference(pk.samples_v, fs, pk.onset_index, **kw)
            keep = np.flatnonzero(~mask)
            phantoms = 0
            if keep.size:
                res = localize(pk.samples_v[keep], fs, pk.onset_index[keep], geometry=cfg.geometry)
                phantoms = int(np.count_nonzero(res.accepted))
            rows.append(
                {
                    "medium": medium,
                    "sample_rate_hz": float(fs),
                    "snr_db": float(snr_db),
                    "echoes": bool(echoes),
                    "noise": "given" if given else "estimated",
                    "coupling": coupling,
                    "kind": kind,
                    "n": int(n),
                    "apex_kept_rate": kept,
                    "rejected_rate": float(mask.mean()),
                    "phantom_events": phantoms,
                }
            )
    return rows
