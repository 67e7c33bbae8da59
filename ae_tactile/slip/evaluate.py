# SPDX-License-Identifier: Apache-2.0
"""Evaluation of the slip detector on the simulator's scenes.

The real pipeline at core level, per trial: a scene with its own seed and randomised
parameters -> the simulator's triggered source (windows cut from the stream around each
emission, as the device's trigger cuts them: overlaps, noise and quantization included)
-> ``ae_tactile.localization.localize`` (default estimator, accepted packets only, time
stamp = onset time - travel time from the fitted point, as the localizer node stamps
events) -> ``SlipDetector``. Nothing of the ground truth reaches the detector.

Trials (each function takes a seed and returns a JSON-able dict):
  incipient_slip_trial   Cattaneo-Mindlin incipient slip (optionally announced by a touch
                         at the contact centre): precursor before gross slip, lead time,
                         load fraction q = Q/(mu P) at detection, SLIP delay
  gross_slip_bound_trial the same scene (never announced, 'events'): the Bayes posterior
                         that gross slip has begun, given truth no detector has (the
                         bound a SLIP decision can reach)
  closed_loop_trial      the same scene, P raised (grip reflex) once SLIP_PRECURSOR arrives:
                         was gross slip averted
  touch_hold_release_trial, random_touches_trial   false alarms (any SLIP_PRECURSOR /
                         SLIP / TEXTURE) and the latched state
  texture_trial          spatial period error of TEXTURE, detection time
  drift_slip_trial       plane slip drifting along x: SLIP delay and direction error
``run_evaluation`` runs them all and summarises (bench/bench_slip.py, test_slip_eval.py).
"""

from __future__ import annotations

import math
import time

import numpy as np

from ae_tactile.localization import Reason, get_estimator, localize
from ae_tactile.localization.weak_release import MIN_SNR_DB as WEAK_MIN_SNR_DB
from ae_tactile.localization.weak_release import (
    WeakReleaseGate,
    kept_with_weak_releases,
    weak_release_confidence,
)
from ae_tactile.records import ContactState, EventType
from ae_tactile.sim.generators import hertz_contact_radius_m
from ae_tactile.sim.scene import load_scene
from ae_tactile.sim.stream import EmissionList, time_ns_of_sample

from .config import SlipConfig
from .detector import SlipDetector
from .types import LocalizedEvent

_NS = 1_000_000_000
#: the 'events' pipeline's share of emissions lost at random (packets the localizer
#: rejects), strong ones included
EVENTS_DROP = 0.02
SLIP_KINDS = (EventType.SLIP_PRECURSOR, EventType.SLIP, EventType.TEXTURE)

# Randomised parameter ranges (SI units); "log" = log-uniform.
INCIPIENT_RANGES = {
    "max_polar_deg": 50.0,  # contact centre, uniform by area over this cap
    "normal_load_n": (0.5, 2.0, "log"),
    "youngs_modulus_pa": (0.7e6, 2.0e6, "log"),  # a_H = 1.1 .. 2.5 mm
    "friction_coefficient": (0.5, 1.2, "uniform"),
    "time_to_gross_slip_s": (0.25, 2.5, "log"),  # mu P / (dQ/dt): sets dQ/dt
    "snr_db": (25.0, 35.0, "uniform"),
}


def _draw(rng, spec):
    lo, hi, kind = spec
    return (
        float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
        if kind == "log"
        else float(rng.uniform(lo, hi))
    )


def _cap_point_xy(rng, radius_m, max_polar_deg):
    cmin = math.cos(math.radians(max_polar_deg))
    th = math.acos(rng.uniform(cmin, 1.0))
    ph = rng.uniform(0.0, 2.0 * math.pi)
    return radius_m * math.sin(th) * math.cos(ph), radius_m * math.sin(th) * math.sin(ph)


class _WithTouch:
    """An emission process plus fixed extra emissions (a touch announcing the contact)."""

    def __init__(self, process, extra: EmissionList):
        self.process = process
        self.extra = extra.sorted()
        self._h = None

    def advance(self, t_ns):
        lo = np.iinfo(np.int64).min if self._h is None else self._h
        if self._h is not None and t_ns <= self._h:
            return EmissionList.empty()
        self._h = int(t_ns)
        return EmissionList.concat(
            [self.extra.between(lo, t_ns), self.process.advance(t_ns)]
        ).sorted()

    def scene_truth(self):
        return self.process.scene_truth()


# ---------------------------------------------------------------------- pipeline
def localized_events(
    packets,
    geometry,
    *,
    id_offset: int = 0,
    weak_release_min_snr_db=WEAK_MIN_SNR_DB,
    weak_release_gate=None,
) -> list[LocalizedEvent]:
    """Localize triggered packets (``StreamPackets``) and turn the accepted ones (and the
    weak releases the driver keeps, `ae_tactile.localization.weak_release`; None: none)
    into LocalizedEvents stamped at onset time - travel time (the localizer node's stamp;
    ``weak_release_gate`` carries the gate's touches across calls). The packets'
    saturation flags go with them, as the device's do in the driver (without them the
    localizer falls back to a flat-top test, which a weak slow pulse quantized to a few
    LSB can pass)."""
    k = len(packets.emissions)
    if k == 0:
        return []
    fs = packets.sample_rate_hz
    sat = getattr(packets, "saturated", None)
    res = localize(packets.samples_v, fs, packets.onset_index, geometry=geometry, saturated=sat)
    onset_ns = time_ns_of_sample(packets.start_index + packets.onset_index, fs)
    travel_ns = np.round(geometry.arrival_times_s(res.point_m).min(axis=1) * 1e9).astype(np.int64)
    t = onset_ns - travel_ns
    kept, conf = _kept(res, t, weak_release_min_snr_db, gate=weak_release_gate)
    out = []
    for i in np.flatnonzero(kept):
        out.append(
            LocalizedEvent(
                int(t[i]),
                res.point_m[i],
                res.covariance_m2[i],
                int(res.polarity[i]),
                float(res.amplitude_v[i]),
                float(conf[i]),
                id_offset + int(i),
            )
        )
    out.sort(key=lambda e: e.time_ns)
    return out


def _kept(res, t_ns, weak_min_snr_db, usable=None, gate=None):
    """(kept mask, confidence) of a batch: the accepted (``usable``) packets and, unless
    ``weak_min_snr_db`` is None, the weak releases the gate keeps."""
    if weak_min_snr_db is None:
        kept = np.asarray(res.accepted, bool)
        return (kept if usable is None else kept & usable), np.asarray(res.confidence, float)
    kept, weak = kept_with_weak_releases(
        res, t_ns, float(weak_min_snr_db), gate=gate, usable=usable
    )
    conf = np.array(res.confidence, dtype=float)
    thr = get_estimator(res.method).overlap_threshold  # `localize`'s default
    for i in np.flatnonzero(weak):
        c = res.covariance_m2[i]
        conf[i] = weak_release_confidence(
            res.snr_db_est[i],
            float(weak_min_snr_db),
            math.sqrt(max(c[0, 0] + c[1, 1], 0.0)),
            res.overlap_excess[i],
            thr,
            res.clamped[i],
        )
    return kept, conf


def stream_localized_events(
    source,
    geometry,
    n_samples: int,
    *,
    chunk_samples: int = 1_000_000,
    detector_config=None,
    weak_release_min_snr_db=WEAK_MIN_SNR_DB,
) -> list[LocalizedEvent]:
    """The stream path instead of ideal triggers: a ``StreamingSource`` read in chunks ->
    ``ae_tactile.dsp.PacketDetector`` (default configuration at the stream's rate) ->
    ``localize_packets``; re-triggers inside a hit (``in_hit``, wall echoes) are dropped as
    the localizer node does; packet ids are the detector's."""
    from ae_tactile.dsp import DetectorConfig, PacketBatch, PacketDetector
    from ae_tactile.localization import localize_packets

    fs = source.config.sample_rate_hz
    det = PacketDetector(detector_config or DetectorConfig(sample_rate_hz=fs))
    parts, pos = [], 0
    while pos < n_samples:
        ch = source.next_chunk(min(chunk_samples, n_samples - pos))
        parts.append(det.process(ch.samples_v, ch.start_index))
        pos += ch.samples_v.shape[1]
    parts.append(det.flush())
    b = PacketBatch.concatenate(parts, det.sample_rate_hz, det.window_samples)
    if len(b) == 0:
        return []
    res = localize_packets(b, geometry=geometry)
    onset_ns = time_ns_of_sample(b.start_index + b.onset_index, fs)
    travel_ns = np.round(geometry.arrival_times_s(res.point_m).min(axis=1) * 1e9).astype(np.int64)
    t = onset_ns - travel_ns
    kept, conf = _kept(res, t, weak_release_min_snr_db, ~np.asarray(b.in_hit, bool))
    out = [
        LocalizedEvent(
            int(t[i]),
            res.point_m[i],
            res.covariance_m2[i],
            int(res.polarity[i]),
            float(res.amplitude_v[i]),
            float(conf[i]),
            int(b.packet_id[i]),
        )
        for i in np.flatnonzero(kept)
    ]
    out.sort(key=lambda e: e.time_ns)
    return out


