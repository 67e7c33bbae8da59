# SPDX-License-Identifier: Apache-2.0
"""Trials of overlapping emissions for the overlap benchmark and tests: windows holding two
or three emissions rendered by the simulator (`simulate_overlaps`), with their truth."""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.sim import SimConfig, render_triggered, signal_power_v2
from ae_tactile.sim.frontend import noise_rms_for_snr, quantize

__all__ = ["simulate_overlaps"]


def simulate_overlaps(
    n,
    config=None,
    *,
    separation_s,
    n_sources=2,
    amplitude_ratio=1.0,
    snr_db=25.0,
    snr_reference="weaker",
    min_distance_m=2e-3,
    max_polar_deg=60.0,
    rng=None,
    pretrigger_s=8e-6,
    window_s=40e-6,
):
    """``n`` windows holding ``n_sources`` (2 or 3) emissions, from the simulator
    (``ae_tactile.sim``). Linear acoustics: each emission is rendered alone, noise-free, by
    `render_triggered` (exact sub-sample arrival, wall echoes per ``config``), shifted to its
    emission time and summed; then white noise and the ADC.

    separation_s: time between successive emissions (scalar, (n,) or (n, J-1)).
    amplitude_ratio: strongest / weakest source strength (>= 1). Two emissions: which one
    is stronger is random; three: the strengths are log-uniform in [1/ratio, 1] with one
    of them at 1 and one at 1/ratio. snr_db: the SNR (docs/conventions.md, over each
    emission's own 30 us window) of the weakest (``snr_reference='weaker'``) or strongest
    emission. Points uniform by area over the cap polar <= max_polar_deg, pairwise at
    least ``min_distance_m`` apart; random polarities.

    Returns dict: samples_v (n, 4, M), clean_v, onset_index (n,), points_m (n, J, 3),
    emission_time_s (n, J) (window time), polarity (n, J), strength (n, J) relative,
    noise_rms_v (n,), arrival_times_s (n, J, 4), sample_rate_hz, config.
    """
    cfg = SimConfig(reflections=True) if config is None else config
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    geo = cfg.geometry
    fs = float(cfg.sample_rate_hz)
    n = int(n)
    J = int(n_sources)
    if J not in (2, 3):
        raise ValueError("n_sources must be 2 or 3")
    ratio = float(amplitude_ratio)
    if not ratio >= 1.0:
        raise ValueError("amplitude_ratio must be >= 1 (strongest / weakest)")
    if snr_reference not in ("weaker", "stronger"):
        raise ValueError("snr_reference must be 'weaker' or 'stronger'")
    sep = np.asarray(separation_s, float)
    sep = np.broadcast_to(sep[:, None] if sep.ndim == 1 else sep, (n, J - 1)).copy()

    def draw(m):
        cos_t = gen.uniform(math.cos(math.radians(max_polar_deg)), 1.0, m)
        phi = gen.uniform(0.0, 2 * math.pi, m)
        return geo.surface_point_from_angles(np.arccos(cos_t), phi)

    pts = [draw(n)]
    for _ in range(1, J):
        p = draw(n)
        close = np.min([np.linalg.norm(q - p, axis=1) for q in pts], axis=0) < min_distance_m
        while close.any():
            p[close] = draw(int(close.sum()))
            close = np.min([np.linalg.norm(q - p, axis=1) for q in pts], axis=0) < min_distance_m
        pts.append(p)
    pts = np.stack(pts, axis=1)
    if J == 2:
        strong_first = gen.random(n) < 0.5
        rel = np.where(strong_first[:, None], [1.0, 1.0 / ratio], [1.0 / ratio, 1.0])
    else:
        rel = np.exp(gen.uniform(-math.log(ratio), 0.0, (n, J)))
        perm = np.argsort(gen.random((n, J)), axis=1)
        rows = np.arange(n)
        rel[rows, perm[:, 0]] = 1.0
        rel[rows, perm[:, 1]] = 1.0 / ratio
    pol = gen.choice([-1.0, 1.0], size=(n, J))
    speed = 0.3 * np.sqrt(rel)
    clean_cfg = cfg.replace(quantization=False)
    first = render_triggered(
        pts[:, 0],
        clean_cfg,
        polarity=pol[:, 0],
        speed_m_s=speed[:, 0],
        pretrigger_s=pretrigger_s,
        window_s=window_s,
        rng=gen,
    )
    m_len = first.clean_v.shape[2]
    clean = first.clean_v.copy()
    powers = [signal_power_v2(first.clean_v, first.onset_index, fs)]
    t_emit = [first.emission_time_s]
    arrivals = [first.arrival_times_s]
    for j in range(1, J):
        te = t_emit[-1] + sep[:, j - 1]
        tf = te + geo.arrival_times_s(pts[:, j]).min(axis=1)
        n_int = np.floor(tf * fs).astype(np.int64)
        u = np.clip(tf * fs - n_int, 0.0, 1.0 - 1e-12)
        b = render_triggered(
            pts[:, j],
            clean_cfg,
            polarity=pol[:, j],
            speed_m_s=speed[:, j],
            pretrigger_s=0.0,
            window_s=window_s,
            subsample_offset=u,
            rng=gen,
        )
        for i in range(n):
            k = int(n_int[i])
            if 0 <= k < m_len:
                clean[i, :, k:] += b.clean_v[i, :, : m_len - k]
        powers.append(signal_power_v2(b.clean_v, b.onset_index, fs))
        t_emit.append(te)
        arrivals.append(te[:, None] + geo.arrival_times_s(pts[:, j]))
    powers = np.stack(powers, axis=1)
    p_ref = powers.min(axis=1) if snr_reference == "weaker" else powers.max(axis=1)
    sigma = noise_rms_for_snr(p_ref, np.broadcast_to(np.asarray(snr_db, float), (n,)))
    noisy = clean + sigma[:, None, None] * gen.standard_normal(clean.shape)
    if cfg.quantization:
        noisy, _ = quantize(noisy, cfg, out=noisy)
    arrivals = np.stack(arrivals, axis=1)
    onset = np.ceil(arrivals.min(axis=(1, 2)) * fs - 1e-9).astype(np.int64)
    return dict(
        samples_v=noisy,
        clean_v=clean,
        onset_index=onset,
        points_m=pts,
        emission_time_s=np.stack(t_emit, axis=1),
        polarity=pol,
        strength=rel,
        noise_rms_v=sigma,
        arrival_times_s=arrivals,
        sample_rate_hz=fs,
        config=cfg,
    )


