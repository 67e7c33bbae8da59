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

import math
from dataclasses import dataclass, field, fields
from typing import Callable

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import fast, gcc, gradient, ml
from ae_tactile.localization.common import (
    REASON_DESCRIPTIONS,
    Reason,
    adc_noise,
    make_plan,
    misfit,
    per_packet,
    prepare,
    primary_reason,
    validate_windows,
)
from ae_tactile.localization.events import (
    confidence,
    polarity_amplitude,
    polarity_amplitude_aligned,
)

#: Default signal band (Hz): the front end's 100 kHz high-pass to its 1 MHz low-pass,
#: the upper edge lowered to fs/4 at low sample rates (see `default_band_hz`).
DEFAULT_BAND_HZ = (100e3, 1e6)


#: Candidate band of the data-driven edge (``ml`` with ``band_hz=None``): 100 kHz to
#: min(0.45 fs, 4 MHz); the edge then follows each packet's spectrum (`common.band_edge_hz`).
AUTO_BAND_MAX_HZ = 4e6


def auto_band_hz(sample_rate_hz):
    """Candidate band (lo, hi) of the data-driven edge."""
    return (DEFAULT_BAND_HZ[0], min(AUTO_BAND_MAX_HZ, 0.45 * float(sample_rate_hz)))


def default_band_hz(sample_rate_hz):
    """(100 kHz, min(1 MHz, fs/4)): above fs/4 a 1 MHz front end aliases at low rates, and
    aliased content does not shift like the rest of the waveform (bias, not noise)."""
    return (DEFAULT_BAND_HZ[0], min(DEFAULT_BAND_HZ[1], 0.25 * float(sample_rate_hz)))


@dataclass(frozen=True)
class EstimatorInfo:
    """A registered delay estimator."""

    name: str
    function: Callable
    description: str
    #: Default overlap threshold on the excess misfit (calibrated, see docs/localization.md).
    overlap_threshold: float


ESTIMATORS: dict[str, EstimatorInfo] = {}


def register_estimator(name, function, description, overlap_threshold=0.1):
    """Add an estimator ``function(prepared, plan, **options) -> core dict`` to the registry."""
    if not isinstance(name, str) or not name:
        raise ValueError("estimator name must be a non-empty string")
    ESTIMATORS[name] = EstimatorInfo(name, function, description, float(overlap_threshold))


def available_methods() -> list[str]:
    return sorted(ESTIMATORS)


def get_estimator(name) -> EstimatorInfo:
    try:
        return ESTIMATORS[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown localization method {name!r}; choose one of {available_methods()}"
        ) from None


# Overlap thresholds: the excess misfit of single clean packets stays below ~0.055 (ML,
# gradient, GCC) and ~0.1 (far-field baseline, whose biased delays leave some misfit) at
# 5-10 dB SNR, 2-20 MS/s, polar angles up to 90 deg (docs/localization.md).
register_estimator(
    "ml",
    ml.estimate,
    "maximum likelihood on the exact sphere: steered response power over (s_x, s_y), "
    "Newton from a cross-correlation start",
    overlap_threshold=0.07,
)
register_estimator(
    "gradient",
    gradient.estimate,
    "the paper's gradient method (ref. [8]) iterated with re-alignment, band-limited derivative",
    overlap_threshold=0.07,
)
register_estimator(
    "gcc_phat",
    gcc.estimate_gcc_phat,
    "GCC-PHAT over the 6 pairs, PHAT in band only, Newton sub-sample peak, LS, exact inversion",
    overlap_threshold=0.07,
)
register_estimator(
    "xcorr_farfield",
    gcc.estimate_xcorr_farfield,
    "paper baseline: plain cross-correlation peaks of channel sums, far-field Eq. 2 inversion",
    overlap_threshold=0.12,
)