def run_detector(
    events,
    config: SlipConfig | None = None,
    end_ns: int | None = None,
    *,
    sliding_speed_m_s=None,
    tick_ns: int | None = None,
    snapshot=None,
):
    """Feed events (time order) to a fresh detector; ``advance`` every ``tick_ns`` between
    events (a node's timer) and up to ``end_ns``. ``snapshot``: (t_ns, fn), fn(detector)
    called once, before the first event at or after t_ns (or at the end). Returns
    (detector, outputs, state trace [(time_ns, ContactState)])."""
    det = SlipDetector(config)
    snap_ns, snap_fn = snapshot if snapshot is not None else (None, None)
    if sliding_speed_m_s is not None:
        det.set_sliding_speed(sliding_speed_m_s)
    outs, trace = [], []
    last = None

    def note(t):
        nonlocal last
        s = det.state.state
        if s != last:
            trace.append((int(t), s))
            last = s

    t_prev = None
    for ev in events:
        if snap_fn is not None and ev.time_ns >= snap_ns:
            snap_fn(det)
            snap_fn = None
        if tick_ns and t_prev is not None:
            for tt in range(t_prev + tick_ns, ev.time_ns, tick_ns):
                det.advance(tt)
                note(tt)
        outs.extend(det.process(ev))
        note(ev.time_ns)
        t_prev = ev.time_ns
    if end_ns is not None:
        if tick_ns and t_prev is not None:
            for tt in range(t_prev + tick_ns, end_ns, tick_ns):
                det.advance(tt)
                note(tt)
        det.advance(int(end_ns))
        note(end_ns)
    if snap_fn is not None:
        snap_fn(det)
    return det, outs, trace


def _n_before(events, t_ns):
    """Localized events before t_ns (all if None): the micro-slips the detector saw."""
    return sum(1 for e in events if t_ns is None or e.time_ns < t_ns)


def _first(outs, kind, onset=True):
    for o in outs:
        if o.kind == kind and (o.onset or not onset):
            return o
    return None


# ---------------------------------------------------------------------- incipient slip
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
    x, y = _cap_point_xy(rng, R, r["max_polar_deg"])
    P = _draw(rng, r["normal_load_n"])
    E = _draw(rng, r["youngs_modulus_pa"])
    mu = _draw(rng, r["friction_coefficient"])
    T = _draw(rng, r["time_to_gross_slip_s"])
    snr = _draw(rng, r["snr_db"])
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
    start_s = 0.1 if announce_touch else 0.0
    if announce_touch and hold_s is not None:
        lo, hi = hold_s
        hrng = np.random.default_rng([7012, int(seed)])
        start_s = 0.02 + float(math.exp(hrng.uniform(math.log(lo), math.log(hi))))
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
    a_h = float(hertz_contact_radius_m(P, R, E, 0.5))
    params = {
        "seed": int(seed),
        "x_m": x,
        "y_m": y,
        "normal_load_n": P,
        "youngs_modulus_pa": E,
        "friction_coefficient": mu,
        "tangential_load_rate_n_per_s": qdot,
        "time_to_gross_slip_s": T,
        "snr_db": snr,
        "hertz_radius_m": a_h,
        "announce_touch": bool(announce_touch),
        "hold_before_load_s": start_s - 0.02 if announce_touch else None,
        "polarity": polarity,
        "micro_slip_count": extra.get("micro_slip_count"),
        "slip_rate_hz": extra.get("slip_rate_hz", 500.0),
    }
    source = None
    if announce_touch:
        c = scene.process.center
        touch = EmissionList.create(
            np.array([int(0.02 * _NS)]),
            c[None, :],
            "touch",
            polarity=1,
            speed_m_s=0.3,
            curvature_1_m=1000.0,
            alpha_1_s=3000.0,
            density_kg_m3=scene.config.density,
            event_id=np.array([1 << 40]),
        )
        source = _WithTouch(scene.process, touch)
    return scene, source, params


def _streaming(scene, source):
    from ae_tactile.sim.stream import StreamingSource

    if source is None:
        return scene.streaming_source()
    return StreamingSource(source, scene.config, noise_rms_v=scene.noise_rms_v, seed=scene.seed)


def emission_events(
    em: EmissionList,
    geometry,
    rng,
    *,
    sigma_m: float = 30e-6,
    drop: float = EVENTS_DROP,
    time_sigma_s: float = 100e-9,
    id_offset: int = 0,
) -> list[LocalizedEvent]:
    """The 'events' pipeline: true emissions -> LocalizedEvents with the localizer's error
    model instead of rendered waveforms (fast enough for thousands of trials): Gaussian
    position error of ``sigma_m`` per tangent axis (the covariance says so), Gaussian
    time error, the emission's polarity, a fraction ``drop`` lost (packets the localizer
    rejects). bench/bench_slip.py checks it against the waveform pipeline."""
    n = len(em)
    if n == 0:
        return []
    P = np.asarray(em.point_m, float)
    nrm = P / np.linalg.norm(P, axis=1, keepdims=True)
    ref = np.where(
        np.abs(nrm[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]])
    )
    e1 = ref - (ref * nrm).sum(1, keepdims=True) * nrm
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(nrm, e1)
    z = rng.normal(0.0, sigma_m, (n, 2))
    Q = P + z[:, :1] * e1 + z[:, 1:] * e2
    Q *= geometry.radius_m / np.linalg.norm(Q, axis=1, keepdims=True)
    cov = sigma_m**2 * (e1[:, :, None] * e1[:, None, :] + e2[:, :, None] * e2[:, None, :])
    t = np.asarray(em.time_ns, np.int64) + np.round(rng.normal(0.0, time_sigma_s * 1e9, n)).astype(
        np.int64
    )
    pol = np.sign(np.asarray(em.strength_pa_m, float)).astype(int)
    keep = rng.uniform(0, 1, n) >= drop
    out = [
        LocalizedEvent(int(t[i]), Q[i], cov[i], int(pol[i]), math.nan, 0.9, id_offset + int(i))
        for i in np.flatnonzero(keep)
    ]
    out.sort(key=lambda e: e.time_ns)
    return out


def _events(scene, source, end_ns, pipeline):
    """(events, number of true emissions) through the chosen pipeline."""
    if pipeline == "events":
        proc = source if source is not None else scene.process
        em = proc.advance(end_ns)
        rng = np.random.default_rng([7100, int(scene.seed)])
        sigma = float(math.exp(rng.uniform(math.log(5e-6), math.log(40e-6))))
        return emission_events(em, scene.config.geometry, rng, sigma_m=sigma), int(len(em))
    if pipeline == "triggered":
        pk = _triggered(scene, source).next_packets(1 << 30, horizon_ns=end_ns)
        return localized_events(pk, scene.config.geometry), int(len(pk.emissions))
    if pipeline == "stream":
        n = int(round(end_ns * 1e-9 * scene.config.sample_rate_hz))
        return stream_localized_events(_streaming(scene, source), scene.config.geometry, n), None
    raise ValueError(f"pipeline must be 'triggered', 'stream' or 'events', got {pipeline!r}")


def _triggered(scene, source):
    from ae_tactile.sim.stream import TriggeredSource

    if source is None:
        return scene.triggered_source()
    return TriggeredSource(source, scene.config, noise_rms_v=scene.noise_rms_v, seed=scene.seed)


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
    end_ns = int(round(scene.duration_s * _NS))
    events, n_em = _events(scene, source, end_ns, pipeline)
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
    pre = _first(outs, EventType.SLIP_PRECURSOR)
    # what a SLIP within 50 ms can rest on: the emissions received in the 50 ms after
    # gross slip, and whether one lies inside the stick zone at q = 0.9 (c = (1 - q)^(1/3)
    # a_H = 0.46 a_H round the centre), where no micro-slip at q < 0.9 can come from
    gross = []
    if t_gross is not None:
        gross = [e for e in events if t_gross <= e.time_ns <= t_gross + 50 * 10**6]
    stick_r = (1.0 - 0.9) ** (1.0 / 3.0) * a_h
    slip = _first(outs, EventType.SLIP)
    micro = [e.time_ns for e in events if t_gross is not None and e.time_ns < t_gross]
    out = dict(params)
    out.update(
        {
            "pipeline": pipeline,
            # load ratio when the 2nd / 3rd micro-slip reached the detector: where a
            # precursor on two / three emissions would come (the bound of sparse emitters)
            "q_at_micro_slip_2": float(proc.state_at(micro[1])["load_ratio"])
            if len(micro) >= 2
            else None,
            "q_at_micro_slip_3": float(proc.state_at(micro[2])["load_ratio"])
            if len(micro) >= 3
            else None,
            "n_emissions": n_em,
            "n_events": len(events),
            "n_micro_slip_events": _n_before(events, t_gross),
            "n_gross_events_50ms": len(gross),
            "gross_event_in_stick_zone_50ms": any(
                float(np.linalg.norm(np.asarray(e.point_m) - centre)) <= stick_r for e in gross
            ),
            **at_gross,
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
            "q_at_slip": None
            if slip is None
            else float(proc.state_at(slip.time_ns)["load_ratio"]),
            "precursor_error_to_ring_m": None,
            "n_precursor_events": sum(o.kind == EventType.SLIP_PRECURSOR for o in outs),
            "n_slip_events": sum(o.kind == EventType.SLIP for o in outs),
            "n_texture_events": sum(o.kind == EventType.TEXTURE for o in outs),
            "states": [[t, int(s)] for t, s in trace],
        }
    )
    if pre is not None:
        c = np.asarray(proc.center)
        out["precursor_error_to_ring_m"] = float(
            abs(np.linalg.norm(pre.position_m - c) - params["hertz_radius_m"])
        )
    return out


#: thresholds on the gross-slip posterior reported by `summarize_gross_slip_bound`
BOUND_THRESHOLDS = (0.5, 0.8, 0.9, 0.95, 0.98, 0.99, 0.999)


