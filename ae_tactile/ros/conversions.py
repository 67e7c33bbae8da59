# SPDX-License-Identifier: Apache-2.0
"""numpy <-> ae_tactile message conversions (the only place that knows the field layout).

Time stamps are integer nanoseconds (int64) on the core side, builtin_interfaces/Time
on the message side. Packet samples are channel-major float32 volts; a (4, N) view of
a received Packet costs no copy (``np.frombuffer`` on the message's array.array).
"""

from __future__ import annotations

import array
import struct

import numpy as np
from builtin_interfaces.msg import Time

from ae_tactile.geometry import N_CHANNELS
from ae_tactile.msg import (
    Contact,
    ContactEvent,
    ContactState,
    Emission,
    Packet,
    PacketArray,
    SensorInfo,
)
from ae_tactile.protocol import PROTOCOL_VERSION
from ae_tactile.records import ContactRecord, EmissionRecord, EventType

NS_PER_S = 1_000_000_000


def ns_to_time_msg(stamp_ns: int) -> Time:
    """Integer nanoseconds -> builtin_interfaces/Time (sec, nanosec), exact."""
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


def time_msg_to_ns(stamp: Time) -> int:
    """builtin_interfaces/Time -> integer nanoseconds, exact."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def float32_array(x) -> array.array:
    """array.array('f') holding x (any shape, C order) by one memcpy.

    Assigning a numpy array to a float32[] field makes the generated setter check every
    element in Python (~1 ms per 1,600 samples); an array.array('f') is taken as is.
    """
    out = array.array("f")
    out.frombytes(np.ascontiguousarray(x, dtype=np.float32).tobytes())
    return out


def make_packet(
    samples_v,
    *,
    stamp_ns: int,
    sample_rate_hz: float,
    onset_index: int,
    sequence_id: int,
    noise_rms_v: float = 0.0,
    saturated: bool = False,
) -> Packet:
    """One Packet from a (4, N) array of volts (any real dtype; stored as float32)."""
    x = np.asarray(samples_v)
    if x.ndim != 2 or x.shape[0] != N_CHANNELS:
        raise ValueError(f"packet samples must have shape (4, N), got {x.shape}")
    if not 0 <= int(onset_index) < max(x.shape[1], 1):
        raise ValueError(f"onset_index {onset_index} outside the window of {x.shape[1]} samples")
    msg = Packet()
    msg.stamp = ns_to_time_msg(stamp_ns)
    msg.sample_rate_hz = float(sample_rate_hz)
    msg.channel_count = N_CHANNELS
    msg.samples_per_channel = int(x.shape[1])
    msg.samples = float32_array(x)
    msg.onset_index = int(onset_index)
    msg.sequence_id = int(sequence_id)
    msg.noise_rms_v = float(noise_rms_v)
    msg.saturated = bool(saturated)
    return msg


def packet_samples(msg: Packet) -> np.ndarray:
    """(4, N) float32 view of a Packet's samples (no copy); ValueError if inconsistent."""
    n = int(msg.samples_per_channel)
    count = int(msg.channel_count)
    data = (
        np.frombuffer(msg.samples, dtype=np.float32)
        if len(msg.samples)
        else np.zeros(0, np.float32)
    )
    if count != N_CHANNELS or data.size != count * n:
        raise ValueError(
            f"inconsistent Packet {msg.sequence_id}: channel_count={count}, "
            f"samples_per_channel={n}, len(samples)={data.size}"
        )
    return data.reshape(count, n)


