# SPDX-License-Identifier: Apache-2.0
"""The link's input: one open port, read without byte-by-byte or timeout-bound reads.

Each read blocks for the first byte (up to ``read_timeout_s``, only when idle) and then
takes everything waiting. Serial ports and ptys: one poll() and one os.read() of
whatever is there (pyserial's own read(n) waits for n bytes or the timeout). socket://
URLs: pyserial's in_waiting is only 0/1 there, so the first byte is awaited and the rest
taken with a zero timeout. Other URLs (loop://, rfc2217://): pyserial's own read.
"""

from __future__ import annotations

import errno
import os
import select
import struct
import tempfile
import threading

import serial

from .config import LinkConfig

try:
    import fcntl
    import termios
    from termios import error as _TermiosError  # tcdrain / tcflush on a vanished pty: EIO
except ImportError:  # not a POSIX system
    fcntl = termios = None
    _TermiosError = OSError

#: What a port that vanished or was closed under us raises (pyserial, the OS, termios'
#: own error class, which is no OSError; TypeError/AttributeError: pyserial internals after
#: its fd is gone): a lost link, never a crash.
PORT_ERRORS = (serial.SerialException, OSError, TypeError, AttributeError, _TermiosError)
#: What a port that cannot be opened raises.
OPEN_ERRORS = (serial.SerialException, OSError, ValueError, _TermiosError)

#: Bytes a Linux tty (serial port, USB CDC, pty) hands over per read at most: its line
#: discipline's buffer (N_TTY_BUF_SIZE); a read that (nearly) fills it leaves more behind.
TTY_LINE_BUFFER_BYTES = 4096


class PortBusy(OSError):
    """The port is owned by another link (this process or another one).

    Parameters
    ----------
    port : str
        The port as configured.
    owner_pid : int or None
        Process id of the owner, as its lock file says (None: unreadable).
    lock_path : str
        The lock file.
    """

    def __init__(self, port: str, owner_pid: int | None, lock_path: str):
        owner = f"pid {owner_pid}" if owner_pid else "an unknown process"
        super().__init__(
            errno.EBUSY, f"port {port} is in use by {owner} (lock {lock_path}); not opened"
        )
        self.port, self.owner_pid, self.lock_path = port, owner_pid, lock_path


def _lock_dir() -> str:
    """/run/lock where this user may write there (the system's place for port locks),
    the temporary directory otherwise."""
    for d in ("/run/lock", "/var/lock"):
        if os.path.isdir(d) and os.access(d, os.W_OK | os.X_OK):
            return d
    return tempfile.gettempdir()


def lock_key(port: str) -> str | None:
    """What identifies ``port`` for its lock: the resolved device path (a symlink such as a
    udev name and its target share one lock), the URL of a socket:// port; None for other
    URLs (loop://, rfc2217://: nothing local to own)."""
    if port.startswith("socket://"):
        return port
    if "://" in port:
        return None
    return os.path.realpath(port)


