# SPDX-License-Identifier: Apache-2.0
"""The results of the localizer: `LocalizationResult` (arrays with K rows, one per packet)
and `PacketLocation` (one packet of the per-packet hot path, as plain floats).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from ae_tactile.localization.common import (
    REASON_DESCRIPTIONS,
    Reason,
    primary_reason,
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
    #: (K,) bool: the point was refined with the device's pulse (`refine.refine_result`)
    refined: np.ndarray = None

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
        "refined",
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
        self.refined = False  # refined with the device's pulse (`Localizer.set_front_end`)

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
        loc = cls(
            out,
            res.point_m[i].copy(),
            res.covariance_m2[i].copy(),
            res.delay_covariance_s2[i].copy(),
        )
        loc.refined = res.refined is not None and bool(res.refined[i])
        return loc

    def __repr__(self):
        p = self.point_m * 1e3
        return (
            f"PacketLocation({self.reason.name}, "
            f"point_mm=({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}), "
            f"polarity={self.polarity:+d}, snr_db={self.snr_db:.1f})"
        )
