# SPDX-License-Identifier: Apache-2.0
"""The link's settings: one frozen dataclass, checked when built."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MODES = ("triggered", "stream")


@dataclass(frozen=True)
class LinkConfig:
    """Settings of the link; None keeps the device's own setting.

    Parameters
    ----------
    port : str
        pyserial URL or device path (a device path, a pty, ``socket://``, ``loop://``).
    baudrate : int
        Line rate [bit/s] (ignored by USB CDC, ptys and sockets).
    mode : str
        "triggered" (the device sends PACKET frames) or "stream" (STREAM blocks, cut into
        packets on the host).
    sample_rate_hz : int or None
        Device sample rate [Hz].
    threshold_counts : int or None
        Device trigger threshold [ADC counts].
    packet_samples : int or None
        Device packet length [samples].
    pre_trigger_samples : int or None
        Device pre-trigger length [samples]; default packet_samples // 4.
    read_timeout_s : float
        Longest idle block of one read [s].
    read_chunk_bytes : int
        Most bytes taken in one read cycle [B].
    link_timeout_s : float
        Time without a valid frame that means the link is dead [s] (the device sends a
        heartbeat >= 1 Hz).
    acquisition_timeout_s : float
        Time [s] without sign of acquisition, while the link expects it (after START),
        that restarts it: no PACKET or STREAM frame and no STATUS reporting the running
        state (a heartbeat saying IDLE is no sign: the device stopped acquiring, by a
        fault or another host's STOP). The link then sends STOP / settings / START; if
        another ``acquisition_timeout_s`` passes without a sign, it reconnects. More than
        the 1 s heartbeat period (a triggered device with nothing to capture reports its
        state only there); 0: never.
    stall_report_s : float
        A partial frame waiting this long without any byte is reported once
        (``stalled_frames``) and kept [s]; the default exceeds the 0.22 s a
        MAX_FRAME_LEN frame takes at 3 Mbit/s.
    reconnect_initial_s, reconnect_max_s : float
        First and longest wait between reconnection attempts [s] (exponential back-off).
    queue_max_batches : int
        Bound of the hand-over queue [batches]; overflow is counted as drops.
    command_timeout_s : float
        ACK wait per command [s].
    command_retries : int
        Tries per command.
    sync_good_pings : int
        Round trips faster than ``sync_rtt_s`` wanted before START.
    sync_max_pings : int
        Most round trips sent for them.
    sync_rtt_s : float
        Longest round trip [s] whose midpoint goes to the clock mapping.
    sync_period_s : float
        One more round trip every sync_period_s while acquiring [s] (0: none), so that
        the clock mapping's window (30 s) always holds round-trip samples.
    clock_step_s : float
        Latency above the clock mapping [s] that, ``clock_step_frames`` frames in a row,
        means the device clock stepped back (or the host clock forward) without a
        restart: the mapping is rebuilt from those frames. Above any host stall or
        device queue the link should ride out (a smaller step is clamped, not rebuilt).
    clock_step_frames : int
        Frames in a row needed for such a step.
    adc_bits : int
        ADC resolution [bit] (full scale = v_per_count * 2^(adc_bits-1), for saturation).
    detector : dict
        Keyword arguments of the stream-mode `ae_tactile.dsp.DetectorConfig`.

    Raises
    ------
    ValueError
        A setting out of its range (the message names it).
    """

    port: str
    baudrate: int = 3_000_000
    mode: str = "triggered"
    sample_rate_hz: int | None = None
    threshold_counts: int | None = None
    packet_samples: int | None = None
    pre_trigger_samples: int | None = None
    read_timeout_s: float = 0.002
    read_chunk_bytes: int = 1 << 16
    link_timeout_s: float = 3.0
    acquisition_timeout_s: float = 2.5
    stall_report_s: float = 0.25
    reconnect_initial_s: float = 0.2
    reconnect_max_s: float = 5.0
    queue_max_batches: int = 256
    command_timeout_s: float = 0.5
    command_retries: int = 3
    sync_good_pings: int = 3
    sync_max_pings: int = 100
    sync_rtt_s: float = 0.0015
    sync_period_s: float = 5.0
    clock_step_s: float = 0.25
    clock_step_frames: int = 4
    adc_bits: int = 12
    detector: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.port, str) or not self.port:
            raise ValueError("port must be a non-empty device path or pyserial URL")
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if not 50 <= int(self.baudrate) <= 100_000_000:
            raise ValueError(f"baudrate must be in [50, 1e8], got {self.baudrate}")
        for name in (
            "read_timeout_s",
            "link_timeout_s",
            "stall_report_s",
            "reconnect_initial_s",
            "reconnect_max_s",
            "command_timeout_s",
            "clock_step_s",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number of seconds, got {v!r}")
        if not (
            isinstance(self.sync_period_s, (int, float))
            and np.isfinite(self.sync_period_s)
            and self.sync_period_s >= 0
        ):
            raise ValueError(f"sync_period_s must be >= 0 s, got {self.sync_period_s!r}")
        a = self.acquisition_timeout_s
        if not (isinstance(a, (int, float)) and np.isfinite(a) and (a == 0 or a > 1.0)):
            raise ValueError(
                f"acquisition_timeout_s must be 0 (never) or > 1 s (the heartbeat period),"
                f" got {a!r}"
            )
        if self.reconnect_max_s < self.reconnect_initial_s:
            raise ValueError("reconnect_max_s must be >= reconnect_initial_s")
        if int(self.queue_max_batches) < 1 or int(self.read_chunk_bytes) < 1:
            raise ValueError("queue_max_batches and read_chunk_bytes must be >= 1")
        if int(self.clock_step_frames) < 1:
            raise ValueError(f"clock_step_frames must be >= 1, got {self.clock_step_frames}")
        if (
            self.packet_samples is not None
            and self.pre_trigger_samples is not None
            and not 0 <= self.pre_trigger_samples < self.packet_samples
        ):
            raise ValueError("pre_trigger_samples must be in [0, packet_samples)")
