# SPDX-License-Identifier: Apache-2.0
"""The records that flow through the package, defined once.

- `EventType`: the ContactEvent types (values of ContactEvent.msg);
- `ContactState`: a finger's latched contact state (values of ContactState.msg);
- `Reading`: what one emission was read as (touch, release, micro-slip, ...);
- `PacketView`: what the pipeline needs of one packet (a link record or a message);
- `ContactRecord`: one event for the robot hand (core side of ContactEvent.msg);
- `packet_record`, `source_record`, `slip_record`: a localized packet, a resolved emission
  and a slip detector event as a ContactRecord; `onset_ns`: a packet's trigger time.

SI units and integer nanoseconds throughout; no rclpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from ae_tactile.geometry import FingertipGeometry


class EventType(IntEnum):
    """ContactEvent types (the values of ContactEvent.msg; a test checks they agree)."""

    TOUCH = 1
    DETOUCH = 2
    SLIP_PRECURSOR = 3
    SLIP = 4
    TEXTURE = 5


class ContactState(IntEnum):
    """Latched contact state of a finger (values of ContactState.msg)."""

    NO_CONTACT = 0
    STICK = 1
    INCIPIENT_SLIP = 2
    GROSS_SLIP = 3


class Reading(IntEnum):
    """What one localized emission was read as (values of Emission.msg's ``reading``).

    The slip detector's interpretation of the emission stream assigns each emission to
    the physical event that best explains it.
    """

    UNKNOWN = 0  # not explained (interference that got through, a lost context)
    TOUCH = 1  # a contact began (or grew: a new point of an arriving object)
    RELEASE = 2  # a contact (or one of its points) ended
    MICRO_SLIP = 3  # Cattaneo-Mindlin micro-slip at the edge of a held, loaded contact
    SLIP = 4  # gross slip of a contact
    TEXTURE = 5  # a periodic emission of a contact sliding over a texture


#: ContactEvent type -> name, ContactState value -> name, Reading -> name (logs, bag exports)
EVENT_NAMES = {int(t): t.name for t in EventType}
STATE_NAMES = {int(s): s.name for s in ContactState}
READING_NAMES = {int(r): r.name for r in Reading}

_NAN3 = (math.nan, math.nan, math.nan)


@dataclass
class PacketView:
    """What the pipeline needs of one packet (a link PacketRecord or a received message)."""

    samples_v: np.ndarray  # (4, N) [V]
    sample_rate_hz: float
    onset_index: int
    stamp_ns: int  # host time of samples_v[:, 0] [ns]
    sequence_id: int
    noise_rms_v: float = 0.0
    saturated: bool = False


@dataclass(slots=True)
class ContactRecord:
    """One event for the robot hand (core side of ContactEvent.msg), SI units, int ns.

    point_m (3,) fingertip frame; covariance_m2 (3, 3); angles in rad; delays in s;
    packet_ids: the source packets (a slip event's last id is the emission that decided it).
    """

    event_type: int
    time_ns: int
    point_m: tuple
    covariance_m2: np.ndarray
    packet_ids: tuple
    polar_rad: float = math.nan
    azimuth_rad: float = math.nan
    tau_x_s: float = math.nan
    tau_y_s: float = math.nan
    amplitude_v: float = math.nan
    confidence: float = 0.0
    emission_rate_hz: float = math.nan
    spatial_period_m: float = math.nan
    slip_direction: tuple = _NAN3
    overlap_excess: float = 0.0  # single-emission misfit beyond noise (localization only)
    weak_release: bool = False  # below min_snr_db, kept by the weak-release gate (localization)


def source_record(p, src) -> ContactRecord:
    """Contact event of one emission resolved in an overlapping window."""
    x, y, z = (float(v) for v in src.point_m)
    tau = FingertipGeometry.delays_from_arrival_times(np.asarray(src.arrival_times_s, dtype=float))
    return ContactRecord(
        event_type=int(EventType.DETOUCH if src.polarity < 0 else EventType.TOUCH),
        time_ns=int(p.stamp_ns) + int(round(float(src.emission_time_s) * 1e9)),
        point_m=(x, y, z),
        covariance_m2=np.asarray(src.covariance_m2, dtype=float).reshape(3, 3),
        packet_ids=(int(p.sequence_id),),
        polar_rad=math.atan2(math.hypot(x, y), z),
        azimuth_rad=math.atan2(y, x),
        tau_x_s=float(tau[0]),
        tau_y_s=float(tau[1]),
        amplitude_v=float(src.amplitude_v),
        confidence=float(src.confidence),
    )


def slip_record(s) -> ContactRecord:
    """A slip detector event as a ContactRecord."""
    x, y, z = (float(v) for v in s.position_m)
    rho = math.hypot(x, y)
    return ContactRecord(
        event_type=int(s.kind),
        time_ns=int(s.time_ns),
        point_m=(x, y, z),
        covariance_m2=np.asarray(s.covariance_m2, dtype=float).reshape(3, 3),
        packet_ids=tuple(int(i) for i in s.packet_ids),
        polar_rad=math.atan2(rho, z),
        azimuth_rad=math.atan2(y, x),
        confidence=float(s.confidence),
        emission_rate_hz=float(s.emission_rate_hz),
        spatial_period_m=float(s.spatial_period_m),
        slip_direction=tuple(float(v) for v in np.asarray(s.slip_direction, dtype=float)),
    )


def packet_record(
    p, point, cov, polar, azimuth, tau_x, tau_y, amp, conf, polarity, offset_s, excess=0.0
) -> ContactRecord:
    """A localized packet as a ContactRecord (compression -> TOUCH, rarefaction -> DETOUCH).

    Parameters
    ----------
    p : PacketView
        The packet (its host stamp and sequence id).
    point, cov : array_like
        Fitted point (3,) [m] and its covariance (3, 3) [m^2].
    polar, azimuth : float
        Direction of the point [rad].
    tau_x, tau_y : float
        Fitted delays [s].
    amp, conf : float
        Amplitude [V] and confidence in [0, 1].
    polarity : int
        Sign of the first arrival (< 0: rarefaction).
    offset_s : float
        Emission instant after the packet's first sample [s].
    excess : float
        Unexplained in-band energy share of the fit.

    Returns
    -------
    ContactRecord
        Stamped ``p.stamp_ns + offset_s`` [ns].
    """
    kind = EventType.DETOUCH if polarity < 0 else EventType.TOUCH
    x, y, z = (float(v) for v in point)
    return ContactRecord(
        event_type=int(kind),
        time_ns=int(p.stamp_ns) + int(round(float(offset_s) * 1e9)),
        point_m=(x, y, z),
        covariance_m2=np.asarray(cov, dtype=float).reshape(3, 3),
        packet_ids=(int(p.sequence_id),),
        polar_rad=float(polar),
        azimuth_rad=float(azimuth),
        tau_x_s=float(tau_x),
        tau_y_s=float(tau_y),
        amplitude_v=float(amp),
        confidence=float(conf),
        overlap_excess=float(excess),
    )


def onset_ns(p) -> float:
    """Host time [ns] of a packet's onset sample (its trigger); NaN if it cannot be told."""
    try:
        return int(p.stamp_ns) + int(p.onset_index) * 1e9 / float(p.sample_rate_hz)
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        return math.nan
