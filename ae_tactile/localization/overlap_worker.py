# SPDX-License-Identifier: Apache-2.0
"""Worker process of the overlap resolver: ``python -m ae_tactile.localization.overlap_worker``.

Resolving a window that holds several emissions costs milliseconds (`resolve_overlaps`:
compiled fits, plus numpy and Python around them). In the driver's process that time
would hold the interpreter lock against the reader thread, which localizes every other
packet in microseconds; in its own process it runs beside it on another core.

Argument ``--idle``: run as SCHED_IDLE (the driver has cores of its own); else niced.

Protocol (pickle, both ways): stdin gets one message per window, ``(samples (4, M) float64
volts, sample_rate_hz, onset_index, saturated, geometry, pulse, quick_first)``; stdout answers with
the `OverlapPacket` of the quick search (``exhaustive=False``) and, when that one is
DEFERRED (the first joint fit left more than noise), with the exhaustive search's (only
the latter when ``quick_first`` is False); or with a
``str`` describing an exception. EOF on stdin ends the process (the parent closed it or
exited); the parent starts it in a session of its own, so a Ctrl-C at the terminal
reaches only the parent, which owns the shutdown (and SIGINT is ignored here too).
The worker warms up (imports, tables, compiled code) and says
``"ready"`` before it reads.
"""

from __future__ import annotations

import os
import pickle
import signal
import sys

import numpy as np

#: Niceness added to background work (the worker; the resolver's thread on a core of its
#: own where SCHED_IDLE is refused)
WORKER_NICENESS = 10
#: worker argument: run as SCHED_IDLE (the driver has cores of its own, `cpu_affinity`)
IDLE_FLAG = "--idle"


def background_priority(idle: bool) -> str:
    """Make the calling thread background work (Linux schedules threads, so in the worker's
    main thread that is the whole process). ``idle``: SCHED_IDLE, so that on the driver's
    own core the reader takes the core the moment it wakes (else a thread in the middle
    of a fit keeps it for up to its time slice, milliseconds); where that is refused, and
    without ``idle``, niceness +WORKER_NICENESS. Returns what was set ("idle", "nice"
    or "")."""
    if idle:
        try:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
            return "idle"
        except (AttributeError, OSError):
            pass
    try:
        os.setpriority(os.PRIO_PROCESS, 0, os.getpriority(os.PRIO_PROCESS, 0) + WORKER_NICENESS)
        return "nice"
    except (AttributeError, OSError):
        return ""


def main() -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    background_priority(IDLE_FLAG in sys.argv[1:])  # the driver's reader comes first
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # stdout carries the answers only
    # imported after stdout is redirected and the priority lowered: nothing the import
    # prints (numba compilation) reaches the answer pipe
    from ae_tactile.localization.overlap import (  # lazy: after the redirect above
        OverlapReason,
        resolve_overlaps,
        warm_up,
    )

    warm_up()  # a two-emission window: every kernel and table of the first real one
    pickle.dump("ready", out)
    out.flush()
    while True:
        try:
            samples, fs, onset, saturated, geometry, pulse, quick_first = pickle.load(inp)
        except (EOFError, OSError):
            return 0
        # the quick answer, then (if DEFERRED) the full one; only the full one for a window
        # whose quick answer (in the driver's reader) was DEFERRED
        for exhaustive in (False, True) if quick_first else (True,):
            try:
                with np.errstate(all="ignore"):
                    res = resolve_overlaps(
                        np.asarray(samples, dtype=np.float64)[None],
                        float(fs),
                        [int(onset)],
                        saturated=[bool(saturated)],
                        geometry=geometry,
                        pulse=pulse,
                        exhaustive=exhaustive,
                    )[0]
            except Exception as exc:  # the parent counts it; the worker goes on
                res = repr(exc)
            try:
                pickle.dump(res, out, protocol=pickle.HIGHEST_PROTOCOL)
                out.flush()
            except (BrokenPipeError, OSError):
                return 0
            if isinstance(res, str) or res.reason != OverlapReason.DEFERRED:
                break


if __name__ == "__main__":
    sys.exit(main())
