# SPDX-License-Identifier: Apache-2.0
"""The trigger stage of `PacketDetector`: decimation, the band-pass trigger path, the noise
floor, the envelope, hysteresis, re-onsets, hits, lockout and echoes, and the invalid
sample bookkeeping (steps 2-5 of the detector's module docstring).
"""

from __future__ import annotations

import numpy as np

from ..geometry import N_CHANNELS


class _Pending:
    __slots__ = ("pid", "crossing", "hit_id", "in_hit", "weights", "aic_lo", "reonset", "onset")

    def __init__(self, pid, crossing, hit_id, in_hit, weights, aic_lo, reonset):
        self.pid = pid
        self.crossing = crossing  # input-sample index of the trigger
        self.hit_id = hit_id
        self.in_hit = in_hit
        self.weights = weights  # 1 / sigma_k^2 for the AIC
        self.aic_lo = aic_lo  # the AIC may not pick before this input index
        self.reonset = reonset  # found by a channel re-onset inside a packet
        self.onset = None


class _TriggerStage:
    """Mixin of `PacketDetector`: turns the filtered trigger path into pending emissions
    (it uses the detector's state; see `ae_tactile.dsp.detector`)."""

    def _decimate(self, xf: np.ndarray):
        """Group sums of d samples (float64, in sample order) for the groups completed by
        xf, continuing the incomplete group held in self._lead.

        Returns (xd (4, m), samples skipped at the stream start, new lead (4, r < d))."""
        d = self.sp.decim
        n = xf.shape[1]
        skip = min(self._skip, n)
        if d == 1:
            return xf[:, skip:].copy(), skip, self._lead
        lead = self._lead
        r = lead.shape[1]
        avail = n - skip
        if r + avail < d:
            return np.zeros((N_CHANNELS, 0)), skip, np.concatenate([lead, xf[:, skip:]], axis=1)
        parts = []
        pos = skip
        if r:
            g = lead[:, 0]
            for j in range(1, r):
                g = g + lead[:, j]
            for j in range(d - r):
                g = g + xf[:, pos + j]
            parts.append(g[:, None])
            pos += d - r
        m = (n - pos) // d
        if m:
            body = xf[:, pos : pos + m * d]
            s = body[:, 0::d] + body[:, 1::d]
            for j in range(2, d):
                s += body[:, j::d]
            parts.append(s)
        pos += m * d
        xd = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1)
        if not xd.flags.c_contiguous:
            xd = np.ascontiguousarray(xd)
        return xd, skip, xf[:, pos:].copy()

    def _filter_phase(self, xd: np.ndarray):
        """Band-pass xd (4, m) and square it into whole blocks; block statistics.

        Returns (y, r (4, nbs, B) y^2 with the current block's earlier part in front and
        zeros after the end, ms, pk (4, ncomp) of the completed blocks, finite flag)."""
        b = self.sp.block
        m = xd.shape[1]
        y = self._filter.process(xd, inplace=True)
        p = self._blk_y2.shape[1]  # samples of the current block seen before
        total = p + m
        nbs = -(-total // b)
        ncomp = total // b
        y2pad = np.empty((N_CHANNELS, nbs * b))
        if p:
            y2pad[:, :p] = self._blk_y2
        np.multiply(y, y, out=y2pad[:, p:total])
        if total < nbs * b:
            y2pad[:, total:] = 0.0
        r = y2pad.reshape(N_CHANNELS, nbs, b)
        ms = r[:, :ncomp].mean(axis=-1)
        pk = r[:, :ncomp].max(axis=-1)
        lim = self._invalid_y2
        finite = bool(pk.max() <= lim) if ncomp else True  # False for NaN, inf, absurd
        if finite and total > ncomp * b:
            finite = bool(r[:, ncomp].max() <= lim)
        return y, r, ms, pk, p, finite

    def _trigger_path(self, phase, u0: int) -> None:
        """Noise floor, envelope and trigger on the filtered trigger-path samples (absolute
        trigger indices u0 ..)."""
        sp = self.sp
        b = sp.block
        y, r, ms, pk, p, _ = phase
        m = y.shape[1]
        blk0 = u0 - p  # first trigger index of the first block
        total = p + m
        nbs = r.shape[1]
        ncomp = ms.shape[1]
        if ncomp:
            starts = blk0 + b * np.arange(ncomp)
            missing = starts < self._origin_u + sp.settle
            if self._invalid:
                missing |= self._blocks_touching_invalid(starts, b)
            var_all, _ = self._tracker.update(ms, pk, missing, blk0 // b)
            var = var_all if nbs > ncomp else var_all[:, :ncomp]
            self._blk_var = var_all[:, -1].copy()
        else:
            var = self._blk_var[:, None]
        self._blk_y2 = r.reshape(N_CHANNELS, -1)[:, ncomp * b : total].copy()
        blind = np.isnan(var[0])
        if blind.any():
            nb_blind = int(blind.sum())
            self.stats.blind_samples += sp.decim * (
                nb_blind * b - (p if blind[0] else 0) - ((nbs * b - total) if blind[-1] else 0)
            )
            w = np.where(np.isnan(var), 0.0, 0.25 / np.where(np.isnan(var), 1.0, var))
        else:
            w = 0.25 / var
        e2 = np.einsum("kbn,kb->bn", r, w).reshape(-1)[p:total]
        if self._invalid:
            self._zero_invalid(e2, u0)
        self._trigger(e2, y, u0, w, blk0)
        lh = sp.onset_window + 1
        if m >= lh:
            self._y_hist = y[:, m - lh :].copy()
        else:
            self._y_hist = np.concatenate([self._y_hist, y], axis=1)[:, -lh:]

    def _invalid_u(self):
        """Invalid ranges in trigger-path indices: groups touching an invalid sample."""
        d = self.sp.decim
        return [(s // d, -(-e // d)) for s, e in self._invalid]

    def _blocks_touching_invalid(self, starts: np.ndarray, b: int) -> np.ndarray:
        bad = np.zeros(starts.shape, bool)
        for s, e in self._invalid_u():
            bad |= (starts < e) & (starts + b > s)
        return bad

    def _zero_invalid(self, e2: np.ndarray, u0: int) -> None:
        n = e2.shape[0]
        for s, e in self._invalid_u():
            a, z = max(s - u0, 0), min(e - u0, n)
            if a < z:
                e2[a:z] = 0.0

    def _prune_invalid(self) -> None:
        """Forget invalid ranges no window or trigger block can touch any more."""
        sp = self.sp
        keep_from = self._proc_end - sp.history - sp.window - sp.block_full
        for p in self._pending:
            lo = (p.onset if p.onset is not None else p.crossing + 1 - sp.aic_pre) - sp.pretrigger
            keep_from = min(keep_from, lo)
        self._invalid = [(s, e) for s, e in self._invalid if e > keep_from]

    def _trigger(self, e2: np.ndarray, y: np.ndarray, u0: int, w: np.ndarray, blk0: int) -> None:
        """Schmitt trigger, per-channel re-onsets and AE hit rules on e2 (trigger indices
        from u0); y (4, m) is the band-passed trigger-path signal."""
        sp = self.sp
        act = np.flatnonzero(e2 >= self._koff2)
        if act.size == 0:
            return
        a_abs = act + u0
        on_pos = np.flatnonzero(e2[act] >= self._kon2)
        prev = self._last_active
        gaps = np.empty_like(a_abs)
        gaps[0] = (1 << 40) if prev is None else a_abs[0] - prev
        np.subtract(a_abs[1:], a_abs[:-1], out=gaps[1:])
        seg_start = gaps > sp.hold
        clu_gid = np.cumsum(gaps > sp.hdt)
        clu_gid += self._cluster
        events = []  # (position in act, channel or -1 for a rising edge)
        if on_pos.size:
            seg_id = np.cumsum(seg_start)
            sid = seg_id[on_pos]
            first = np.empty(sid.shape, bool)
            first[0] = True
            np.not_equal(sid[1:], sid[:-1], out=first[1:])
            rising = on_pos[first]
            if self._seg_triggered and not seg_start[0] and sid[0] == 0:
                rising = rising[1:]
            last_sid = int(seg_id[-1])
            self._seg_triggered = bool(
                sid[-1] == last_sid or (last_sid == 0 and self._seg_triggered)
            )
            events.extend((p_, -1) for p_ in rising.tolist())
        elif seg_start.any():
            self._seg_triggered = False
        events.extend(self._channel_onsets(act, a_abs, y, w, blk0))
        if events:
            events.sort()
            self._events(events, a_abs, clu_gid, w, blk0)
        self._last_active = int(a_abs[-1])
        self._cluster = int(clu_gid[-1])
        if self._hit_cluster is not None and self._hit_cluster >= int(clu_gid[0]):
            sel = np.flatnonzero(clu_gid == self._hit_cluster)
            if sel.size:
                self._hit_cluster_last = int(a_abs[sel[-1]])

    def _channel_onsets(self, act, a_abs, y, w, blk0) -> list:
        """Channel onsets on the active samples: [(position in act, channel)].

        z_k[n] = (y_k[n] - y_k[n-1])^2 / sigma_dk^2 (first difference of the band-passed
        signal, in its own noise units) reaches channel_onset_sigma^2 and jump_ratio^2
        times max_{l=1..L} z_k[n-l] g^l (the decayed maximum of the preceding
        onset_window); the first sample of each run is the onset.
        """
        sp = self.sp
        lh = sp.onset_window + 1
        # squared first differences over the span the active samples and their windows need
        lo = int(act[0]) - lh  # may reach into the history
        hi = int(act[-1]) + 1
        if lo >= 0:
            ys = y[:, lo:hi]
        else:
            ys = np.concatenate([self._y_hist[:, lh + lo :], y[:, :hi]], axis=1)
        d = ys[:, 1:] - ys[:, :-1]  # d[j] = y[lo + j + 1] - y[lo + j]
        d *= d
        q = act - (lo + 1)  # d[q] is (y[n] - y[n-1])^2
        # absolute level first (cheap, prunes most samples), then the decayed reference
        wd = w[:, (a_abs - blk0) // sp.block] * self._wd_scale  # 1 / sigma_dk^2, (4, na)
        cur = d[:, q]
        kk, pp = np.nonzero(cur * wd >= self._chk2)
        if kk.size == 0:
            return []
        qq = q[pp]
        ref = (d[kk[:, None], qq[:, None] - self._onset_offs] * self._onset_gpow).max(axis=-1)
        ok = cur[kk, pp] >= self._jump2 * ref
        if not ok.any():
            return []
        kk, pp = kk[ok], pp[ok]
        out = []
        tt = a_abs[pp].tolist()
        last = list(self._ch_last_cond)
        for k, p_, t in zip(kk.tolist(), pp.tolist(), tt):  # channel-major, time order
            lc = last[k]
            if lc is None or t - lc != 1:
                out.append((p_, k))
            last[k] = t
        self._ch_last_cond = last
        return out

    def _events(self, events, a_abs, clu_gid, w, blk0) -> None:
        """Turn rising edges and channel onsets (time order) into emissions.

        A rising edge is a candidate when it is not inside the running hit (its cluster
        of active samples). A channel onset is a candidate (a re-onset: a new emission
        inside a running packet) when the same channel already had an onset in the same
        hit at least channel_refractory earlier, and no emission was accepted within
        channel_spread before it (then it is that emission's late channel).
        Candidates then go through min_separation, the echo rule and the AE hit rules.
        """
        sp = self.sp
        d = sp.decim
        for p_, k in events:
            c = int(a_abs[p_])
            g = int(clu_gid[p_])
            if k >= 0:
                is_re = (
                    self._ch_last_cluster[k] == g
                    and c - self._ch_last_event[k] >= sp.channel_refractory
                )
                if self._ch_last_cluster[k] == g and not is_re:
                    continue  # same burst as before
                self._ch_last_event[k] = c
                self._ch_last_cluster[k] = g
                if not is_re or c <= self._assign_until:
                    continue
            elif g == self._hit_cluster:
                # a threshold re-crossing inside the running hit is the packet's own tail
                # unless a channel onset says otherwise (handled above)
                continue
            if self._last_cand is not None and c - self._last_cand < sp.min_separation:
                continue
            if sp.echo_delay and self._is_echo(c):
                self.stats.echoes += 1
                self._assign_until = c + sp.channel_spread  # its late channels too
                continue
            if g == self._hit_cluster:
                in_hit = True
                self.stats.in_hit_emissions += 1
            else:
                if self._hit_cluster is not None:
                    sel = np.flatnonzero(clu_gid == self._hit_cluster)
                    hl = int(a_abs[sel[-1]]) if sel.size else int(self._hit_cluster_last)
                    if c < hl + sp.hdt + sp.hlt:
                        self.stats.locked_out += 1
                        continue
                in_hit = False
                self.stats.hits += 1
                self._hit_id += 1
                self._hit_cluster = g
            # the previous emission's channels have all arrived by its crossing + spread:
            # the AIC must not pick them
            aic_lo = (
                -1
                if self._last_cand is None
                else (self._last_cand + sp.channel_spread) * d + d - 1
            )
            if k >= 0:
                # a re-onset is timed by the channel's own onset: search close to it (the
                # decaying packet before it would pull the AIC early)
                aic_lo = max(aic_lo, c * d + d - sp.reonset_aic_pre)
            self._last_cand = c
            self._assign_until = c + sp.channel_spread
            if sp.echo_delay:
                self._accepted_u.append(c)
            wc = 4.0 * w[:, (c - blk0) // sp.block]  # 1 / sigma_k^2 (0 if blind)
            # crossing in input samples: the last sample of the trigger group
            self._pending.append(
                _Pending(
                    self._next_id,
                    c * d + d - 1,
                    self._hit_id,
                    in_hit,
                    np.where(wc > 0, wc, 1.0),
                    aic_lo,
                    k >= 0,
                )
            )
            self._next_id += 1

    def _is_echo(self, c: int) -> bool:
        """c lies in [k D - tol, k D + spread + tol] after an accepted crossing (D: echo
        delay, k = 1 .. echo_orders; the echo's first element can be as late as the
        direct wave's last one, hence the spread)."""
        sp = self.sp
        dly, tol = sp.echo_delay, sp.echo_tolerance
        span = self.config.echo_orders * dly + sp.channel_spread + tol
        self._accepted_u = [a for a in self._accepted_u if c - a <= span]
        for a in self._accepted_u:
            dt = c - a
            for k in range(1, self.config.echo_orders + 1):
                if k * dly - tol <= dt <= k * dly + sp.channel_spread + tol:
                    return True
        return False
