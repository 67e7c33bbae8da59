# SPDX-License-Identifier: Apache-2.0
"""One interface for the delay estimators: `localize`, `LocalizationResult`, the registry.

    res = localize(windows (K, 4, M), sample_rate_hz, onset_index (K,), method="ml")

Pipeline (vectorised over the K packets, never raising on data):
  1. validate shapes and parameters (ValueError / TypeError), copy to float64;
  2. flag non-finite samples (zeroed), constant channels, onsets outside the window,
     saturation; estimate the noise from the pre-onset samples;
  3. the chosen estimator (registry ``ESTIMATORS``) returns delays, the contact point and
     the four channels aligned by its fit;
  4. common post-processing: misfit of the aligned channels (overlap test), SNR
     estimate (conventions.md definition), covariance, polarity, amplitude, horizon
     check, confidence, and the reason code of every rejected packet.

Every output array is finite. For a rejected packet the position is still the
estimator's answer when it had one (e.g. overlap, low SNR: useful for diagnostics),
else the pole (0, 0, R); only ``accepted`` packets should be published.
"""

from __future__ import annotations

import numpy as np

from ae_tactile.dsp.channel_checks import identical_channels
from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import fast
from ae_tactile.localization.common import (
    Reason,
    adc_noise,
    make_plan,
    per_packet,
    primary_reason,
    validate_windows,
)
from ae_tactile.localization.covariance import delay_noise_covariance
from ae_tactile.localization.events import (
    confidence,
    polarity_amplitude,
    polarity_amplitude_aligned,
)
from ae_tactile.localization.pairs import misfit
from ae_tactile.localization.registry import (
    DEFAULT_BAND_HZ,
    auto_band_hz,
    default_band_hz,
    get_estimator,
)
from ae_tactile.localization.result import (
    LocalizationResult,
    _empty,
    _result_from_kernel,
)
from ae_tactile.localization.segments import prepare


def _horizon_excess(geometry, tau):
    """|tau| beyond the exact horizon delay along the measured azimuth (s; <= 0 inside)."""
    phi = np.arctan2(tau[:, 1], tau[:, 0])
    h = geometry.exact_delays_s(
        geometry.surface_point_from_angles(np.full_like(phi, np.pi / 2), phi)
    )
    return np.hypot(tau[:, 0], tau[:, 1]) - np.hypot(h[:, 0], h[:, 1])


def _noise_arg(noise_rms_v, k):
    """(K,) noise sigma, NaN where unknown; ValueError for <= 0 or infinite values."""
    if noise_rms_v is None:
        return np.full(k, np.nan)
    try:
        nr = per_packet("noise_rms_v", noise_rms_v, k)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"noise_rms_v must be a positive number or (K,) array: {exc}") from None
    bad = ~np.isnan(nr) & ~(np.isfinite(nr) & (nr > 0))
    if bad.any():
        raise ValueError(
            f"noise_rms_v must be positive and finite (NaN: unknown), got {nr[bad][0]!r}"
        )
    return nr


def resolve_engine(engine, method="ml", options=None):
    """'numba' or 'numpy': the compiled kernel serves ``ml`` (its only option: iterations)
    when numba is importable and AE_TACTILE_NO_NUMBA is not set; ``engine`` forces one."""
    if engine not in (None, "auto", "numba", "numpy"):
        raise ValueError(f"engine must be 'numba', 'numpy' or None, got {engine!r}")
    if engine == "numpy":
        return "numpy"
    ok = fast.NUMBA_AVAILABLE and method == "ml" and set(options or ()) <= {"iterations"}
    if engine == "numba" and not ok:
        raise ValueError("engine='numba' needs numba and method 'ml' (options: iterations only)")
    return "numba" if ok else "numpy"


def _iterations(options):
    it = options.get("iterations", 4)
    if isinstance(it, bool) or not isinstance(it, (int, np.integer)) or it < 1:
        raise ValueError(f"iterations must be a positive integer, got {it!r}")
    return int(it)