# ------------------------------------------------------------------ the live path, per device
def _single_touches(cfg, n, rng, snr_db=30.0):
    """``n`` isolated touches / releases within 60 deg of the apex (the learner's input)."""
    geo = cfg.geometry
    cos_t = rng.uniform(math.cos(math.radians(60.0)), 1.0, n)
    pts = geo.surface_point_from_angles(np.arccos(cos_t), rng.uniform(0, 2 * math.pi, n))
    return render_triggered(pts, cfg, snr_db=snr_db, rng=rng, polarity=rng.choice([-1, 1], n))


#: [ns] between the windows of the live-path trials: 100 windows/s, under the late check's
#: rate limit (LATE_CHECK_MAX_RATE_HZ), so that every single emission is checked
WINDOW_SPACING_NS = 10**7


def _views(samples, onsets, fs, id0):
    """PacketViews of windows WINDOW_SPACING_NS apart, sequence ids from ``id0``."""
    from ae_tactile.records import PacketView  # lazy: only the live-path trials need it

    return [PacketView(np.asarray(samples[i]), fs, int(onsets[i]), WINDOW_SPACING_NS * (id0 + i),
                       id0 + i) for i in range(len(samples))]


def _loss_counted(before, after) -> bool:
    """The pipeline counted a window's missing emissions: an overlap answer rejected or
    dropped, an overlap error, a single emission the late check could not look at, or the
    whole window rejected by a screen (``rejected_<reason>`` other than OVERLAP, which
    sends the window to the resolver)."""
    keys = [k for k in after if k.startswith(("overlap_rejected_", "overlap_dropped_"))
            or k in ("overlap_errors", "overlap_unchecked")
            or (k.startswith("rejected_") and k != "rejected_OVERLAP")]
    return any(after[k] > before.get(k, 0) for k in keys)


def live_pairs(pipe, d, id0, tol_m=0.1e-3, wrong_m=0.5e-3):
    """The pairs of ``d`` (`simulate_overlaps`) through ``pipe.process`` one window at a
    time (the resolver answered before the next): per window, whether both emissions came
    out within ``tol_m`` of the truth, a point came out farther than ``wrong_m`` from
    both, fewer than two points came out without a count (silent), and the window reached
    the overlap resolver (rejected as OVERLAP or withdrawn as a suspect).

    Returns dict: resolved, wrong, silent, counted, reached (bool arrays), n_events (int
    array).
    """
    n = len(d["samples_v"])
    got: dict = {}

    def take(records):
        for r in records:
            got.setdefault(r.packet_ids[0], []).append(np.asarray(r.point_m, float))

    out = {k: np.zeros(n, bool) for k in ("resolved", "wrong", "silent", "counted",
                                          "reached")}
    out["n_events"] = np.zeros(n, int)
    for i, v in enumerate(_views(d["samples_v"], d["onset_index"], d["sample_rate_hz"], id0)):
        before = dict(pipe.all_counts())
        pipe.process([v], take)
        pipe.wait_idle(60.0)
        after = pipe.all_counts()
        out["reached"][i] = any(after[k] > before.get(k, 0)
                                for k in ("rejected_OVERLAP", "overlap_suspects"))
        pts = np.array(got.get(id0 + i, np.zeros((0, 3))))
        truth = d["points_m"][i]
        out["n_events"][i] = len(pts)
        if len(pts):
            err = np.linalg.norm(pts[:, None, :] - truth[None], axis=2)
            out["resolved"][i] = len(pts) >= 2 and bool(
                (err.min(axis=0) <= tol_m).all() and (err.min(axis=1) <= tol_m).all())
            out["wrong"][i] = bool((err.min(axis=1) > wrong_m).any())
        if len(pts) < 2:
            counted = _loss_counted(before, after)
            out["counted"][i], out["silent"][i] = counted, not counted
    return out


