# SPDX-License-Identifier: Apache-2.0
"""The public calls: `resolve_overlaps`, `warm_up`, `calibrate_pulse` and
`localize_with_overlaps`.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy.optimize import minimize

from ae_tactile.dsp.channel_checks import identical_channels
from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization.common import Reason, adc_noise, make_plan, validate_windows
from ae_tactile.localization.covariance import with_delay_noise
from ae_tactile.localization.estimators import delay_noise_arg, localize
from ae_tactile.localization.overlap.decide import _decide, _first_reason, _resolve_quick
from ae_tactile.localization.overlap.learner import PulseLearner
from ae_tactile.localization.overlap.model import (
    OverlapPacket,
    OverlapReason,
    _compiled_medium,
    _lm,
    _Model,
    _positive,
)
from ae_tactile.localization.overlap.pulse import _PR_CACHE, _TAB_CACHE, PulseModel, _given
from ae_tactile.localization.overlap.search import _segments, _surface_grid
from ae_tactile.localization.overlap.suspect import _time_search, suspect_overlap
from ae_tactile.localization.segments import prepare, subset


def resolve_overlaps(
    windows, sample_rate_hz, onset_index, *, geometry=None, pulse=None, noise_rms_v=None,
    saturated=None, full_scale_v=None, max_sources=3, band_hz=(100e3, 1e6), analysis_s=None,
    add_threshold=60.0, max_chi2_ratio=None, max_sigma_m=0.2e-3, min_snr_db=5.0, echo=True,
    grid_spacing_m=1.0e-3, min_separation_s=1.5e-6, engine="auto", exhaustive=True,
) -> list:
    """Localize every emission in each of K windows (two or three overlapping emissions).

    Parameters
    ----------
    windows : array_like, (K, 4, M) or (4, M)
        Packet windows [V]; sample_rate_hz [Hz] > 0.
    sample_rate_hz : float
    onset_index : array_like of int, (K,)
        First sample at/after the earliest arrival (detector or trigger).
    geometry : FingertipGeometry, optional
        The fingertip (default tip).
    pulse : PulseModel, optional
        The front end's pulse; default `PulseModel.for_sample_rate`: 100 kHz 2nd-order
        high-pass, 1 MHz 4th-order low-pass, below 3.33 MS/s the 0.3 fs 8th-order
        anti-alias low-pass.
    noise_rms_v : float or array_like (K,), optional
        Known noise sigma [V]; default measured before the onset (with the ADC's rounding,
        `common.adc_noise`).
    saturated, full_scale_v : optional
        As for `localize`.
    max_sources, band_hz : int, (float, float)
        1, 2 or 3 emissions at most; band [Hz] of the analysis plan.
    analysis_s : float, optional
        Length of the fit window after the onset [s]; default up to just before the
        second wall echo.
    add_threshold, max_chi2_ratio : float
        Residual-energy drop [sigma^2] needed to add an emission; largest accepted
        residual / (sigma^2 dof) (default 1 + 5 sqrt(2/n_noise + 2/dof)).
    max_sigma_m : float
        [m] emissions with a larger in-plane 1-sigma are dropped.
    min_snr_db : float
        [dB] SNR floor of an emission.
    echo, grid_spacing_m : bool, float
        Model the first wall echo; [m] spacing of the matched-filter grid on the surface.
    min_separation_s : float
        [s] emissions fitted closer in time are not separated reliably (the joint
        likelihood has several nearly equal optima): such windows are rejected
        (UNRESOLVED).
    engine : {"auto", "numpy"}
        "auto": the compiled kernels (`overlap_kernels`) when numba is present and the
        medium lossless; "numpy": always the numpy path.
    exhaustive : bool
        False: a window whose first joint fit still leaves more than noise is answered
        DEFERRED (the quick answer of the driver's resolver, which then runs the
        exhaustive search on it).

    Returns
    -------
    list of OverlapPacket
        K packets: ``sources`` earliest first, or a rejection reason. Bad parameters or
        shapes raise ValueError / TypeError; data problems are rejections.
    """
    geo, pulse, add_threshold, max_sigma_m, max_chi2_ratio, min_snr_db, analysis_s, \
        grid_spacing_m, min_separation_s = _checked(
            geometry, pulse, sample_rate_hz, max_sources, add_threshold, max_sigma_m,
            max_chi2_ratio, min_snr_db, analysis_s, grid_spacing_m, min_separation_s, engine)
    x, on = validate_windows(windows, onset_index)
    K = x.shape[0]
    if K == 0:
        return []
    # one waveform copied onto the four channels is no acoustic signal (as for `localize`)
    same = np.asarray(identical_channels(x, on, noise_rms_v), bool).reshape(K)
    out: list = [OverlapPacket(False, int(OverlapReason.NO_SIGNAL)) for _ in range(K)]
    ids = np.nonzero(~same)[0]
    if ids.size == 0:
        return out
    res = _resolve_ids(x, on, ids, sample_rate_hz, geo, pulse, noise_rms_v, saturated,
                       full_scale_v, band_hz, grid_spacing_m, echo, analysis_s, engine,
                       exhaustive, (max_sources, add_threshold, max_chi2_ratio, max_sigma_m,
                                    min_snr_db, min_separation_s))
    for i, r in zip(ids, res):
        out[i] = r
    return out


def _resolve_ids(x, on, ids, fs, geo, pulse, noise_rms_v, saturated, full_scale_v, band_hz,
                 grid_spacing_m, echo, analysis_s, engine, exhaustive, decide_args):
    """`resolve_overlaps` of the windows ``ids`` of x (K, 4, M) (the per-window noise and
    flags taken at ``ids``; ``full_scale_v`` is one value): the compiled quick search or
    `_resolve_full`."""
    K = x.shape[0]
    if noise_rms_v is not None:
        noise_rms_v = np.broadcast_to(np.asarray(noise_rms_v, float), (K,))[ids]
    x, noise_rms_v = pulse.correct_channels(x[ids], fs, noise_rms_v, on[ids])
    if saturated is not None:
        saturated = np.broadcast_to(np.asarray(saturated, bool), (K,))[ids]
    plan = make_plan(fs, geo, x.shape[2], band_hz)
    grid = _surface_grid(geo, grid_spacing_m)
    with np.errstate(all="ignore"):
        if not exhaustive and engine == "auto" and _compiled_medium(pulse):
            return _resolve_quick(x, on[ids], plan, geo, pulse, noise_rms_v, saturated,
                                  full_scale_v, echo, analysis_s, grid, decide_args)
        return _resolve_full(x, on[ids], plan, geo, pulse, noise_rms_v, saturated,
                             full_scale_v, echo, analysis_s, engine, grid, decide_args,
                             exhaustive)


def _checked(geometry, pulse, sample_rate_hz, max_sources, add_threshold, max_sigma_m,
             max_chi2_ratio, min_snr_db, analysis_s, grid_spacing_m, min_separation_s, engine):
    """`resolve_overlaps`' parameters checked and converted (TypeError / ValueError)."""
    geo = FingertipGeometry() if geometry is None else geometry
    if not isinstance(geo, FingertipGeometry):
        raise TypeError(f"geometry must be a FingertipGeometry, got {type(geo).__name__}")
    pulse = PulseModel.for_sample_rate(sample_rate_hz) if pulse is None else pulse
    if not isinstance(pulse, PulseModel):
        raise TypeError(f"pulse must be a PulseModel, got {type(pulse).__name__}")
    if (
        isinstance(max_sources, bool)
        or not isinstance(max_sources, (int, np.integer))
        or not 1 <= max_sources <= 3
    ):
        raise ValueError(f"max_sources must be 1, 2 or 3, got {max_sources!r}")
    add_threshold = _positive("add_threshold", add_threshold)
    max_sigma_m = _positive("max_sigma_m", max_sigma_m)
    if max_chi2_ratio is not None:
        max_chi2_ratio = _positive("max_chi2_ratio", max_chi2_ratio)
    min_snr_db = float(min_snr_db)
    if not math.isfinite(min_snr_db):
        raise ValueError(f"min_snr_db must be finite, got {min_snr_db!r}")
    if analysis_s is not None:
        analysis_s = _positive("analysis_s", analysis_s)
    grid_spacing_m = _positive("grid_spacing_m", grid_spacing_m)
    min_separation_s = float(min_separation_s)
    if not (math.isfinite(min_separation_s) and min_separation_s >= 0):
        raise ValueError(f"min_separation_s must be >= 0, got {min_separation_s!r}")
    if engine not in ("auto", "numpy"):
        raise ValueError(f"engine must be 'auto' or 'numpy', got {engine!r}")
    return (geo, pulse, add_threshold, max_sigma_m, max_chi2_ratio, min_snr_db, analysis_s,
            grid_spacing_m, min_separation_s)


