# SPDX-License-Identifier: Apache-2.0
"""A process exit at a deadline that needs no Python thread: the clean-up deadline's last
resort when the main thread is stuck inside a call that keeps the GIL (rclpy's bindings
keep it around the middleware's teardown), so that no Python code can run again.

A POSIX timer with SIGEV_THREAD notification: on expiry the C library starts a thread
that calls the notification function with the timer's value; the function is the C
library's ``_exit`` and the value the exit code, so the process leaves with the stop's
code (not faulthandler's 1) without the interpreter. Linux (glibc, musl); elsewhere, or
when the calls fail, `start_exit_timer` returns None and the caller keeps its fallback.
"""
from __future__ import annotations

import ctypes
import ctypes.util

_CLOCK_MONOTONIC = 1
_SIGEV_THREAD = 2


class _SigEvent(ctypes.Structure):
    """Linux's struct sigevent (64 bytes): the value, then the thread notification."""

    _fields_ = [("value", ctypes.c_void_p), ("signo", ctypes.c_int),
                ("notify", ctypes.c_int), ("function", ctypes.c_void_p),
                ("attribute", ctypes.c_void_p), ("pad", ctypes.c_int * 8)]


class _TimeSpec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _ITimerSpec(ctypes.Structure):
    _fields_ = [("interval", _TimeSpec), ("value", _TimeSpec)]


def _timer_library():
    """The library with timer_create: the C library itself (glibc >= 2.34, musl) or librt."""
    libc = ctypes.CDLL(None, use_errno=True)
    if hasattr(libc, "timer_create"):
        return libc, libc
    return libc, ctypes.CDLL(ctypes.util.find_library("rt"), use_errno=True)


class ExitTimer:
    """An armed timer; `cancel` disarms and deletes it (idempotent)."""

    def __init__(self, lib, timer_id):
        self._lib = lib
        self._id = timer_id

    def cancel(self) -> None:
        if self._id is not None:
            self._lib.timer_delete(self._id)
            self._id = None


def start_exit_timer(delay_s: float, exit_code: int) -> ExitTimer | None:
    """Arm a timer that ends the process with ``exit_code`` after ``delay_s`` [s] unless
    cancelled; None when this system cannot (the caller keeps its own fallback)."""
    try:
        libc, lib = _timer_library()
        lib.timer_create.argtypes = [ctypes.c_int, ctypes.POINTER(_SigEvent),
                                     ctypes.POINTER(ctypes.c_void_p)]
        lib.timer_settime.argtypes = [ctypes.c_void_p, ctypes.c_int,
                                      ctypes.POINTER(_ITimerSpec), ctypes.c_void_p]
        lib.timer_delete.argtypes = [ctypes.c_void_p]
        ev = _SigEvent(value=int(exit_code) & 0xFF, notify=_SIGEV_THREAD,
                       function=ctypes.cast(libc._exit, ctypes.c_void_p).value)
        timer_id = ctypes.c_void_p()
        if lib.timer_create(_CLOCK_MONOTONIC, ctypes.byref(ev), ctypes.byref(timer_id)):
            return None
        timer = ExitTimer(lib, timer_id)
        sec = int(delay_s)
        spec = _ITimerSpec(value=_TimeSpec(sec, int((delay_s - sec) * 1e9)))
        if lib.timer_settime(timer_id, 0, ctypes.byref(spec), None):
            timer.cancel()
            return None
        return timer
    except (OSError, AttributeError, TypeError, ValueError):
        return None