def localize(
    windows,
    sample_rate_hz,
    onset_index,
    *,
    method="ml",
    geometry=None,
    band_hz=None,
    noise_rms_v=None,
    saturated=None,
    full_scale_v=None,
    channel_gains=None,
    min_snr_db=5.0,
    overlap_threshold=None,
    pre_onset_s=1e-6,
    echo_guard_s=0.3e-6,
    engine=None,
    delay_noise=None,
    **options,
) -> LocalizationResult:
    """Localize K packets (see the module docstring).

    Parameters
    ----------
    windows : array_like, (K, 4, M) or (4, M)
        Packet windows [V], any real dtype.
    sample_rate_hz : float
        Sample rate [Hz], > 0.
    onset_index : array_like of int, (K,)
        First sample at/after the earliest arrival (the detector's or the simulator's).
    method : str, geometry : FingertipGeometry, optional
        A name in `available_methods()` (default ``"ml"``); the fingertip (default tip).
    band_hz : (float, float), optional
        Signal band [Hz] of the estimators; None: ``ml`` picks each packet's upper edge
        from its spectrum, the others use `default_band_hz(fs)`.
    noise_rms_v : float or array_like (K,), optional
        Known noise sigma [V], > 0 (NaN entries: unknown). Default: measured on the
        samples before ``onset - pre_onset_s``, else from the fit residual.
    saturated, full_scale_v : array_like of bool (K,), float, optional
        Upstream clip flags; ADC clip level [V]. With neither, a flat top of >= max(4,
        0.3 us fs) samples at a channel's dominant extreme flags saturation.
    channel_gains : array_like (4,), optional: the channels' relative gains (divided out).
    min_snr_db, overlap_threshold : float
        LOW_SNR below this [dB]; OVERLAP above that excess misfit (default per method).
    pre_onset_s, echo_guard_s : float
        Noise ends this long before the onset [s]; analysis, before the first echo [s].
    engine : {None, "numba", "numpy"}
        None: the compiled kernel for ``ml`` when numba is available.
    delay_noise : (float, float), optional
        A device's delay noise (`ChannelDelayLearner.applied_noise`), carried by the
        covariances: (scale >= 1, per-channel timing sd [s]); None: the model's.
    **options
        Passed to the estimator (e.g. ``iterations=``).

    Returns
    -------
    LocalizationResult
        K rows: point, covariance, accepted, reason, polarity, confidence, ...
        Bad parameters or shapes raise ValueError / TypeError; data problems are
        rejections, never exceptions.
    """
    info = get_estimator(method)
    geo = FingertipGeometry() if geometry is None else geometry
    eng = resolve_engine(engine, method, options)
    x, onset = validate_windows(windows, onset_index, copy=eng != "numba")
    plan = _plan(sample_rate_hz, geo, x.shape[2], band_hz, pre_onset_s, echo_guard_s, method)
    min_snr_db, thr = _thresholds(info, min_snr_db, overlap_threshold)
    dn = delay_noise_arg(delay_noise)
    same = identical_channels(x, onset, noise := _noise_arg(noise_rms_v, x.shape[0]))
    if eng == "numba":
        return _reject_identical(_localize_compiled(x, onset, plan, method, options, noise,
            saturated, full_scale_v, channel_gains, min_snr_db, thr, dn), same)
    if x.shape[0] == 0:
        return _empty(method, options)
    with np.errstate(all="ignore"):
        prep = prepare(x, onset, plan, noise_rms_v=None if noise_rms_v is None else noise,
                       saturated=saturated, full_scale_v=full_scale_v,
                       channel_gains=channel_gains)
        return _reject_identical(_finish(info.function(prep, plan, **options), prep, plan,
                                         geo, method, min_snr_db, thr, options, dn), same)