@dataclass
class LocalizationResult:
    """Per-packet results, arrays with K rows (SI units).

    tau_x_s, tau_y_s, twist_s   delays of the fit (geometry.py definitions)
    point_m (K, 3)              contact point on the upper hemisphere
    covariance_m2 (K, 3, 3)     its covariance (linear propagation of the delay covariance)
    delay_covariance_s2 (K, 2, 2)  covariance of (tau_x, tau_y)
    polar_rad, azimuth_rad      direction of point_m
    residual                    misfit: fraction of in-band energy of the aligned channels
                                not explained by one common waveform, in [0, 1]
    overlap_excess              residual minus its expected noise-only value
    pair_residual_s             RMS residual of the 6-pair LS (pairwise methods' start), s
    snr_db_est                  SNR per docs/conventions.md, estimated from the data
    noise_rms_v_est             noise sigma used (pre-onset, given, or fit residual)
    polarity                    +1 touch, -1 release, 0 undetermined (int8)
    amplitude_v                 signed first-lobe amplitude of the aligned channel mean
    confidence                  in [0, 1] (events.py); 0 when rejected
    clamped                     point clamped onto the horizon (|sin theta| > 1 implied)
    accepted                    bool
    reason                      uint8 `Reason` code (0 when accepted)
    reason_flags                bit (1 << code) for every reason that applied
    emission_offset_s           emission instant relative to the window's first sample:
                                onset_index / fs - min_k |s - e_k| / c (the onset marks the
                                arrival at the nearest element), s
    """

    method: str
    tau_x_s: np.ndarray
    tau_y_s: np.ndarray
    twist_s: np.ndarray
    point_m: np.ndarray
    covariance_m2: np.ndarray
    delay_covariance_s2: np.ndarray
    polar_rad: np.ndarray
    azimuth_rad: np.ndarray
    residual: np.ndarray
    overlap_excess: np.ndarray
    pair_residual_s: np.ndarray
    snr_db_est: np.ndarray
    noise_rms_v_est: np.ndarray
    polarity: np.ndarray
    amplitude_v: np.ndarray
    confidence: np.ndarray
    clamped: np.ndarray
    accepted: np.ndarray
    reason: np.ndarray
    reason_flags: np.ndarray
    options: dict = field(default_factory=dict)
    emission_offset_s: np.ndarray = None

    def __len__(self):
        return int(self.accepted.shape[0])

    @property
    def reason_names(self) -> list[str]:
        return [Reason(int(r)).name for r in self.reason]

    @staticmethod
    def describe_reason(code) -> str:
        return REASON_DESCRIPTIONS[Reason(int(code))]

    def packet(self, i) -> dict:
        """Row i as a plain dict (for logging and tests)."""
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = v[i] if isinstance(v, np.ndarray) else v
        out["reason_name"] = Reason(int(self.reason[i])).name
        return out


def _empty(method, options):
    z = np.zeros(0)
    return LocalizationResult(
        method,
        z,
        z,
        z,
        np.zeros((0, 3)),
        np.zeros((0, 3, 3)),
        np.zeros((0, 2, 2)),
        z,
        z,
        z,
        z,
        z,
        z,
        z,
        np.zeros(0, np.int8),
        z,
        z,
        np.zeros(0, bool),
        np.zeros(0, bool),
        np.zeros(0, np.uint8),
        np.zeros(0, np.uint16),
        options,
        z,
    )


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
    **options,
) -> LocalizationResult:
    """Localize K packets (see the module docstring).

    windows (K, 4, M) volts (any real dtype; a single (4, M) window is accepted),
    sample_rate_hz, onset_index (K,) first sample at/after the earliest arrival (the
    detector's or the simulator's), method: a name in `available_methods()`.
    geometry: FingertipGeometry (default tip). band_hz: signal band for the estimators
    (default `default_band_hz(fs)`).
    noise_rms_v: scalar or (K,) known noise sigma (V, > 0; NaN entries: unknown). Default:
    measured on the samples before ``onset - pre_onset_s``, else from the fit residual.
    saturated: (K,) flags from upstream; full_scale_v: ADC clip level (either one, or
    neither: a flat top of >= max(4, 0.3 us fs) samples at a channel's dominant extreme
    then flags saturation). channel_gains: relative gains of the 4 channels (divided out).
    min_snr_db: LOW_SNR below this. overlap_threshold: OVERLAP when the excess misfit
    exceeds it (default per method). engine: None (compiled kernel for ``ml`` when numba
    is available), 'numba' or 'numpy'. Extra keyword options go to the estimator (e.g.
    iterations=).
    """
    info = get_estimator(method)
    geo = FingertipGeometry() if geometry is None else geometry
    eng = resolve_engine(engine, method, options)
    x, onset = validate_windows(windows, onset_index, copy=eng != "numba")
    plan = _plan(sample_rate_hz, geo, x.shape[2], band_hz, pre_onset_s, echo_guard_s, method)
    min_snr_db = float(min_snr_db)
    if not np.isfinite(min_snr_db):
        raise ValueError(f"min_snr_db must be finite, got {min_snr_db!r}")
    thr = info.overlap_threshold if overlap_threshold is None else float(overlap_threshold)
    if not (np.isfinite(thr) and thr > 0):
        raise ValueError(f"overlap_threshold must be positive, got {overlap_threshold!r}")
    k = x.shape[0]
    noise = _noise_arg(noise_rms_v, k)
    if eng == "numba":
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
        )
        return _result_from_kernel(method, options, out, pt, cov, ctau)
    if k == 0:
        return _empty(method, options)
    with np.errstate(all="ignore"):
        prep = prepare(
            x,
            onset,
            plan,
            noise_rms_v=None if noise_rms_v is None else noise,
            saturated=saturated,
            full_scale_v=full_scale_v,
            channel_gains=channel_gains,
        )
        core = info.function(prep, plan, **options)
        return _finish(core, prep, plan, geo, method, min_snr_db, thr, options)


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


