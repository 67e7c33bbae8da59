# SPDX-License-Identifier: Apache-2.0
"""The records that flow through the package, defined once.

- `EventType`: the ContactEvent types (values of ContactEvent.msg);
- `ContactState`: a finger's latched contact state (values of ContactState.msg);
- `Reading`: what one emission was read as (touch, release, micro-slip, ...);
- `PacketView`: what the pipeline needs of one packet (a link record or a message);
- `ContactRecord`: one event for the robot hand (core side of ContactEvent.msg);
- `EmissionRecord`: one localized emission with its reading (core side of Emission.msg);
- `ContactSnapshot`: one current contact (core side of Contact.msg);
- `packet_record`, `source_record`, `slip_record`: a localized packet, a resolved emission
  and a slip detector event as a ContactRecord; `emission_record`: a localized packet's
  record with its reading; `onset_ns`: a packet's trigger time.

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
    device_sample_index: int | None = None  # device sample count at samples_v[:, 0]; None: unknown


@dataclass(slots=True)
class ContactRecord:
    """One event for the robot hand (core side of ContactEvent.msg), SI units, int ns.

    point_m (3,) fingertip frame; covariance_m2 (3, 3); angles in rad; delays in s;
    packet_ids: the source packets (a slip event's last id is the emission that decided it).
    A localized emission's record (the localizer's output) is TOUCH for a compression and
    DETOUCH for a rarefaction; what the hand receives on ``contacts`` is the slip
    detector's TOUCH at a contact's begin and DETOUCH at its end, with ``contact_id``.
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
    contact_id: int = 0  # the slip detector's contact (from 1); 0: none
    device_time_ns: int = -1  # emission time on the device clock [ns]; -1 unknown


@dataclass(slots=True)
class EmissionRecord:
    """One localized emission and what it was read as (core side of Emission.msg).

    Attributes
    ----------
    time_ns : int
        Emission time, host clock [ns].
    point_m : tuple
        (x, y, z) emission point, fingertip frame [m].
    covariance_m2 : numpy.ndarray
        (3, 3) covariance of the point [m^2].
    packet_ids : tuple
        Source packets' sequence ids.
    polarity : int
        +1 compression, -1 rarefaction, 0 unknown.
    reading : int
        A `Reading` value.
    contact_id : int
        The contact it was assigned to (from 1); 0: none.
    polar_rad, azimuth_rad : float
        Direction of the point [rad].
    tau_x_s, tau_y_s : float
        Fitted delays [s].
    amplitude_v : float
        Signed amplitude [V].
    confidence : float
        Localization confidence in [0, 1].
    device_time_ns : int
        Emission time on the device clock [ns]; -1 unknown.
    """

    time_ns: int
    point_m: tuple
    covariance_m2: np.ndarray
    packet_ids: tuple
    polarity: int
    reading: int = int(Reading.UNKNOWN)
    contact_id: int = 0
    polar_rad: float = math.nan
    azimuth_rad: float = math.nan
    tau_x_s: float = math.nan
    tau_y_s: float = math.nan
    amplitude_v: float = math.nan
    confidence: float = 0.0
    device_time_ns: int = -1


@dataclass(slots=True)
class ContactSnapshot:
    """One current contact of a finger (core side of Contact.msg).

    Attributes
    ----------
    contact_id : int
        The contact's id (from 1).
    point_m : tuple
        (x, y, z) its centre, fingertip frame [m].
    state : int
        A `ContactState` value (its own state).
    since_ns : int
        When that state began, host clock [ns].
    slip_emission_rate_hz : float
        Recent rate of its micro-slip / slip emissions [Hz].
    precursor_count : int
        Its SLIP_PRECURSOR events since it began.
    """

    contact_id: int
    point_m: tuple
    state: int
    since_ns: int
    slip_emission_rate_hz: float = 0.0
    precursor_count: int = 0


def emission_record(c: ContactRecord, reading=Reading.UNKNOWN, contact_id: int = 0
                    ) -> EmissionRecord:
    """A localized emission's record (`packet_record`, `source_record`) with its reading.

    Parameters
    ----------
    c : ContactRecord
        The localizer's record (TOUCH: compression, DETOUCH: rarefaction).
    reading : Reading or int
        What the slip detector read it as.
    contact_id : int
        The contact it was assigned to; 0 (or negative): none.

    Returns
    -------
    EmissionRecord
    """
    return EmissionRecord(
        time_ns=c.time_ns,
        point_m=c.point_m,
        covariance_m2=c.covariance_m2,
        packet_ids=c.packet_ids,
        polarity=-1 if c.event_type == EventType.DETOUCH else 1,
        reading=int(reading),
        contact_id=max(int(contact_id), 0),
        polar_rad=c.polar_rad,
        azimuth_rad=c.azimuth_rad,
        tau_x_s=c.tau_x_s,
        tau_y_s=c.tau_y_s,
        amplitude_v=c.amplitude_v,
        confidence=c.confidence,
        device_time_ns=c.device_time_ns,
    )


def contact_snapshot(info) -> ContactSnapshot:
    """A slip detector's `ContactInfo` as a ContactSnapshot.

    Parameters
    ----------
    info : ae_tactile.slip.ContactInfo
        One tracked contact.

    Returns
    -------
    ContactSnapshot
    """
    x, y, z = (float(v) for v in info.centre_m)
    return ContactSnapshot(
        contact_id=int(info.contact_id),
        point_m=(x, y, z),
        state=int(info.state),
        since_ns=int(info.since_ns),
        slip_emission_rate_hz=float(info.slip_emission_rate_hz),
        precursor_count=int(info.precursor_count),
    )


def _device_time_ns(p, offset_s: float) -> int:
    """Device-clock time [ns] of ``offset_s`` after a packet's first sample; -1 unknown."""
    k = getattr(p, "device_sample_index", -1)
    if k is None or k < 0:
        return -1
    try:
        return int(round((int(k) / float(p.sample_rate_hz) + float(offset_s)) * 1e9))
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        return -1


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
        device_time_ns=_device_time_ns(p, float(src.emission_time_s)),
    )


def slip_record(s) -> ContactRecord:
    """A slip detector event (a contact's TOUCH / DETOUCH, its SLIP_PRECURSOR, SLIP or
    TEXTURE) as a ContactRecord carrying the contact's id."""
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
        contact_id=max(int(s.contact_id), 0),
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
        device_time_ns=_device_time_ns(p, offset_s),
    )


def earliest_emission_ns(p, geometry) -> int:
    """Earliest possible emission stamp of a window [ns]: its emissions are at most one
    sphere diameter's travel time older than its first sample (``geometry``: a
    `FingertipGeometry`)."""
    g = geometry
    return int(p.stamp_ns) - int(math.ceil(2.0 * g.radius_m / g.sound_speed_m_s * 1e9))


def onset_ns(p) -> float:
    """Host time [ns] of a packet's onset sample (its trigger); NaN if it cannot be told."""
    try:
        return int(p.stamp_ns) + int(p.onset_index) * 1e9 / float(p.sample_rate_hz)
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        return math.nan