def delay_noise_arg(delay_noise):
    """A checked delay noise (scale, timing sd [s]): None or (1, 0) -> None (the model's);
    ValueError unless 1 <= scale < inf and 0 <= sd < 1 us."""
    if delay_noise is None:
        return None
    try:
        scale, sd = (float(v) for v in delay_noise)
    except (TypeError, ValueError):
        raise ValueError(f"delay_noise must be (scale, timing_sd_s), got {delay_noise!r}") \
            from None
    if not (1.0 <= scale < np.inf and 0.0 <= sd < 1e-6):
        raise ValueError("delay_noise needs 1 <= scale < inf and 0 <= timing_sd_s < 1 us, "
                         f"got {delay_noise!r}")
    return None if (scale, sd) == (1.0, 0.0) else (scale, sd)


def _reject_identical(res, same):
    """The entry check every caller gets: packets whose four channels are one signal
    (``same``: `ae_tactile.dsp.channel_checks.identical_channels`, equal beyond what
    independent channel noise allows, which four sensors never are) are rejected as
    NO_SIGNAL (no acoustic signal: one waveform copied onto four inputs, which a fit would
    place at the pole), confidence 0, polarity 0."""
    if same.any():
        flags = res.reason_flags.copy()
        flags[same] |= np.uint16(1 << Reason.NO_SIGNAL)
        res.reason_flags = flags
        res.reason = primary_reason(flags)
        res.accepted = res.reason == 0
        res.confidence = np.where(same, 0.0, res.confidence)
        res.polarity = np.where(same, 0, res.polarity).astype(np.int8)
    return res


def _thresholds(info, min_snr_db, overlap_threshold):
    """(min_snr_db [dB], overlap threshold) of `localize`, checked (ValueError)."""
    min_snr_db = float(min_snr_db)
    if not np.isfinite(min_snr_db):
        raise ValueError(f"min_snr_db must be finite, got {min_snr_db!r}")
    thr = info.overlap_threshold if overlap_threshold is None else float(overlap_threshold)
    if not (np.isfinite(thr) and thr > 0):
        raise ValueError(f"overlap_threshold must be positive, got {overlap_threshold!r}")
    return min_snr_db, thr


def _localize_compiled(x, onset, plan, method, options, noise, saturated, full_scale_v,
                       channel_gains, min_snr_db, thr, delay_noise=None):
    """`localize` through the compiled ``ml`` kernel (`fast.run_batch`)."""
    k = x.shape[0]
    iterations = _iterations(options)
    sat = (
        np.full(k, -1, np.int8)
        if saturated is None
        else per_packet("saturated", saturated, k, dtype=bool).astype(np.int8)
    )
    fsv = np.nan if full_scale_v is None else _positive_arg("full_scale_v", full_scale_v)
    gains = _gains_arg(channel_gains)
    if k == 0:
        return _empty(method, options)
    out, pt, cov, ctau = fast.run_batch(
        x,
        onset,
        fast.tables_for(plan),
        noise_rms=noise,
        sat=sat,
        full_scale=fsv,
        gains=gains,
        iterations=iterations,
        min_snr_db=min_snr_db,
        thr=thr,
        delay_noise=delay_noise,
    )
    return _result_from_kernel(method, options, out, pt, cov, ctau)


def _plan(sample_rate_hz, geo, n, band_hz, pre_onset_s, echo_guard_s, method):
    """The analysis plan: ``band_hz`` given -> that fixed band; else ``ml`` chooses each
    packet's upper edge from its spectrum within `auto_band_hz` (fallback
    `default_band_hz` when the noise is unknown), the other methods use `default_band_hz`."""
    auto = None
    if band_hz is None:
        try:
            band_hz = default_band_hz(sample_rate_hz)
            if method == "ml":
                auto = band_hz[1]
                band_hz = auto_band_hz(sample_rate_hz)
        except (TypeError, ValueError):
            band_hz = DEFAULT_BAND_HZ  # make_plan reports the bad sample rate
    return make_plan(sample_rate_hz, geo, n, band_hz, pre_onset_s, echo_guard_s, auto)


def _positive_arg(name, value):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {value!r}") from None
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v