def _result_from_kernel(method, options, out, pt, cov, ctau):
    flags = out[:, 12].astype(np.int64)
    reason = primary_reason(flags)
    col = out.T.copy()
    return LocalizationResult(
        method=method,
        tau_x_s=col[0],
        tau_y_s=col[1],
        twist_s=col[2],
        point_m=pt,
        covariance_m2=cov,
        delay_covariance_s2=ctau,
        polar_rad=col[14],
        azimuth_rad=col[15],
        residual=col[3],
        overlap_excess=col[4],
        pair_residual_s=col[5],
        snr_db_est=col[6],
        noise_rms_v_est=col[7],
        polarity=col[8].astype(np.int8),
        amplitude_v=col[9],
        confidence=col[10],
        clamped=col[11] > 0,
        accepted=reason == 0,
        reason=reason,
        reason_flags=flags.astype(np.uint16),
        options=dict(options),
        emission_offset_s=col[13],
    )


def _finish(core, prep, plan, geo, method, min_snr_db, thr, options):
    flags = prep.flags.copy()
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
    flags[snr < min_snr_db] |= 1 << Reason.LOW_SNR
    excess = mis - 3.0 * nb * L * sigma2 / np.maximum(tot_e, 1e-300)
    excess = np.where(np.isfinite(excess), excess, 1.0)
    flags[excess > thr] |= 1 << Reason.OVERLAP

    theta = np.asarray(core["theta"], float)
    point = np.asarray(core["point"], float)
    clamped = np.asarray(core["clamped"], bool).copy()
    c_tau, cov_ok = core["covariance"](sigma2)
    c_tau = np.where(np.isfinite(c_tau), c_tau, np.nan)
    # Horizon check on the raw delays of the method.
    raw = np.asarray(core["raw_delays"], float)
    sd = np.sqrt(np.maximum(np.trace(np.nan_to_num(c_tau, nan=0.0), axis1=1, axis2=2), 0.0))
    over = _horizon_excess(geo, np.nan_to_num(raw)) > 4.0 * sd + 0.25 / plan.fs
    over |= np.asarray(core.get("at_edge", False), bool)
    flags[over] |= 1 << Reason.OUT_OF_RANGE

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
        emission_offset_s=prep.onset / plan.fs - geo.arrival_times_s(point).min(axis=1),
    )


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


_FLOATS = (np.dtype(np.float64), np.dtype(np.float32))
_REALS = (int, np.integer, float, np.floating)