def _resolve_full(x, on, plan, geo, pulse, noise_rms_v, saturated, full_scale_v, echo,
                  analysis_s, engine, grid, decide_args, exhaustive):
    """The numpy preparation and the search of `resolve_overlaps` (every path but the
    compiled quick one); one `OverlapPacket` per window."""
    (max_sources, add_threshold, max_chi2_ratio, max_sigma_m, min_snr_db,
     min_separation_s) = decide_args
    K = x.shape[0]
    prep = prepare(
        x,
        on,
        plan,
        noise_rms_v=noise_rms_v,
        saturated=saturated,
        full_scale_v=full_scale_v,
        spectra=False,
    )
    sigma2 = adc_noise(prep.sigma2, prep.quant2, _given(prep))
    n_noise = np.maximum(4 * (prep.onset - plan.pre), 4).astype(float)
    if noise_rms_v is not None:
        n_noise[:] = np.inf
    unknown = ~np.isfinite(sigma2) | (sigma2 <= 0)
    flags = prep.flags.copy()
    flags[unknown] |= 1 << Reason.WINDOW
    ok = flags == 0
    out: list = [None] * K
    ids = np.nonzero(ok)[0]
    if ids.size:
        seg, start, length, inside = _segments(
            subset(prep, ids), plan, geo, plan.fs, analysis_s
        )
        model = _Model(geo, plan.fs, start, length, pulse, echo, inside, engine)
        res = _decide(
            model,
            seg,
            sigma2[ids],
            n_noise[ids],
            max_sources,
            add_threshold,
            max_chi2_ratio,
            max_sigma_m,
            min_snr_db,
            prep.scale[ids],
            geo,
            grid,
            min_separation_s,
            exhaustive,
        )
        for i, r in zip(ids, res):
            out[i] = r
    for i in np.nonzero(~ok)[0]:
        code = _first_reason(int(flags[i]))
        out[i] = OverlapPacket(
            False, code, noise_rms_v=float(np.sqrt(np.nan_to_num(sigma2[i])) * prep.scale[i])
        )
    return out


