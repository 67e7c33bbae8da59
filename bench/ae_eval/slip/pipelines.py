# SPDX-License-Identifier: Apache-2.0
"""From a simulated scene to the slip detector's outputs, through one of three pipelines:

  'triggered'  the simulator's trigger windows (cut from the stream around each emission,
               overlaps, noise and quantization included) -> ``localize`` ->
               LocalizedEvents stamped at onset time - travel time (as the localizer node
               stamps them), accepted packets and kept weak releases only;
  'stream'     the stream read in chunks -> ``PacketDetector`` -> ``localize_packets``;
  'events'     the true emissions with the localizer's error model instead of rendered
               waveforms (fast enough for thousands of trials).

Nothing of the ground truth reaches the detector (``run_detector``).
"""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.dsp import DetectorConfig, PacketBatch, PacketDetector
from ae_tactile.localization import get_estimator, localize, localize_packets
from ae_tactile.localization.weak_release import MIN_SNR_DB as WEAK_MIN_SNR_DB
from ae_tactile.localization.weak_release import (
    kept_with_weak_releases,
    weak_release_confidence,
)
from ae_tactile.sim.stream import (
    EmissionList,
    StreamingSource,
    TriggeredSource,
    time_ns_of_sample,
)
from ae_tactile.slip import LocalizedEvent, SlipConfig, SlipDetector

from .common import EVENTS_DROP


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


#: keyword options of every SlipDetector the evaluation builds (none: the detector's
#: defaults, the fingertip model; ``model=False``: the older per-emission rules, which
#: bench_everyday.py --rules and bench_slip.py --rules set)
DETECTOR_OPTIONS: dict = {}


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
    det = SlipDetector(config, **DETECTOR_OPTIONS)
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


def scene_events(scene, source, end_ns, pipeline):
    """(events, number of true emissions; None for 'stream') of a scene up to ``end_ns``
    through the chosen pipeline; ``source``: the scene's process with extra emissions
    (`common.WithTouch`), or None for the scene's own."""
    if pipeline == "events":
        proc = source if source is not None else scene.process
        em = proc.advance(end_ns)
        rng = np.random.default_rng([7100, int(scene.seed)])
        sigma = float(math.exp(rng.uniform(math.log(5e-6), math.log(40e-6))))
        return emission_events(em, scene.config.geometry, rng, sigma_m=sigma), int(len(em))
    if pipeline == "triggered":
        pk = triggered_source(scene, source).next_packets(1 << 30, horizon_ns=end_ns)
        return localized_events(pk, scene.config.geometry), int(len(pk.emissions))
    if pipeline == "stream":
        n = int(round(end_ns * 1e-9 * scene.config.sample_rate_hz))
        return stream_localized_events(streaming_source(scene, source), scene.config.geometry,
                                       n), None
    raise ValueError(f"pipeline must be 'triggered', 'stream' or 'events', got {pipeline!r}")


def triggered_source(scene, source):
    """The scene's triggered source, over ``source``'s emissions when given."""
    if source is None:
        return scene.triggered_source()
    return TriggeredSource(source, scene.config, noise_rms_v=scene.noise_rms_v, seed=scene.seed)


def streaming_source(scene, source):
    """The scene's streaming source, over ``source``'s emissions when given."""
    if source is None:
        return scene.streaming_source()
    return StreamingSource(source, scene.config, noise_rms_v=scene.noise_rms_v, seed=scene.seed)