class PacketLocation:
    """One packet's localization (`Localizer.localize_one`), SI units; fields as in
    `LocalizationResult` (scalars, point_m (3,), covariance_m2 (3, 3)), plus snr_db (the
    estimated SNR) and emission_offset_s (emission instant relative to the window's first
    sample: the onset time minus the travel time from the fitted point to the nearest
    element)."""

    __slots__ = (
        "accepted",
        "reason",
        "reason_flags",
        "point_m",
        "covariance_m2",
        "delay_covariance_s2",
        "polar_rad",
        "azimuth_rad",
        "tau_x_s",
        "tau_y_s",
        "twist_s",
        "amplitude_v",
        "confidence",
        "polarity",
        "snr_db",
        "noise_rms_v_est",
        "residual",
        "overlap_excess",
        "clamped",
        "emission_offset_s",
    )

    def __init__(self, out, point, cov, ctau):
        flags = int(out[12])
        reason = 0
        for r in range(1, 8):
            if flags & (1 << r):
                reason = r
                break
        self.accepted = reason == 0
        self.reason = Reason(reason)
        self.reason_flags = flags
        self.point_m = point
        self.covariance_m2 = cov
        self.delay_covariance_s2 = ctau
        (
            self.tau_x_s,
            self.tau_y_s,
            self.twist_s,
            self.residual,
            self.overlap_excess,
            _,
            self.snr_db,
            self.noise_rms_v_est,
            pol,
            self.amplitude_v,
            self.confidence,
            clamped,
            _,
            self.emission_offset_s,
            self.polar_rad,
            self.azimuth_rad,
        ) = out.tolist()
        self.polarity = int(pol)
        self.clamped = bool(clamped)

    @classmethod
    def from_result(cls, res: LocalizationResult, i: int = 0):
        """Row i of a batched result."""
        out = np.array(
            [
                res.tau_x_s[i],
                res.tau_y_s[i],
                res.twist_s[i],
                res.residual[i],
                res.overlap_excess[i],
                res.pair_residual_s[i],
                res.snr_db_est[i],
                res.noise_rms_v_est[i],
                res.polarity[i],
                res.amplitude_v[i],
                res.confidence[i],
                res.clamped[i],
                res.reason_flags[i],
                res.emission_offset_s[i],
                res.polar_rad[i],
                res.azimuth_rad[i],
            ],
            dtype=float,
        )
        return cls(
            out,
            res.point_m[i].copy(),
            res.covariance_m2[i].copy(),
            res.delay_covariance_s2[i].copy(),
        )

    def __repr__(self):
        p = self.point_m * 1e3
        return (
            f"PacketLocation({self.reason.name}, "
            f"point_mm=({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}), "
            f"polarity={self.polarity:+d}, snr_db={self.snr_db:.1f})"
        )


