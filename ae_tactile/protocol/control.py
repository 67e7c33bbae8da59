# SPDX-License-Identifier: Apache-2.0
"""The control bodies: STATUS (heartbeat), COMMAND (host -> device) and its ACK."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ..geometry import N_CHANNELS
from .fields import _Body, _enum, _int, _v_per_count
from .layout import (
    _ACK,
    _ALL_COMMAND_ARGS,
    _COMMAND,
    _OPCODE_ARG_STRUCT,
    _OPCODE_ARGS,
    _STATUS,
    _U8,
    _U16,
    _U32,
    _U64,
    MAX_SAMPLES,
    MAX_SERIAL_LEN,
    MAX_THRESHOLD_COUNTS,
    STATUS_PREFIX_LEN,
    AckResult,
    AcqMode,
    DeviceState,
    ErrorBits,
    FrameType,
    Opcode,
)


# ---------------------------------------------------------------- status
@dataclass(frozen=True)
class Status(_Body):
    """Status / heartbeat (frame type STATUS), sent >= 1 Hz in every state.

    Parameters
    ----------
    uptime_us : int
        Full 64-bit device clock [us] since boot (its low 32 bits equal the header
        timestamp_us of this frame).
    state : DeviceState
        What the device is doing.
    sample_rate_hz : int
        Current ADC sample rate [Hz].
    v_per_count : float
        Current volts per ADC count [V].
    threshold_counts : int
        Trigger threshold |x| >= threshold [ADC counts], 1..32767.
    packet_samples : int
        PACKET length N in effect [samples].
    pre_trigger : int
        Pre-trigger length in effect [samples], < packet_samples.
    error_bits : int
        ErrorBits (bits 16..31 firmware-specific).
    device_dropped : int
        Frames the device discarded since boot because its transmit queue was full
        (u32). They also show as sequence gaps on the host.
    firmware_version : tuple of int
        (major, minor, patch), each 0..255.
    serial_number : str
        1..32 printable ASCII characters (0x20..0x7E): tells fingertips apart.
    """

    uptime_us: int
    state: DeviceState
    sample_rate_hz: int
    v_per_count: float
    threshold_counts: int
    packet_samples: int
    pre_trigger: int
    error_bits: int
    device_dropped: int
    firmware_version: tuple[int, int, int]
    serial_number: str

    frame_type: ClassVar[FrameType] = FrameType.STATUS

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "uptime_us", _int("uptime_us", self.uptime_us, 0, _U64))
        set_(self, "state", _enum("state", DeviceState, self.state))
        set_(self, "sample_rate_hz", _int("sample_rate_hz", self.sample_rate_hz, 1, _U32))
        set_(self, "v_per_count", _v_per_count(self.v_per_count))
        set_(
            self,
            "threshold_counts",
            _int("threshold_counts", self.threshold_counts, 1, MAX_THRESHOLD_COUNTS),
        )
        n = _int("packet_samples", self.packet_samples, 1, MAX_SAMPLES)
        set_(self, "packet_samples", n)
        set_(self, "pre_trigger", _int("pre_trigger", self.pre_trigger, 0, n - 1))
        set_(self, "error_bits", ErrorBits(_int("error_bits", self.error_bits, 0, _U32)))
        set_(self, "device_dropped", _int("device_dropped", self.device_dropped, 0, _U32))
        fw = self.firmware_version
        if not isinstance(fw, (tuple, list)) or len(fw) != 3:
            raise TypeError(f"firmware_version must be a (major, minor, patch) tuple, got {fw!r}")
        set_(
            self,
            "firmware_version",
            tuple(_int(f"firmware_version[{i}]", v, 0, _U8) for i, v in enumerate(fw)),
        )
        sn = self.serial_number
        if not isinstance(sn, str):
            raise TypeError(f"serial_number must be a str, got {type(sn).__name__}")
        if not 1 <= len(sn) <= MAX_SERIAL_LEN or not all(" " <= ch <= "~" for ch in sn):
            raise ValueError(
                f"serial_number must be 1..{MAX_SERIAL_LEN} printable ASCII characters"
                f" (0x20..0x7E), got {sn!r}"
            )

    def _pack(self) -> bytes:
        sn = self.serial_number.encode("ascii")
        return (
            _STATUS.pack(
                self.uptime_us,
                self.sample_rate_hz,
                self.v_per_count,
                self.threshold_counts,
                self.packet_samples,
                self.pre_trigger,
                self.state,
                N_CHANNELS,
                self.error_bits,
                self.device_dropped,
                *self.firmware_version,
                len(sn),
            )
            + sn
        )

    @classmethod
    def _unpack(cls, buf, off: int, length: int) -> "Status":
        if length < STATUS_PREFIX_LEN:
            raise ValueError(
                f"STATUS payload of {length} bytes is shorter than its"
                f" {STATUS_PREFIX_LEN}-byte prefix"
            )
        (
            up,
            sr,
            vpc,
            thr,
            n,
            pre,
            state,
            nch,
            err,
            dropped,
            fw_major,
            fw_minor,
            fw_patch,
            sn_len,
        ) = _STATUS.unpack_from(buf, off)
        if nch != N_CHANNELS:
            raise ValueError(f"STATUS n_channels must be {N_CHANNELS}, got {nch}")
        if length != STATUS_PREFIX_LEN + sn_len:
            raise ValueError(
                f"STATUS serial_len={sn_len} but the payload holds"
                f" {length - STATUS_PREFIX_LEN} bytes after its prefix"
            )
        start = off + STATUS_PREFIX_LEN
        raw = bytes(buf[start : start + sn_len])
        try:
            sn = raw.decode("ascii")
        except UnicodeDecodeError:
            raise ValueError(f"STATUS serial_number is not ASCII: {raw!r}") from None
        return cls(
            up, state, sr, vpc, thr, n, pre, err, dropped, (fw_major, fw_minor, fw_patch), sn
        )


# ---------------------------------------------------------------- commands
@dataclass(frozen=True)
class Command(_Body):
    """Host -> device command (frame type COMMAND); the device answers one ACK.

    Prefer the constructors ``Command.start(...)``, ``Command.stop(...)``, ...

    Parameters
    ----------
    opcode : Opcode
        What to do; exactly the arguments of that opcode are given, the others None:
        START: mode; SET_THRESHOLD: threshold_counts (1..32767);
        SET_SAMPLE_RATE: sample_rate_hz (>= 1);
        SET_PACKET_LENGTH: n_samples (1..MAX_SAMPLES), pre_trigger (< n_samples).
    command_id : int
        u16 chosen by the host, echoed in the ACK (the host increments it).
    mode : AcqMode or None
        START's acquisition mode.
    threshold_counts : int or None
        SET_THRESHOLD's threshold [ADC counts].
    sample_rate_hz : int or None
        SET_SAMPLE_RATE's rate [Hz].
    n_samples, pre_trigger : int or None
        SET_PACKET_LENGTH's packet and pre-trigger lengths [samples].
    """

    opcode: Opcode
    command_id: int = 0
    mode: AcqMode | None = None
    threshold_counts: int | None = None
    sample_rate_hz: int | None = None
    n_samples: int | None = None
    pre_trigger: int | None = None

    frame_type: ClassVar[FrameType] = FrameType.COMMAND

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        op = _enum("opcode", Opcode, self.opcode)
        set_(self, "opcode", op)
        set_(self, "command_id", _int("command_id", self.command_id, 0, _U16))
        needed = _OPCODE_ARGS[op]
        for name in _ALL_COMMAND_ARGS:
            given = getattr(self, name) is not None
            if given and name not in needed:
                raise ValueError(
                    f"{op.name} takes no argument {name!r}"
                    f" (its arguments: {', '.join(needed) or 'none'})"
                )
            if not given and name in needed:
                raise ValueError(f"{op.name} requires argument {name!r}")
        if op is Opcode.START:
            set_(self, "mode", _enum("mode", AcqMode, self.mode))
        elif op is Opcode.SET_THRESHOLD:
            set_(
                self,
                "threshold_counts",
                _int("threshold_counts", self.threshold_counts, 1, MAX_THRESHOLD_COUNTS),
            )
        elif op is Opcode.SET_SAMPLE_RATE:
            set_(self, "sample_rate_hz", _int("sample_rate_hz", self.sample_rate_hz, 1, _U32))
        elif op is Opcode.SET_PACKET_LENGTH:
            n = _int("n_samples", self.n_samples, 1, MAX_SAMPLES)
            set_(self, "n_samples", n)
            set_(self, "pre_trigger", _int("pre_trigger", self.pre_trigger, 0, n - 1))

    @classmethod
    def start(cls, mode: AcqMode, command_id: int = 0) -> "Command":
        return cls(Opcode.START, command_id, mode=mode)

    @classmethod
    def stop(cls, command_id: int = 0) -> "Command":
        return cls(Opcode.STOP, command_id)

    @classmethod
    def get_status(cls, command_id: int = 0) -> "Command":
        return cls(Opcode.GET_STATUS, command_id)

    @classmethod
    def set_threshold(cls, threshold_counts: int, command_id: int = 0) -> "Command":
        return cls(Opcode.SET_THRESHOLD, command_id, threshold_counts=threshold_counts)

    @classmethod
    def set_sample_rate(cls, sample_rate_hz: int, command_id: int = 0) -> "Command":
        return cls(Opcode.SET_SAMPLE_RATE, command_id, sample_rate_hz=sample_rate_hz)

    @classmethod
    def set_packet_length(cls, n_samples: int, pre_trigger: int, command_id: int = 0) -> "Command":
        return cls(
            Opcode.SET_PACKET_LENGTH, command_id, n_samples=n_samples, pre_trigger=pre_trigger
        )

    @property
    def args(self) -> tuple[int, ...]:
        """The opcode's arguments in wire order."""
        return tuple(int(getattr(self, name)) for name in _OPCODE_ARGS[self.opcode])

    def _pack(self) -> bytes:
        return _COMMAND.pack(self.command_id, self.opcode) + _OPCODE_ARG_STRUCT[self.opcode].pack(
            *self.args
        )

    @classmethod
    def _unpack(cls, buf, off: int, length: int) -> "Command":
        if length < _COMMAND.size:
            raise ValueError(f"COMMAND payload of {length} bytes is shorter than 3")
        cid, op = _COMMAND.unpack_from(buf, off)
        try:
            opcode = Opcode(op)
        except ValueError:
            raise ValueError(f"COMMAND {cid}: unknown opcode {op}") from None
        st = _OPCODE_ARG_STRUCT[opcode]
        if length != _COMMAND.size + st.size:
            raise ValueError(
                f"COMMAND {cid} {opcode.name}: payload must be {_COMMAND.size + st.size}"
                f" bytes, got {length}"
            )
        values = st.unpack_from(buf, off + _COMMAND.size)
        return cls(opcode, cid, **dict(zip(_OPCODE_ARGS[opcode], values)))