def warm_up(geometry=None, sample_rate_hz=10e6, n_samples=400, pulse=None) -> OverlapPacket:
    """Resolve one synthetic two-emission window (4 us apart, opposite polarities, light
    noise) by the quick and by the exhaustive search: loads every table and compiled
    kernel the first real overlap would otherwise wait for (the driver's overlap worker
    does this before it says it is ready).

    Parameters
    ----------
    geometry : FingertipGeometry, optional
        Sensor geometry and medium (default `FingertipGeometry()`).
    sample_rate_hz : float
        Sample rate [Hz] of the window.
    n_samples : int
        Window length [samples] (at least 64).
    pulse : PulseModel, optional
        The front end's pulse (default `PulseModel.for_sample_rate(sample_rate_hz)`).

    Returns
    -------
    OverlapPacket
        The exhaustive search's answer.
    """
    geo = FingertipGeometry() if geometry is None else geometry
    fs = float(sample_rate_hz)
    pulse = PulseModel.for_sample_rate(fs) if pulse is None else pulse
    n = max(int(n_samples), 64)
    on = n // 4
    pts = geo.surface_point_from_angles(np.array([0.35, 0.3]), np.array([0.4, 3.5]))
    tt = geo.arrival_times_s(pts)  # (2, 4)
    gain = geo.radius_m / (tt * geo.sound_speed_m_s)  # R / d
    t0 = on / fs - tt.min()
    t = np.arange(n) / fs
    x = np.random.default_rng(0).normal(0.0, 1e-4, (4, n))
    for j, (amp, delay) in enumerate(((1e-2, 0.0), (-0.7e-2, 4e-6))):
        x += amp * gain[j][:, None] * pulse.waveform(t[None, :] - t0 - delay - tt[j][:, None])
    with np.errstate(all="ignore"):
        resolve_overlaps(x[None], fs, [on], geometry=geo, pulse=pulse, exhaustive=False)
        return resolve_overlaps(x[None], fs, [on], geometry=geo, pulse=pulse)[0]