class Localizer:
    """A configured `localize` (what the ROS node holds):
    ``Localizer(method='ml', ...)(windows, fs, onset)``.

    ``localize_one(window (4, M), fs, onset)`` is the per-packet hot path: with numba and
    ``ml`` one compiled call per packet (plans and tables cached per (fs, M, geometry));
    ``warm_up(geometry, fs, n_samples)`` compiles and caches it before acquisition.
    """

    _ONE_KEYS = frozenset(
        {
            "band_hz",
            "min_snr_db",
            "overlap_threshold",
            "pre_onset_s",
            "echo_guard_s",
            "full_scale_v",
            "engine",
            "iterations",
            "geometry",
        }
    )

    def __init__(self, method="ml", **kwargs):
        info = get_estimator(method)
        self.method = method
        self.kwargs = kwargs
        opts = {
            k: v
            for k, v in kwargs.items()
            if k not in self._ONE_KEYS and k not in ("noise_rms_v", "saturated", "channel_gains")
        }
        if "iterations" in kwargs:
            opts["iterations"] = kwargs["iterations"]
        self._one_engine = resolve_engine(kwargs.get("engine"), method, opts)
        if self._one_engine == "numba":
            self._iterations = _iterations(kwargs)
            self._min_snr_db = float(kwargs.get("min_snr_db", 5.0))
            thr = kwargs.get("overlap_threshold")
            self._thr = info.overlap_threshold if thr is None else float(thr)
            fsv = kwargs.get("full_scale_v")
            self._full_scale = np.nan if fsv is None else _positive_arg("full_scale_v", fsv)
            if not (np.isfinite(self._min_snr_db) and np.isfinite(self._thr) and self._thr > 0):
                raise ValueError("min_snr_db must be finite and overlap_threshold positive")
        self._plans = {}
        self._default_geometry = kwargs.get("geometry") or FingertipGeometry()

    def __call__(self, windows, sample_rate_hz, onset_index, **overrides):
        kw = dict(self.kwargs)
        kw.update(overrides)
        return localize(windows, sample_rate_hz, onset_index, method=self.method, **kw)

    def _tables(self, fs, m, geometry):
        key = (fs, m, geometry)
        hit = self._plans.get(key)
        if hit is None:
            plan = _plan(
                fs,
                geometry,
                m,
                self.kwargs.get("band_hz"),
                self.kwargs.get("pre_onset_s", 1e-6),
                self.kwargs.get("echo_guard_s", 0.3e-6),
                self.method,
            )
            hit = fast.tables_for(plan)
            if len(self._plans) > 32:
                self._plans.clear()
            self._plans[key] = hit
        return hit

    def localize_one(
        self,
        samples_v,
        sample_rate_hz,
        onset_index,
        *,
        noise_rms_v=None,
        saturated=False,
        geometry=None,
        channel_gains=None,
    ) -> PacketLocation:
        """Localize one (4, M) window (float32 / float64 volts). Never raises on the data
        (NaN, zeros, clipping: a rejection with its reason); ValueError / TypeError on bad
        arguments. noise_rms_v: known sigma (V, > 0) or None / NaN (measured);
        saturated: upstream clip flag (None: the flat-top heuristic decides)."""
        geo = self._default_geometry if geometry is None else geometry
        if self._one_engine != "numba":
            kw = dict(self.kwargs)
            kw.update(
                geometry=geo,
                noise_rms_v=noise_rms_v,
                channel_gains=channel_gains,
                saturated=None if saturated is None else [bool(saturated)],
            )
            x = np.asarray(samples_v)
            if x.ndim != 2:
                raise ValueError(f"samples_v must have shape (4, M), got {x.shape}")
            res = localize(x[None], sample_rate_hz, [onset_index], method=self.method, **kw)
            return PacketLocation.from_result(res, 0)
        x = samples_v
        if not (type(x) is np.ndarray and x.dtype in _FLOATS and x.flags.c_contiguous):
            x = np.asarray(x)
            if x.dtype == object or not (
                np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)
            ):
                raise TypeError(f"samples_v must be a real numeric array, got dtype {x.dtype}")
            x = np.ascontiguousarray(x, dtype=np.float64)
        if x.ndim != 2 or x.shape[0] != 4 or x.shape[1] < 4:
            raise ValueError(f"samples_v must have shape (4, M) with M >= 4, got {x.shape}")
        fs = sample_rate_hz
        if type(fs) is not float:
            fs = _positive_arg("sample_rate_hz", fs)
        elif not (fs > 0 and fs < np.inf):
            raise ValueError(
                f"sample_rate_hz must be a positive finite number, got {sample_rate_hz!r}"
            )
        on = onset_index
        if type(on) is not int:
            if isinstance(on, (bool, np.bool_)) or not isinstance(on, _REALS):
                raise TypeError(f"onset_index must be an integer sample index, got {on!r}")
            if not (np.isfinite(on) and on == int(on)):
                raise ValueError(f"onset_index must be an integer sample index, got {on!r}")
            on = int(on)
        if noise_rms_v is None:
            nr = np.nan
        else:
            nr = float(noise_rms_v)
            if not (nr > 0 and nr < np.inf) and not math.isnan(nr):
                raise ValueError(
                    f"noise_rms_v must be positive and finite (NaN: unknown), got {noise_rms_v!r}"
                )
        sat = -1 if saturated is None else int(bool(saturated))
        if not isinstance(geo, FingertipGeometry):
            raise TypeError(f"geometry must be a FingertipGeometry, got {type(geo).__name__}")
        tb = self._tables(fs, x.shape[1], geo)
        gains = None if channel_gains is None else _gains_arg(channel_gains)
        out = np.empty(fast.N_SCALAR_OUT)
        pt = np.empty(3)
        cov = np.empty((3, 3))
        ctau = np.empty((2, 2))
        fast.run_one(
            x,
            on,
            nr,
            sat,
            self._full_scale,
            gains,
            tb,
            self._iterations,
            self._min_snr_db,
            self._thr,
            out,
            pt,
            cov,
            ctau,
        )
        return PacketLocation(out, pt, cov, ctau)

    def warm_up(self, geometry=None, sample_rate_hz=10e6, n_samples=400):
        """Compile and cache the kernels (float32 and float64 windows) and the plan for this
        (geometry, fs, M) so that the first packet is fast. Returns self."""
        geo = self._default_geometry if geometry is None else geometry
        fs = _positive_arg("sample_rate_hz", sample_rate_hz)
        m = int(n_samples)
        rng = np.random.default_rng(0)
        x = rng.standard_normal((4, m)) * 1e-3
        for dt in (np.float64, np.float32):
            self.localize_one(x.astype(dt), fs, m // 4, geometry=geo)
            self(x.astype(dt)[None], fs, [m // 4], geometry=geo)
        return self
