# SPDX-License-Identifier: Apache-2.0
"""Host side of the fingertip serial link (pure Python, no rclpy).

`FingertipLink` owns the port (any pyserial URL: a device path, a pty, ``socket://``,
``loop://``), reads it in a background thread, decodes frames with the protocol's
incremental decoder, maps device time to host time (`DeviceClockMapper`), turns
PACKET frames (triggered mode) or STREAM blocks cut by the packet detector (stream
mode) into `PacketRecord`s, and hands them out in bounded per-read-cycle batches.

Liveness is valid frames, not bytes. States: ``disconnected`` (port closed),
``connecting`` (port open, no valid frame yet), ``connected`` (a valid frame within
``link_timeout_s``). A real read error (EIO, a hang-up), or ``link_timeout_s`` without a
valid frame (a dead device, a reset device that stays silent, a wrong baud rate that
only yields garbage) closes the port; it is reopened with exponential back-off, the
device re-configured, acquisition restarted and the clock mapping re-synced. A
spurious wake-up (readable but nothing to read, EAGAIN) is counted, never a disconnect.
A partial frame left waiting ``stall_report_s`` with no byte arriving is reported
(``stalled_frames``, a warning) and kept: the device may still finish it, and a new
frame cuts it short at once (the decoder's rule 3), so no valid frame is lost to a pause.

Nothing is silently lost: every byte (decoded or discarded), every rejected frame by
reason, duplicates, sequence gaps, queue overflows, stream gaps and packets refused by
the link (non-finite volts) are counted (`stats()`). No input stops the reader thread:
an unexpected error while handling a frame is counted (``internal_errors``) and logged.

Memory is bounded: the decoder holds < MAX_FRAME_LEN + ``read_chunk_bytes`` bytes, the
hand-over queue ``queue_max_batches`` batches of one read each (a read of
``read_chunk_bytes`` yields at most read_chunk_bytes / 60 packets; 2 float32 bytes per
wire byte of samples), the ACK table 64 entries; overload is dropped and counted.

Reads are neither byte-by-byte nor timeout-bound: each cycle blocks for the first
byte (up to ``read_timeout_s``, only when idle) and then takes everything waiting.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import queue
import select
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import serial

try:
    from termios import error as _TermiosError  # tcdrain / tcflush on a vanished pty: EIO
except ImportError:  # not a POSIX system
    _TermiosError = OSError

from ae_tactile.jit import NUMBA_AVAILABLE, njit
from ae_tactile.protocol import (
    NO_ONSET,
    Ack,
    AckResult,
    AcqMode,
    Command,
    FrameEncoder,
    Packet,
    Status,
    StreamBlock,
    StreamDecoder,
)
from ae_tactile.timesync import DeviceClockMapper

#: What a port that vanished or was closed under us raises (pyserial, the OS, termios'
#: own error class, which is no OSError; TypeError/AttributeError: pyserial internals after
#: its fd is gone): a lost link, never a crash.
PORT_ERRORS = (serial.SerialException, OSError, TypeError, AttributeError, _TermiosError)

LOG = logging.getLogger("ae_tactile.link")

MODES = ("triggered", "stream")
#: Bytes a Linux tty (serial port, USB CDC, pty) hands over per read at most: its line
#: discipline's buffer (N_TTY_BUF_SIZE); a read that (nearly) fills it leaves more behind.
TTY_LINE_BUFFER_BYTES = 4096
_FLOAT32_MAX = float(np.finfo(np.float32).max)


@dataclass(frozen=True)
class LinkConfig:
    """Settings of the link; None keeps the device's own setting.

    port: pyserial URL or device path. baudrate: bits/s (ignored by USB CDC, ptys, sockets).
    mode: "triggered" (device sends PACKET frames) or "stream" (STREAM blocks, cut on the host).
    sample_rate_hz, threshold_counts, packet_samples, pre_trigger_samples: device settings.
    read_timeout_s: longest idle block of one read (s). link_timeout_s: time without a valid
    frame that means the link is dead (the device sends a heartbeat >= 1 Hz).
    stall_report_s: a partial frame waiting this long without any byte is reported once
    (``stalled_frames``) and kept (the default exceeds the 0.22 s a MAX_FRAME_LEN frame
    takes at 3 Mbit/s).
    reconnect_*: back-off (s).
    queue_max_batches: bound of the hand-over queue (overflow is counted as drops).
    command_timeout_s / command_retries: ACK wait per command and retries.
    sync_good_pings / sync_max_pings / sync_rtt_s: clock sync before START (see _sync_clock).
    sync_period_s: one more round trip every sync_period_s while acquiring (0: none), so
    that the clock mapping's window (30 s) always holds round-trip samples.
    adc_bits: ADC resolution (full scale = v_per_count * 2^(adc_bits-1), for saturation).
    detector: keyword arguments of the stream-mode `ae_tactile.dsp.DetectorConfig`.
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
        if self.reconnect_max_s < self.reconnect_initial_s:
            raise ValueError("reconnect_max_s must be >= reconnect_initial_s")
        if int(self.queue_max_batches) < 1 or int(self.read_chunk_bytes) < 1:
            raise ValueError("queue_max_batches and read_chunk_bytes must be >= 1")
        if (
            self.packet_samples is not None
            and self.pre_trigger_samples is not None
            and not 0 <= self.pre_trigger_samples < self.packet_samples
        ):
            raise ValueError("pre_trigger_samples must be in [0, packet_samples)")


