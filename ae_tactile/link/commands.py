# SPDX-License-Identifier: Apache-2.0
"""The command half of the link: configure the device, sync the clock, await ACKs.

`DeviceControl` is mixed into `FingertipLink` and runs in its reader thread: a command
is written to the port and the link's read cycle (`_cycle`) runs until the ACK arrives,
so frames arriving meanwhile are handled as usual.
"""

from __future__ import annotations

import time
from typing import Callable

from ae_tactile.protocol import Ack, AckResult, AcqMode, Command

from .port import PORT_ERRORS


class DeviceControl:
    """Commands and clock-sync round trips of `FingertipLink` (its reader thread).

    Uses the link's ``config``, ``encoder``, ``mapper``, ``counters``, ``log``,
    ``clock_ns``, ``_port``, ``_stop``, ``_cycle`` and ``_close``; keeps the ACKs the
    frame handler files in ``_pending_acks``.
    """

    _last_sync_mono = 0.0

    def _init_commands(self) -> None:
        self._next_command_id = 1
        self._pending_acks: dict[int, tuple[Ack, int, int]] = {}
        self._reconfigure_pending = False
        self._last_ack_receive_ns = 0
        self._last_ack_device_ns = 0

    def _file_ack(self, ack: Ack, receive_ns: int, device_ns: int) -> None:
        """Keep an ACK for the command waiting on it (the table holds the last 64)."""
        self._pending_acks[ack.command_id] = (ack, receive_ns, device_ns)
        if len(self._pending_acks) > 64:
            self._pending_acks.pop(next(iter(self._pending_acks)))

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
            if self._stop.is_set() or self._port is None:
                return
            self.send_command(make)
        self._sync_clock()
        for make in (lambda cid: Command.start(mode, cid), Command.get_status):
            if self._stop.is_set() or self._port is None:
                return
            self.send_command(make)
        self._acquisition_expected = True  # from now on, acquisition must show
        self._last_acquiring_mono = time.monotonic()

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
            if good >= cfg.sync_good_pings or self._stop.is_set() or self._port is None:
                break
            good += self._ping_for_clock()
            self._stop.wait(0.003)
        self.counters["sync_good_pings"] = good

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
        """Send a command and wait for its ACK (reader thread only).

        Parameters
        ----------
        make : callable
            ``make(command_id)`` builds the Command (e.g. ``Command.get_status``); called
            again with a new id for each retry.

        Returns
        -------
        Ack or None
            The device's ACK (a refusal is counted in ``commands_failed`` and logged), or
            None after ``command_retries`` tries without one or a failed write.
        """
        for _ in range(self.config.command_retries):
            cid = self._new_command_id()
            cmd = make(cid)
            try:
                self._port.write(
                    self.encoder.encode(cmd, int(time.monotonic() * 1e6) & 0xFFFFFFFF)
                )
            except PORT_ERRORS as exc:
                self._close(f"write failed: {exc}")
                return None
            self.counters["commands_sent"] += 1
            deadline = time.monotonic() + self.config.command_timeout_s
            while (
                time.monotonic() < deadline and self._port is not None and not self._stop.is_set()
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