def calibrate_pulse(
    windows,
    sample_rate_hz,
    onset_index,
    *,
    geometry=None,
    initial=None,
    noise_rms_v=None,
    max_packets=64,
    echo=True,
):
    """Fit the front end's corner frequencies (`PulseModel` high-pass and low-pass) to
    single-emission packets, e.g. a few dozen single touches recorded at start-up.

    The known-pulse model needs the pulse shape: a front end whose corners are off by 10 %
    makes every overlap fit fail the residual test (rejected, not wrong; docs/localization.md).
    Each packet is localized by `localize` (ml); the objective is the summed residual of
    the one-emission model (3 LM steps from that point) over the accepted packets,
    minimised over (log f_hp, log f_lp) by Nelder-Mead from ``initial``.

    Parameters
    ----------
    windows : array_like, (K, 4, M)
        Single-emission packets [V].
    sample_rate_hz : float
        Sample rate [Hz].
    onset_index : array_like of int, (K,)
        Packet onset per window [samples].
    geometry : FingertipGeometry, optional
        Sensor geometry and medium (default `FingertipGeometry()`).
    initial : PulseModel, optional
        Start of the fit (default `PulseModel.for_sample_rate(sample_rate_hz)`).
    noise_rms_v : float or array_like (K,), optional
        Known noise sigma [V]; default measured before the onset.
    max_packets : int
        At most this many accepted packets enter the objective (the first ones).
    echo : bool
        Model the first wall echo.

    Returns
    -------
    PulseModel
        The fitted model (orders, alpha and medium loss as in ``initial``).

    Raises
    ------
    ValueError
        No packet is accepted by `localize`.
    """
    geo = FingertipGeometry() if geometry is None else geometry
    init = PulseModel.for_sample_rate(sample_rate_hz) if initial is None else initial
    x, on = validate_windows(windows, onset_index)
    ml = localize(x, sample_rate_hz, on, geometry=geo, noise_rms_v=noise_rms_v)
    ids = np.nonzero(ml.accepted)[0][: int(max_packets)]
    if ids.size == 0:
        raise ValueError("calibrate_pulse needs single-emission packets that localize accepts")
    plan = make_plan(sample_rate_hz, geo, x.shape[2], (100e3, 1e6))
    with np.errstate(all="ignore"):
        prep = prepare(x[ids], on[ids], plan)
        seg, start, length, inside = _segments(prep, plan, geo, plan.fs, None)
    y = seg.reshape(len(ids), -1)
    pts = ml.point_m[ids, :2]
    lp0 = init.lowpass_hz
    fit = (geo, plan.fs, start, length, echo, inside, seg, pts, y)
    v0 = np.log([init.highpass_hz, lp0 if lp0 is not None else 1.0])
    r = minimize(
        _calibration_rss,
        v0,
        args=(init, fit),
        method="Nelder-Mead",
        options=dict(
            xatol=2e-3, fatol=1e-9, initial_simplex=[v0, v0 + [0.15, 0], v0 + [0, 0.15]], maxfev=80
        ),
    )
    return _pulse_of(init, r.x)


def _pulse_of(init, v):
    """``init`` with the corners exp(v[0]) and exp(v[1]) [Hz] (the low-pass only where
    ``init`` has one)."""
    lp0 = init.lowpass_hz
    return PulseModel(
        float(np.exp(v[0])),
        init.highpass_order,
        None if lp0 is None else float(np.exp(v[1])),
        init.lowpass_order,
        init.alpha_1_s,
        init.attenuation_db_per_m_at_1mhz,
        attenuation_exponent=init.attenuation_exponent,
        attenuation_ref_hz=init.attenuation_ref_hz,
    )