def _gains_arg(channel_gains):
    if channel_gains is None:
        return None
    g = np.asarray(channel_gains, dtype=float)
    if g.shape != (4,) or not np.all(np.isfinite(g)) or np.any(g <= 0):
        raise ValueError(f"channel_gains must be 4 positive finite numbers, got {channel_gains!r}")
    return g


def _noise_snr_excess(core, prep):
    """(misfit, noise variance sigma^2 [V^2, scaled], SNR [dB], excess misfit) of the
    estimator's aligned channels: noise pre-onset (or given), else from the fit residual."""
    zb = core["zb"]
    count = core["count"]
    mis, res_e, tot_e = misfit(zb)
    L = count.mean(axis=1)
    # bins in use per packet (a data-driven band zeroes the others)
    nb = np.broadcast_to(np.asarray(core.get("n_bins", zb.shape[2]), float), L.shape)
    # Noise: pre-onset (or given), else from the residual of the fit.
    sigma2 = prep.sigma2.copy()
    fallback = ~np.isfinite(sigma2)
    sigma2[fallback] = res_e[fallback] / np.maximum(3.0 * nb[fallback] * L[fallback], 1.0)
    # ADC rounding (q = apparent quantum): the signal samples carry sigma^2 + q^2/12. A
    # given (analog) sigma gets + q^2/12; a variance V measured on the quiet, quantized
    # pre-onset samples is inverted through the mid-tread relation V(sigma) (`adc_noise`).
    given = np.zeros(len(sigma2), bool) if prep.noise_given is None else prep.noise_given
    sigma2 = np.where(fallback, sigma2, adc_noise(sigma2, prep.quant2, given))
    p_total = prep.p_signal
    floor = 1e-12 * np.maximum(p_total, 0.0) + 1e-300
    sigma2 = np.maximum(sigma2, floor)
    p_sig = np.maximum(p_total - sigma2, 1e-300)
    snr = np.clip(10.0 * np.log10(p_sig / sigma2), -100.0, 120.0)
    excess = mis - 3.0 * nb * L * sigma2 / np.maximum(tot_e, 1e-300)
    excess = np.where(np.isfinite(excess), excess, 1.0)
    return mis, sigma2, snr, excess


def _point_covariance(geo, point, theta, c_tau, cov_ok):
    """Finite point (the pole where the fit gave none), delays, 3-D covariance [m^2] and
    the delay covariance used [s^2] (a horizon-wide one where the fit's is unusable)."""
    finite_pt = np.all(np.isfinite(point), axis=1) & np.all(np.isfinite(theta), axis=1)
    pole = np.array([0.0, 0.0, geo.radius_m])
    point = np.where(finite_pt[:, None], point, pole)
    theta = np.where(finite_pt[:, None], theta, 0.0)
    big = geo.radius_m**2
    cov_fin = finite_pt & cov_ok & np.all(np.isfinite(c_tau), axis=(1, 2))
    c_tau_safe = np.where(cov_fin[:, None, None], c_tau, np.eye(2) * geo.max_delay_s**2)
    cov = geo.point_covariance(point, c_tau_safe)
    cov_good = cov_fin & np.all(np.isfinite(cov), axis=(1, 2))
    cov = np.where(cov_good[:, None, None], cov, np.eye(3) * big)
    cov = np.minimum(cov, 1e3 * big)
    cov = np.maximum(cov, -1e3 * big)
    return point, theta, cov, c_tau_safe, finite_pt


