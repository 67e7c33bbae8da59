# SPDX-License-Identifier: Apache-2.0
"""The release stage of `PacketDetector`: AIC onset refinement of the pending emissions,
their windows of the original samples, overlap flags and features, and the release of the
packets whose windows are complete (steps 6-8 of the detector's module docstring).
"""

from __future__ import annotations

import numpy as np

from .batch import PacketBatch
from .features import window_features_fixed
from .onset import aic_pick


class _ReleaseStage:
    """Mixin of `PacketDetector`: refines pending onsets and releases complete windows
    (it uses the detector's state; see `ae_tactile.dsp.detector`)."""

    def _raw_span(self) -> int:
        """First absolute index of the raw samples held (history + last piece)."""
        held = (
            self._raw_hist_prev.shape[1] + self._raw_last.shape[1]
            if self._raw_last is not None
            else self._raw_hist.shape[1]
        )
        return self._proc_end - held

    def _gather(self, idx: np.ndarray) -> np.ndarray:
        """Raw samples at absolute indices idx (K, L) -> (K, 4, L), from the history and
        the last piece without joining them."""
        last = self._raw_last
        if last is None:
            src = self._raw_hist
            out = src[:, idx - (self._proc_end - src.shape[1])]
        else:
            rel = idx - (self._proc_end - last.shape[1])
            if rel.min() >= 0:
                out = last[:, rel]
            else:
                hist = self._raw_hist_prev
                nl, nh = last.shape[1], hist.shape[1]
                out = np.where(
                    rel >= 0,
                    last[:, np.clip(rel, 0, nl - 1)],
                    hist[:, np.clip(rel + nh, 0, nh - 1)],
                )
        return np.ascontiguousarray(out.transpose(1, 0, 2))

    def _refine(self) -> None:
        """AIC onsets for the pending candidates whose search segment is complete."""
        sp = self.sp
        todo = [
            p
            for p in self._pending
            if p.onset is None and p.crossing + 1 + sp.aic_post <= self._proc_end
        ]
        if not todo:
            return
        ext_start = self._raw_span()
        starts = np.array([p.crossing + 1 - sp.aic_pre for p in todo], dtype=np.int64)
        ok = starts >= max(ext_start, self._origin)
        if not ok.all():
            for p, good in zip(todo, ok.tolist()):
                if not good:  # too close to the stream start: cannot refine
                    p.onset = -1
            todo = [p for p, good in zip(todo, ok.tolist()) if good]
            starts = starts[ok]
            if not todo:
                return
        seg = self._gather(starts[:, None] + self._aic_range)  # (K, 4, L)
        wts = np.stack([p.weights for p in todo])
        re = np.array([p.reonset for p in todo])
        if re.any():
            # inside a decaying packet the AIC works on the first difference, which keeps
            # the new emission's sharp onset and drops the slow tail of the previous one
            dseg = np.diff(seg, axis=-1, prepend=seg[..., :1])
            seg = np.where(re[:, None, None], dseg, seg)
        lo = np.array([p.aic_lo for p in todo], dtype=np.int64) - starts
        m, _ = aic_pick(seg, wts, margin=2, start=np.maximum(lo, 0) if (lo > 0).any() else None)
        for p, st, mm in zip(todo, starts.tolist(), m.tolist()):
            p.onset = st + mm

    def _release(self, final: bool) -> PacketBatch:
        """Refine what can be refined and publish the windows that are final."""
        taken = self._take_ready(final)
        if taken is None:
            return self._empty_batch
        cand, neigh = taken
        if not cand:
            return self._empty_batch
        cut = self._cut_windows(cand)
        if cut is None:
            return self._empty_batch
        cand, start, win = cut
        sp = self.sp
        k = len(cand)
        prev_id, next_id, clear = self._overlap_links(cand, neigh, sp.window, sp.posttrigger)
        overlap = (prev_id >= 0) | (next_id >= 0)
        feats = window_features_fixed(
            win,
            sp.pretrigger,
            noise_guard=sp.noise_guard,
            peak_window=sp.peak_window,
            polarity_window=sp.polarity_window,
            snr_window=sp.snr_window,
            sat_lo=self._sat_lo,
            sat_hi=self._sat_hi,
            var_floor=self._floor_var * 1e-2,
        )
        self.stats.packets += k
        self.stats.overlapping_packets += int(overlap.sum())
        self.stats.saturated_packets += int(feats["saturated"].sum())
        return PacketBatch(
            sample_rate_hz=self.sample_rate_hz,
            start_index=start,
            samples=win,
            onset_index=np.full(k, sp.pretrigger, np.int64),
            trigger_index=np.array([p.crossing for p in cand], np.int64) - start,
            overlap=overlap,
            overlap_prev_id=prev_id,
            overlap_next_id=next_id,
            clear_after=np.array(clear, np.int64),
            packet_id=np.array([p.pid for p in cand], np.int64),
            hit_id=np.array([p.hit_id for p in cand], np.int64),
            in_hit=np.array([p.in_hit for p in cand], bool),
            valid=np.ones(k, bool),
            **feats,
        )

    def _take_ready(self, final: bool):
        """Take the pending emissions whose windows are final out of the pending list.

        Returns None when nothing is ready, else (the ready ones whose windows lie inside
        the samples held, the (pid, onset) neighbours for the overlap flags); the ready
        ones cut by the stream start, a gap or the end are counted as truncated."""
        sp = self.sp
        if not self._pending:
            return None
        # earliest possible onset of each pending packet -> can anything be released?
        lower = min(
            p.onset if p.onset is not None else p.crossing + 1 - sp.aic_pre for p in self._pending
        )
        if not final and lower + sp.posttrigger + sp.release_lag > self._proc_end:
            return None
        self._refine()
        if final:
            for p in self._pending:
                if p.onset is None:
                    p.onset = -1
        known = [p for p in self._pending if p.onset is not None]
        ready = [
            p
            for p in known
            if p.onset < 0 or final or p.onset + sp.posttrigger + sp.release_lag <= self._proc_end
        ]
        if not ready:
            return None
        # neighbours for the overlap flags: recent released + all known pending
        neigh = self._recent + [(p.pid, p.onset) for p in known if p.onset >= 0]
        lo_ok = max(self._origin, self._raw_span())
        cand = []
        drop_trunc = 0
        for p in ready:
            if (
                p.onset < 0
                or p.onset - sp.pretrigger < lo_ok
                or p.onset + sp.posttrigger > self._proc_end
            ):
                drop_trunc += 1
            else:
                cand.append(p)
        ready_ids = {p.pid for p in ready}
        self._pending = [p for p in self._pending if p.pid not in ready_ids]
        horizon = self._proc_end - 4 * sp.window - sp.release_lag
        self._recent = [t for t in self._recent if t[1] > horizon]
        self._recent.extend((p.pid, p.onset) for p in ready if p.onset >= 0)
        self.stats.dropped_truncated += drop_trunc
        return cand, neigh

    def _cut_windows(self, cand: list):
        """Windows [onset - pre, onset + post) of the original samples; the ones touching
        invalid samples are dropped and counted.

        Returns None when none is left, else (kept emissions, start indices (K,),
        windows (K, 4, M))."""
        sp = self.sp
        onset = np.array([p.onset for p in cand], dtype=np.int64)
        start = onset - sp.pretrigger
        win = self._gather(start[:, None] + self._win_range)  # (K, 4, M)
        good = np.abs(win).max(axis=(1, 2)) <= self._invalid_level
        if self._invalid:
            end = start + sp.window
            for a, z in self._invalid:
                good &= ~((start < z) & (end > a))
        if not good.all():
            self.stats.dropped_invalid += int((~good).sum())
            gl = good.tolist()
            cand = [p for p, g in zip(cand, gl) if g]
            if not cand:
                return None
            start, win = start[good], win[good]
        return cand, start, win

    @staticmethod
    def _overlap_links(cand: list, neigh: list, m: int, post: int):
        """Overlap links of each released emission among its neighbours (pid, onset).

        Returns (previous overlapping packet id (K,), next one (K,), -1 when none; samples
        after the onset clear of the next onset, at most ``post``, list of K)."""
        k = len(cand)
        prev_id = [-1] * k
        next_id = [-1] * k
        clear = [post] * k
        for i, p in enumerate(cand):
            po, pp = p.onset, p.pid
            for pid, on in neigh:
                if pid == pp:
                    continue
                if abs(on - po) < m:
                    if pp > pid > prev_id[i]:
                        prev_id[i] = pid
                    if pid > pp and (next_id[i] < 0 or pid < next_id[i]):
                        next_id[i] = pid
                if po < on < po + clear[i]:
                    clear[i] = on - po
        return np.array(prev_id, np.int64), np.array(next_id, np.int64), clear