def live_device(dev, *, n_pairs=20, max_singles=48, rng=None, sample_rate_hz=10e6,
                medium="water_skin", fit_in_process=False, delay_touches=None):
    """One device through the driver's pipeline (`ContactPipeline`, defaults, its resolver
    and worker process): pairs cold (the nominal pulse), then single touches (30 dB,
    batches of 12) until the pipeline's pulse learner trusts a pulse or ``max_singles``
    were given, then the same pairs warm. The fit runs in the calling thread at normal
    priority (the same fit; ``fit_in_process``: in the niced process of its own, as in
    the driver, where on a loaded machine it waits for idle time). Before the single
    touches, the pipeline's localizer gets the channel delays a driver learns from
    ``delay_touches`` ordinary touches (None: `ae_eval.delays.DELAY_WARM_TOUCHES`, 0:
    none), which the resolver then fits with.

    Pairs: 2-10 us apart (uniform), 1:2, 25 dB on the weaker, wall echo unless the device
    says otherwise (`simulate_overlaps`). Returns a dict of the figures.
    """
    import time  # lazy: only the live-path trials time anything

    from ae_eval.delays import DELAY_WARM_TOUCHES, learnt_channel_model  # lazy: see above
    from ae_tactile.pipeline import ContactPipeline, PacketLocalizer

    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    cfg = dev.config(medium, sample_rate_hz, reflections=True)
    pipe = ContactPipeline(PacketLocalizer("ml", geometry=cfg.geometry), None)
    try:
        pipe.start_overlaps(wait_s=60.0)
        d = simulate_overlaps(n_pairs, cfg, separation_s=gen.uniform(2e-6, 10e-6, n_pairs),
                              amplitude_ratio=2.0, snr_db=25.0, rng=gen)
        cold = live_pairs(pipe, d, 100_000)
        # the channel delays a driver learns in its first minutes (its own stream of draws:
        # the pairs and singles are those of a run without)
        n_delay = DELAY_WARM_TOUCHES if delay_touches is None else int(delay_touches)
        delays, noise = learnt_channel_model(
            cfg, np.random.default_rng([sum(map(ord, dev.name)), 37]), n_delay
        )[:2] if n_delay else (None, None)
        pipe.localizer.localizer.set_channel_delays(delays, noise)
        learner = pipe.overlap_stage.pulse_learner
        learner.background = "process" if fit_in_process else False
        learner.reset()  # the pairs' blends are no learning material: start clean
        t0 = time.perf_counter()
        given = 0
        while given < max_singles and not learner.converged:
            pk = _single_touches(cfg, 12, gen)
            pipe.process(_views(pk.samples_v, pk.onset_index, sample_rate_hz, 200_000 + given))
            given += 12
            learner.wait()
        learn_s = time.perf_counter() - t0
        late0 = pipe.all_counts().get("overlap_late_found", 0)
        warm = live_pairs(pipe, d, 300_000)
        late = pipe.all_counts().get("overlap_late_found", 0) - late0
        st = learner.state()
    finally:
        pipe.close()
    pct = lambda a: round(100.0 * float(np.mean(a)), 1)  # noqa: E731
    return dict(
        device=dev.name, description=dev.description, reflections=bool(cfg.reflections),
        n_pairs=int(n_pairs), singles_given=int(given), learn_wall_s=round(learn_s, 1),
        converged=bool(st["pulse_converged"]), fits=int(st["pulse_fits"]),
        inliers=int(st["pulse_inliers"]), candidates=int(st["pulse_candidates_kept"]),
        cold_resolved_pct=pct(cold["resolved"]), warm_resolved_pct=pct(warm["resolved"]),
        warm_reached=int(warm["reached"].sum()),
        warm_resolved_of_reached_pct=pct(warm["resolved"][warm["reached"]])
        if warm["reached"].any() else None,
        cold_wrong=int(cold["wrong"].sum()), warm_wrong=int(warm["wrong"].sum()),
        cold_silent=int(cold["silent"].sum()), warm_silent=int(warm["silent"].sum()),
        cold_counted=int(cold["counted"].sum()), warm_counted=int(warm["counted"].sum()),
        delays_learnt_ns=None if delays is None else [round(float(v) * 1e9, 2) for v in delays],
        delay_noise_learnt=None if noise is None else [round(noise[0], 3),
                                                       round(noise[1] * 1e9, 3)],
        warm_late_found=int(late),
    )