def gross_slip_bound_trial(
    seed: int,
    *,
    micro_slip_count=(4.0, 12.0),
    slip_rate_hz=(100.0, 200.0),
    post_s: float = 0.25,
    use_position: bool = True,
    announce_touch: bool = False,
    n_t: int = 600,
) -> dict:
    """What any SLIP decision could do on `incipient_slip_trial`'s scene ('events'
    pipeline, the same seed: the same emissions; never announced, or ``announce_touch``:
    a grasp loaded 80 ms after its touch, the touch itself left out): the Bayes
    posterior that gross slip has begun, P(T <= t - t_0 | emissions up to t), at each
    emission, computed with what no detector has: the scene family's prior (T
    log-uniform over time_to_gross_slip_s, N uniform over ``micro_slip_count``, s
    log-uniform over ``slip_rate_hz``: a grid of ``n_t`` x 17 x 5), the ramp's start
    (t_0 = 0, or 0.1 s after a touch; q = (t - t_0) / T), the simulator's emission model,
    and (``use_position``) the contact's true centre and a_H:

      micro-slips (t < T): Poisson at k N (2/3) (1 - q)^(-1/3) / T (uniform in the slip
      fraction f = 1 - (1 - q)^(2/3)), radially uniform by area over kappa < rho < 1,
      kappa = (1 - q)^(1/3), rho = r / a_H; gross slip (t >= T): Poisson at k s, over
      0 < rho < 1; k = 1 - EVENTS_DROP; each radial density blurred by the emission's
      localization sigma_rho: [Phi((rho - kappa) / sigma_rho) - Phi((rho - 1) / sigma_rho)]
      / (1 - kappa^2); log L = sum log(rate x density) - k N f(min(t / T, 1)) - k s (t - T)+.

    A decision 'SLIP once the posterior reaches pi' (Shiryaev's rule) is the Bayes-optimal
    quickest detection for this prior; it bounds the detector, which knows none of that."""
    from scipy.special import ndtr

    scene, source, params = incipient_slip_scene(
        seed,
        post_s=post_s,
        micro_slip_count=micro_slip_count,
        slip_rate_hz=slip_rate_hz,
        announce_touch=announce_touch,
    )
    end_ns = int(round(scene.duration_s * _NS))
    events, _ = _events(scene, source, end_ns, "events")
    t0_ns = int(round(scene.process.t_start_ns))
    events = [e for e in events if e.time_ns >= t0_ns]  # the touch is no micro-slip
    t_g = scene.process.scene_truth(end_ns)["gross_slip_time_ns"]
    centre = np.asarray(scene.process.center, dtype=float)
    a_h = float(params["hertz_radius_m"])
    lo, hi, _ = INCIPIENT_RANGES["time_to_gross_slip_s"]
    T, N, S = (
        x.ravel()
        for x in np.meshgrid(
            np.exp(np.linspace(math.log(lo), math.log(hi), n_t)),
            np.linspace(*micro_slip_count, 17),
            np.exp(np.linspace(math.log(slip_rate_hz[0]), math.log(slip_rate_hz[1]), 5)),
            indexing="ij",
        )
    )
    k = 1.0 - EVENTS_DROP
    log_sum = np.zeros(T.size)
    post = []
    for e in events:
        u = (e.time_ns - t0_ns) * 1e-9
        pre = u < T
        one_q = np.where(pre, 1.0 - u / T, 1.0)
        rate = np.where(pre, k * N * (2.0 / 3.0) * one_q ** (-1.0 / 3.0) / T, k * S)
        if use_position:
            # the simulator places emissions in the tangent plane at the centre, then on
            # the sphere along their radius: back into that plane
            pt = np.asarray(e.point_m, dtype=float)
            pt = pt * (float(centre @ centre) / float(pt @ centre))
            rho = float(np.linalg.norm(pt - centre)) / a_h
            s_rho = max(math.sqrt(max(float(np.trace(e.covariance_m2)), 0.0) / 2.0) / a_h, 1e-3)
            kap = np.where(pre, one_q ** (1.0 / 3.0), 0.0)
            outer = float(ndtr((rho - 1.0) / s_rho))
            dens = (ndtr((rho - kap) / s_rho) - outer) / np.maximum(1.0 - kap * kap, 1e-12)
            rate = rate * np.maximum(dens, 1e-300)
        log_sum += np.log(rate)
        f = np.where(pre, 1.0 - one_q ** (2.0 / 3.0), 1.0)  # slip fraction at t
        ll = log_sum - k * N * f - k * S * np.maximum(u - T, 0.0)
        w = np.exp(ll - ll.max())
        post.append(min(1.0, float(w[~pre].sum() / w.sum())))
    return {
        "seed": int(seed),
        "use_position": bool(use_position),
        "time_to_gross_slip_s": float(params["time_to_gross_slip_s"]),
        "ramp_start_ns": t0_ns,
        "gross_slip_time_ns": t_g,
        "times_ns": [int(e.time_ns) for e in events],
        "posterior": post,
    }


def summarize_gross_slip_bound(trials: list[dict], thresholds=BOUND_THRESHOLDS) -> dict:
    """Per posterior threshold pi, the rule 'SLIP at the first emission whose posterior
    reaches pi': share of trials with SLIP within 50 ms of gross slip, with SLIP at
    q < 0.9 (t < 0.9 T: the ramp starts at 0), and the delay's p95 (none: infinite)."""
    out = {"n_trials": len(trials), "by_threshold": {}}
    for pi in thresholds:
        d, early = [], 0
        for r in trials:
            tg = r["gross_slip_time_ns"]
            t = next((t for t, p in zip(r["times_ns"], r["posterior"]) if p >= pi), None)
            d.append(math.inf if t is None else (t - tg) / 1e6)
            q090_ns = r["ramp_start_ns"] + 0.9 * r["time_to_gross_slip_s"] * _NS
            early += t is not None and t < q090_ns
        n = max(len(trials), 1)
        out["by_threshold"][f"{pi:g}"] = {
            "slip_within_50ms_rate": sum(x <= 50.0 for x in d) / n,
            "slip_before_q090_rate": early / n,
            "slip_delay_p95_ms": float(np.percentile(d, 95, method="higher")) if d else None,
        }
    return out


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
    src = _triggered(scene, source)
    geo = scene.config.geometry
    det = SlipDetector(config)
    end_ns = int(round(scene.duration_s * _NS))
    step = int(round(chunk_s * _NS))
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
            t_reflex = max(t_pre + int(round(latency_s * _NS)), proc.horizon_ns, h)
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


# ---------------------------------------------------------------------- false alarms
def _alarm_summary(outs):
    return {
        "n_precursor": sum(o.kind == EventType.SLIP_PRECURSOR for o in outs),
        "n_slip": sum(o.kind == EventType.SLIP for o in outs),
        "n_texture": sum(o.kind == EventType.TEXTURE for o in outs),
        "n_alarm_onsets": sum(o.onset for o in outs if o.kind in SLIP_KINDS),
    }


def _state_at(trace, t):
    s = ContactState.NO_CONTACT
    for tt, st in trace:
        if tt <= t:
            s = st
    return s


def touch_hold_release_trial(
    seed: int,
    config: SlipConfig | None = None,
    *,
    pipeline: str = "triggered",
    hold_max_s: float = 30.0,
) -> dict:
    """Touch anywhere on the cap (polar <= 60 deg), hold 20 ms .. ``hold_max_s``
    (log-uniform: a grasp held for seconds, longer than the detector's 2 s evidence window,
    as well as a tap), release; random speeds, medium and SNR. False alarms and the latched
    state during the hold and 0.1 s after the release (NO_CONTACT once the release ended
    the contact)."""
    rng = np.random.default_rng([7002, int(seed)])
    medium = "silicone" if rng.uniform() < 0.5 else "water_skin"
    x, y = _cap_point_xy(rng, 0.01, 60.0)
    hold = float(math.exp(rng.uniform(math.log(0.02), math.log(hold_max_s))))
    t0 = 0.005
    spec = {
        "generator": "touch_hold_release",
        "duration_s": t0 + hold + 0.1,
        "seed": int(seed) + 2000,
        "sensor": {"medium": medium},
        "effects": {"attenuation": medium == "silicone"},
        "noise": {"snr_db": float(rng.uniform(25, 35))},
        "params": {
            "x_m": x,
            "y_m": y,
            "time_s": t0,
            "hold_s": hold,
            "speed_m_s": float(rng.uniform(0.15, 0.5)),
            "release_speed_m_s": float(rng.uniform(0.1, 0.3)),
        },
    }
    scene = load_scene(spec)
    end_ns = int(round(scene.duration_s * _NS))
    events, n_em = _events(scene, None, end_ns, pipeline)
    det, outs, trace = run_detector(events, config, end_ns, tick_ns=int(0.01 * _NS))
    out = {
        "seed": int(seed),
        "duration_s": scene.duration_s,
        "hold_s": hold,
        "medium": medium,
        "pipeline": pipeline,
        "n_emissions": n_em,
        "n_events": len(events),
        "state_mid_hold": int(_state_at(trace, int((t0 + hold / 2) * _NS))),
        "state_end": int(det.state.state),
        "state_after_all_released": int(det.state.state),  # 0.1 s after the release
    }
    out.update(_alarm_summary(outs))
    return out


