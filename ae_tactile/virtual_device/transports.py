# SPDX-License-Identifier: Apache-2.0
"""How the virtual fingertip's bytes reach the driver: a pseudo-terminal or a TCP server.

Both offer the same small interface to `DeviceRunner`: ``read()`` (host bytes in),
``write(data)`` (device bytes out; returns how many were taken), ``fileno()`` (what to
wait on), ``connected()``, ``replug()`` / ``unplug()`` (a cable pulled and put back),
``close()`` and ``port`` (what the driver opens).
"""

from __future__ import annotations

import errno
import logging
import os
import socket
import time
import tty

LOG = logging.getLogger("ae_tactile.virtual_device")


class PtyTransport:
    """A pseudo-terminal pair in raw mode; the driver opens ``path`` (the slave side).

    ``link_path`` (optional) is a symlink kept pointing at the current slave, like a udev
    rule: `unplug()` closes the pty and removes it, `replug()` opens a new pty and puts it
    back. While unplugged nothing answers at ``link_path``: a driver retrying it cannot
    open another program's pty that reused the closed one's number (/dev/pts/N).

    Parameters
    ----------
    link_path : str or None
        Path of the symlink to the current slave (None: none; the driver opens ``path``).
    """

    def __init__(self, link_path: str | None = None):
        self.link_path = link_path
        self.master = self.slave = None
        self.path = None
        self.replug()

    def replug(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        if self.link_path:
            tmp = f"{self.link_path}.tmp{os.getpid()}"
            if os.path.lexists(tmp):
                os.unlink(tmp)
            os.symlink(self.path, tmp)
            os.replace(tmp, self.link_path)

    def unplug(self) -> None:
        if self.link_path and os.path.islink(self.link_path):
            os.unlink(self.link_path)  # first: the number of the pty closed next is free
        for fd in (self.master, self.slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = None

    @property
    def port(self) -> str:
        return self.link_path or self.path

    def fileno(self):
        return self.master

    def read(self) -> bytes:
        try:
            return os.read(self.master, 65536)
        except BlockingIOError:
            return b""
        except OSError as exc:  # EIO: no reader attached yet
            if exc.errno == errno.EIO:
                return b""
            raise

    def write(self, data: memoryview) -> int:
        try:
            return os.write(self.master, data)
        except BlockingIOError:
            return 0

    def connected(self) -> bool:
        return self.master is not None

    def close(self) -> None:
        self.unplug()


class _TcpClient:
    __slots__ = ("sock", "out", "last_progress", "address")

    def __init__(self, sock, address, now: float):
        self.sock, self.address, self.out, self.last_progress = sock, address, bytearray(), now


class TcpTransport:
    """A TCP server on ``host:port`` (127.0.0.1 unless told otherwise; port 0 picks one);
    the driver opens ``socket://host:port``.

    Several clients at once (up to ``max_clients``; one more is accepted and closed at
    once, counted in ``refused``). Each client gets every device byte sent after it
    connected, through its own buffer of at most ``max_client_buffer`` bytes; commands
    from any client reach the device. A client that takes no byte for ``idle_timeout_s``
    while bytes wait for it, or whose buffer overflows, is disconnected (``timed_out``,
    ``overflowed``): a client that connects and never reads cannot lock the others out
    nor make the device's memory grow.

    Parameters
    ----------
    host : str
        Address to listen on.
    port : int
        TCP port (0: any free one; `port` then names it).
    max_clients : int
        Clients served at once.
    idle_timeout_s : float
        A client that takes no byte for this long while bytes wait is dropped [s].
    max_client_buffer : int
        Bytes waiting for one client at most [B]; more drops it.
    client_sndbuf : int or None
        SO_SNDBUF of each client's socket [B] (None: the system's).
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        max_clients: int = 4,
        idle_timeout_s: float = 5.0,
        max_client_buffer: int = 4 << 20,
        client_sndbuf: int | None = None,
    ):
        if int(max_clients) < 1 or not idle_timeout_s > 0 or int(max_client_buffer) < 1:
            raise ValueError("need max_clients >= 1, idle_timeout_s > 0, max_client_buffer >= 1")
        self.host = host
        self._port = port
        self.max_clients = int(max_clients)
        self.idle_timeout_s = float(idle_timeout_s)
        self.max_client_buffer = int(max_client_buffer)
        self.client_sndbuf = client_sndbuf
        self.listener = None
        self.clients: list[_TcpClient] = []
        self.accepted = self.refused = self.timed_out = self.overflowed = 0
        self.replug()

    def replug(self) -> None:
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind((self.host, self._port))
        self._port = self.listener.getsockname()[1]
        self.listener.listen(16)
        self.listener.setblocking(False)

    def unplug(self) -> None:
        for c in self.clients:
            c.sock.close()
        self.clients = []
        if self.listener is not None:
            self.listener.close()
        self.listener = None

    @property
    def conn(self):
        """The first client's socket (None without clients)."""
        return self.clients[0].sock if self.clients else None

    @property
    def port(self) -> str:
        return f"socket://{self.host}:{self._port}"

    def fileno(self):
        return self.listener.fileno() if self.listener is not None else None

    def filenos(self) -> list[int]:
        """Descriptors to wait on: the listener and every client."""
        if self.listener is None:
            return []
        return [self.listener.fileno()] + [c.sock.fileno() for c in self.clients]

    def _drop(self, c: _TcpClient, why: str) -> None:
        LOG.info("virtual device: client %s disconnected (%s)", c.address, why)
        try:
            c.sock.close()
        except OSError:
            pass
        self.clients.remove(c)

    def _accept(self) -> None:
        while self.listener is not None:
            try:
                sock, address = self.listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            if len(self.clients) >= self.max_clients:
                self.refused += 1  # accepted and closed: a clean refusal
                sock.close()
                continue
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if self.client_sndbuf:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, int(self.client_sndbuf))
            self.clients.append(_TcpClient(sock, address, time.monotonic()))
            self.accepted += 1

    def read(self) -> bytes:
        """Accept new clients; the bytes (commands) every client sent, concatenated."""
        self._accept()
        data = []
        for c in list(self.clients):
            try:
                got = c.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                got = b""
            if not got:  # the client closed
                self._drop(c, "closed by the client")
                continue
            data.append(got)
        return b"".join(data)

    def write(self, data: memoryview) -> int:
        """Queue the device bytes for every client and send what they take; all consumed."""
        data = bytes(data)
        for c in list(self.clients):
            if len(c.out) + len(data) > self.max_client_buffer:
                self._drop(c, f"more than {self.max_client_buffer} bytes waiting")
                self.overflowed += 1  # counted once gone: never counted and still listed
                continue
            c.out += data
        self.service()
        return len(data)

    def service(self) -> None:
        """Send what each client takes; disconnect the ones stuck for idle_timeout_s."""
        now = time.monotonic()
        for c in list(self.clients):
            if c.out:
                try:
                    n = c.sock.send(c.out)
                except (BlockingIOError, InterruptedError):
                    n = 0
                except OSError:
                    self._drop(c, "send failed")
                    continue
                if n:
                    del c.out[:n]
                    c.last_progress = now
            else:
                c.last_progress = now
            if c.out and now - c.last_progress > self.idle_timeout_s:
                self._drop(c, f"took no byte for {self.idle_timeout_s:g} s")
                self.timed_out += 1  # counted once gone: never counted and still listed

    def connected(self) -> bool:
        return self.listener is not None

    def close(self) -> None:
        self.unplug()
