# SPDX-License-Identifier: Apache-2.0
"""Input and output records of the slip detector (plain dataclasses, SI units, int ns)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ae_tactile.records import ContactState, EventType


def _nan3():
    return np.full(3, np.nan)


@dataclass(frozen=True)
class LocalizedEvent:
    """One accepted, localized emission, as the localizer publishes it.

    time_ns        emission (or onset) time, integer ns
    point_m        (3,) point on the fingertip surface (fingertip frame, m)
    covariance_m2  (3, 3) its covariance (m^2); None: unknown (zeros)
    (non-finite point or covariance values are kept: the detector rejects and counts them,
    ``SlipDetector.counts["rejected_non_finite"]``)
    polarity       +1 compression (TOUCH-like), -1 rarefaction (DETOUCH-like), 0 unknown
    amplitude_v    signed first-lobe amplitude (V)
    confidence     localization confidence in [0, 1]
    packet_id      sequence id of the source packet
    """

    time_ns: int
    point_m: np.ndarray
    covariance_m2: np.ndarray | None = None
    polarity: int = 0
    amplitude_v: float = math.nan
    confidence: float = 1.0
    packet_id: int = -1

    def __post_init__(self):
        p, c, pol, conf = self.point_m, self.covariance_m2, self.polarity, self.confidence
        if (
            type(self.time_ns) is int
            and type(p) is np.ndarray
            and p.dtype == np.float64
            and p.shape == (3,)
            and type(c) is np.ndarray
            and c.dtype == np.float64
            and c.shape == (3, 3)
            and type(pol) is int
            and -1 <= pol <= 1
            and type(conf) is float
            and 0.0 <= conf <= 1.0
            and type(self.amplitude_v) is float
            and type(self.packet_id) is int
        ):
            # already the stored types: only the covariance is symmetrized (a new array)
            object.__setattr__(self, "covariance_m2", 0.5 * (c + c.T))
            return
        self._validate()

    @classmethod
    def trusted(
        cls,
        time_ns: int,
        point_m: np.ndarray,
        covariance_m2: np.ndarray,
        polarity: int,
        amplitude_v: float,
        confidence: float,
        packet_id: int,
    ) -> LocalizedEvent:
        """An event from fields already of the stored types and checked by the caller
        (int ns, float64 (3,) point, symmetric float64 (3, 3) covariance, polarity in
        {-1, 0, 1}, confidence in [0, 1]): no validation, no copies. Non-finite values are
        still rejected and counted by the detector."""
        ev = object.__new__(cls)
        d = ev.__dict__
        d["time_ns"], d["point_m"], d["covariance_m2"] = time_ns, point_m, covariance_m2
        d["polarity"], d["amplitude_v"], d["confidence"] = polarity, amplitude_v, confidence
        d["packet_id"] = packet_id
        return ev

    def _validate(self):
        if isinstance(self.time_ns, bool) or not hasattr(self.time_ns, "__index__"):
            raise TypeError(
                f"LocalizedEvent.time_ns must be an integer (ns), got {self.time_ns!r}"
            )
        object.__setattr__(self, "time_ns", int(self.time_ns.__index__()))
        p = np.asarray(self.point_m, dtype=float)
        if p.shape != (3,):
            raise ValueError(f"LocalizedEvent.point_m must be 3 numbers, got {self.point_m!r}")
        object.__setattr__(self, "point_m", p)
        if self.covariance_m2 is None:
            c = np.zeros((3, 3))
        else:
            c = np.asarray(self.covariance_m2, dtype=float)
            if c.shape != (3, 3):
                raise ValueError("LocalizedEvent.covariance_m2 must be a 3x3 array (m^2)")
            c = 0.5 * (c + c.T)
        object.__setattr__(self, "covariance_m2", c)
        pol = self.polarity
        if isinstance(pol, bool) or not hasattr(pol, "__index__") and not isinstance(pol, float):
            raise ValueError(f"LocalizedEvent.polarity must be -1, 0 or +1, got {pol!r}")
        if pol not in (-1, 0, 1):
            raise ValueError(f"LocalizedEvent.polarity must be -1, 0 or +1, got {pol!r}")
        object.__setattr__(self, "polarity", int(pol))
        conf = float(self.confidence)
        if not 0.0 <= conf <= 1.0:
            raise ValueError(
                f"LocalizedEvent.confidence must be in [0, 1], got {self.confidence!r}"
            )
        object.__setattr__(self, "confidence", conf)
        object.__setattr__(self, "amplitude_v", float(self.amplitude_v))
        object.__setattr__(self, "packet_id", int(self.packet_id))


@dataclass(frozen=True)
class SlipEvent:
    """One output event (a ContactEvent of type SLIP_PRECURSOR, SLIP or TEXTURE).

    kind               EventType (SLIP_PRECURSOR, SLIP or TEXTURE)
    time_ns            time of the emission that produced it (ns)
    position_m         (3,) SLIP_PRECURSOR: the micro-slip emission point; SLIP, TEXTURE:
                       the contact centre (fingertip frame, m)
    covariance_m2      (3, 3) of position_m
    contact_id         tracker id of the contact
    emission_rate_hz   SLIP_PRECURSOR / SLIP: recent slip emission rate of the contact;
                       TEXTURE: the periodic emission rate 1/T (Hz)
    spatial_period_m   TEXTURE with a known sliding speed: v T (m); NaN otherwise
    slip_direction     (3,) unit tangent direction of travel of the contact (NaN if unknown)
    (packet_ids ends with the packet of the emission that decided the event)
    confidence         in [0, 1]
    packet_ids         source packets (the evidence behind the event)
    onset              True for the event that started the state (first SLIP_PRECURSOR
                       of an INCIPIENT_SLIP episode, first SLIP of a GROSS_SLIP episode,
                       first TEXTURE of a periodic run)
    evidence           SLIP_PRECURSOR: micro-slip evidence in the window; SLIP: emissions
                       near the centre in the test window; TEXTURE: regular intervals
    """

    kind: EventType
    time_ns: int
    position_m: np.ndarray
    covariance_m2: np.ndarray
    contact_id: int
    emission_rate_hz: float
    spatial_period_m: float = math.nan
    slip_direction: np.ndarray = field(default_factory=_nan3)
    confidence: float = 0.0
    packet_ids: tuple = ()
    onset: bool = False
    evidence: float = math.nan


@dataclass(frozen=True)
class ContactInfo:
    """Snapshot of one tracked contact."""

    contact_id: int
    state: ContactState
    since_ns: int
    centre_m: np.ndarray
    radius_m: float
    announced: bool
    confirmed: bool
    release_pending: bool
    slip_emission_rate_hz: float
    precursor_count: int
    n_members: int
    last_time_ns: int
    velocity_m_s: np.ndarray = field(default_factory=_nan3)  # along the surface (0 if held)
    moving: bool = False


@dataclass(frozen=True)
class FingerState:
    """Latched state of the finger (ContactState.msg).

    state                  the most severe state over the confirmed contacts
    since_ns               when that state began
    contact_point_m        (3,) centre of the contact that sets the state (NaN if none)
    slip_emission_rate_hz  its recent slip emission rate (Hz)
    precursor_count        SLIP_PRECURSOR events of that contact since it appeared
    contact_id             its tracker id (-1 if none)
    n_contacts             confirmed contacts on the finger
    time_ns                time of the last update
    """

    state: ContactState
    since_ns: int
    contact_point_m: np.ndarray
    slip_emission_rate_hz: float
    precursor_count: int
    contact_id: int
    n_contacts: int
    time_ns: int
