# SPDX-License-Identifier: Apache-2.0
"""Fault injection of the virtual fingertip, for tests: what a real link does wrong.

`FaultInjection` is mixed into `VirtualFingertip`: `inject_garbage`, `corrupt_next`
(flip one payload bit: the host sees a CRC error and a sequence gap), `drop_next`
(sequence gap), `repeat_next` (a frame sent twice), `inject_frame` (any body, numbered
like the rest), `reset_mid_frame` (a watchdog reset while a frame is on the wire, port
left open), `garble` (every output byte replaced by noise, as a wrong baud rate would),
`step_clock` (the device clock steps, no reboot), `halt_acquisition` (the device stops
acquiring, no reboot: a firmware fault or another host's STOP; heartbeats go on).
"""

from __future__ import annotations

import numpy as np

from ae_tactile.protocol import MAX_SAMPLES, DeviceState, Packet

#: Frames the faults of corrupt_next / drop_next / repeat_next apply to.
_DATA_KINDS = ("packet", "stream")


class FaultInjection:
    """The faults of `VirtualFingertip` (uses its ``out``, ``encoder``, ``boot``,
    ``_send``, ``device_us``, ``clock_step_ns``, ``state``, ``_source``,
    ``sample_rate_hz`` and ``v_per_count``)."""

    #: frames sent twice by repeat_next so far
    frames_repeated = 0

    def _init_faults(self) -> None:
        self._corrupt = 0
        self._drop = 0
        self._repeat = 0
        self.garbled = False
        self._garble_rng = np.random.default_rng(12345)

    def inject_garbage(self, data: bytes) -> None:
        """Bytes sent as they are, between frames."""
        self.out += bytes(data)

    def corrupt_next(self, n: int = 1) -> None:
        """The next n PACKET/STREAM frames get one payload bit flipped (a CRC error)."""
        self._corrupt += int(n)

    def drop_next(self, n: int = 1) -> None:
        """The next n PACKET/STREAM frames are numbered but not sent (a sequence gap)."""
        self._drop += int(n)

    def repeat_next(self, n: int = 1) -> None:
        """The next n PACKET/STREAM frames are sent twice (byte-identical)."""
        self._repeat += int(n)

    def inject_frame(self, body, now_ns: int) -> None:
        """Send any frame body now, numbered and stamped like the device's own frames."""
        self._send(body, int(now_ns), "injected")

    def reset_mid_frame(
        self, now_ns: int, n_samples: int = MAX_SAMPLES, fraction: float = 0.5
    ) -> int:
        """A watchdog reset while a PACKET of ``n_samples`` is on the wire: its first
        ``fraction`` goes out, then the device reboots (the port stays open; the host sees
        the rebooted device's BOOT frame and heartbeats next). Returns the bytes cut off."""
        body = Packet(
            np.zeros((4, int(n_samples)), np.int16), self.sample_rate_hz, self.v_per_count
        )
        frame = self.encoder.encode(body, self.device_us(now_ns) & 0xFFFFFFFF)
        cut = frame[: max(24, int(len(frame) * float(fraction)))]
        pending = bytes(self.out)
        self.boot()
        self.out += pending + cut
        return len(frame) - len(cut)

    def step_clock(self, delta_s: float) -> None:
        """The device clock steps by ``delta_s`` [s] (back if negative) without a reboot:
        every later frame's ``timestamp_us`` is shifted (wrapping modulo 2^32 us)."""
        self.clock_step_ns += int(round(float(delta_s) * 1e9))

    def halt_acquisition(self) -> None:
        """Stop acquiring without a reboot or an ACK (a firmware fault, another host's
        STOP): the device goes IDLE and keeps sending its heartbeat STATUS."""
        self.state = DeviceState.IDLE
        self._source = None

    def garble(self, on: bool = True) -> None:
        """Replace every output byte by noise (a wrong baud rate) until garble(False)."""
        self.garbled = bool(on)

    def _fate(self, kind: str, data: bytes) -> tuple[bytes, str]:
        """What a pending drop / corruption does to a frame of ``kind``: (its bytes,
        'sent' | 'dropped' | 'corrupted')."""
        if kind in _DATA_KINDS and self._drop > 0:
            self._drop -= 1
            return data, "dropped"
        if kind in _DATA_KINDS and self._corrupt > 0:
            self._corrupt -= 1
            data = bytearray(data)
            data[len(data) // 2] ^= 0x10  # a payload bit: frame CRC fails
            return data, "corrupted"
        return data, "sent"

    def _repeat_due(self, kind: str, fate: str) -> bool:
        """Whether this frame goes out a second time (repeat_next)."""
        if kind in _DATA_KINDS and fate == "sent" and self._repeat > 0:
            self._repeat -= 1
            self.frames_repeated += 1
            return True
        return False

    def _garbled(self, out: bytes) -> bytes:
        """The output as a wrong baud rate would deliver it (while garble is on)."""
        if self.garbled and out:
            return self._garble_rng.integers(0, 256, len(out), dtype=np.uint8).tobytes()
        return out