@dataclass
class PacketRecord:
    """One packet ready to publish. stamp_ns: host time of samples_v[:, 0] (int ns)."""

    stamp_ns: int
    samples_v: np.ndarray  # (4, N) float32 volts
    sample_rate_hz: float
    onset_index: int
    sequence_id: int
    noise_rms_v: float
    saturated: bool
    device_sample_index: int  # device sample counter of samples_v[:, 0]


@dataclass
class PacketBatch:
    """The packets of one read cycle, with the running loss counters at that time."""

    receive_ns: int
    packets: list[PacketRecord]
    packets_dropped: int
    frames_bad_crc: int


def window_noise_and_onset(volts: np.ndarray, pre_trigger: int) -> tuple[float, int]:
    """Noise RMS (V, DC removed) of the pre-trigger samples, and the onset index.

    The device triggered at sample ``pre_trigger``; the onset is the first sample at or
    after ``pre_trigger // 2`` whose largest |x - DC| over the 4 channels exceeds 4 noise
    sigma (``pre_trigger`` if none does or the pre-trigger part is too short):

        DC_c = mean(x_c[:P]),  sigma^2 = mean_c,n (x_c[n] - DC_c)^2 over n < P,
        onset = min { n >= P // 2 : max_c |x_c[n] - DC_c| > 4 sigma }.

    The numpy reference; `packet_volts_noise_onset` is the compiled form of the link.
    """
    x = np.asarray(volts, dtype=np.float64)
    n = x.shape[1]
    pre_trigger = int(min(max(pre_trigger, 0), n - 1))
    if pre_trigger < 4:
        return 0.0, pre_trigger
    dc = x[:, :pre_trigger].mean(axis=1, keepdims=True)
    pre = x[:, :pre_trigger] - dc
    noise = float(np.sqrt(np.mean(pre * pre)))
    env = np.abs(x - dc).max(axis=0)
    start = pre_trigger // 2
    above = np.flatnonzero(env[start:] > 4.0 * noise)
    onset = int(start + above[0]) if above.size and noise > 0 else pre_trigger
    return noise, onset