def contact_event_msg(rec, frame_id: str):
    """ContactEvent message of a core `ae_tactile.pipeline.ContactRecord` (~7 us; the
    driver publishes `ContactEventWire` bytes instead). The covariance is handed over as
    a float64 array, the packet ids as array('Q'): the setters take both at once."""
    msg = ContactEvent()
    stamp = msg.header.stamp
    stamp.sec, stamp.nanosec = divmod(int(rec.time_ns), NS_PER_S)
    msg.header.frame_id = frame_id
    msg.event_type = int(rec.event_type)
    pos = msg.position
    pos.x, pos.y, pos.z = rec.point_m
    msg.position_covariance = np.asarray(rec.covariance_m2, dtype=np.float64).reshape(9)
    msg.polar_angle_rad, msg.azimuth_angle_rad = rec.polar_rad, rec.azimuth_rad
    msg.tau_x_s, msg.tau_y_s = rec.tau_x_s, rec.tau_y_s
    msg.amplitude_v = rec.amplitude_v
    msg.confidence = rec.confidence
    msg.packet_ids = array.array("Q", rec.packet_ids)
    msg.emission_rate_hz, msg.spatial_period_m = rec.emission_rate_hz, rec.spatial_period_m
    d = msg.slip_direction
    d.x, d.y, d.z = rec.slip_direction
    msg.contact_id = int(rec.contact_id)
    return msg


class ContactEventWire:
    """ContactEvent records -> the serialized message (CDR, little endian), ready for
    ``Publisher.publish(bytes)``: what rclpy would send for `contact_event_msg`, without
    building a Python message and converting it field by field (~1.3 us instead of ~15 us).

    Layout (XCDR1: encapsulation 00 01 00 00, then each field aligned to its size,
    counted from the byte after the encapsulation; a string is a uint32 length that
    counts its NUL, then the bytes and the NUL):

        int32 sec, uint32 nanosec, string frame_id, uint8 event_type, <pad to 8>,
        float64 x3 position, x9 covariance, polar, azimuth, tau_x, tau_y,
        float32 amplitude_v, confidence, uint32 n, <pad to 8>, uint64 x n packet_ids,
        float64 emission_rate_hz, spatial_period_m, x3 slip_direction, uint32 contact_id.

    A test checks it byte for byte against ``rclpy.serialization.serialize_message``.
    """

    ENCAPSULATION = b"\x00\x01\x00\x00"

    def __init__(self, frame_id: str):
        fid = frame_id.encode("utf-8") + b"\0"
        end = 12 + len(fid) + 1  # after sec, nanosec, the string and event_type
        self._head = f"<4siII{len(fid)}sB{-end % 8}x"
        self._frame_id = fid
        self._structs: dict[int, struct.Struct] = {}

    def encode(self, rec) -> bytes:
        ids = rec.packet_ids
        n = len(ids)
        st = self._structs.get(n)
        if st is None:
            st = self._structs[n] = struct.Struct(self._head + f"16dffI4x{n}Q5dI")
        sec, nanosec = divmod(int(rec.time_ns), NS_PER_S)
        x, y, z = rec.point_m
        dx, dy, dz = rec.slip_direction
        return st.pack(
            self.ENCAPSULATION,
            sec,
            nanosec,
            len(self._frame_id),
            self._frame_id,
            int(rec.event_type),
            x,
            y,
            z,
            *np.asarray(rec.covariance_m2, dtype=np.float64).reshape(9).tolist(),
            rec.polar_rad,
            rec.azimuth_rad,
            rec.tau_x_s,
            rec.tau_y_s,
            rec.amplitude_v,
            rec.confidence,
            n,
            *ids,
            rec.emission_rate_hz,
            rec.spatial_period_m,
            dx,
            dy,
            dz,
            rec.contact_id,
        )


def emission_msg(rec, frame_id: str):
    """Emission message of a core `ae_tactile.records.EmissionRecord` (the driver
    publishes `EmissionWire` bytes instead)."""
    msg = Emission()
    stamp = msg.header.stamp
    stamp.sec, stamp.nanosec = divmod(int(rec.time_ns), NS_PER_S)
    msg.header.frame_id = frame_id
    msg.device_time_ns = int(rec.device_time_ns)
    msg.packet_ids = array.array("Q", rec.packet_ids)
    pos = msg.position
    pos.x, pos.y, pos.z = rec.point_m
    msg.position_covariance = np.asarray(rec.covariance_m2, dtype=np.float64).reshape(9)
    msg.polar_angle_rad, msg.azimuth_angle_rad = rec.polar_rad, rec.azimuth_rad
    msg.tau_x_s, msg.tau_y_s = rec.tau_x_s, rec.tau_y_s
    msg.polarity = int(rec.polarity)
    msg.amplitude_v = rec.amplitude_v
    msg.confidence = rec.confidence
    msg.reading = int(rec.reading)
    msg.contact_id = int(rec.contact_id)
    return msg


