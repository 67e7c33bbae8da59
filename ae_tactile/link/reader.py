# SPDX-License-Identifier: Apache-2.0
"""`FingertipLink`: the reader thread, its reconnect state machine and its counters.

One read cycle: the port's bytes -> the protocol's incremental decoder -> each frame
maps device time to host time and becomes packet records (`PacketBuilder`), device
status or an ACK -> the records of the cycle are handed on as one `PacketBatch` (to the
sink, or to the queue `poll()` empties).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Callable

import numpy as np

from ae_tactile.protocol import (
    Ack,
    AckResult,
    Command,
    DeviceState,
    FrameEncoder,
    Opcode,
    Packet,
    Status,
    StreamBlock,
    StreamDecoder,
)
from ae_tactile.timesync import DeviceClockMapper

from .commands import DeviceControl
from .config import LinkConfig
from .frontend import warm_up
from .lag import ReadLag
from .packets import PacketBatch, PacketBuilder, PacketRecord
from .port import OPEN_ERRORS, PORT_ERRORS, PortBusy, PortLock, SerialPort, open_serial

LOG = logging.getLogger("ae_tactile.link")

_FLOAT32_MAX = float(np.finfo(np.float32).max)

#: The link's own counters (`FingertipLink.stats` adds the decoder's and the state).
COUNTER_NAMES = (
    "connects", "disconnects", "connect_failures", "port_busy", "read_errors", "link_timeouts",
    "acquisition_restarts", "acquisition_reconnects", "packets_out", "batches_out",
    "queue_overflow_packets", "stream_gaps", "stream_samples_lost", "device_restarts_handled",
    "commands_sent", "commands_unacked", "commands_failed", "frames_ignored",
    "sync_good_pings", "clock_pings", "clock_pings_used", "sink_errors", "stalled_frames",
    "spurious_wakeups", "hangups", "internal_errors", "packets_rejected_nonfinite",
    "packets_rejected_sample_rate", "frames_unusable", "bytes_cut_at_disconnect",
)


class FingertipLink(DeviceControl):
    """Background reader of one fingertip. Thread-safe `poll()`, `stats()`, `stop()`.

    Parameters
    ----------
    config : LinkConfig
        Port, mode, device settings, timeouts.
    clock_ns : callable
        Host clock for time stamps [ns] (the ROS node passes its ROS clock).
    on_batch : callable or None
        Called from the reader thread after a batch is queued (e.g. to wake an executor
        through a guard condition); keep it cheap.
    logger : logging.Logger or None
        Where the link logs; default the ``ae_tactile.link`` logger.
    sink : callable or None
        When given, each batch is handed to ``sink(batch)`` in the reader thread as soon
        as it is decoded, instead of being queued for `poll()` (the lowest-latency path:
        the caller localizes and publishes right there). An exception in the sink is
        counted (``sink_errors``) and logged, never allowed to stop the reader.
    on_idle : callable or None
        Called from the reader thread after a read cycle that completed no frame
        (nothing arrived within ``read_timeout_s``, or only part of a frame): the moment
        for work the sink put off while more bytes were waiting (`bytes_waiting`). Same
        rules as the sink.
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
        self._port: SerialPort | None = None
        self._lock = threading.Lock()
        self.decoder = StreamDecoder()
        # Restarts come from the protocol (BOOT flag, sequence): the mapper's own
        # "device time stepped back by > 1 s" guess would fire on a device that lags
        # (packets carry their sample time, older than the STATUS it sent just before).
        # A clock step without a restart shows as a latency above the model, frame after
        # frame (step_back_s, step_frames): the mapping is rebuilt from those frames.
        self.mapper = DeviceClockMapper(
            max_backstep_s=3600.0,
            step_back_s=config.clock_step_s,
            step_frames=config.clock_step_frames,
        )
        self.encoder = FrameEncoder(boot=False)
        self.state = "disconnected"
        self.device_status: Status | None = None
        self.counters = dict.fromkeys(COUNTER_NAMES, 0)
        self.lag = ReadLag(self.log)  # how far behind the device the reader is
        self._packets = PacketBuilder(
            config, self.mapper, self.counters, lambda r: self._emit(int(self.clock_ns()), r)
        )
        self._init_commands()
        self.last_error = ""
        self._last_frame_mono = 0.0  # last valid frame (liveness)
        self._last_byte_mono = 0.0  # last byte of any kind (stall report)
        self._stall_reported = False  # this stall of a partial frame is reported
        self._open_failure_logged = False
        self._clock_step_logged = False
        self._host_minus_mono: int | None = None  # host clock - monotonic clock [ns]
        self._rate_mismatch_logged = False
        self._device_fs = 0.0  # [Hz] its STATUS / SET_SAMPLE_RATE ACK rate; 0: unknown
        self._acquisition_expected = False  # START sent on this connection
        self._acquisition_restarted = False  # restarted, no sign of acquisition since
        self._last_acquiring_mono = 0.0  # last sign of acquisition (or its START)

    # ---------------------------------------------------------------- control
    def start(self) -> None:
        """Start the reader thread (it opens the port, retrying with back-off)."""
        if self._thread is not None:
            raise RuntimeError("FingertipLink already started")
        self._thread = threading.Thread(target=self._run, name="ae_tactile_link", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop the reader; sends STOP to the device if connected; closes the port.

        Parameters
        ----------
        timeout_s : float
            Longest wait for the reader thread to end [s].
        """
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        self._close("stopped")

    def poll(self, max_batches: int = 64, timeout_s: float = 0.0) -> list[PacketBatch]:
        """Batches queued since the last call (without a sink).

        Parameters
        ----------
        max_batches : int
            Most batches returned.
        timeout_s : float
            Longest wait for the first batch [s] (0: do not wait).

        Returns
        -------
        list of PacketBatch
            Oldest first; empty if none came.
        """
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
        """Snapshot of counters and link state.

        Returns
        -------
        dict
            The link's counters (COUNTER_NAMES), the decoder's, ``state``
            ("disconnected", "connecting" or "connected"), ``queue_depth``,
            ``last_error``, the clock mapping's ``clock_resyncs`` / ``clock_clamped`` /
            ``clock_steps`` (device clock steps without a restart, each a re-sync),
            ``clock_host_steps`` (host clock steps the mapping followed),
            ``packets_dropped`` and, once the device sent a STATUS, its ``device_*``
            fields.
        """
        with self._lock:
            s = dict(self.counters)
            s.update(self.decoder.stats())
            s.update(
                state=self.state,
                queue_depth=self._queue.qsize(),
                last_error=self.last_error,
                clock_resyncs=self.mapper.resyncs,
                clock_clamped=self.mapper.clamped,
                clock_steps=self.mapper.steps,
                clock_host_steps=self.mapper.host_steps,
                packets_dropped=self.packets_dropped(),
                **self.lag.stats(),
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
        return int(self.decoder.dropped_frames + self.counters["queue_overflow_packets"])

    def bytes_waiting(self) -> bool:
        """Whether bytes are waiting on the port now (one poll(0); False where the port
        has no file descriptor to poll). For the sink: more packets are coming at once."""
        port = self._port
        return port.bytes_waiting() if port is not None else False

    def unread_bytes(self) -> int:
        """Bytes waiting in the port's input buffer now (FIONREAD; 0 where the port has no
        file descriptor, e.g. a socket:// URL). Safe from any thread, unlike
        `bytes_waiting`, whose poll object is the reader's."""
        port = self._port
        return port.unread_bytes() if port is not None else 0

    # ---------------------------------------------------------------- thread
    def _run(self) -> None:
        backoff = self.config.reconnect_initial_s
        while not self._stop.is_set():
            try:
                if self._port is None:
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
                    and self._port is not None
                    and self.state == "connected"
                    and time.monotonic() - self._last_sync_mono > self.config.sync_period_s
                ):
                    self._ping_for_clock()
                if self._reconfigure_pending and self._port is not None:
                    self._reconfigure_pending = False
                    self._configure_device()
                self._check_acquisition()
            except Exception as exc:  # no input may stop the reader: count, go on
                self.counters["internal_errors"] += 1
                self.last_error = f"internal error: {exc!r}"
                self.log.exception("link: unexpected error (reader continues)")
                self._stop.wait(self.config.read_timeout_s)

    def _cycle(self) -> None:
        try:
            port = self._port
            if port is None:
                return
            data = port.read()
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
            self._report_stall(now_mono)
            self._idle()
        if (
            self._port is not None
            and time.monotonic() - self._last_frame_mono > self.config.link_timeout_s
        ):
            self._close(
                f"no valid frame for {self.config.link_timeout_s:g} s"
                f" ({self.decoder.bytes_received} bytes received in all)"
            )
            self.counters["link_timeouts"] += 1  # after the reason is readable in stats()

    def _check_acquisition(self) -> None:
        """Restart acquisition that shows no sign of life for ``acquisition_timeout_s``
        (see `LinkConfig`): first STOP / settings / START, then, if that did not help,
        a reconnect. Each step counted and logged."""
        timeout = self.config.acquisition_timeout_s
        if (
            not timeout
            or not self._acquisition_expected
            or self._port is None
            or self.state != "connected"
            or time.monotonic() - self._last_acquiring_mono <= timeout
        ):
            return
        st = self.device_status
        seen = st.state.name if st is not None else "no status"
        if self._acquisition_restarted:
            self.counters["acquisition_reconnects"] += 1
            self.log.error(
                "%s: still no acquisition %g s after restarting it (device state %s):"
                " reconnecting",
                self.config.port,
                timeout,
                seen,
            )
            self._close(f"acquisition did not resume (device state {seen})")
            return
        self.counters["acquisition_restarts"] += 1
        self.log.warning(
            "%s: connected but not acquiring for %g s (no packet, device state %s):"
            " restarting acquisition",
            self.config.port,
            timeout,
            seen,
        )
        self._configure_device()
        self._acquisition_restarted = True

    def _acquiring(self) -> None:
        """A sign that the device acquires (a data frame, a STATUS in the running state)."""
        self._last_acquiring_mono = time.monotonic()
        self._acquisition_restarted = False

    def _report_stall(self, now_mono: float) -> None:
        """Report once a partial frame left waiting ``stall_report_s`` without a byte."""
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

    def _idle(self) -> None:
        if self.on_idle is not None:
            try:
                self.on_idle()
            except Exception as exc:  # the reader must survive any consumer bug
                self.counters["sink_errors"] += 1
                self.log.error("idle work of the packet consumer failed: %r", exc)

    def _open(self) -> bool:
        # the state stays "disconnected" through a failed attempt ("connecting" once the
        # port is open, until a valid frame): a reader never sees a retry flap it
        lock = None
        try:
            lock = PortLock(self.config.port)  # one owner per port: before touching it
            ser = open_serial(self.config)
        except OPEN_ERRORS as exc:
            if lock is not None:
                lock.release()
            with self._lock:  # counted with its reason, for stats() readers
                self.counters["connect_failures"] += 1
                self.counters["port_busy"] += isinstance(exc, PortBusy) or (
                    "exclusive" in str(exc).lower()
                )
                self.last_error = f"open failed: {exc}"
                self.state = "disconnected"
            if not self._open_failure_logged:  # once per outage, not every retry
                log = self.log.error if isinstance(exc, PortBusy) else self.log.warning
                log("cannot open %s: %s (retrying with back-off)", self.config.port, exc)
                self._open_failure_logged = True
            return False
        port = SerialPort(ser, self.config, self._stop, self.counters, lock)
        with self._lock:
            self._port = port
            # A (re)connected device may have restarted: decode it as a new sender and
            # rebuild the clock mapping from scratch.
            self.decoder.flush()
            self.decoder.forget_senders()
            self.mapper.reset()
            self._device_fs = 0.0  # until its STATUS says
            self._packets.stream_next_index = None
            self._acquisition_expected = self._acquisition_restarted = False  # until START
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
        self.counters["bytes_cut_at_disconnect"] += self.decoder.bytes_discarded - discarded_before
        self._packets.end_stream()
        self._packets.stream_ref = None
        with self._lock:  # state and reason change together for stats() readers
            port, self._port = self._port, None
            was = self.state
            self.state = "disconnected"
            lost = port is not None and was in ("connected", "connecting") and reason != "stopped"
            if lost:
                self.last_error = reason
        if port is None:
            return
        if reason == "stopped":
            try:
                port.write(self.encoder.encode(Command.stop(self._new_command_id()), 0))
                port.flush()
            except PORT_ERRORS:
                pass
        port.close()
        if lost:
            self.counters["disconnects"] += 1
            self.log.warning("link to %s lost: %s; reconnecting", self.config.port, reason)

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
        if self.state != "connected" and self._port is not None:
            with self._lock:
                self.state = "connected"
        receive_ns = int(self.clock_ns())
        self._follow_host_clock(receive_ns)
        records: list[PacketRecord] = []
        for frame in frames:
            try:
                self._handle_frame(frame, receive_ns, records)
            except Exception as exc:  # e.g. a stream block the detector refuses
                self.counters["frames_unusable"] += 1
                self.log.warning("frame seq %d unusable: %r", frame.seq, exc)
        if records:
            self._emit(receive_ns, records)

    def _follow_host_clock(self, receive_ns: int) -> None:
        """The host clock stepped (its offset to the monotonic clock moved > clock_step_s:
        NTP, a paused sim clock): the mapping moves with it (``clock_host_steps``)."""
        last, self._host_minus_mono = self._host_minus_mono, receive_ns - time.monotonic_ns()
        step_ns = 0 if last is None else self._host_minus_mono - last
        if abs(step_ns) <= self.mapper.step_back_ns:
            return
        self.mapper.shift_host(step_ns)
        self.log.warning("host clock stepped by %+.3f s: mapping moved with it", step_ns / 1e9)

    def _handle_frame(self, frame, receive_ns: int, records: list) -> None:
        """One decoded frame: clock mapping, device status, ACKs, packet records."""
        if frame.restart and self.mapper.synced:
            # The device rebooted under us: new clock, and it lost its settings.
            self._packets.end_stream()
            self.mapper.reset()
            self.counters["device_restarts_handled"] += 1
            self._packets.stream_next_index = None
            self._packets.stream_ref = None
            self._reconfigure_pending = True
            self._device_fs = 0.0  # its settings are lost: until its STATUS says
        body = frame.body
        device_ns = int(frame.device_time_us) * 1000
        if isinstance(body, (Packet, StreamBlock)) and self._rate_disagrees(body):
            return  # before the clock mapping: its duration would move the mapping
        steps = self.mapper.steps
        if isinstance(body, (Packet, StreamBlock)):
            last_ns = device_ns + int(round((body.n_samples - 1) * 1e9 / body.sample_rate_hz))
            self.mapper.update(last_ns, receive_ns)
        else:
            self.mapper.update(device_ns, receive_ns)
        if self.mapper.steps != steps:
            self._report_clock_step()
        if (
            isinstance(body, (Packet, StreamBlock))
            and float(body.v_per_count) * 32768.0 > _FLOAT32_MAX
        ):
            self.counters["packets_rejected_nonfinite"] += 1  # counts x v_per_count = inf
            return
        if isinstance(body, Packet):
            self._acquiring()
            records.append(self._packets.packet(body, device_ns))
        elif isinstance(body, StreamBlock):
            self._acquiring()
            records.extend(self._packets.stream(body, device_ns))
        elif isinstance(body, Status):
            self.device_status = body
            self._device_fs = float(body.sample_rate_hz)
            running = (
                DeviceState.STREAMING if self.config.mode == "stream" else DeviceState.TRIGGERED
            )
            if body.state == running:
                self._acquiring()
        elif isinstance(body, Ack):
            if body.opcode == Opcode.SET_SAMPLE_RATE and body.result == AckResult.OK:
                self._device_fs = float(body.value)  # the rate actually used
            self._file_ack(body, receive_ns, device_ns)
        else:
            self.counters["frames_ignored"] += 1

    def _rate_disagrees(self, body) -> bool:
        """A PACKET / STREAM block whose sample rate is not the device's (its last STATUS
        or SET_SAMPLE_RATE ACK; the rate changes only while IDLE) is counted
        (``packets_rejected_sample_rate``), logged once per connection and dropped: read
        at the wrong rate its delays, and so its point, would be wrong."""
        fs = float(body.sample_rate_hz)
        if self._device_fs <= 0.0 or abs(fs - self._device_fs) <= 1e-6 * self._device_fs:
            return False
        self.counters["packets_rejected_sample_rate"] += 1
        if not self._rate_mismatch_logged:
            self._rate_mismatch_logged = True
            self.log.warning(
                "packet at %g Hz from a device running at %g Hz: dropped (the sample rate"
                " changes only while idle; packets_rejected_sample_rate counts them)",
                fs,
                self._device_fs,
            )
        return True

    def _report_clock_step(self) -> None:
        """Log a clock step once per connection (every one is counted: ``clock_steps``)."""
        if self._clock_step_logged:
            return
        self._clock_step_logged = True
        self.log.warning(
            "device clock stepped (frames %g s or more behind the clock mapping, %d in a"
            " row): mapping rebuilt, stamps held monotonic (clock_steps counts further"
            " steps)",
            self.config.clock_step_s,
            self.config.clock_step_frames,
        )

    # ---------------------------------------------------------------- hand-over
    def _emit(self, receive_ns: int, records: list[PacketRecord]) -> None:
        batch = PacketBatch(receive_ns, records, 0, 0)
        last = records[-1]
        if self.sink is not None:
            with self._lock:
                self.lag.add(receive_ns, last.stamp_ns, last.samples_v.shape[1],
                             last.sample_rate_hz)
                batch.packets_dropped = self.packets_dropped()
                batch.frames_bad_crc = int(self.decoder.crc_errors)
            self.counters["packets_out"] += len(records)
            self.counters["batches_out"] += 1
            try:
                self.sink(batch)
            except Exception as exc:  # the reader must survive any consumer bug
                self.counters["sink_errors"] += 1
                self.log.error("packet consumer failed: %r", exc)
            if self.config.mode == "triggered":  # a raw stream always has bytes coming
                with self._lock:
                    self.lag.after_batch(int(self.clock_ns()), self.bytes_waiting())
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