def random_touches_trial(
    seed: int,
    config: SlipConfig | None = None,
    *,
    duration_s: float = 10.0,
    rate_hz: float = 20.0,
    hold_max_s: float = 0.05,
) -> dict:
    """The random_touches scene (Poisson touches over the cap with releases): false alarms."""
    rng = np.random.default_rng([7003, int(seed)])
    medium = "silicone" if rng.uniform() < 0.5 else "water_skin"
    spec = {
        "generator": "random_touches",
        "duration_s": duration_s,
        "seed": int(seed) + 3000,
        "sensor": {"medium": medium},
        "effects": {"attenuation": medium == "silicone", "release_emissions": True},
        "noise": {"snr_db": 30.0},
        "params": {
            "rate_hz": rate_hz,
            "max_polar_deg": 60.0,
            "hold_min_s": 0.005,
            "hold_max_s": hold_max_s,
        },
    }
    scene = load_scene(spec)
    end_ns = int(round(duration_s * _NS))
    pk = scene.triggered_source().next_packets(1 << 30, horizon_ns=end_ns)
    events = localized_events(pk, scene.config.geometry)
    det, outs, trace = run_detector(events, config, end_ns, tick_ns=int(0.01 * _NS))
    out = {
        "seed": int(seed),
        "duration_s": duration_s,
        "rate_hz": rate_hz,
        "hold_max_s": hold_max_s,
        "medium": medium,
        "n_emissions": int(len(pk.emissions)),
        "n_events": len(events),
        "counts": dict(det.counts),
    }
    out.update(_alarm_summary(outs))
    return out


def _touch_list(scene, t_s, pts, pol, speed, ids):
    return EmissionList.create(
        np.round(np.asarray(t_s) * _NS).astype(np.int64),
        pts,
        np.where(np.asarray(pol) > 0, "touch", "release") if np.ndim(pol) else "touch",
        polarity=pol,
        speed_m_s=speed,
        curvature_1_m=1000.0,
        alpha_1_s=3000.0,
        density_kg_m3=scene.config.density,
        event_id=ids,
    )


def _custom_trial(seed, spec, build, config, pipeline, tick=True):
    """Run a hand-built emission list (``build(scene, rng) -> EmissionList``) on the base
    scene ``spec``'s sensor and noise through a pipeline and the detector."""
    scene = load_scene(spec)
    rng = np.random.default_rng([7020, int(seed)])
    em = build(scene, rng)
    end_ns = int(round(scene.duration_s * _NS))
    source = _WithTouch(_Empty(), em)
    events, n_em = _events(scene, source, end_ns, pipeline)
    det, outs, trace = run_detector(
        events, config, end_ns, tick_ns=int(0.01 * _NS) if tick else None
    )
    return scene, det, outs, trace, events, n_em


class _Empty:
    def advance(self, t_ns):
        return EmissionList.empty()

    def scene_truth(self):
        return {}


def _cap_xy(rng, r_max=6e-3):
    r = r_max * math.sqrt(rng.uniform())
    th = rng.uniform(0, 2 * math.pi)
    return r * math.cos(th), r * math.sin(th)


def tapping_trial(
    seed: int,
    config: SlipConfig | None = None,
    *,
    pipeline: str = "triggered",
    duration_s: float = 3.0,
) -> dict:
    """A touch held for the whole trial while another spot 1.5 .. 8 mm away is tapped at
    1 .. 10 Hz (each tap: a touch, held 10 .. 100 ms, and its release at the same spot):
    false alarms."""
    rng = np.random.default_rng([7021, int(seed)])
    medium = "silicone" if rng.uniform() < 0.5 else "water_skin"
    spec = {
        "generator": "single_touch",
        "duration_s": duration_s,
        "seed": int(seed) + 6000,
        "sensor": {"medium": medium},
        "effects": {"attenuation": medium == "silicone"},
        "noise": {"snr_db": float(rng.uniform(25, 35))},
    }
    x0, y0 = _cap_xy(rng)
    d = float(rng.uniform(1.5e-3, 8e-3))
    ang = rng.uniform(0, 2 * math.pi)
    x1, y1 = x0 + d * math.cos(ang), y0 + d * math.sin(ang)
    if math.hypot(x1, y1) > 7.5e-3:
        x1, y1 = x0 - d * math.cos(ang), y0 - d * math.sin(ang)
    r1 = math.hypot(x1, y1)
    if r1 > 7.5e-3:
        x1, y1 = x1 * 7.5e-3 / r1, y1 * 7.5e-3 / r1
    rate = float(rng.uniform(1.0, 10.0))

    def build(scene, g):
        geo = scene.config.geometry
        p0, p1 = geo.surface_point_from_xy(x0, y0), geo.surface_point_from_xy(x1, y1)
        n = int(duration_s * rate)
        t = 0.05 + np.arange(n) / rate + g.uniform(0, 0.2 / rate, n)
        hold = g.uniform(0.01, 0.1, n)
        ok = t + hold < duration_s - 0.05
        t, hold = t[ok], hold[ok]
        times = np.concatenate([[0.01], t, t + hold, [duration_s - 0.02]])
        pts = np.vstack([p0[None], np.repeat(p1[None], 2 * t.size, 0), p0[None]])
        pol = np.concatenate([[1], np.ones(t.size), -np.ones(t.size), [-1]])
        spd = np.concatenate(
            [[0.3], g.uniform(0.1, 0.5, t.size), g.uniform(0.05, 0.2, t.size), [0.15]]
        )
        return _touch_list(scene, times, pts, pol, spd, np.arange(times.size))

    scene, det, outs, trace, events, n_em = _custom_trial(seed, spec, build, config, pipeline)
    out = {
        "seed": int(seed),
        "duration_s": duration_s,
        "distance_m": d,
        "tap_rate_hz": rate,
        "medium": medium,
        "pipeline": pipeline,
        "n_emissions": n_em,
        "n_events": len(events),
        "state_mid": int(_state_at(trace, int(duration_s / 2 * _NS))),
        "state_end": int(det.state.state),
    }
    out.update(_alarm_summary(outs))
    return out


def cycles_trial(
    seed: int,
    config: SlipConfig | None = None,
    *,
    pipeline: str = "triggered",
    duration_s: float = 3.0,
    hold_s: tuple[float, float] = (0.02, 0.5),
) -> dict:
    """Touch-release cycles: touches held ``hold_s`` (uniform; 20 .. 500 ms: a finger
    pressing and lifting; seconds: grasps, releases and re-grasps), 10 .. 300 ms apart,
    each within 3 mm of the previous one: false alarms, and the latched state 0.1 s after
    the scene's end (every touch released by then)."""
    spec, build, medium = _cycles_scene(seed, duration_s, hold_s)
    scene, det, outs, trace, events, n_em = _custom_trial(seed, spec, build, config, pipeline)
    out = {
        "seed": int(seed),
        "duration_s": duration_s,
        "medium": medium,
        "pipeline": pipeline,
        "n_emissions": n_em,
        "n_events": len(events),
        "state_end": int(det.state.state),
        "state_after_all_released": int(
            det.advance(int(round((duration_s + 0.1) * _NS))).state
        ),
    }
    out.update(_alarm_summary(outs))
    return out


#: grasp-release cycles: `cycles_trial`'s scene with a robot hand's holds (s)
GRASP_CYCLES = {"duration_s": 30.0, "hold_s": (0.5, 10.0)}


def grasp_cycles_trial(
    seed: int, config: SlipConfig | None = None, *, pipeline: str = "triggered"
) -> dict:
    """Grasp-release cycles: grasps held 0.5 .. 10 s (longer than the detector's evidence
    window), released, the next within 3 mm, over 30 s (``GRASP_CYCLES``): false alarms,
    and the latched state at the end (every touch released)."""
    return cycles_trial(seed, config, pipeline=pipeline, **GRASP_CYCLES)


def cycles_packets(seed: int, duration_s: float = 3.0, hold_s=(0.02, 0.5)):
    """(triggered packets, geometry) of `cycles_trial`'s scene: the waveforms the
    'triggered' pipeline localizes, with their emissions (the truth)."""
    spec, build, _ = _cycles_scene(seed, duration_s, hold_s)
    scene = load_scene(spec)
    em = build(scene, np.random.default_rng([7020, int(seed)]))  # as `_custom_trial`
    end_ns = int(round(scene.duration_s * _NS))
    pk = _triggered(scene, _WithTouch(_Empty(), em)).next_packets(1 << 30, horizon_ns=end_ns)
    return pk, scene.config.geometry


def _cycles_scene(seed, duration_s, hold_s=(0.02, 0.5)):
    """(scene spec, emission builder, medium) of the touch-release cycles family."""
    rng = np.random.default_rng([7022, int(seed)])
    medium = "silicone" if rng.uniform() < 0.5 else "water_skin"
    spec = {
        "generator": "single_touch",
        "duration_s": duration_s,
        "seed": int(seed) + 7000,
        "sensor": {"medium": medium},
        "effects": {"attenuation": medium == "silicone"},
        "noise": {"snr_db": float(rng.uniform(25, 35))},
    }

    def build(scene, g):
        geo = scene.config.geometry
        times, pts, pol, spd = [], [], [], []
        t = 0.01
        x, y = _cap_xy(g, 5e-3)
        while True:
            hold = g.uniform(*hold_s)
            if t + hold > duration_s - 0.01:
                break
            p = geo.surface_point_from_xy(x, y)
            times += [t, t + hold]
            pts += [p, p]
            pol += [1, -1]
            spd += [g.uniform(0.1, 0.5), g.uniform(0.05, 0.2)]
            t += hold + g.uniform(0.01, 0.3)
            r, a = g.uniform(0, 3e-3), g.uniform(0, 2 * math.pi)
            x, y = x + r * math.cos(a), y + r * math.sin(a)
            if math.hypot(x, y) > 7e-3:
                x, y = 0.5 * x, 0.5 * y
        return _touch_list(
            scene, times, np.array(pts), np.array(pol), np.array(spd), np.arange(len(times))
        )

    return spec, build, medium