def _calibration_rss(v, init, fit):
    """`calibrate_pulse`'s objective: the summed residual [V^2] of the one-emission model
    (3 LM steps) over the calibration packets ``fit`` under the corners exp(v) [Hz]."""
    geo, fs, start, length, echo, inside, seg, pts, y = fit
    pm = _pulse_of(init, v)
    with np.errstate(all="ignore"):
        model = _Model(geo, fs, start, length, pm, echo, inside)
        th0 = _time_search(model, seg, pts)
        _, _, rss, _ = _lm(model, y, th0[:, None, :], iterations=3)
    _TAB_CACHE.pop((pm, fs, length), None)
    _PR_CACHE.pop(pm, None)
    return float(np.sum(rss))


def _carry_delay_noise(overlap, geo, noise):
    """The resolved emissions of ``overlap`` ({index: OverlapPacket}) made to carry a
    device's delay noise (None: unchanged), as `localize`'s points do."""
    for res in overlap.values() if noise is not None else ():
        for src in res.sources:
            src.covariance_m2 = with_delay_noise(geo, src.point_m, src.covariance_m2, noise)


def localize_with_overlaps(windows, sample_rate_hz, onset_index, *, geometry=None, pulse=None,
                           noise_rms_v=None, saturated=None, max_sources=3,
                           overlap_kwargs=None, **localize_kwargs):
    """The fast single-source path plus the overlap path only where needed.

    1. ``localize`` (``method``, default ml) on every window;
    2. `suspect_overlap` on what it accepted;
    3. `resolve_overlaps` on the windows it rejected as OVERLAP and on the suspects.
    The pulse is *trusted* when it is given (a `PulseModel`), learnt (a converged
    `PulseLearner`), or, by default, when the batch's single emissions agree with it (at
    least MIN_JUDGED accepted windows, at most MAX_SUSPECT_SHARE of them suspects). A
    suspect the overlap fit resolves is replaced by its emissions either way; one it does
    not resolve is withdrawn under a trusted pulse, but under an untrusted one (a device
    unlike the default model) its single-source point is kept, its OVERLAP flag set in
    ``reason_flags`` and its overlap answer `OverlapReason.UNMODELLED`: one point with a
    count, never a silently dropped emission nor a rejected single touch.

    Parameters
    ----------
    windows : array_like, (K, 4, M) or (4, M)
        Packet windows [V].
    sample_rate_hz : float
        Sample rate [Hz], > 0.
    onset_index : array_like of int, (K,)
        First sample at/after the earliest arrival.
    geometry : FingertipGeometry, optional: the fingertip (default tip).
    pulse : PulseModel or PulseLearner, optional
        The front end's pulse (default `PulseModel.for_sample_rate`, judged on the batch),
        or a learner: it is offered this batch's accepted packets first, and its pulse is
        used once converged.
    noise_rms_v : float or array_like (K,), optional
        Known noise sigma [V]; default measured before the onset.
    saturated : array_like of bool (K,), optional: upstream clip flags.
    max_sources : int: 1, 2 or 3 emissions per window.
    overlap_kwargs : dict, optional
        Further keyword arguments of `resolve_overlaps`.
    **localize_kwargs
        Of `localize` (``method``, ``delay_noise``: the resolved emissions carry it too).

    Returns
    -------
    single : LocalizationResult
        The result of `localize`, with ``accepted`` False (reason OVERLAP) for the
        suspects withdrawn: publish their overlap result.
    overlap : dict of int to OverlapPacket
        {window index: `OverlapPacket`} for the OVERLAP rejections and the suspects.
    """
    geo = FingertipGeometry() if geometry is None else geometry
    x, on = validate_windows(windows, onset_index)
    single = localize(x, sample_rate_hz, on, geometry=geo, noise_rms_v=noise_rms_v,
                      saturated=saturated, **localize_kwargs)
    pulse, trusted = _pulse_of_call(pulse, x, sample_rate_hz, on, single, noise_rms_v)
    if pulse is not None and (pulse.channel_gain or pulse.channel_delay_s):
        # the device's channels made alike once, for every step (then none does it again)
        x, noise_rms_v = pulse.correct_channels(x, sample_rate_hz, noise_rms_v, on)
        pulse = replace(pulse, channel_gain=(), channel_delay_s=())
        single = localize(x, sample_rate_hz, on, geometry=geo, noise_rms_v=noise_rms_v,
                          saturated=saturated, **localize_kwargs)
    sus = suspect_overlap(
        x, sample_rate_hz, on, single, geometry=geo, pulse=pulse, noise_rms_v=noise_rms_v
    )
    n_acc = int(np.sum(single.accepted))
    if trusted is None:  # the default pulse: judged by the batch's single emissions
        trusted = n_acc >= MIN_JUDGED and sus.sum() <= MAX_SUSPECT_SHARE * n_acc
    ids = np.nonzero(sus | (single.reason == int(Reason.OVERLAP)))[0]
    overlap = {}
    if ids.size:
        overlap = _overlaps_of(x, sample_rate_hz, on, ids, geo, pulse, noise_rms_v, saturated,
                               max_sources, overlap_kwargs)
    _carry_delay_noise(overlap, geo, delay_noise_arg(localize_kwargs.get("delay_noise")))
    drop = sus & ~_kept_suspects(sus, overlap, trusted)
    single.accepted = single.accepted & ~drop
    single.confidence = np.where(drop, 0.0, single.confidence)
    single.reason = np.where(drop, np.uint8(Reason.OVERLAP), single.reason).astype(np.uint8)
    single.reason_flags = (
        single.reason_flags | np.where(sus, 1 << int(Reason.OVERLAP), 0)
    ).astype(np.uint16)
    return single, overlap