def _finish(core, prep, plan, geo, method, min_snr_db, thr, options, delay_noise=None):
    flags = prep.flags.copy()
    mis, sigma2, snr, excess = _noise_snr_excess(core, prep)
    flags[snr < min_snr_db] |= 1 << Reason.LOW_SNR
    flags[excess > thr] |= 1 << Reason.OVERLAP

    theta = np.asarray(core["theta"], float)
    point = np.asarray(core["point"], float)
    clamped = np.asarray(core["clamped"], bool).copy()
    c_tau, cov_ok = core["covariance"](sigma2)
    if delay_noise is not None:  # the device's own delay noise (the kernel's cnoise)
        c_tau = delay_noise[0] * c_tau + delay_noise_covariance(delay_noise[1])
    c_tau = np.where(np.isfinite(c_tau), c_tau, np.nan)
    # Horizon check on the raw delays of the method.
    raw = np.asarray(core["raw_delays"], float)
    sd = np.sqrt(np.maximum(np.trace(np.nan_to_num(c_tau, nan=0.0), axis1=1, axis2=2), 0.0))
    over = _horizon_excess(geo, np.nan_to_num(raw)) > 4.0 * sd + 0.25 / plan.fs
    over |= np.asarray(core.get("at_edge", False), bool)
    flags[over] |= 1 << Reason.OUT_OF_RANGE

    point, theta, cov, c_tau_safe, finite_pt = _point_covariance(geo, point, theta, c_tau,
                                                                 cov_ok)
    bad_numeric = ~finite_pt
    flags[bad_numeric & (flags == 0)] |= 1 << Reason.OUT_OF_RANGE

    if core.get("aligned_seg") is not None:
        pol, amp = polarity_amplitude_aligned(core["aligned_seg"], core["eps_samples"], plan)
    else:
        pol, amp = polarity_amplitude(core["z"], plan)
    amp = np.where(np.isfinite(amp), amp, 0.0)
    reason = primary_reason(flags)
    accepted = reason == 0
    polar, azim = geo.angles_from_points(point)
    sigma_pos = np.sqrt(np.maximum(cov[:, 0, 0] + cov[:, 1, 1], 0.0))
    conf = confidence(accepted, snr, min_snr_db, excess, thr, sigma_pos, clamped)
    no_sig = (flags & ((1 << Reason.NONFINITE) | (1 << Reason.NO_SIGNAL))) != 0
    pol = np.where(no_sig, 0, pol).astype(np.int8)
    amp = np.where(no_sig, 0.0, amp)

    def fin(a, fill=0.0):
        return np.where(np.isfinite(a), a, fill)

    return LocalizationResult(
        method=method,
        tau_x_s=fin(theta[:, 0]),
        tau_y_s=fin(theta[:, 1]),
        twist_s=fin(theta[:, 2]),
        point_m=point,
        covariance_m2=cov,
        delay_covariance_s2=fin(c_tau_safe),
        polar_rad=fin(polar),
        azimuth_rad=fin(azim),
        residual=fin(mis, 1.0),
        overlap_excess=excess,
        pair_residual_s=fin(np.asarray(core["pair_residual_s"], float)),
        snr_db_est=snr,
        noise_rms_v_est=fin(np.sqrt(sigma2) * prep.scale),
        polarity=pol,
        amplitude_v=fin(amp * prep.scale),
        confidence=conf,
        clamped=clamped,
        accepted=accepted,
        reason=reason,
        reason_flags=flags.astype(np.uint16),
        options=dict(options),
        emission_offset_s=prep.onset / plan.fs - _first_arrival_s(geo, point, options),
    )


def _first_arrival_s(geo, point, options) -> np.ndarray:
    """(K,) [s] the earliest arrival after the emission: t_k(s) + d_k with the channels'
    own delays d (``channel_delays_s``, `ml`), else t_k(s)."""
    t = geo.arrival_times_s(point)
    d = options.get("channel_delays_s")
    return (t if d is None else t + np.asarray(d, dtype=float)).min(axis=1)


def localize_packets(batch, *, method="ml", **kwargs) -> LocalizationResult:
    """`localize` the windows of a detector's `ae_tactile.dsp.PacketBatch` (or anything with
    ``samples``, ``sample_rate_hz``, ``onset_index`` and ``saturated``): its saturation
    flags are used; the noise is measured here on the same pre-onset samples."""
    return localize(
        batch.samples,
        batch.sample_rate_hz,
        batch.onset_index,
        method=method,
        saturated=batch.saturated,
        **kwargs,
    )