class EmissionWire:
    """EmissionRecords -> the serialized Emission message (CDR, little endian), as
    `ContactEventWire` does for ContactEvent. Layout (XCDR1, aligned as there):

        int32 sec, uint32 nanosec, string frame_id, <pad to 8>, int64 device_time_ns,
        uint32 n, <pad to 8>, uint64 x n packet_ids, float64 x3 position, x9 covariance,
        polar, azimuth, tau_x, tau_y, int8 polarity, <pad to 4>, float32 amplitude_v,
        confidence, uint8 reading, <pad to 4>, uint32 contact_id.

    A test checks it byte for byte against ``rclpy.serialization.serialize_message``.
    """

    ENCAPSULATION = b"\x00\x01\x00\x00"

    def __init__(self, frame_id: str):
        fid = frame_id.encode("utf-8") + b"\0"
        end = 12 + len(fid)  # after sec, nanosec and the string
        self._head = f"<4siII{len(fid)}s{-end % 8}x"
        self._frame_id = fid
        self._structs: dict[int, struct.Struct] = {}

    def encode(self, rec) -> bytes:
        ids = rec.packet_ids
        n = len(ids)
        st = self._structs.get(n)
        if st is None:
            st = self._structs[n] = struct.Struct(self._head + f"qI4x{n}Q16db3xffB3xI")
        sec, nanosec = divmod(int(rec.time_ns), NS_PER_S)
        x, y, z = rec.point_m
        return st.pack(
            self.ENCAPSULATION,
            sec,
            nanosec,
            len(self._frame_id),
            self._frame_id,
            int(rec.device_time_ns),
            n,
            *ids,
            x,
            y,
            z,
            *np.asarray(rec.covariance_m2, dtype=np.float64).reshape(9).tolist(),
            rec.polar_rad,
            rec.azimuth_rad,
            rec.tau_x_s,
            rec.tau_y_s,
            int(rec.polarity),
            rec.amplitude_v,
            rec.confidence,
            int(rec.reading),
            int(rec.contact_id),
        )


def contact_record_of_msg(msg):
    """Core ContactRecord of a received ContactEvent (the slip_detector node's input)."""
    return ContactRecord(
        event_type=int(msg.event_type),
        time_ns=time_msg_to_ns(msg.header.stamp),
        point_m=(float(msg.position.x), float(msg.position.y), float(msg.position.z)),
        covariance_m2=np.asarray(msg.position_covariance, dtype=float).reshape(3, 3),
        packet_ids=tuple(int(i) for i in msg.packet_ids),
        polar_rad=msg.polar_angle_rad,
        azimuth_rad=msg.azimuth_angle_rad,
        tau_x_s=msg.tau_x_s,
        tau_y_s=msg.tau_y_s,
        amplitude_v=float(msg.amplitude_v),
        confidence=float(msg.confidence),
        contact_id=int(msg.contact_id),
    )


def contact_record_of_emission(msg) -> ContactRecord:
    """The localizer's record of a received Emission (the slip_detector node's input):
    TOUCH for a compression, DETOUCH for a rarefaction (ValueError: a polarity that is
    neither +1 nor -1)."""
    if msg.polarity not in (1, -1):
        raise ValueError(f"emission polarity {msg.polarity}: neither +1 nor -1")
    return ContactRecord(
        event_type=int(EventType.TOUCH if msg.polarity > 0 else EventType.DETOUCH),
        time_ns=time_msg_to_ns(msg.header.stamp),
        point_m=(float(msg.position.x), float(msg.position.y), float(msg.position.z)),
        covariance_m2=np.asarray(msg.position_covariance, dtype=float).reshape(3, 3),
        packet_ids=tuple(int(i) for i in msg.packet_ids),
        polar_rad=msg.polar_angle_rad,
        azimuth_rad=msg.azimuth_angle_rad,
        tau_x_s=msg.tau_x_s,
        tau_y_s=msg.tau_y_s,
        amplitude_v=float(msg.amplitude_v),
        confidence=float(msg.confidence),
        device_time_ns=int(msg.device_time_ns),
    )