def weak_release_trial(seed: int, duration_s: float = 3.0, hold_s=(0.02, 0.5)) -> dict:
    """The releases of a touch-release cycles scene (`cycles_trial`'s, waveforms) that the
    localizer rejects for low SNR alone, against the simulator's truth: estimated SNR,
    position error (m), polarity right, kept by the weak-release gate; and the packets the
    gate keeps that are not releases (should be none)."""
    pk, geo = cycles_packets(seed, duration_s, hold_s)
    res = localize(pk.samples_v, pk.sample_rate_hz, pk.onset_index, geometry=geo,
                   saturated=pk.saturated)
    kept, weak = kept_with_weak_releases(res, np.asarray(pk.emissions.time_ns, np.int64))
    truth_pol = np.sign(np.asarray(pk.emissions.strength_pa_m, float))
    err = np.linalg.norm(res.point_m - np.asarray(pk.emissions.point_m, float), axis=1)
    low = (np.asarray(res.reason_flags) == (1 << int(Reason.LOW_SNR))) & (truth_pol < 0)
    idx = np.flatnonzero(low)
    return {
        "seed": int(seed),
        "n_releases": int((truth_pol < 0).sum()),
        "low_snr_db": [float(res.snr_db_est[i]) for i in idx],
        "low_error_m": [float(err[i]) for i in idx],
        "low_polarity_right": [bool(res.polarity[i] < 0) for i in idx],
        "low_kept": [bool(weak[i]) for i in idx],
        "kept_not_release": int((weak & (truth_pol >= 0)).sum()),
    }


def noise_window_snr_db(n: int = 20000, sample_rate_hz: float = 5e6, seed: int = 0):
    """(estimated SNR dB, polarity, position 1-sigma per axis m, NaN unless the packet was
    rejected for low SNR alone) of ``n`` windows of white noise alone (the triggered
    windows' 40 us, onset 8 us in, at ``sample_rate_hz``): what the weak-release gate has
    to keep out."""
    from ae_tactile.geometry import FingertipGeometry

    rng = np.random.default_rng([7400, int(seed)])
    m = int(round(40e-6 * sample_rate_hz))
    x = rng.normal(0.0, 1e-3, (int(n), 4, m))
    on = np.full(int(n), int(round(8e-6 * sample_rate_hz)))
    res = localize(x, sample_rate_hz, on, geometry=FingertipGeometry())
    sd = np.sqrt(np.trace(res.covariance_m2, axis1=1, axis2=2) / 2.0)
    sd = np.where(np.asarray(res.reason_flags) == (1 << int(Reason.LOW_SNR)), sd, np.nan)
    return np.asarray(res.snr_db_est, float), np.asarray(res.polarity, int), sd


def stylus_events(
    seed: int,
    *,
    pipeline: str = "triggered",
    jitter: tuple = (0.0, 0.2),
    period_m: tuple = (0.2e-3, 0.6e-3),
):
    """(scene, its scene spec, localized events (time order), number of true emissions,
    end_ns) of `stylus_trial`'s slide ``seed``: speed 5 .. 50 mm/s and period (m) log-uniform,
    timing jitter uniform in ``jitter`` (fraction of the period), a great-circle stroke of
    40 periods (8 .. 14 mm)."""
    rng = np.random.default_rng([7023, int(seed)])
    v = float(math.exp(rng.uniform(math.log(0.005), math.log(0.05))))
    lam = float(math.exp(rng.uniform(math.log(period_m[0]), math.log(period_m[1]))))
    jit = float(rng.uniform(*jitter))
    path = float(min(14e-3, max(8e-3, 40 * lam)))
    heading = float(rng.uniform(0, 360))
    h = math.radians(heading)
    x0, y0 = -0.5 * path * math.cos(h), -0.5 * path * math.sin(h)
    medium = "silicone" if rng.uniform() < 0.5 else "water_skin"
    dur = 0.01 + path / v + 0.1
    spec = {
        "generator": "stylus",
        "duration_s": dur,
        "seed": int(seed) + 8000,
        "sensor": {"medium": medium},
        "effects": {"attenuation": medium == "silicone"},
        "noise": {"snr_db": float(rng.uniform(25, 35))},
        "params": {
            "x_m": x0,
            "y_m": y0,
            "heading_deg": heading,
            "slide_speed_m_s": v,
            "period_m": lam,
            "path_m": path,
            "jitter_fraction": jit,
            "contact_radius_m": float(rng.uniform(0.1e-3, 0.4e-3)),
            "polarity": str(rng.choice(["random", "compression", "rarefaction"])),
        },
    }
    scene = load_scene(spec)
    end_ns = int(round(dur * _NS))
    events, n_em = _events(scene, None, end_ns, pipeline)
    return scene, spec, events, n_em, end_ns


def stylus_trial(
    seed: int,
    config: SlipConfig | None = None,
    *,
    pipeline: str = "triggered",
    jitter: tuple = (0.0, 0.2),
    period_m: tuple = (0.2e-3, 0.6e-3),
) -> dict:
    """A stylus dragged over the tip (the stylus scene, `stylus_events`): one tracked
    contact, TEXTURE with the spatial period from the tracked speed (no sliding speed
    given), its error, the time to the first TEXTURE, the number of contacts the emissions
    were split into."""
    scene, spec, events, n_em, end_ns = stylus_events(
        seed, pipeline=pipeline, jitter=jitter, period_m=period_m
    )
    v, lam = spec["params"]["slide_speed_m_s"], spec["params"]["period_m"]
    jit, path = spec["params"]["jitter_fraction"], spec["params"]["path_m"]
    det, outs, trace = run_detector(events, config, end_ns)
    truth = scene.process.scene_truth()
    tex = [o for o in outs if o.kind == EventType.TEXTURE]
    lam_est = np.array([o.spatial_period_m for o in tex])
    first = tex[0] if tex else None
    ids = {o.contact_id for o in outs}
    from ae_tactile.sim.generators import stylus_track

    dir_err = []
    for o in outs:
        if o.kind in (EventType.SLIP, EventType.TEXTURE) and np.all(
            np.isfinite(o.slip_direction)
        ):
            _, vel = stylus_track(truth, scene.config.geometry.radius_m, [o.time_ns])
            u = vel[0] / np.linalg.norm(vel[0])
            dir_err.append(math.degrees(math.acos(float(np.clip(o.slip_direction @ u, -1, 1)))))
    return {
        "seed": int(seed),
        "slide_speed_m_s": v,
        "period_m": lam,
        "jitter_fraction": jit,
        "path_m": path,
        "polarity": spec["params"]["polarity"],
        "n_emissions": n_em,
        "n_events": len(events),
        "n_contacts_reporting": len(ids),
        "n_texture": len(tex),
        "texture_delay_ms": None
        if first is None
        else (first.time_ns - truth["start_time_ns"]) / 1e6,
        "rel_error_first": None if first is None else float(first.spatial_period_m / lam - 1.0),
        "rel_error_median": None if not tex else float(np.nanmedian(lam_est) / lam - 1.0),
        "rel_error_max": None if not tex else float(np.nanmax(np.abs(lam_est / lam - 1.0))),
        "direction_error_deg_median": None if not dir_err else float(np.median(dir_err)),
        "n_precursor": sum(o.kind == EventType.SLIP_PRECURSOR for o in outs),
    }


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
    st = _interference_finger(
        seed,
        discriminate=discriminate,
        duration_s=duration_s,
        input_without_echoes=input_without_echoes,
    )
    return _interference_outcome(st, config)


