"""numpy <-> ae_tactile message conversions (the only place that knows the field layout).

Time stamps are integer nanoseconds (int64) on the core side, builtin_interfaces/Time
on the message side. Packet samples are channel-major float32 volts; a (4, N) view of
a received Packet costs no copy (``np.frombuffer`` on the message's array.array).
"""
from __future__ import annotations

import array

import numpy as np
from builtin_interfaces.msg import Time

from ae_tactile.geometry import N_CHANNELS
from ae_tactile.msg import Packet

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


def make_packet(samples_v, *, stamp_ns: int, sample_rate_hz: float, onset_index: int,
                sequence_id: int, noise_rms_v: float = 0.0, saturated: bool = False) -> Packet:
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
    data = np.frombuffer(msg.samples, dtype=np.float32) if len(msg.samples) else np.zeros(0, np.float32)
    if count != N_CHANNELS or data.size != count * n:
        raise ValueError(
            f"inconsistent Packet {msg.sequence_id}: channel_count={count}, "
            f"samples_per_channel={n}, len(samples)={data.size}")
    return data.reshape(count, n)