def emission_record_of_msg(msg) -> EmissionRecord:
    """Core EmissionRecord of a received Emission message (the slip_detector node's
    input, the bag tools' export)."""
    return EmissionRecord(
        time_ns=time_msg_to_ns(msg.header.stamp),
        point_m=(float(msg.position.x), float(msg.position.y), float(msg.position.z)),
        covariance_m2=np.asarray(msg.position_covariance, dtype=float).reshape(3, 3),
        packet_ids=tuple(int(i) for i in msg.packet_ids),
        polarity=int(msg.polarity),
        reading=int(msg.reading),
        contact_id=int(msg.contact_id),
        polar_rad=msg.polar_angle_rad,
        azimuth_rad=msg.azimuth_angle_rad,
        tau_x_s=msg.tau_x_s,
        tau_y_s=msg.tau_y_s,
        amplitude_v=float(msg.amplitude_v),
        confidence=float(msg.confidence),
        device_time_ns=int(msg.device_time_ns),
    )


class ContactStateWire:
    """FingerState and ContactSnapshots -> the serialized ContactState message (CDR,
    little endian), as `ContactEventWire` does for ContactEvent: what rclpy would send for
    `contact_state_msg`. Layout (XCDR1, each field aligned to its size counted from the
    byte after the encapsulation):

        int32 sec, uint32 nanosec, string frame_id, uint8 state, <pad to 4>, int32 sec,
        uint32 nanosec (state_since), <pad to 8>, float64 x3 contact_point,
        slip_emission_rate_hz, uint32 precursor_count, contact_id, uint32 n, then per
        contact: uint32 id, <pad to 8>, float64 x3 position, uint8 state, <pad to 4>,
        int32 sec, uint32 nanosec, <pad to 8>, float64 rate, uint32 precursor_count.

    A test checks it against ``rclpy.serialization.serialize_message``.
    """

    def __init__(self, frame_id: str):
        self._frame_id = frame_id.encode("utf-8") + b"\0"
        self._structs: dict[int, struct.Struct] = {}

    def _struct(self, n: int) -> struct.Struct:
        st = self._structs.get(n)
        if st is None:
            fields = ["i", "I", "I", f"{len(self._frame_id)}s", "B", "i", "I", "3d", "d",
                      "I", "I", "I"] + ["I", "3d", "B", "i", "I", "d", "I"] * n
            fmt, off = "<4s", 0
            for f in fields:
                size = struct.calcsize("<" + f)
                align = 1 if f.endswith("s") else min(struct.calcsize("<" + f[-1]), 8)
                pad = -off % align
                fmt += f"{pad}x{f}" if pad else f
                off += pad + size
            st = self._structs[n] = struct.Struct(fmt)
        return st

    def encode(self, st, now_ns: int, contacts=()) -> bytes:
        """The serialized message of ``st`` (a FingerState) and ``contacts``
        (ContactSnapshots), stamped as `contact_state_msg` stamps it."""
        stamp = int(st.time_ns) if st.time_ns > 0 else int(now_ns)
        x, y, z = (float(v) for v in st.contact_point_m)
        values = [ContactEventWire.ENCAPSULATION, *divmod(stamp, NS_PER_S),
                  len(self._frame_id), self._frame_id, int(st.state),
                  *divmod(max(int(st.since_ns), 0), NS_PER_S), x, y, z,
                  float(st.slip_emission_rate_hz), int(st.precursor_count),
                  max(int(st.contact_id), 0), len(contacts)]
        for c in contacts:
            values += [int(c.contact_id), *(float(v) for v in c.point_m), int(c.state),
                       *divmod(max(int(c.since_ns), 0), NS_PER_S),
                       float(c.slip_emission_rate_hz), int(c.precursor_count)]
        return self._struct(len(contacts)).pack(*values)


