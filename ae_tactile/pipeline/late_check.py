# SPDX-License-Identifier: Apache-2.0
"""The late check: single emissions already handed out, looked at again for a second
emission the single-source fit cannot see.

A second emission that arrives after the first one's echo-free segment (7-10 us after it)
leaves the single-source fit good, so the screens' suspect gate (`Screens.withdraw_suspects`)
lets the packet through as one emission. The echo-modelled fit (`suspect_overlap`, about
0.1 ms a packet) sees it, which the reflex path cannot pay on every packet: here it runs
in the overlap resolver's thread when that has no window to answer, on the packets the
pipeline kept as single emissions, once a pulse learnt from the device is trusted (the
nominal pulse flags a device it does not describe everywhere). A packet it flags goes to
the resolver as an overlapping window; the emission handed out already is dropped there as
a duplicate and the second one comes late, with its own stamp. Packets that cannot be
checked are counted, never silently passed: ``overlap_unchecked`` (no trusted pulse yet,
over the rate limit, or the queue full), beside ``overlap_late_checked`` and
``overlap_late_found``.
"""

from __future__ import annotations

import threading
from collections import Counter, deque
from types import SimpleNamespace

import numpy as np

from ae_tactile.localization.overlap import suspect_overlap
from ae_tactile.pipeline.config import LATE_CHECK_BATCH, LATE_CHECK_MAX, LATE_CHECK_MAX_RATE_HZ


class LateCheck:
    """Packets kept as single emissions, waiting for their late check.

    Parameters
    ----------
    counts : collections.Counter
        The pipeline's counters (``overlap_unchecked``, ``overlap_late_checked``,
        ``overlap_late_found``).
    max_rate_hz : float
        Packets checked per second of their stamps at most [1/s] (the rest are counted).
    max_waiting : int
        Packets waiting at most (the oldest beyond are counted and dropped).
    """

    def __init__(self, counts: Counter, *, max_rate_hz: float = LATE_CHECK_MAX_RATE_HZ,
                 max_waiting: int = LATE_CHECK_MAX):
        self.counts = counts
        for key in ("overlap_unchecked", "overlap_late_checked", "overlap_late_found"):
            counts.setdefault(key, 0)  # made here: another thread never adds a key later
        self.spacing_ns = 1e9 / float(max_rate_hz) if max_rate_hz > 0 else float("inf")
        self.max_waiting = int(max_waiting)
        self.lock = threading.Lock()  # a leaf: the reader offers, the resolver's thread takes
        self._waiting: deque = deque()  # (packet, point (3,)), oldest first
        self._last_ns = -(1 << 62)  # stamp of the newest packet taken [ns]

    def __len__(self) -> int:
        return len(self._waiting)

    def offer(self, packets, records, trusted) -> tuple[list, list]:
        """Queue the packets of a batch's single-emission records (one packet each, not
        weak releases) for the check; ``trusted(sample_rate_hz)``: a pulse learnt from
        the device is trusted at that rate. Returns (packets queued, packets dropped
        from the queue to make room): the caller keeps the first in the duplicate check's
        memory and lets the second go."""
        by_id = None
        taken, dropped = [], []
        with self.lock:
            for ev in records:
                if ev.weak_release or len(ev.packet_ids) != 1:
                    continue
                if by_id is None:
                    by_id = {p.sequence_id: p for p in packets}
                p = by_id.get(ev.packet_ids[0])
                if p is None:
                    continue
                if not trusted(float(p.sample_rate_hz)) or (
                        ev.time_ns - self._last_ns < self.spacing_ns):
                    self.counts["overlap_unchecked"] += 1
                    continue
                self._last_ns = ev.time_ns
                self._waiting.append((p, np.asarray(ev.point_m, dtype=float)))
                taken.append(p)
                if len(self._waiting) > self.max_waiting:
                    dropped.append(self._waiting.popleft()[0])
                    self.counts["overlap_unchecked"] += 1
        return taken, dropped

    def run(self, geometry, pulse_at) -> tuple[list, list]:
        """Check up to LATE_CHECK_BATCH waiting packets (`suspect_overlap` with the pulse
        ``pulse_at(sample_rate_hz)``, None: not trusted any more, the packet is counted
        unchecked). Returns ((packet, point handed out [m]) of the packets holding a
        second emission, packets done with)."""
        with self.lock:
            n = min(LATE_CHECK_BATCH, len(self._waiting))
            items = [self._waiting.popleft() for _ in range(n)]
        found, clean = [], []
        groups: dict = {}
        for p, point in items:
            groups.setdefault((p.samples_v.shape, float(p.sample_rate_hz)), []).append(
                (p, point))
        for (_, fs), group in groups.items():
            pulse = pulse_at(fs)
            ps = [p for p, _ in group]
            if pulse is None:
                self._count("overlap_unchecked", len(ps))
                clean += ps
                continue
            single = SimpleNamespace(accepted=np.ones(len(ps), bool),
                                     point_m=np.array([pt for _, pt in group]))
            try:
                with np.errstate(all="ignore"):
                    mask = suspect_overlap(np.stack([p.samples_v for p in ps]), fs,
                                           [int(p.onset_index) for p in ps], single,
                                           geometry=geometry, pulse=pulse)
            except ValueError:
                self._count("overlap_unchecked", len(ps))
                clean += ps
                continue
            self._count("overlap_late_checked", len(ps))
            for (p, point), m in zip(group, np.asarray(mask, bool)):
                if m:
                    found.append((p, point))
                else:
                    clean.append(p)
        self._count("overlap_late_found", len(found))
        return found, clean

    def _count(self, key: str, n: int) -> None:
        if n:
            with self.lock:
                self.counts[key] += n