def _kept_suspects(sus, overlap, trusted):
    """(K,) bool: the suspects whose single-source point stays: under an untrusted pulse,
    those the overlap fit did not resolve (their answer becomes UNMODELLED)."""
    kept = np.zeros(len(sus), bool)
    if not trusted:
        for i in np.nonzero(sus)[0]:
            o = overlap.get(int(i))
            if o is not None and not o.accepted:
                o.reason = int(OverlapReason.UNMODELLED)
                kept[i] = True
    return kept


#: accepted windows a batch needs for its single emissions to judge the default pulse
MIN_JUDGED = 4
#: largest share of a batch's accepted windows that may be suspects under a pulse that
#: describes the device (a wrong pulse makes nearly every single emission a suspect)
MAX_SUSPECT_SHARE = 0.5


def _pulse_of_call(pulse, x, fs, on, single, noise_rms_v):
    """(PulseModel or None, trusted: True / False / None = judge by the batch) of
    `localize_with_overlaps`' ``pulse`` argument."""
    if pulse is None:
        return None, None
    if isinstance(pulse, PulseModel):
        return pulse, True
    if isinstance(pulse, PulseLearner):
        pulse.offer(x, fs, on, single, noise_rms_v)
        learnt = pulse.pulse
        return (learnt, True) if learnt is not None else (None, False)
    raise TypeError(f"pulse must be a PulseModel or a PulseLearner, got {type(pulse).__name__}")


def _overlaps_of(x, sample_rate_hz, on, ids, geo, pulse, noise_rms_v, saturated, max_sources,
                 overlap_kwargs):
    """{window index: `OverlapPacket`} of `resolve_overlaps` on the windows ``ids``."""
    nr = (
        None
        if noise_rms_v is None
        else np.broadcast_to(np.asarray(noise_rms_v, float), (len(on),))[ids]
    )
    sat = (
        None
        if saturated is None
        else np.broadcast_to(np.asarray(saturated, bool), (len(on),))[ids]
    )
    res = resolve_overlaps(
        x[ids],
        sample_rate_hz,
        on[ids],
        geometry=geo,
        pulse=pulse,
        noise_rms_v=nr,
        saturated=sat,
        max_sources=max_sources,
        **(overlap_kwargs or {}),
    )
    return {int(i): r for i, r in zip(ids, res)}