def _interference_finger(
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
    from ae_tactile.dsp.interference import (
        TRAIN_TOL_S,
        TRAIN_TOL_SAMPLES,
        BurstTrain,
        common_mode_interference,
        common_mode_share,
    )
    from ae_tactile.pipeline import (
        APEX_POLAR_RAD,
        ROUTE_ALL,
        ROUTE_SPECTRUM,
        interference_route,
    )
    from ae_tactile.sim.interference import InterferenceSource

    rng = np.random.default_rng([7024, int(seed)])
    medium = "silicone" if rng.uniform() < 0.5 else "water_skin"
    fs = float(rng.choice([2e6, 5e6, 10e6]))
    rate = float(math.exp(rng.uniform(math.log(1.0), math.log(1e4))))
    coupling = "input" if rng.uniform() < 0.25 else "adc"
    if input_without_echoes:
        coupling = "input"
    reflections = coupling == "input" and not input_without_echoes
    x, y = _cap_xy(rng)
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
    scene = load_scene(spec)
    geo = scene.config.geometry
    end_ns = int(round(duration_s * _NS))
    pk = scene.triggered_source().next_packets(1 << 30, horizon_ns=end_ns)
    source = InterferenceSource(scene)
    if hand is not None:
        source.bursts[0]["times_ns"] = np.asarray(hand["burst_times_ns"], np.int64)
    t_if, ip = source.next_packets(end_ns)
    n_if = int(t_if.size)
    kw = dict(
        noise_rms_v=scene.noise_rms_v,
        geometry=geo,
        lowpass_hz=scene.config.lowpass_hz,
        lowpass_order=scene.config.lowpass_order,
        # the driver's default: the echo test learnt from the device's first touches
        echo_min=learnt_echo_min(scene.config, scene.noise_rms_v, rng),
    )
    events = localized_events(pk, geo)
    n_acoustic = len(events)
    # every packet the localizer accepted at the apex or with a poor fit goes through the
    # discriminator; the apex ones (masked or not) make the timing's history, in time order
    cand = []  # (onset ns, acoustic?, index, masked)

    def masks(x, onset):
        """(the full tests' mask, the spectrum tests' mask, common-mode share), as the
        driver applies them: the full tests at the apex or a poor fit, the spectrum tests
        on the other packets with one waveform on the four channels."""
        z = np.zeros(x.shape[0], bool)
        if not discriminate or x.shape[0] == 0:
            return z, z, np.zeros(x.shape[0])
        full, _ = common_mode_interference(x, fs, onset, **kw)
        spec_kw = {**kw, "echo_min": None, "shape_min": None}
        spectrum, _ = common_mode_interference(x, fs, onset, **spec_kw)
        return full, spectrum, common_mode_share(x, scene.noise_rms_v, onset)

    m_full, m_spec, share_ac = masks(pk.samples_v, pk.onset_index)
    ev_keep = []
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
    n_train = 0
    phantom = []
    train = set()
    if n_if:
        res = localize(ip.samples_v, fs, ip.onset_index, geometry=geo)
        f_if, s_if, share_if = masks(ip.samples_v, ip.onset_index)
        pol = np.arccos(np.clip(res.point_m[:, 2] / np.linalg.norm(res.point_m, axis=1), -1, 1))
        route = np.array([interference_route(pol[i], res.confidence[i], share_if[i])
                          for i in range(n_if)])
        mask = np.where(route == ROUTE_ALL, f_if, (route == ROUTE_SPECTRUM) & s_if)
        mask &= res.accepted
        onset_ns = t_if + int(round(1e9 / fs))
        for i in np.flatnonzero(res.accepted & (pol < APEX_POLAR_RAD)):
            cand.append((int(onset_ns[i]), False, int(i), bool(mask[i])))
        if discriminate:
            hist = BurstTrain()
            tol = max(TRAIN_TOL_S, TRAIN_TOL_SAMPLES / fs)
            for t_ns, acoustic, ref, masked in sorted(cand, key=lambda c: c[0]):
                if not masked and hist.is_member(t_ns * 1e-9, tol):
                    train.add((acoustic, id(ref) if acoustic else ref))
                hist.add(t_ns * 1e-9)
        n_train = sum(1 for a, _ in train if not a)
        ev_keep = [e for e in ev_keep if (True, id(e)) not in train]
        travel = np.round(geo.arrival_times_s(res.point_m).min(axis=1) * 1e9).astype(np.int64)
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


def _interference_outcome(st: dict, config: SlipConfig | None, coincident=()) -> dict:
    """The detector's outcome of `_interference_finger`'s events; ``coincident``: the
    apex packets' refs ((acoustic?, the event's id() or the burst's index)) the hand's
    coincidence rejected."""
    drop = set(coincident)
    ev_keep = [e for e in st["ev_keep"] if (True, id(e)) not in drop]
    phantom = [e for e in st["phantom"] if (False, e.packet_id - 1_000_000) not in drop]
    n_if, n_train, end_ns = st["n_interference"], st["n_train"], st["end_ns"]
    n_rej = n_if - len(phantom)  # rejected by the localizer, the packet tests or the timing
    allev = sorted(ev_keep + phantom, key=lambda e: e.time_ns)
    det, outs, trace = run_detector(allev, config, end_ns, tick_ns=int(0.01 * _NS))
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
        "state_mid": int(_state_at(trace, end_ns // 2)),
    })
    out.update(_alarm_summary(outs))
    return out


def link_clock(rng, warmup_s: float = 12.0):
    """A fingertip's link on the simulator's model of a USB device, as `DeviceClockMapper`
    sees it: the device's sample clock runs at 1 + skew (|skew| <= 50 ppm, a crystal's
    tolerance) from an offset of its own; it sends a frame every 1 ms of its clock, which
    reaches the host after a latency floor of its own (50 .. 500 us: the host controller's
    polling and the driver's wake-up; two fingertips' mapped stamps of one burst differ by
    the difference of their floors, 0.44 ms between two simulated fingertips' ptys here)
    plus the wait for the next 1 ms poll (uniform) plus a tail (exponential, mean 200 us).
    Returns ``(to_host, arrival)``: to_host(t_ns)
    is the mapped host stamp (ns) of a device onset at true time t_ns (s on the scene's
    clock = host time), from the link's mapper as it stands when the frame that carries it
    has come; arrival(t_ns) that frame's host arrival time (ns)."""
    from ae_tactile.timesync import DeviceClockMapper

    skew = rng.uniform(-50e-6, 50e-6)
    d0 = rng.uniform(0.0, 10.0) * _NS
    floor = rng.uniform(50e3, 500e3)
    frame = 1_000_000  # ns of device clock

    def device(t_ns):
        return (np.asarray(t_ns, np.float64) + d0) * (1.0 + skew)

    def true_of_device(d):
        return np.asarray(d, np.float64) / (1.0 + skew) - d0

    k0 = int(device(-warmup_s * _NS) // frame) + 1
    mapper = DeviceClockMapper()
    state = {"k": k0}
    arrivals: dict[int, float] = {}

    def frame_arrival(k):
        if k not in arrivals:
            sent = float(true_of_device(k * frame))
            arrivals[k] = sent + floor + rng.uniform(0, 1e6) + rng.exponential(200e3)
        return arrivals[k]

    def advance(k_to):
        for k in range(state["k"], k_to + 1):
            mapper.update(k * frame, int(frame_arrival(k)))
        state["k"] = max(state["k"], k_to + 1)

    def carrier(t_ns):
        return int(float(device(t_ns)) // frame) + 1  # the first frame sent after the onset

    def to_host(t_ns):
        k = carrier(t_ns)
        advance(k)
        return mapper.to_host_ns(int(round(float(device(t_ns)))))

    def arrival(t_ns):
        return frame_arrival(carrier(t_ns))

    return to_host, arrival


def hand_interference_trial(
    seed: int,
    config: SlipConfig | None = None,
    *,
    n_fingers: int | None = None,
    duration_s: float = 1.0,
    window_s: float | None = None,
    wait_s: float | None = None,
    touch_rate_hz: float = 5.0,
) -> list[dict]:
    """Interference across the fingertips of one hand: one source's bursts (1 Hz .. 10 kHz,
    70 % periodic) enter the amplifier's input of every fingertip (2 .. 5, no wall echoes:
    one packet cannot tell them from an apex touch), each fingertip holding a touch of its
    own, through `_interference_finger` (the packet tests and the timing, as the driver)
    and then `HandCoincidence`: every fingertip's apex packets, mapped to host time by its
    own link (`link_clock`), reach the others a transport delay (0.2 .. 1 ms) after their
    frame; an apex packet its own tests kept waits ``wait_s`` for them. Apex touches at
    random times (Poisson, ``touch_rate_hz`` on each fingertip, not rendered: their packet
    tests are measured per packet) go through the same test: the coincidence's cost to
    touches. Returns one row per fingertip: `interference_trial`'s counts after the
    coincidence, plus ``n_rejected_coincidence``, ``n_apex_touches``,
    ``n_apex_touches_kept``, ``reports_late`` and ``stamp_error_us`` (each burst's mapped
    stamp less its true time, this fingertip's bursts); ``alone_*``: the same fingertip
    without the hand (the control: phantom events, contacts, alarm onsets)."""
    from ae_tactile.dsp.coincidence import (
        COINCIDENCE_WAIT_S,
        COINCIDENCE_WINDOW_S,
        HandCoincidence,
    )
    from ae_tactile.sim.interference import burst_times_s

    rng = np.random.default_rng([7031, int(seed)])
    n_f = int(n_fingers) if n_fingers else int(rng.integers(2, 6))
    rate = float(math.exp(rng.uniform(math.log(1.0), math.log(1e4))))
    periodic = bool(rng.uniform() < 0.7)
    hand = {
        "medium": "silicone" if rng.uniform() < 0.5 else "water_skin",
        "sample_rate_hz": float(rng.choice([2e6, 5e6, 10e6])),
        "rate_hz": rate,
        "periodic": periodic,
        "burst_times_ns": np.round(
            burst_times_s(duration_s, rate, periodic=periodic, rng=rng) * _NS
        ).astype(np.int64),
    }
    window_s = COINCIDENCE_WINDOW_S if window_s is None else window_s
    wait_s = COINCIDENCE_WAIT_S if wait_s is None else wait_s
    fingers = []
    for f in range(n_f):
        st = _interference_finger(
            1_000_000 + 8 * int(seed) + f,
            discriminate=True,
            duration_s=duration_s,
            input_without_echoes=True,
            hand=hand,
        )
        to_host, arrival = link_clock(rng)
        n_touch = int(rng.poisson(touch_rate_hz * duration_s))
        touch_ns = np.sort(rng.uniform(0.0, duration_s * _NS, n_touch)).astype(np.int64)
        apex = list(st["apex"]) + [(int(t), None, i, False) for i, t in enumerate(touch_ns)]
        apex.sort(key=lambda a: a[0])
        mapped = [to_host(a[0]) for a in apex]
        came = [arrival(a[0]) for a in apex]
        fingers.append((st, apex, mapped, came, n_touch))
    rows = []
    for f, (st, apex, mapped, came, n_touch) in enumerate(fingers):
        hc = HandCoincidence(window_s=window_s, wait_s=wait_s)
        events = []  # (host time ns, order, kind, payload)
        for g, (_, _, o_mapped, o_came, _) in enumerate(fingers):
            if g == f:
                continue
            for m, c in zip(o_mapped, o_came):
                events.append((c + rng.uniform(0.2e6, 1e6), 1, "report", (m, g)))
        for a, m, c in zip(apex, mapped, came):
            events.append((c, 2, "own", m))
            if a[3]:
                continue  # rejected by this fingertip's own tests
            events.append((c, 3, "hold", (m, a)))
            # decided when its wait is over, or when its frame comes if that is later
            events.append((m + hc.wait_ns, 0, "due", None) if c < m + hc.wait_ns
                          else (c, 4, "due", None))
        coincident, touches_kept = _hand_decisions(hc, events)
        # a touch at a random time is kept when no report lies within the window: the
        # share of the trial the reports' windows leave free (their union's complement),
        # each fingertip's reports less the offset learnt for it
        rep = np.sort(np.asarray(
            [m - hc.offsets_ns.get(str(g), 0)
             for g, fg in enumerate(fingers) if g != f for m in fg[2]], np.float64
        ))
        covered = (
            2 * hc.window_ns + np.minimum(np.diff(rep), 2 * hc.window_ns).sum() if rep.size else 0
        )
        alone = _interference_outcome(st, config)
        out = _interference_outcome(st, config, coincident)
        out.update(
            {
                "n_fingers": n_f,
                "finger": f,
                "window_s": hc.window_ns * 1e-9,
                "alone_phantom_events": alone["n_phantom_events"],
                "alone_contacts_created": alone["contacts_created"],
                "alone_alarm_onsets": alone["n_alarm_onsets"],
                "n_rejected_coincidence": sum(1 for k in coincident if not k[0]),
                "n_acoustic_rejected_coincidence": sum(1 for k in coincident if k[0]),
                "n_apex_touches": n_touch,
                "n_apex_touches_kept": touches_kept,
                "apex_touch_kept_expected": max(0.0, 1.0 - covered / (duration_s * _NS)),
                "hand_seed": int(seed),
                "reports_late": int(hc.counts["reports_late"]),
                "offsets_learnt": int(hc.counts["offsets_learnt"]),
                "stamp_error_us": [
                    round((m - a[0]) * 1e-3, 2) for a, m in zip(apex, mapped) if a[1] is False
                ],
            }
        )
        rows.append(out)
    return rows


def _hand_decisions(hc, events) -> tuple[set, int]:
    """Play a fingertip's (host time ns, order, kind, payload) events through its
    `HandCoincidence` in time order: (the refs it rejected, the apex touches it kept)."""
    coincident: set = set()
    touches_kept = 0
    for t, _, kind, payload in sorted(events, key=lambda e: (e[0], e[1])):
        if kind == "report":
            hc.add_others([payload[0]], payload[1])
        elif kind == "own":
            hc.add_own([payload])
        elif kind == "hold":
            hc.hold(payload[0], payload[1])
        else:
            kept, rejected = hc.due(int(t))
            touches_kept += sum(1 for a in kept if a[1] is None)
            coincident.update(_apex_key(a) for a in rejected if a[1] is not None)
    return coincident, touches_kept


def _apex_key(a) -> tuple:
    """The ref `_interference_outcome` knows an apex packet (onset, acoustic?, ref, ...) by."""
    return (a[1], id(a[2]) if a[1] else a[2])


def learnt_echo_min(config, noise_rms_v: float, rng, n: int = 3, n_touches: int = 24):
    """The echo test's threshold the driver learns by default (`EchoLearner`,
    ``interference_echo_min`` -1) from the device's first ``n`` touches away from the apex
    whose echo it could measure (of ``n_touches``: polar 10 .. 45 deg, 0.1 .. 0.5 m/s,
    localized; a weak one is not measured): None on a device without wall echoes (or when
    fewer than ``n`` were measured)."""
    from ae_tactile.dsp.interference import EchoLearner, echo_ratio
    from ae_tactile.sim.triggered import render_triggered

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
    from ae_tactile.sim.triggered import render_triggered

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
    from ae_tactile.dsp.interference import common_mode_interference
    from ae_tactile.sim.config import SimConfig
    from ae_tactile.sim.interference import KINDS, render_interference
    from ae_tactile.sim.scene import reference_noise_rms

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


# ---------------------------------------------------------------------- texture, drift
def texture_trial(
    seed: int, config: SlipConfig | None = None, *, speed_known: bool = True
) -> dict:
    """Sliding at v (5-50 mm/s) over a texture with emission rate v/lambda in 10-150 Hz."""
    rng = np.random.default_rng([7004, int(seed)])
    v = float(math.exp(rng.uniform(math.log(0.005), math.log(0.05))))
    rate = float(math.exp(rng.uniform(math.log(10.0), math.log(150.0))))
    lam = v / rate
    x, y = _cap_point_xy(rng, 0.01, 50.0)
    dur = max(1.0, 40.0 / rate)
    spec = {
        "generator": "texture",
        "duration_s": dur,
        "seed": int(seed) + 4000,
        "sensor": {"medium": "silicone"},
        "effects": {"attenuation": True},
        "noise": {"snr_db": float(rng.uniform(25, 35))},
        "params": {
            "x_m": x,
            "y_m": y,
            "slide_speed_m_s": v,
            "period_m": lam,
            "jitter_fraction": float(rng.uniform(0.02, 0.08)),
            "contact_radius_m": float(rng.uniform(0.5e-3, 1.5e-3)),
        },
    }
    scene = load_scene(spec)
    end_ns = int(round(dur * _NS))
    pk = scene.triggered_source().next_packets(1 << 30, horizon_ns=end_ns)
    events = localized_events(pk, scene.config.geometry)
    det, outs, trace = run_detector(
        events, config, end_ns, sliding_speed_m_s=v if speed_known else None
    )
    tex = [o for o in outs if o.kind == EventType.TEXTURE]
    first = tex[0] if tex else None
    lam_est = np.array([o.spatial_period_m for o in tex])
    out = {
        "seed": int(seed),
        "slide_speed_m_s": v,
        "period_m": lam,
        "rate_hz": rate,
        "jitter_fraction": spec["params"]["jitter_fraction"],
        "n_emissions": int(len(pk.emissions)),
        "n_events": len(events),
        "n_texture": len(tex),
        "texture_time_ms": None if first is None else first.time_ns / 1e6,
        "period_first_m": None if first is None else float(first.spatial_period_m),
        "period_median_m": None if not tex else float(np.median(lam_est)),
        "rate_first_hz": None if first is None else float(first.emission_rate_hz),
        "rel_error_first": None if first is None else float(first.spatial_period_m / lam - 1.0),
        "rel_error_median": None if not tex else float(np.median(lam_est) / lam - 1.0),
        "rel_error_max": None if not tex else float(np.max(np.abs(lam_est / lam - 1.0))),
        "final_state": int(det.state.state),
    }
    out.update(
        {
            "n_precursor": sum(o.kind == EventType.SLIP_PRECURSOR for o in outs),
            "n_slip": sum(o.kind == EventType.SLIP for o in outs),
        }
    )
    return out


def drift_slip_trial(
    seed: int, config: SlipConfig | None = None, *, pipeline: str = "triggered"
) -> dict:
    """plane_slip with the contact drifting along +x: SLIP delay after the slip start and
    the angle between the reported direction and +x (projected on the tangent plane)."""
    rng = np.random.default_rng([7005, int(seed)])
    drift = float(rng.uniform(0.01, 0.04))
    rad = float(rng.uniform(1e-3, 2.5e-3))
    x0 = float(rng.uniform(-3e-3, 0.0))
    y0 = float(rng.uniform(-2e-3, 2e-3))
    dur_slip = 0.15
    spec = {
        "generator": "plane_slip",
        "duration_s": 0.2,
        "seed": int(seed) + 5000,
        "sensor": {"medium": "silicone"},
        "effects": {"attenuation": True},
        "noise": {"snr_db": 30.0},
        "params": {
            "x_m": x0,
            "y_m": y0,
            "start_s": 0.01,
            "slip_duration_s": dur_slip,
            "rate_hz": float(rng.uniform(150, 500)),
            "contact_radius_m": rad,
            "drift_m_s": drift,
        },
    }
    scene = load_scene(spec)
    end_ns = int(0.2 * _NS)
    events, _ = _events(scene, None, end_ns, pipeline)
    det, outs, trace = run_detector(events, config, end_ns)
    slips = [o for o in outs if o.kind == EventType.SLIP]
    first = _first(outs, EventType.SLIP)
    angles = []
    for o in slips:
        if np.all(np.isfinite(o.slip_direction)):
            n = o.position_m / np.linalg.norm(o.position_m)
            ex = np.array([1.0, 0.0, 0.0]) - n[0] * n
            ex /= np.linalg.norm(ex)
            angles.append(math.degrees(math.acos(float(np.clip(o.slip_direction @ ex, -1, 1)))))
    return {
        "seed": int(seed),
        "drift_m_s": drift,
        "contact_radius_m": rad,
        "rate_hz": spec["params"]["rate_hz"],
        "n_events": len(events),
        "slip_delay_ms": None if first is None else (first.time_ns - int(0.01 * _NS)) / 1e6,
        "n_slip": len(slips),
        "n_with_direction": len(angles),
        "direction_error_deg_median": None if not angles else float(np.median(angles)),
        "direction_error_deg_mean": None if not angles else float(np.mean(angles)),
        "direction_errors_deg": [float(a) for a in angles],
        "direction_error_deg_max": None if not angles else float(np.max(angles)),
    }


# ---------------------------------------------------------------------- summary
def _pct(x, qs=(0, 5, 50, 95, 100)):
    x = np.asarray([v for v in x if v is not None], dtype=float)
    if x.size == 0:
        return None
    return {
        ("min" if q == 0 else "max" if q == 100 else f"p{q}"): float(np.percentile(x, q))
        for q in qs
    }


def summarize_incipient(trials: list[dict]) -> dict:
    n = len(trials)
    ok = [t for t in trials if t["precursor_before_gross"]]
    return {
        "n_trials": n,
        "precursor_before_gross_rate": len(ok) / n if n else None,
        "n_precursor_before_gross": len(ok),
        "lead_ms": _pct([t["lead_ms"] for t in ok]),
        "lead_fraction_of_ramp": _pct(
            [t["lead_ms"] / (1e3 * t["time_to_gross_slip_s"]) for t in ok]
        ),
        "q_at_precursor": _pct([t["q_at_precursor"] for t in ok]),
        "lead_ge_100ms_rate": (sum(t["lead_ms"] >= 100 for t in ok) / n) if n else None,
        "lead_ge_74ms_rate": (sum(t["lead_ms"] >= 74 for t in ok) / n) if n else None,
        "slip_detected_rate": sum(t["slip_time_ns"] is not None for t in trials) / n
        if n
        else None,
        "slip_delay_ms": _pct([t["slip_delay_ms"] for t in trials]),
        "q_at_slip": _pct([t["q_at_slip"] for t in trials]),
        "slip_before_gross_rate": (
            sum(t["slip_delay_ms"] is not None and t["slip_delay_ms"] < 0 for t in trials) / n
            if n
            else None
        ),
        "precursor_error_to_ring_m": _pct([t["precursor_error_to_ring_m"] for t in trials]),
        "texture_events_total": int(sum(t["n_texture_events"] for t in trials)),
        "failures": [t["seed"] for t in trials if not t["precursor_before_gross"]],
    }


def summarize_alarms(trials: list[dict]) -> dict:
    minutes = sum(t["duration_s"] for t in trials) / 60.0
    onsets = sum(t["n_alarm_onsets"] for t in trials)
    return {
        "n_trials": len(trials),
        "minutes": minutes,
        "alarm_onsets": onsets,
        "false_alarms_per_minute": onsets / minutes if minutes else None,
        "precursor_events": sum(t["n_precursor"] for t in trials),
        "slip_events": sum(t["n_slip"] for t in trials),
        "texture_events": sum(t["n_texture"] for t in trials),
        "trials_with_alarm": [t["seed"] for t in trials if t["n_alarm_onsets"]],
        **_release_summary(trials),
    }


def _release_summary(trials: list[dict]) -> dict:
    """Trials whose every touch is released (touch-hold-release, cycles): how often the
    finger was free 0.1 s after the last release (the latched state NO_CONTACT); for
    touch-hold-release also for holds within / beyond the evidence window."""
    rel = [t for t in trials if "state_after_all_released" in t]
    if not rel:
        return {}
    free = [t["state_after_all_released"] == ContactState.NO_CONTACT for t in rel]
    out = {"free_after_release_rate": sum(free) / len(rel)}
    held = [t for t in rel if "hold_s" in t]
    if not held:
        return out
    w_s = SlipConfig().evidence_window_s
    out["evidence_window_s"] = w_s
    for name, rows in (
        ("short", [t for t in held if t["hold_s"] <= w_s]),
        ("long", [t for t in held if t["hold_s"] > w_s]),
    ):
        out[f"n_holds_{name}"] = len(rows)
        out[f"ended_at_release_rate_{name}"] = (
            sum(t["state_after_all_released"] == ContactState.NO_CONTACT for t in rows)
            / len(rows)
            if rows
            else None
        )
    return out


def summarize_texture(trials: list[dict]) -> dict:
    det = [t for t in trials if t["n_texture"]]
    n = len(trials)
    return {
        "n_trials": n,
        "detected_rate": len(det) / n if n else None,
        "abs_rel_error_first": _pct([abs(t["rel_error_first"]) for t in det]),
        "abs_rel_error_median": _pct([abs(t["rel_error_median"]) for t in det]),
        "abs_rel_error_max_over_events": _pct([t["rel_error_max"] for t in det]),
        "within_10pct_rate": (sum(t["rel_error_max"] <= 0.10 for t in det) / n) if n else None,
        "detection_time_ms": _pct([t["texture_time_ms"] for t in det]),
        "failures": [t["seed"] for t in trials if not t["n_texture"]],
    }


def run_evaluation(
    *,
    n_incipient: int = 100,
    n_incipient_touch: int = 30,
    n_closed_loop: int = 30,
    n_thr: int = 100,
    n_random: int = 12,
    random_duration_s: float = 10.0,
    n_texture: int = 50,
    n_drift: int = 20,
    n_incipient_stream: int = 0,
    n_thr_stream: int = 0,
    seed: int = 0,
    config: SlipConfig | None = None,
    post_s: float = 0.25,
    progress=None,
) -> dict:
    """Every trial family with consecutive seeds from ``seed``; returns the summaries and
    the per-trial records (JSON-able)."""
    cfg = config or SlipConfig()
    out = {
        "config": cfg.as_dict(),
        "ranges": {k: list(v) if isinstance(v, tuple) else v for k, v in INCIPIENT_RANGES.items()},
    }
    timing = {}

    def run(name, fn, n):
        t0 = time.perf_counter()
        rows = []
        for i in range(n):
            rows.append(fn(seed + i))
            if progress:
                progress(name, i + 1, n)
        timing[name] = time.perf_counter() - t0
        return rows

    inc = run("incipient", lambda s: incipient_slip_trial(s, cfg, post_s=post_s), n_incipient)
    inc_t = run(
        "incipient_touch",
        lambda s: incipient_slip_trial(s, cfg, announce_touch=True, post_s=post_s),
        n_incipient_touch,
    )
    cl = run("closed_loop", lambda s: closed_loop_trial(s, cfg), n_closed_loop)
    thr = run("touch_hold_release", lambda s: touch_hold_release_trial(s, cfg), n_thr)
    rnd = run(
        "random_touches",
        lambda s: random_touches_trial(s, cfg, duration_s=random_duration_s),
        n_random,
    )
    rnd_dense = run(
        "random_touches_dense",
        lambda s: random_touches_trial(
            s + 10_000, cfg, duration_s=random_duration_s, rate_hz=50.0, hold_max_s=0.5
        ),
        n_random,
    )
    tex = run("texture", lambda s: texture_trial(s, cfg), n_texture)
    drift = run("drift", lambda s: drift_slip_trial(s, cfg), n_drift)
    inc_s = run(
        "incipient_stream",
        lambda s: incipient_slip_trial(s, cfg, post_s=post_s, pipeline="stream"),
        n_incipient_stream,
    )
    thr_s = run(
        "touch_hold_release_stream",
        lambda s: touch_hold_release_trial(s, cfg, pipeline="stream"),
        n_thr_stream,
    )
    out["summary"] = {
        "incipient_slip": summarize_incipient(inc),
        "incipient_slip_announced": summarize_incipient(inc_t) if inc_t else None,
        "closed_loop": None
        if not cl
        else {
            "n_trials": len(cl),
            "averted_rate": sum(t["averted"] for t in cl) / len(cl),
            "latency_s": cl[0]["latency_s"],
            "load_factor": cl[0]["load_factor"],
            "q_at_reflex": _pct([t["q_at_reflex"] for t in cl]),
            "failures": [t["seed"] for t in cl if not t["averted"]],
        },
        "touch_hold_release": dict(
            summarize_alarms(thr),
            **{
                "state_mid_hold_stick_rate": (
                    sum(t["state_mid_hold"] == ContactState.STICK for t in thr) / len(thr)
                    if thr
                    else None
                ),
                "state_end_no_contact_rate": (
                    sum(t["state_end"] == ContactState.NO_CONTACT for t in thr) / len(thr)
                    if thr
                    else None
                ),
            },
        ),
        "incipient_slip_stream": summarize_incipient(inc_s) if inc_s else None,
        "touch_hold_release_stream": summarize_alarms(thr_s) if thr_s else None,
        "random_touches": summarize_alarms(rnd) if rnd else None,
        "random_touches_dense": summarize_alarms(rnd_dense) if rnd_dense else None,
        "texture": summarize_texture(tex) if tex else None,
        "drift": None
        if not drift
        else {
            "n_trials": len(drift),
            "slip_detected_rate": sum(t["slip_delay_ms"] is not None for t in drift) / len(drift),
            "slip_delay_ms": _pct([t["slip_delay_ms"] for t in drift]),
            "direction_reported_rate": sum(t["n_with_direction"] > 0 for t in drift) / len(drift),
            "direction_error_deg_median": _pct([t["direction_error_deg_median"] for t in drift]),
            "direction_error_deg_max": _pct([t["direction_error_deg_max"] for t in drift]),
        },
    }
    out["timing_s"] = timing
    out["trials"] = {
        "incipient_slip": inc,
        "incipient_slip_announced": inc_t,
        "closed_loop": cl,
        "touch_hold_release": thr,
        "random_touches": rnd,
        "random_touches_dense": rnd_dense,
        "texture": tex,
        "drift": drift,
        "incipient_slip_stream": inc_s,
        "touch_hold_release_stream": thr_s,
    }
    return out
