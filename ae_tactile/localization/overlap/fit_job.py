# SPDX-License-Identifier: Apache-2.0
"""One pulse fit in a process of its own (``python -m
ae_tactile.localization.overlap.fit_job``): `PulseLearner` in a driver runs its fits here,
so that seconds of numpy and scipy never hold the driver's interpreter lock against the
thread that localizes every packet.

Protocol: one pickled mapping of `fit_pulse` arguments on stdin (``windows``,
``sample_rate_hz``, ``onset_index`` and its keywords); one pickled `PulseFit` on stdout
(or a str: the error). The process runs niced and exits after the one answer (or when
its parent has gone).
"""

from __future__ import annotations

import os
import pickle
import signal
import sys
import threading
import time

#: niceness added where SCHED_IDLE is refused [1]: the driver's threads come first
FIT_NICENESS = 10


def _background() -> None:
    """This process as background work: niceness +FIT_NICENESS (not SCHED_IDLE: on cores
    kept busy by other processes an idle-class fit would never finish, and the driver's
    reader, at normal priority, preempts a niced process when it wakes)."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, os.getpriority(os.PRIO_PROCESS, 0) + FIT_NICENESS)
    except (AttributeError, OSError):
        pass


def _orphan_watch(parent: int) -> None:
    """End this process once its parent has gone (the driver or a test ended during the
    fit): nobody reads the answer then. Polls every second."""
    while os.getppid() == parent:
        time.sleep(1.0)
    os._exit(1)


def main() -> int:
    """Read one request, fit, answer; 0 when answered (an error is answered as text)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the driver's Ctrl-C is its own
    threading.Thread(target=_orphan_watch, args=(os.getppid(),), daemon=True).start()
    _background()
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # stdout carries the answer only
    try:
        req = pickle.load(inp)
    except (EOFError, pickle.UnpicklingError):
        return 1
    try:
        from ae_tactile.localization.overlap.learn import (  # lazy: after the redirect
            fit_pulse,
        )

        args = dict(req)
        fit = fit_pulse(args.pop("windows"), args.pop("sample_rate_hz"),
                        args.pop("onset_index"), **args)
    except Exception as exc:  # answered as text: the learner counts it
        fit = f"{type(exc).__name__}: {exc}"
    pickle.dump(fit, out, protocol=pickle.HIGHEST_PROTOCOL)
    out.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
