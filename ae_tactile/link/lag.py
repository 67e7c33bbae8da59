# SPDX-License-Identifier: Apache-2.0
"""Whether the reader keeps up with the fingertip (in the driver's in-process path, a
sink; the device sending packets, mode ``triggered``).

The reader thread reads what the port holds, decodes it and hands each batch to its
consumer (in the driver: localization, slip step, publishing) before it reads again. A
reader that keeps up finds the port empty now and then after a batch; one that cannot
(the device sends more packets per second than the consumer processes) finds bytes
waiting after every batch: they pile up in the kernel's buffer, then in the device's, and
the device drops packets once its buffers are full (its STATUS counts them) or, on a pty,
the writer blocks. `ReadLag` says so once in the log when bytes have been waiting after
every batch for BEHIND_FOR_S (and again when the reader is back in step), and gives its
figures for the link's diagnostics: ``behind`` (1 while behind), ``behind_episodes``, and
the read lag of the recent batches, ``read_lag_ms`` (median) and ``read_lag_max_ms``:
receive time - (last packet's stamp + its window), the transfer plus the time the bytes
waited (a millisecond or two when keeping up; the clock mapping takes a lag beyond
``clock_step_s`` that does not fall for a clock step and re-syncs, so it reads small
again then: ``behind`` is the test, the lag a figure).
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

#: [s] bytes waiting after every batch for this long: the reader is behind (a short burst,
#: a garbage collection or another process taking the core for a moment, is not)
BEHIND_FOR_S = 0.5
#: batches whose lags the figures are taken over
LAG_KEEP = 256


class ReadLag:
    """Whether the reader keeps up, batch by batch (updated by the reader thread only).

    Parameters
    ----------
    log : logging.Logger
        Where the start and the end of a backlog are said.
    """

    def __init__(self, log: logging.Logger):
        self.log = log
        self._lags_ns: deque[int] = deque(maxlen=LAG_KEEP)
        self._waiting_since_ns: int | None = None  # first batch after which bytes waited
        self.behind = False
        self.episodes = 0

    def add(self, receive_ns: int, stamp_ns: int, n_samples: int, sample_rate_hz: float
            ) -> None:
        """The lag of one batch read at ``receive_ns`` whose last packet's first sample is
        stamped ``stamp_ns`` and holds ``n_samples`` at ``sample_rate_hz`` (host clock)."""
        end_ns = stamp_ns + (int(n_samples / sample_rate_hz * 1e9) if sample_rate_hz > 0
                             else 0)
        self._lags_ns.append(int(receive_ns - end_ns))

    def after_batch(self, now_ns: int, bytes_waiting: bool) -> None:
        """The consumer is done with a batch at ``now_ns``; ``bytes_waiting``: the port
        holds more already."""
        if not bytes_waiting:
            self._waiting_since_ns = None
            if self.behind:
                self.behind = False
                self.log.info("the reader is back in step with the fingertip")
            return
        if self._waiting_since_ns is None:
            self._waiting_since_ns = now_ns
        waited_s = (now_ns - self._waiting_since_ns) * 1e-9
        if not self.behind and waited_s >= BEHIND_FOR_S:
            self.behind = True
            self.episodes += 1
            lag_ms = self._lags_ns[-1] * 1e-6 if self._lags_ns else float("nan")
            self.log.warning(
                "the driver is behind the fingertip: bytes waiting on the port after every "
                "batch for %.1f s (the last packet read %.0f ms after it was taken); it "
                "cannot keep up with the device's packet rate, its events reach the hand "
                "late, and the device drops packets once its buffers are full", waited_s,
                lag_ms)

    def stats(self) -> dict:
        """``read_lag_ms`` (median of the last LAG_KEEP batches), ``read_lag_max_ms``,
        ``behind`` (0 / 1), ``behind_episodes``."""
        lags = np.fromiter(self._lags_ns, dtype=np.int64, count=len(self._lags_ns))
        return {
            "read_lag_ms": round(float(np.median(lags)) * 1e-6, 3) if lags.size else 0.0,
            "read_lag_max_ms": round(float(lags.max()) * 1e-6, 3) if lags.size else 0.0,
            "behind": int(self.behind),
            "behind_episodes": self.episodes,
        }
