# SPDX-License-Identifier: Apache-2.0
"""One overlap worker process for every `OverlapResolver` of a process, where several
fingertips share one process (`ae_tactile.ros.hand_driver`).

A worker answers each window from the window alone (samples, geometry, pulse travel in the
request), so resolvers can take turns on one: ``io_lock`` keeps one resolver's request
and its answers together. The worker holds ~130 MB of its own (numpy, numba's kernels);
one per process instead of one per fingertip. Off unless `enable` was called: a process
with one pipeline gains nothing, and tests that own their pipeline's worker stay apart.
"""

from __future__ import annotations

import pickle
import subprocess
import sys
import threading

from ae_tactile.localization import overlap_worker

_registry_lock = threading.Lock()
_enabled = False
_shared: dict[bool, SharedWorker] = {}  # by the worker's idle flag


def enable(on: bool = True) -> None:
    """Resolvers made from now on share one worker per priority class (see module)."""
    global _enabled
    _enabled = bool(on)


def enabled() -> bool:
    """Whether resolvers share their worker (`enable`)."""
    return _enabled


class SharedWorker:
    """A worker process and its users. ``proc`` is None when it could not start."""

    def __init__(self, idle: bool):
        self.idle = idle
        self.users = 0
        #: held from a request to its last answer: one resolver's window at a time
        self.io_lock = threading.RLock()
        self._ready_lock = threading.Lock()
        self._ready: bool | None = None  # None: not read yet; False: it failed
        try:
            # its own session, as `OverlapResolver._start_worker` (Ctrl-C reaches the node)
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "ae_tactile.localization.overlap_worker"]
                + ([overlap_worker.IDLE_FLAG] if idle else []),
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, start_new_session=True)
        except OSError:
            self.proc = None

    def wait_ready(self) -> bool:
        """Block until the worker said "ready" (read once, by the first user to ask);
        False when it cannot answer."""
        with self._ready_lock:
            if self._ready is None:
                try:
                    self._ready = self.proc is not None and \
                        pickle.load(self.proc.stdout) == "ready"
                except (OSError, EOFError, pickle.UnpicklingError):
                    self._ready = False
            return self._ready

    def broken(self) -> None:
        """A user met a dead pipe: nobody else tries it."""
        with self._ready_lock:
            self._ready = False

    def close(self) -> None:
        proc, self.proc = self.proc, None
        end_worker(proc)


def end_worker(proc) -> None:
    """End a worker process (None: nothing): EOF on its stdin, killed if it lingers."""
    if proc is None:
        return
    try:
        proc.stdin.close()  # EOF: the worker exits
        proc.wait(2.0)
    except (OSError, subprocess.TimeoutExpired):
        proc.kill()
        proc.wait()


def acquire(idle: bool) -> SharedWorker:
    """The process's shared worker of that priority class (started on first use); every
    `acquire` needs its `release`."""
    with _registry_lock:
        w = _shared.get(bool(idle))
        if w is None or w.proc is None or w.proc.poll() is not None:
            w = _shared[bool(idle)] = SharedWorker(bool(idle))
        w.users += 1
        return w


def release(w: SharedWorker) -> None:
    """One user fewer; the last one ends the worker."""
    with _registry_lock:
        w.users -= 1
        if w.users > 0:
            return
        if _shared.get(w.idle) is w:
            del _shared[w.idle]
    w.close()