class PortLock:
    """An exclusive flock on a lock file keyed by the port (`lock_key`), holding the
    owner's pid; released by `release` or when the process ends (the kernel drops flocks).

    Parameters
    ----------
    port : str
        The port as configured (named in the error).

    Raises
    ------
    PortBusy
        Another open file description holds the lock (another link, in any process).
    OSError
        The lock file cannot be created.
    """

    def __init__(self, port: str):
        self.fd: int | None = None
        key = lock_key(port)
        if key is None or fcntl is None:
            return
        name = "ae_tactile" + "".join(c if c.isalnum() else "_" for c in key) + ".lock"
        self.path = os.path.join(_lock_dir(), name)
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        except PermissionError:  # another user's lock file: flock works read-only too
            fd = os.open(self.path, os.O_RDONLY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            try:
                pid = int(os.pread(fd, 32, 0).split()[0])
            except (OSError, ValueError, IndexError):
                pid = None
            os.close(fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EACCES, errno.EAGAIN):
                raise PortBusy(port, pid, self.path) from None
            raise
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError:  # read-only: the owner's pid stays unknown to a second link
            pass
        self.fd = fd

    def release(self) -> None:
        """Give the port up (the lock file stays: removing it would race a new owner)."""
        fd, self.fd = self.fd, None
        if fd is not None:
            os.close(fd)  # closing the last descriptor drops the flock


def open_serial(config: LinkConfig):
    """The pyserial object of ``config.port``; raises one of OPEN_ERRORS if it cannot be
    opened. A device path is opened exclusively (pyserial's ``exclusive``: a flock on the
    tty itself, which also keeps out programs that do not know `PortLock`)."""
    kw = {} if "://" in config.port else {"exclusive": True}
    return serial.serial_for_url(
        config.port,
        baudrate=int(config.baudrate),
        timeout=config.read_timeout_s,
        write_timeout=1.0,
        **kw,
    )


class SerialPort:
    """One open port of the link (the reader thread's; `unread_bytes` is safe from any).

    Parameters
    ----------
    ser : serial.Serial
        The open pyserial port (`open_serial`).
    config : LinkConfig
        ``port`` (a socket:// URL is read differently), ``read_timeout_s`` and
        ``read_chunk_bytes`` are used.
    stop : threading.Event
        The link's stop flag (a hang-up waits on it).
    counters : dict
        The link's counters (``hangups`` and ``spurious_wakeups`` are counted here).
    lock : PortLock or None
        The port's lock, released when the port is closed.
    """

    def __init__(
        self,
        ser,
        config: LinkConfig,
        stop: threading.Event,
        counters: dict,
        lock: PortLock | None = None,
    ):
        self.ser = ser
        self.lock = lock
        self.read_timeout_s = config.read_timeout_s
        self.chunk = config.read_chunk_bytes
        self.is_socket = config.port.startswith("socket://")
        self._stop = stop
        self._counters = counters
        self._empty_hup_reads = 0
        fd = None
        if not self.is_socket:
            try:
                fd = ser.fileno()
            except (AttributeError, NotImplementedError, serial.SerialException, OSError):
                fd = None  # loop://, rfc2217:// ...: pyserial's own read
        self.fd: int | None = fd
        if fd is not None:
            self._poller = select.poll()
            self._poller.register(fd, select.POLLIN | select.POLLPRI)

    def write(self, data: bytes) -> None:
        self.ser.write(data)

    def flush(self) -> None:
        self.ser.flush()

    def close(self) -> None:
        """Close the port, then release its lock; a port already gone is no error."""
        try:
            self.ser.close()
        except PORT_ERRORS:
            pass
        if self.lock is not None:
            self.lock.release()

    def bytes_waiting(self) -> bool:
        """Whether bytes are waiting now (one poll(0); False without a file descriptor)."""
        if self.fd is None:
            return False
        try:
            return bool(self._poller.poll(0))
        except (OSError, ValueError, AttributeError):
            return False

    def unread_bytes(self) -> int:
        """Bytes waiting in the port's input buffer now (FIONREAD; 0 without a file
        descriptor, e.g. a socket:// URL). Safe from any thread."""
        fd = self.fd
        if fd is None or fcntl is None:
            return 0
        try:
            return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]
        except (OSError, ValueError):
            return 0

    def read(self) -> bytes:
        """Everything waiting, or block (<= read_timeout_s) for the first byte when idle.

        Returns
        -------
        bytes
            What was read (empty: nothing within the timeout).

        Raises
        ------
        serial.SerialException, OSError
            The port is gone (a hang-up, EIO of a vanished pty, POLLNVAL).
        """
        if self.fd is not None:
            return self._read_fd()
        ser, chunk = self.ser, self.chunk
        data = ser.read(1)
        if not data:
            return data
        if self.is_socket:
            ser.timeout = 0
            try:
                return data + ser.read(chunk - 1)
            finally:
                ser.timeout = self.read_timeout_s
        n = ser.in_waiting
        return data + ser.read(min(n, chunk - 1)) if n else data

    def _read_fd(self) -> bytes:
        """`read` of a port with a file descriptor: poll, then one os.read."""
        fd, chunk = self.fd, self.chunk
        events = self._poller.poll(self.read_timeout_s * 1e3)
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
                self._counters["hangups"] += 1
                raise serial.SerialException("port hung up (POLLHUP and no data)")
            self._stop.wait(self.read_timeout_s)
            return b""
        self._counters["spurious_wakeups"] += 1
        return b""

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