def contact_msg(c) -> Contact:
    """Contact message of a core `ae_tactile.records.ContactSnapshot`."""
    msg = Contact()
    msg.id = int(c.contact_id)
    msg.position.x, msg.position.y, msg.position.z = (float(v) for v in c.point_m)
    msg.state = int(c.state)
    msg.since = ns_to_time_msg(max(int(c.since_ns), 0))
    msg.slip_emission_rate_hz = float(c.slip_emission_rate_hz)
    msg.precursor_count = int(c.precursor_count)
    return msg


def contact_state_msg(st, frame_id: str, now_ns: int, contacts=()):
    """ContactState message of the slip detector's FingerState and the current contacts
    (`ae_tactile.records.ContactSnapshot`, e.g. `SlipStage.contacts`)."""
    msg = ContactState()
    msg.header.stamp = ns_to_time_msg(st.time_ns if st.time_ns > 0 else now_ns)
    msg.header.frame_id = frame_id
    msg.state = int(st.state)
    msg.state_since = ns_to_time_msg(max(int(st.since_ns), 0))
    p = np.asarray(st.contact_point_m, dtype=float)
    msg.contact_point.x, msg.contact_point.y, msg.contact_point.z = (float(v) for v in p)
    msg.slip_emission_rate_hz = float(st.slip_emission_rate_hz)
    msg.precursor_count = int(st.precursor_count)
    msg.contact_id = max(int(st.contact_id), 0)
    msg.contacts = [contact_msg(c) for c in contacts]
    return msg


#: Most packets in one PacketArray (~0.8 MB at 4 x 400 float32): a DDS message stays small
#: enough to be delivered best effort; a larger batch goes out as several arrays.
MAX_PACKETS_PER_ARRAY = 128


def packet_array_msgs(batch, frame_id: str) -> list:
    """PacketArrays of a link PacketBatch (several when it holds more than
    MAX_PACKETS_PER_ARRAY packets)."""
    out = []
    recs = batch.packets
    for i in range(0, max(len(recs), 1), MAX_PACKETS_PER_ARRAY):
        msg = PacketArray()
        msg.header.stamp = ns_to_time_msg(batch.receive_ns)
        msg.header.frame_id = frame_id
        msg.packets = [
            make_packet(
                r.samples_v,
                stamp_ns=r.stamp_ns,
                sample_rate_hz=r.sample_rate_hz,
                onset_index=r.onset_index,
                sequence_id=r.sequence_id,
                noise_rms_v=r.noise_rms_v,
                saturated=r.saturated,
            )
            for r in recs[i : i + MAX_PACKETS_PER_ARRAY]
        ]
        msg.packets_dropped = batch.packets_dropped
        msg.frames_bad_crc = batch.frames_bad_crc
        out.append(msg)
    return out


def sensor_info_msg(status, p: dict, geometry, frame_id: str, stamp) -> SensorInfo:
    """SensorInfo of a driver: the fingertip's geometry and front end from its parameters
    ``p``, the device's identity and settings from its STATUS (None: not known yet).

    Parameters
    ----------
    status : ae_tactile.protocol.Status or None
    p : dict
        The driver's parameter values (medium, channel_gains, highpass_hz, sample_rate_hz).
    geometry : FingertipGeometry
    frame_id : str
    stamp : builtin_interfaces.msg.Time

    Returns
    -------
    SensorInfo
    """
    msg = SensorInfo()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.medium = p["medium"]
    msg.radius_m = geometry.radius_m
    msg.element_offset_m = geometry.element_offset_m
    msg.sound_speed_m_s = geometry.sound_speed_m_s
    msg.channel_gains = [float(g) for g in p["channel_gains"]]
    msg.highpass_hz = p["highpass_hz"]
    msg.adc_bits = 12
    msg.protocol_version = PROTOCOL_VERSION
    if status is not None:
        msg.serial_number = status.serial_number
        msg.firmware_version = ".".join(str(v) for v in status.firmware_version)
        msg.sample_rate_hz = float(status.sample_rate_hz)
        msg.volts_per_count = float(status.v_per_count)
        msg.trigger_threshold_v = float(status.threshold_counts * status.v_per_count)
    else:
        msg.sample_rate_hz = float(p["sample_rate_hz"])
    return msg