@njit(cache=True, nogil=True)
def _volts_noise_onset_kernel(counts, v_per_count, pre_trigger, volts):  # pragma: no cover
    """Compiled `window_noise_and_onset` of counts * v_per_count (float32), in one pass
    over the window; writes the volts into ``volts``; returns (noise, onset)."""
    nch, n = counts.shape
    for c in range(nch):
        for i in range(n):
            volts[c, i] = np.float32(counts[c, i]) * v_per_count
    p = min(max(pre_trigger, 0), n - 1)
    if p < 4:
        return 0.0, p
    dc = np.empty(nch)
    ss = 0.0
    for c in range(nch):
        s = 0.0
        for i in range(p):
            s += np.float64(volts[c, i])
        dc[c] = s / p
        for i in range(p):
            d = np.float64(volts[c, i]) - dc[c]
            ss += d * d
    noise = math.sqrt(ss / (nch * p))
    if not noise > 0.0:
        return noise, p
    thr = 4.0 * noise
    for i in range(p // 2, n):
        for c in range(nch):
            if abs(np.float64(volts[c, i]) - dc[c]) > thr:
                return noise, i
    return noise, p


def packet_volts_noise_onset(
    counts: np.ndarray, v_per_count: float, pre_trigger: int
) -> tuple[np.ndarray, float, int]:
    """One PACKET's (4, N) int16 counts -> (float32 volts, noise RMS (V), onset index).

    volts = counts * float32(v_per_count); noise and onset as `window_noise_and_onset`.
    One compiled pass where numba is available (~2 us instead of ~18 us per packet), the
    numpy reference otherwise; the two agree (tests), up to the order of a sum.
    """
    vpc = np.float32(v_per_count)
    if NUMBA_AVAILABLE and counts.ndim == 2 and counts.dtype == np.int16:
        volts = np.empty(counts.shape, dtype=np.float32)
        noise, onset = _volts_noise_onset_kernel(counts, vpc, int(pre_trigger), volts)
        return volts, float(noise), int(onset)
    volts = (counts * vpc).astype(np.float32)
    noise, onset = window_noise_and_onset(volts, pre_trigger)
    return volts, noise, onset


def warm_up() -> None:
    """Compile (or load from numba's cache) the link's kernel for the arrays it meets:
    read-only counts (decoded from the wire) and writable ones."""
    counts = np.zeros((4, 16), dtype=np.int16)
    packet_volts_noise_onset(counts, 1e-3, 8)
    counts.flags.writeable = False
    packet_volts_noise_onset(counts, 1e-3, 8)


class FingertipLink:
    """Background reader of one fingertip. Thread-safe `poll()`, `stats()`, `stop()`.

    clock_ns: host clock for time stamps (the ROS node passes its ROS clock).
    on_batch: called from the reader thread after a batch is queued (e.g. to wake an
    executor through a guard condition); keep it cheap.
    sink: when given, each batch is handed to ``sink(batch)`` in the reader thread as soon
    as it is decoded, instead of being queued for `poll()` (the lowest-latency path: the
    caller localizes and publishes right there). An exception in the sink is counted
    (``sink_errors``) and logged, never allowed to stop the reader.
    on_idle: called from the reader thread after a read cycle that completed no frame
    (nothing arrived within ``read_timeout_s``, or only part of a frame): the moment for
    work the sink put off while more bytes were waiting (`bytes_waiting`). Same rules
    as the sink.
    """

    def __init__(
        self,
        config: LinkConfig,
        clock_ns: Callable[[], int] = time.time_ns,
        on_batch: Callable[[], None] | None = None,
        logger: logging.Logger | None = None,
        sink: Callable[[PacketBatch], None] | None = None,
        on_idle: Callable[[], None] | None = None,
    ):
        warm_up()  # the per-packet kernel is ready before the first packet
        self.config = config
        self.sink = sink
        self.on_idle = on_idle
        self.clock_ns = clock_ns
        self.on_batch = on_batch
        self.log = logger or LOG
        self._queue: queue.Queue[PacketBatch] = queue.Queue(maxsize=int(config.queue_max_batches))
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._serial = None
        self._lock = threading.Lock()
        self.decoder = StreamDecoder()
        # Restarts come from the protocol (BOOT flag, sequence): the mapper's own
        # "device time stepped back by > 1 s" guess would fire on a device that lags
        # (packets carry their sample time, older than the STATUS it sent just before).
        self.mapper = DeviceClockMapper(max_backstep_s=3600.0)
        self.encoder = FrameEncoder(boot=False)
        self._detector = None
        self._next_sequence_id = 0
        self._next_command_id = 1
        self._pending_acks: dict[int, Ack] = {}
        self._stream_next_index: int | None = None
        self._stream_ref: tuple[int, int, float] | None = None  # (sample index, device ns, fs)
        self.state = "disconnected"
        self.device_status: Status | None = None
        self.counters = {
            "connects": 0,
            "disconnects": 0,
            "connect_failures": 0,
            "read_errors": 0,
            "link_timeouts": 0,
            "packets_out": 0,
            "batches_out": 0,
            "queue_overflow_packets": 0,
            "stream_gaps": 0,
            "stream_samples_lost": 0,
            "device_restarts_handled": 0,
            "commands_sent": 0,
            "commands_unacked": 0,
            "commands_failed": 0,
            "frames_ignored": 0,
            "sync_good_pings": 0,
            "clock_pings": 0,
            "clock_pings_used": 0,
            "sink_errors": 0,
            "stalled_frames": 0,
            "spurious_wakeups": 0,
            "hangups": 0,
            "internal_errors": 0,
            "packets_rejected_nonfinite": 0,
            "frames_unusable": 0,
            "bytes_cut_at_disconnect": 0,
        }
        self.last_error = ""
        self._last_frame_mono = 0.0  # last valid frame (liveness)
        self._last_byte_mono = 0.0  # last byte of any kind (stall report)
        self._stall_reported = False  # this stall of a partial frame is reported
        self._empty_hup_reads = 0
        self._reconfigure_pending = False
        self._last_ack_receive_ns = 0
        self._last_ack_device_ns = 0
        self._open_failure_logged = False
        self._detector_key = None
        self._stream_ref = None
        self._is_socket = config.port.startswith("socket://")
        self._fd: int | None = None

    # ---------------------------------------------------------------- control
    def start(self) -> None:
        if self._thread is not None:
            raise RuntimeError("FingertipLink already started")
        self._thread = threading.Thread(target=self._run, name="ae_tactile_link", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop the reader; sends STOP to the device if connected; closes the port."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        self._close("stopped")

    def poll(self, max_batches: int = 64, timeout_s: float = 0.0) -> list[PacketBatch]:
        """Batches queued since the last call; waits up to timeout_s for the first one."""
        out = []
        if timeout_s > 0:
            try:
                out.append(self._queue.get(timeout=timeout_s))
            except queue.Empty:
                return out
        while len(out) < max_batches:
            try:
                out.append(self._queue.get_nowait())
            except queue.Empty:
                break
        return out

    def stats(self) -> dict:
        """Snapshot of counters and link state (decoder counters merged in)."""
        with self._lock:
            s = dict(self.counters)
            s.update(self.decoder.stats())
            s.update(
                state=self.state,
                queue_depth=self._queue.qsize(),
                last_error=self.last_error,
                clock_resyncs=self.mapper.resyncs,
                clock_clamped=self.mapper.clamped,
                packets_dropped=self.packets_dropped(),
            )
            st = self.device_status
            if st is not None:
                s.update(
                    device_serial=st.serial_number,
                    device_firmware=".".join(str(v) for v in st.firmware_version),
                    device_state=st.state.name,
                    device_sample_rate_hz=st.sample_rate_hz,
                    device_v_per_count=st.v_per_count,
                    device_dropped=st.device_dropped,
                )
            return s

    def packets_dropped(self) -> int:
        """Frames lost on the link (sequence gaps; a lost frame's type is unknown, so each
        counts as one packet) + packets dropped by a full hand-over queue."""
        return int(
            self.decoder.dropped_frames + self.counters["queue_overflow_packets"]
        )

    # ---------------------------------------------------------------- thread
    def _run(self) -> None:
        backoff = self.config.reconnect_initial_s
        while not self._stop.is_set():
            try:
                if self._serial is None:
                    if not self._open():
                        self._stop.wait(backoff)
                        backoff = min(2 * backoff, self.config.reconnect_max_s)
                        continue
                    backoff = self.config.reconnect_initial_s
                    self._configure_device()
                    continue
                self._cycle()
                if (
                    self.config.sync_period_s > 0
                    and self._serial is not None
                    and self.state == "connected"
                    and time.monotonic() - self._last_sync_mono > self.config.sync_period_s
                ):
                    self._ping_for_clock()
                if self._reconfigure_pending and self._serial is not None:
                    self._reconfigure_pending = False
                    self._configure_device()
            except Exception as exc:  # no input may stop the reader: count, go on
                self.counters["internal_errors"] += 1
                self.last_error = f"internal error: {exc!r}"
                self.log.exception("link: unexpected error (reader continues)")
                self._stop.wait(self.config.read_timeout_s)

    def _cycle(self) -> None:
        try:
            ser = self._serial
            if ser is None:
                return
            data = self._read(ser)
        except PORT_ERRORS as exc:
            # TypeError/AttributeError: pyserial internals after the fd vanished.
            self.counters["read_errors"] += 1
            self._close(f"read failed: {exc}")
            return
        now_mono = time.monotonic()
        if data:
            self._last_byte_mono = now_mono
            self._stall_reported = False
            frames = self._handle_bytes(data)
            if not frames:
                self._idle()
        else:
            if (
                not self._stall_reported
                and self.decoder.pending_bytes
                and now_mono - self._last_byte_mono > self.config.stall_report_s
            ):
                # kept, not flushed: the rest of the frame may still come, and a new
                # frame would cut it short anyway (counted then as truncated_frames)
                self._stall_reported = True
                self.counters["stalled_frames"] += 1
                self.log.warning(
                    "%d bytes of a frame waiting, no byte for %.2f s (kept)",
                    self.decoder.pending_bytes,
                    now_mono - self._last_byte_mono,
                )
            self._idle()
        if (
            self._serial is not None
            and time.monotonic() - self._last_frame_mono > self.config.link_timeout_s
        ):
            self._close(
                f"no valid frame for {self.config.link_timeout_s:g} s"
                f" ({self.decoder.bytes_received} bytes received in all)"
            )
            self.counters["link_timeouts"] += 1  # after the reason is readable in stats()

    def _idle(self) -> None:
        if self.on_idle is not None:
            try:
                self.on_idle()
            except Exception as exc:  # the reader must survive any consumer bug
                self.counters["sink_errors"] += 1
                self.log.error("idle work of the packet consumer failed: %r", exc)

    def bytes_waiting(self) -> bool:
        """Whether bytes are waiting on the port now (one poll(0); False where the port
        has no file descriptor to poll). For the sink: more packets are coming at once."""
        fd = self._fd
        if fd is None:
            return False
        try:
            return bool(self._poller.poll(0))
        except (OSError, ValueError, AttributeError):
            return False

    def unread_bytes(self) -> int:
        """Bytes waiting in the port's input buffer now (FIONREAD; 0 where the port has no
        file descriptor, e.g. a socket:// URL). Safe from any thread, unlike
        `bytes_waiting`, whose poll object is the reader's."""
        fd = self._fd
        if fd is None:
            return 0
        try:
            import fcntl
            import struct
            import termios

            return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]
        except (ImportError, OSError, ValueError):
            return 0

    def _read(self, ser) -> bytes:
        """Everything waiting, or block (<= read_timeout_s) for the first byte when idle.

        Serial ports and ptys: one select() and one os.read() of whatever is there (pyserial's
        own read(n) waits for n bytes or the timeout). socket:// URLs: pyserial's in_waiting
        is only 0/1 there, so the first byte is awaited and the rest taken with a zero timeout.
        """
        chunk = self.config.read_chunk_bytes
        fd = self._fd
        if fd is not None:
            events = self._poller.poll(self.config.read_timeout_s * 1e3)
            if not events:
                return b""
            flags = events[0][1]
            if flags & select.POLLNVAL:
                raise serial.SerialException("port file descriptor closed (POLLNVAL)")
            try:
                data = os.read(fd, chunk)
            except (BlockingIOError, InterruptedError):
                data = None  # readable, then nothing: spurious
            except OSError as exc:
                if exc.errno in (errno.EAGAIN, errno.EINTR):
                    data = None
                else:
                    raise  # EIO of a vanished pty, ENXIO, ...
            if data:
                self._empty_hup_reads = 0
                if TTY_LINE_BUFFER_BYTES - 96 <= len(data) < chunk:
                    return self._drain(fd, data, chunk)  # the line buffer was full: more waits
                return data
            if flags & (select.POLLHUP | select.POLLERR):
                # Hang-up: a few empty reads in a row mean the other end is gone.
                self._empty_hup_reads += 1
                if self._empty_hup_reads >= 3:
                    self.counters["hangups"] += 1
                    raise serial.SerialException("port hung up (POLLHUP and no data)")
                self._stop.wait(self.config.read_timeout_s)
                return b""
            self.counters["spurious_wakeups"] += 1
            return b""
        data = ser.read(1)
        if not data:
            return data
        if self._is_socket:
            ser.timeout = 0
            try:
                return data + ser.read(chunk - 1)
            finally:
                ser.timeout = self.config.read_timeout_s
        n = ser.in_waiting
        return data + ser.read(min(n, chunk - 1)) if n else data

    @staticmethod
    def _drain(fd: int, data: bytes, chunk: int) -> bytes:
        """The first read's bytes plus whatever else is already waiting (up to ``chunk``).

        A tty hands over at most its line buffer (4 KiB) per read, about one PACKET frame:
        when the reader fell behind, the rest waits in the kernel. Taking it now makes the
        backlog one batch (localized together, cheaper per packet). Called only when the
        first read (nearly) filled the line buffer, so a reader that keeps up pays no extra
        read. A real error is left for the next cycle's read, which reports it.
        """
        parts, total = [data], len(data)
        while total < chunk:
            try:
                more = os.read(fd, chunk - total)
            except OSError:  # EAGAIN: drained (EINTR / EIO: the next read decides)
                break
            if not more:
                break
            parts.append(more)
            total += len(more)
        return data if len(parts) == 1 else b"".join(parts)

    def _open(self) -> bool:
        # the state stays "disconnected" through a failed attempt ("connecting" once the
        # port is open, until a valid frame): a reader never sees a retry flap it
        try:
            ser = serial.serial_for_url(
                self.config.port,
                baudrate=int(self.config.baudrate),
                timeout=self.config.read_timeout_s,
                write_timeout=1.0,
            )
        except (serial.SerialException, OSError, ValueError, _TermiosError) as exc:
            with self._lock:  # counted with its reason, for stats() readers
                self.counters["connect_failures"] += 1
                self.last_error = f"open failed: {exc}"
                self.state = "disconnected"
            if not self._open_failure_logged:  # once per outage, not every retry
                self.log.warning(
                    "cannot open %s: %s (retrying with back-off)", self.config.port, exc
                )
                self._open_failure_logged = True
            return False
        fd = None
        if not self._is_socket:
            try:
                fd = ser.fileno()
            except (AttributeError, NotImplementedError, serial.SerialException, OSError):
                fd = None  # loop://, rfc2217:// ...: pyserial's own read
        if fd is not None:
            self._poller = select.poll()
            self._poller.register(fd, select.POLLIN | select.POLLPRI)
            self._empty_hup_reads = 0
        with self._lock:
            self._serial = ser
            self._fd = fd
            # A (re)connected device may have restarted: decode it as a new sender and
            # rebuild the clock mapping from scratch.
            self.decoder.flush()
            self.decoder.forget_senders()
            self.mapper.reset()
            self._stream_next_index = None
            self.state = "connecting"  # "connected" once a valid frame arrives
            self.counters["connects"] += 1
            self._open_failure_logged = False
        self._last_frame_mono = self._last_byte_mono = time.monotonic()
        self.log.info("connected to %s", self.config.port)
        return True

    def _close(self, reason: str) -> None:
        # What was read before the port went away is still the device's data: valid
        # frames in the buffer are delivered; a frame cut short by the disconnect is
        # counted (its bytes are also in bytes_discarded).
        discarded_before = self.decoder.bytes_discarded
        with self._lock:
            frames = self.decoder.flush()
        if reason != "stopped":  # stopping: nobody is listening any more
            self._handle_frames(frames)
        self.counters["bytes_cut_at_disconnect"] += (
            self.decoder.bytes_discarded - discarded_before
        )
        self._reset_detector()
        self._stream_ref = None
        with self._lock:  # state and reason change together for stats() readers
            ser, self._serial = self._serial, None
            self._fd = None
            was = self.state
            self.state = "disconnected"
            lost = ser is not None and was in ("connected", "connecting") and reason != "stopped"
            if lost:
                self.last_error = reason
        if ser is None:
            return
        if reason == "stopped":
            try:
                ser.write(self.encoder.encode(Command.stop(self._new_command_id()), 0))
                ser.flush()
            except PORT_ERRORS:
                pass
        try:
            ser.close()
        except PORT_ERRORS:
            pass
        if lost:
            self.counters["disconnects"] += 1
            self.log.warning("link to %s lost: %s; reconnecting", self.config.port, reason)

    # ---------------------------------------------------------------- commands
    def _new_command_id(self) -> int:
        cid = self._next_command_id
        self._next_command_id = cid % 0xFFFF + 1
        return cid

    def _configure_device(self) -> None:
        """Stop, apply the configured settings, start in the configured mode."""
        cfg = self.config
        commands = [Command.stop]
        if cfg.sample_rate_hz is not None:
            commands.append(lambda cid: Command.set_sample_rate(int(cfg.sample_rate_hz), cid))
        if cfg.threshold_counts is not None:
            commands.append(lambda cid: Command.set_threshold(int(cfg.threshold_counts), cid))
        if cfg.packet_samples is not None:
            pre = (
                cfg.pre_trigger_samples
                if cfg.pre_trigger_samples is not None
                else cfg.packet_samples // 4
            )
            commands.append(
                lambda cid: Command.set_packet_length(int(cfg.packet_samples), int(pre), cid)
            )
        mode = AcqMode.STREAM if cfg.mode == "stream" else AcqMode.TRIGGERED
        for make in commands:
            if self._stop.is_set() or self._serial is None:
                return
            self.send_command(make)
        self._sync_clock()
        for make in (lambda cid: Command.start(mode, cid), Command.get_status):
            if self._stop.is_set() or self._serial is None:
                return
            self.send_command(make)

    def _sync_clock(self) -> None:
        """Status round trips before acquisition starts, until ``sync_good_pings`` of them
        took less than ``sync_rtt_s`` (or ``sync_max_pings`` were sent).

        Each ACK, created by the device between the host's send (t_s) and its arrival (t_r),
        gives the clock mapping the sample (device time, (t_s + t_r) / 2), off by at most
        half the round trip (by (reply delay - request delay) / 2: ~0 when the two ways
        are alike), so fast round trips pin the mapping down before the first packet.
        Without them the first packets would be stamped with whatever latency the first
        frames after a (re)connect had (port buffers, a process still starting).
        """
        cfg = self.config
        good = 0
        for _ in range(cfg.sync_max_pings):
            if good >= cfg.sync_good_pings or self._stop.is_set() or self._serial is None:
                break
            good += self._ping_for_clock()
            self._stop.wait(0.003)
        self.counters["sync_good_pings"] = good

    _last_sync_mono = 0.0

    def _ping_for_clock(self) -> bool:
        """One status round trip; if it took at most ``sync_rtt_s``, its midpoint goes to the
        clock mapping (the ACK was created between send and arrival: the midpoint halves
        the error that arrival alone carries, the reply's delay). Frames arriving
        meanwhile are handled as usual."""
        self._last_sync_mono = time.monotonic()
        t_send = int(self.clock_ns())
        ack = self.send_command(Command.get_status)
        self.counters["clock_pings"] += 1
        if ack is None or self._last_ack_receive_ns - t_send > self.config.sync_rtt_s * 1e9:
            return False
        self.counters["clock_pings_used"] += 1
        self.mapper.update(self._last_ack_device_ns, (t_send + self._last_ack_receive_ns) // 2)
        return True

    def send_command(self, make: Callable[[int], Command]) -> Ack | None:
        """Send a command built by ``make(command_id)`` and wait for its ACK (reader thread)."""
        for _ in range(self.config.command_retries):
            cid = self._new_command_id()
            cmd = make(cid)
            try:
                self._serial.write(
                    self.encoder.encode(cmd, int(time.monotonic() * 1e6) & 0xFFFFFFFF)
                )
            except PORT_ERRORS as exc:
                self._close(f"write failed: {exc}")
                return None
            self.counters["commands_sent"] += 1
            deadline = time.monotonic() + self.config.command_timeout_s
            while (
                time.monotonic() < deadline
                and self._serial is not None
                and not self._stop.is_set()
            ):
                self._cycle()
                ack = self._pending_acks.pop(cid, None)
                if ack is not None:
                    ack, self._last_ack_receive_ns, self._last_ack_device_ns = ack
                    if ack.result != AckResult.OK:
                        self.counters["commands_failed"] += 1
                        self.log.warning("device refused %s: %s", cmd.opcode.name, ack.result.name)
                    return ack
        self.counters["commands_unacked"] += 1
        self.log.warning(
            "no ACK for %s after %d tries", cmd.opcode.name, self.config.command_retries
        )
        return None

    # ---------------------------------------------------------------- frames
    def _handle_bytes(self, data: bytes) -> list:
        """Decode ``data`` and hand on its frames (returned). The decoder is fed under the
        stats lock: stats() sees a frame counted and its bytes gone together."""
        with self._lock:
            frames = self.decoder.feed(data)
        self._handle_frames(frames)
        return frames

    def _handle_frames(self, frames: list) -> None:
        for ev in self.decoder.pop_events():
            self.log.debug("decoder: %s at byte %s: %s", ev.reason, ev.stream_offset, ev.detail)
        if not frames:
            return
        self._last_frame_mono = time.monotonic()
        if self.state != "connected" and self._serial is not None:
            with self._lock:
                self.state = "connected"
        receive_ns = int(self.clock_ns())
        records: list[PacketRecord] = []
        for frame in frames:
            try:
                self._handle_frame(frame, receive_ns, records)
            except Exception as exc:  # e.g. a stream block the detector refuses
                self.counters["frames_unusable"] += 1
                self.log.warning("frame seq %d unusable: %r", frame.seq, exc)
        if records:
            self._emit(receive_ns, records)

    def _handle_frame(self, frame, receive_ns: int, records: list) -> None:
        """One decoded frame: clock mapping, device status, ACKs, packet records."""
        if frame.restart and self.mapper.synced:
            # The device rebooted under us: new clock, and it lost its settings.
            self._reset_detector()
            self.mapper.reset()
            self.counters["device_restarts_handled"] += 1
            self._stream_next_index = None
            self._stream_ref = None
            self._reconfigure_pending = True
        body = frame.body
        device_ns = int(frame.device_time_us) * 1000
        if isinstance(body, (Packet, StreamBlock)):
            last_ns = device_ns + int(round((body.n_samples - 1) * 1e9 / body.sample_rate_hz))
            self.mapper.update(last_ns, receive_ns)
        else:
            self.mapper.update(device_ns, receive_ns)
        if (
            isinstance(body, (Packet, StreamBlock))
            and float(body.v_per_count) * 32768.0 > _FLOAT32_MAX
        ):
            self.counters["packets_rejected_nonfinite"] += 1  # counts x v_per_count = inf
            return
        if isinstance(body, Packet):
            records.append(self._packet_record(body, device_ns))
        elif isinstance(body, StreamBlock):
            records.extend(self._stream_records(body, device_ns))
        elif isinstance(body, Status):
            self.device_status = body
        elif isinstance(body, Ack):
            self._pending_acks[body.command_id] = (body, receive_ns, device_ns)
            if len(self._pending_acks) > 64:
                self._pending_acks.pop(next(iter(self._pending_acks)))
        else:
            self.counters["frames_ignored"] += 1

    def _next_id(self) -> int:
        sid = self._next_sequence_id
        self._next_sequence_id += 1
        return sid

    def _packet_record(self, body: Packet, device_ns: int) -> PacketRecord:
        volts, noise, onset = packet_volts_noise_onset(
            body.samples, body.v_per_count, body.pre_trigger
        )
        if body.onset_index != NO_ONSET:
            onset = int(body.onset_index)
        return PacketRecord(
            stamp_ns=self.mapper.to_host_ns(device_ns),
            samples_v=volts,
            sample_rate_hz=float(body.sample_rate_hz),
            onset_index=onset,
            sequence_id=self._next_id(),
            noise_rms_v=noise,
            saturated=bool(body.saturation_mask),
            device_sample_index=int(body.first_sample_index),
        )

    # ---------------------------------------------------------------- stream mode
    def _reset_detector(self) -> None:
        """End the detector's stream (gap, reconnect, restart): complete windows it still
        holds are published, windows the gap cuts are dropped (counted by the detector)."""
        det, self._detector = self._detector, None
        if det is None or self._stream_ref is None:
            return
        records = self._records_from_batch(det.flush(), *self._stream_ref)
        if records:
            self._emit(int(self.clock_ns()), records)

    def _stream_records(self, body: StreamBlock, device_ns: int) -> list[PacketRecord]:
        from ae_tactile.dsp import PacketDetector  # imported lazily: stream mode only

        fs = float(body.sample_rate_hz)
        full_scale_v = float(body.v_per_count) * 2 ** (self.config.adc_bits - 1)
        if self._detector is None or self._detector_key != (fs, full_scale_v):
            self._reset_detector()
            self._detector = PacketDetector(
                sample_rate_hz=fs,
                full_scale_v=full_scale_v,
                adc_bits=self.config.adc_bits,
                **self.config.detector,
            )
            self._detector_key = (fs, full_scale_v)
            self._stream_next_index = None
        first = int(body.first_sample_index)
        if self._stream_next_index is not None and first != self._stream_next_index:
            self.counters["stream_gaps"] += 1
            self.counters["stream_samples_lost"] += max(first - self._stream_next_index, 0)
        self._stream_next_index = body.next_sample_index
        self._stream_ref = (first, device_ns, fs)
        batch = self._detector.process(body.samples * np.float32(body.v_per_count), first)
        return self._records_from_batch(batch, first, device_ns, fs)

    def _records_from_batch(
        self, batch, ref_index: int, ref_device_ns: int, fs: float
    ) -> list[PacketRecord]:
        """PacketRecords of a detector batch; sample index -> device time through the
        reference (sample ref_index was taken at device time ref_device_ns)."""
        out = []
        for k in range(len(batch.start_index)):
            if not bool(batch.valid[k]):
                continue
            start = int(batch.start_index[k])
            start_ns = ref_device_ns + int(round((start - ref_index) * 1e9 / fs))
            out.append(
                PacketRecord(
                    stamp_ns=self.mapper.to_host_ns(start_ns),
                    samples_v=np.asarray(batch.samples[k], dtype=np.float32),
                    sample_rate_hz=fs,
                    onset_index=int(batch.onset_index[k]),
                    sequence_id=self._next_id(),
                    noise_rms_v=float(batch.noise_rms_v[k]),
                    saturated=bool(batch.saturated[k]),
                    device_sample_index=start,
                )
            )
        return out

    # ---------------------------------------------------------------- hand-over
    def _emit(self, receive_ns: int, records: list[PacketRecord]) -> None:
        batch = PacketBatch(receive_ns, records, 0, 0)
        if self.sink is not None:
            with self._lock:
                batch.packets_dropped = self.packets_dropped()
                batch.frames_bad_crc = int(self.decoder.crc_errors)
            self.counters["packets_out"] += len(records)
            self.counters["batches_out"] += 1
            try:
                self.sink(batch)
            except Exception as exc:  # the reader must survive any consumer bug
                self.counters["sink_errors"] += 1
                self.log.error("packet consumer failed: %r", exc)
            return
        try:
            with self._lock:
                batch.packets_dropped = self.packets_dropped()
                batch.frames_bad_crc = int(self.decoder.crc_errors)
            self._queue.put_nowait(batch)
        except queue.Full:
            self.counters["queue_overflow_packets"] += len(records)
            self.log.warning("hand-over queue full: %d packets dropped", len(records))
            return
        self.counters["packets_out"] += len(records)
        self.counters["batches_out"] += 1
        if self.on_batch is not None:
            self.on_batch()
