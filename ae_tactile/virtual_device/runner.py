# SPDX-License-Identifier: Apache-2.0
"""`DeviceRunner`: the virtual fingertip's real-time loop over a transport (a thread)."""

from __future__ import annotations

import select
import threading
import time

from .firmware import VirtualFingertip


class DeviceRunner:
    """Real-time loop moving bytes between a VirtualFingertip and a transport (thread).

    Writes never block the loop (pending bytes wait for the reader); the outgoing buffer
    is bounded like a device's transmit queue (``max_out_bytes``; overflow = frames lost).

    Parameters
    ----------
    device : VirtualFingertip
        The firmware model.
    transport : PtyTransport or TcpTransport
        Where its bytes go.
    period_s : float
        Longest wait of the loop between two passes [s].
    max_out_bytes : int
        Bound of the outgoing buffer [B]; what would overflow it is counted in
        ``out_overflow_bytes`` and lost.
    """

    def __init__(
        self,
        device: VirtualFingertip,
        transport,
        *,
        period_s: float = 0.0005,
        max_out_bytes: int = 8 << 20,
    ):
        self.device = device
        self.transport = transport
        self.period_s = period_s
        self.max_out_bytes = max_out_bytes
        self._out = bytearray()
        self._stop = threading.Event()
        self._lock = threading.RLock()
        self._callers = 0  # threads waiting in call(): the loop stays out of the lock
        self._callers_lock = threading.Lock()
        self._unplugged_until = None
        self.out_overflow_bytes = 0
        self.thread = threading.Thread(
            target=self._run, name="ae_tactile_virtual_device", daemon=True
        )

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        """Stop the loop (if it was started: a node stopped while it was being built
        never started it) and close the transport."""
        self._stop.set()
        if self.thread.ident is not None:
            self.thread.join(2.0)
        self.transport.close()

    def call(self, fn, *args):
        """Run fn(*args) while the device loop is held (for changes from other threads).

        The device loop takes its lock again right after each short wait, so a caller that
        merely waited for the lock could starve on a busy machine (a grip command applied
        seconds late): the caller raises a flag that the loop honours by staying out of the
        lock until the call is done."""
        with self._callers_lock:  # "+= 1" is not atomic between threads
            self._callers += 1
        try:
            with self._lock:
                return fn(*args)
        finally:
            with self._callers_lock:
                self._callers -= 1

    @property
    def pending_out_bytes(self) -> int:
        """Bytes the device produced that the transport has not taken yet."""
        return len(self._out)

    def unplug(self, duration_s: float) -> None:
        """Pull the cable for duration_s: transport closed, device unpowered; then re-plug,
        which boots the device again (bus powered), as real USB hardware would."""
        with self._lock:
            self.transport.unplug()
            self._out.clear()
            self._unplugged_until = time.monotonic() + float(duration_s)

    def _run(self) -> None:
        while not self._stop.is_set():
            while self._callers and not self._stop.is_set():
                time.sleep(0.0001)  # another thread is waiting for the lock: let it in
            with self._lock:
                self._replug_when_due()
                if self._unplugged_until is None and self.transport.connected():
                    self._step()
                fds = self._wait_fds()
            if fds and not self._out:
                try:
                    select.select(fds, [], [], self.period_s)
                except (OSError, ValueError):
                    time.sleep(self.period_s)
            else:
                time.sleep(self.period_s / 4 if self._out else self.period_s)

    def _replug_when_due(self) -> None:
        """The cable goes back in once the unplugged time is over: the device boots."""
        if self._unplugged_until is not None and time.monotonic() >= self._unplugged_until:
            self._unplugged_until = None
            self.transport.replug()
            self.device.boot()

    def _step(self) -> None:
        """One pass: host bytes to the device, the device's due bytes to the transport."""
        dev = self.device
        now = int(dev.clock_ns())
        try:
            data = self.transport.read()
        except OSError:
            data = b""
        if data:
            dev.receive(data, now)
        new = dev.poll(now)
        if new:
            if len(self._out) + len(new) > self.max_out_bytes:
                self.out_overflow_bytes += len(new)
            else:
                self._out += new
        if self._out:
            try:
                n = self.transport.write(memoryview(self._out))
            except OSError:
                n = len(self._out)
            del self._out[:n]
        if hasattr(self.transport, "service"):
            self.transport.service()

    def _wait_fds(self) -> list[int]:
        """The transport's descriptors to wait on (none while it is unplugged)."""
        if not self.transport.connected():
            return []
        fds = (
            self.transport.filenos()
            if hasattr(self.transport, "filenos")
            else [self.transport.fileno()]
        )
        return [fd for fd in fds if fd is not None]