@dataclass(frozen=True)
class Ack(_Body):
    """Device's answer to one COMMAND (frame type ACK).

    Parameters
    ----------
    command_id : int
        Echo of Command.command_id.
    opcode : Opcode or int
        Echo of the opcode byte (the raw int for UNKNOWN_OPCODE).
    result : AckResult
        Whether the command was applied.
    value : int
        u32, the setting in effect after the command: START -> mode, SET_THRESHOLD ->
        threshold_counts, SET_SAMPLE_RATE -> sample_rate_hz actually used (the device
        may round to a rate it supports), SET_PACKET_LENGTH -> n_samples | pre_trigger
        << 16; STOP, GET_STATUS -> 0.
    """

    command_id: int
    opcode: int
    result: AckResult = AckResult.OK
    value: int = 0

    frame_type: ClassVar[FrameType] = FrameType.ACK

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "command_id", _int("command_id", self.command_id, 0, _U16))
        op = _int("opcode", self.opcode, 0, _U8)
        set_(self, "opcode", Opcode(op) if op in Opcode._value2member_map_ else op)
        set_(self, "result", _enum("result", AckResult, self.result))
        set_(self, "value", _int("value", self.value, 0, _U32))

    @property
    def ok(self) -> bool:
        return self.result is AckResult.OK

    def _pack(self) -> bytes:
        return _ACK.pack(self.command_id, self.opcode, self.result, self.value)

    @classmethod
    def _unpack(cls, buf, off: int, length: int) -> "Ack":
        if length != _ACK.size:
            raise ValueError(f"ACK payload must be {_ACK.size} bytes, got {length}")
        return cls(*_ACK.unpack_from(buf, off))
