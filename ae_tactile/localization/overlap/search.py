# SPDX-License-Identifier: Apache-2.0
"""The search for the emissions of a window: the matched-filter grid over the surface, the
analysis segments, the cyclic (RELAX) search of one to three emissions, and the quick
search as one compiled call.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import overlap_kernels as _kernels
from ae_tactile.localization.common import per_packet
from ae_tactile.localization.overlap.model import (
    LM_ITERATIONS,
    _compiled,
    _kernel_args,
    _lm,
    _max_rho,
    _Model,
    _positive,
    _residual,
    _sub,
)


def _surface_grid(geo: FingertipGeometry, spacing_m, max_polar_deg=80.0):
    """(G, 2) square grid of (s_x, s_y) over the cap polar <= max_polar_deg (cached; do
    not modify the array)."""
    key = (geo, float(spacing_m), float(max_polar_deg))
    grid = _GRID_CACHE.get(key)
    if grid is None:
        rmax = geo.radius_m * math.sin(math.radians(max_polar_deg))
        n = int(math.ceil(rmax / spacing_m))
        g = np.arange(-n, n + 1) * spacing_m
        gx, gy = np.meshgrid(g, g, indexing="ij")
        keep = np.hypot(gx, gy) <= rmax
        grid = np.stack([gx[keep], gy[keep]], axis=1)
        grid.setflags(write=False)
        if len(_GRID_CACHE) > 16:
            _GRID_CACHE.clear()
        _GRID_CACHE[key] = grid
    return grid


_GRID_CACHE: dict = {}


@dataclass(frozen=True)
class _GridTables:
    """What the grid search needs of a grid, a geometry and a pulse (cached per segment
    length): distances d (G, 4), direct gains R / d, travel times tt, integer relative
    delays rel (G, 4), ||phi||^2 per point, float32 copies, the conjugate spectrum of h."""

    d: np.ndarray
    gain: np.ndarray
    tt: np.ndarray
    rel: np.ndarray
    pad: int
    norm: np.ndarray
    gain32: np.ndarray
    norm32: np.ndarray
    nfft: int
    h_conj_spectrum: np.ndarray


def _grid_tables(model: _Model, grid, L) -> _GridTables:
    key = (model.geo, model.fs, model.pulse, L, grid.shape, grid.tobytes())
    t = _GRID_TAB_CACHE.get(key)
    if t is None:
        fs = model.fs
        nfft = sfft.next_fast_len(2 * L, real=True)
        d = model.geo._xy_distances(grid[:, 0], grid[:, 1])  # (G, 4)
        h = _template(model, d)
        gain = model.R / d
        tt = d / model.c
        rel = np.rint((tt - tt.min(axis=1, keepdims=True)) * fs).astype(np.int64)  # (G, 4)
        # ||phi||^2 for an arrival inside the segment: sum_k gain^2 sum h^2
        norm = (gain**2).sum(axis=1) * float((h * h).sum())
        t = _GridTables(
            d, gain, tt, rel, int(rel.max()) + 1, norm, gain.astype(np.float32),
            norm.astype(np.float32), nfft, np.conj(sfft.rfft(h, n=nfft)),
        )
        if len(_GRID_TAB_CACHE) > 64:
            _GRID_TAB_CACHE.clear()
        _GRID_TAB_CACHE[key] = t
    return t


_GRID_TAB_CACHE: dict = {}


def _template(model: _Model, d) -> np.ndarray:
    """The matched filter's pulse (L,): h(m dt), in a lossy medium through the loss of
    the grid's median direct path (``d`` (G, 4) [m]), since the shape the fits compare
    is the pulse after its path's loss; one path for all points (the correlation is one
    FFT per channel), the fit then follows each path's own loss."""
    h = model.tab.h_samples
    if not model.pulse.attenuation_db_per_m_at_1mhz > 0:
        return h
    path = np.full((1, 1), float(np.median(d)))
    one = _sub(model, np.array([0]))
    return one.pulses(one.start[:, None] / model.fs, path)[0][0, 0]


def _grid_step(fs: float) -> int:
    """Arrival samples the grid tries first: every second one at >= 5 MS/s (the matched
    filter is smooth: the band ends at 1 MHz <= fs / 5), else every one."""
    return 2 if fs >= 5e6 else 1


def _grid_search(model: _Model, r, grid, chunk=64, n_peaks=1, min_sep_s=0.8e-6):
    """Best (s_x, s_y, T) (K, 3) of one emission in residual r (K, 4, L): matched filter per
    channel (correlation with h), summed over channels along each grid point's travel
    times (integer samples), maximising |C|^2 / ||phi||^2. With ``n_peaks`` > 1 it returns
    (K, n_peaks, 3): the best, then the best points at the next peaks in time of the
    profile max_g |C|^2 / ||phi||^2 (>= ``min_sep_s`` from earlier ones)."""
    K, _, L = r.shape
    fs = model.fs
    gt = _grid_tables(model, grid, L)
    gain, tt, rel, pad, norm, gain32 = gt.gain, gt.tt, gt.rel, gt.pad, gt.norm, gt.gain32
    cp = np.zeros((K, 4, L + pad + 2), np.float32)
    if _compiled(model):  # the same correlation by the pulse's poles (no FFT)
        rf = np.ascontiguousarray(r, dtype=np.float64).reshape(K, 4 * L)
        for k in range(K):
            _kernels.matched_filter(rf[k], L, model.tab.half_z, model.tab.half_res, cp[k])
    else:
        nfft, H = gt.nfft, gt.h_conj_spectrum
        corr = sfft.irfft(sfft.rfft(r, n=nfft, axis=2) * H, n=nfft, axis=2)
        cp[:, :, :L] = corr[..., :L]  # arrival at n
    # every second arrival sample first (`_grid_step`), then the best point's neighbours
    step = _grid_step(fs)
    mm = np.arange(0, L, step)
    min_sep = max(1, int(round(min_sep_s * fs)))
    prof = np.zeros((K, mm.size))
    prof_g = np.zeros((K, mm.size), np.int64)
    if _compiled(model):
        p32 = np.empty(mm.size, np.float32)
        for k in range(K):
            _kernels.grid_profile(cp[k], gain32, rel, gt.norm32, step, p32, prof_g[k])
            prof[k] = p32
    else:
        idx = rel[:, :, None] + mm[None, None, :]  # (G, 4, L/2)
    for k0 in range(0, K if not _compiled(model) else 0, chunk):
        sl = slice(k0, min(K, k0 + chunk))
        c = np.zeros((sl.stop - sl.start, grid.shape[0], mm.size), np.float32)
        for ch in range(4):
            c += gain32[None, :, ch, None] * cp[sl, ch][:, idx[:, ch]]
        stat = (c * c) / norm[None, :, None].astype(np.float32)
        gi = np.argmax(stat, axis=1)  # (k, L/2)
        prof_g[sl] = gi
        prof[sl] = np.take_along_axis(stat, gi[:, None, :], axis=1)[:, 0]
    i = np.argmax(prof, axis=1)
    best_g = prof_g[np.arange(K), i]
    best_m = mm[i]
    if n_peaks > 1:
        extra = _further_peaks(model, grid, tt, prof, prof_g, mm, i, n_peaks, min_sep)
    rows = np.arange(K)
    cand = np.clip(best_m[:, None] + np.array([-1, 0, 1]), 0, L - 1)  # (K, 3)
    ix = rel[best_g][:, :, None] + cand[:, None, :]  # (K, 4, 3)
    cv = (gain[best_g][:, :, None] * cp[rows[:, None, None], np.arange(4)[None, :, None], ix]).sum(
        axis=1
    )
    st = cv * cv / norm[best_g][:, None]
    pick = np.argmax(st, axis=1)
    best_m = cand[rows, pick]
    best_val = st[rows, pick]
    s = grid[best_g]
    t_first = (model.start + best_m) / fs
    T = t_first - tt[best_g].min(axis=1)
    best = np.concatenate([s, T[:, None]], axis=1)
    if n_peaks > 1:
        return np.stack([best] + extra, axis=1), best_val
    return best, best_val


def _further_peaks(model: _Model, grid, tt, prof, prof_g, mm, i, n_peaks, min_sep):
    """(s_x, s_y, T) (K, 3) of each further peak of `_grid_search`'s time profile
    max_g stat(g, m) (``prof`` (K, len(mm)) with its grid points ``prof_g``), each >=
    ``min_sep`` samples from the earlier ones, after the best at ``i``."""
    K = prof.shape[0]
    fs = model.fs
    peaks = []
    pr = prof.copy()
    rows_ = np.arange(K)
    last = i
    for _ in range(n_peaks - 1):
        lo = np.searchsorted(mm, mm[last] - min_sep)
        hi = np.searchsorted(mm, mm[last] + min_sep, side="right")
        mask = (np.arange(mm.size)[None, :] >= lo[:, None]) & (
            np.arange(mm.size)[None, :] < hi[:, None]
        )
        pr[mask] = -np.inf
        last = np.argmax(pr, axis=1)
        g2 = prof_g[rows_, last]
        peaks.append(np.stack([grid[g2, 0], grid[g2, 1], mm[last].astype(float)], 1))
    extra = []
    for pk in peaks:
        gidx = np.argmin(
            np.abs(grid[:, None, 0] - pk[None, :, 0])
            + np.abs(grid[:, None, 1] - pk[None, :, 1]),
            axis=0,
        )
        T2 = (model.start + pk[:, 2]) / fs - tt[gidx].min(axis=1)
        extra.append(np.stack([pk[:, 0], pk[:, 1], T2], 1))
    return extra


@dataclass
class _Fit:
    theta: np.ndarray  # (K, J, 3)
    amp: np.ndarray  # (K, 2J)
    rss: np.ndarray  # (K,)
    gram: np.ndarray  # (K, 5J, 5J) Gram matrix of the Jacobian (Fisher x sigma^2)


def _analysis_s(geo, analysis_s) -> float:
    """Span of the fit after the onset (s): up to before the earliest emission's second
    wall echo, 4R/c - 2 sqrt(2) a / c - 0.3 us, unless given."""
    if analysis_s is not None:
        return analysis_s
    a = geo.element_offset_m
    return (4.0 * geo.radius_m - 2.0 * math.sqrt(2.0) * a) / geo.sound_speed_m_s - 0.3e-6


def _segments(prep, plan, geo, fs, analysis_s):
    m = prep.x.shape[2]
    start = np.clip(prep.onset - plan.pre, 0, m - 1)
    nominal = plan.pre + int(math.floor(_analysis_s(geo, analysis_s) * fs))
    length = max(int(np.max(np.minimum(m - start, nominal), initial=8)), 8)
    idx = start[:, None] + np.arange(length)[None, :]
    inside = idx < m  # samples past the window end are masked out of the fit
    seg = np.take_along_axis(prep.x, np.clip(idx, 0, m - 1)[:, None, :].repeat(4, axis=1), axis=2)
    seg = (seg - prep.pre_mean[..., None]) * inside[:, None, :]
    return seg, start, length, inside


def _search(
    model: _Model,
    seg,
    max_sources,
    grid,
    sigma2=None,
    add_threshold=None,
    search_limit=None,
    deferred=None,
):
    """RELAX search for 1..max_sources emissions. Returns the list of _Fit, one per J
    (packets that stop adding emissions keep their previous fit in later entries).

    With ``sigma2`` (K,), emission j + 1 is searched only where the j-emission residual is
    above ``search_limit`` (K,) x sigma^2 x dof (the data are not yet explained: a
    single-source packet costs one fit) and, for j >= 2, the j-th emission was significant
    (residual drop > ``add_threshold`` sigma^2). ``deferred`` (K,) bool: where given, a
    packet whose first joint fit still leaves more than noise is marked there and searched
    no further (the caller answers it later with the exhaustive search)."""
    K = seg.shape[0]
    y = seg.reshape(K, -1)
    cands, _ = _grid_search(model, seg, grid, n_peaks=3)
    theta, amp, rss, jac = _lm(model, y, cands[:, :1].copy())
    fits = [_Fit(theta, amp, rss, jac)]
    for j in range(2, max_sources + 1):
        prev = fits[-1]
        go = np.ones(K, bool)
        if sigma2 is not None:
            n_in = y.shape[1] if model.mask is None else model.mask.sum(axis=1)
            dof = np.maximum(n_in - 5 * (j - 1), 1)
            go = prev.rss > search_limit * sigma2 * dof
            if j > 2:
                go &= (fits[-2].rss - prev.rss) > add_threshold * sigma2
        if deferred is not None:
            go &= ~deferred
        ids = np.nonzero(go)[0]
        theta = np.concatenate([prev.theta, np.zeros((K, 1, 3))], axis=1)
        amp = np.concatenate([prev.amp, np.zeros((K, 2))], axis=1)
        rss = prev.rss.copy()
        jac = np.zeros((K, 5 * j, 5 * j))
        if ids.size:
            sub = _sub(model, ids)
            ys = y[ids]
            res = _residual(sub, ys, prev.theta[ids], prev.amp[ids])
            thn, _ = _grid_search(sub, res.reshape(len(ids), 4, -1), grid)
            start = np.concatenate([prev.theta[ids], thn[:, None, :]], axis=1)
            t1, a1, r1, j1 = _lm(sub, ys, start)
            # Other starting points, only where this fit leaves more than noise (a fit at
            # the noise level explains the data; the others guard against local optima).
            alt = np.arange(len(ids))
            if sigma2 is not None:
                n_in = y.shape[1] if sub.mask is None else sub.mask.sum(axis=1)
                dof = np.maximum(n_in - 5 * j, 1)
                alt = np.nonzero(r1 > search_limit[ids] * sigma2[ids] * dof)[0]
            if alt.size and deferred is not None:
                deferred[ids[alt]] = True
                alt = alt[:0]
            if alt.size:
                _alternatives(
                    _sub(sub, alt), ys[alt], j, cands[ids[alt]], grid, alt, t1, a1, r1, j1
                )
            # order emissions by emission time
            order = np.argsort(t1[..., 2], axis=1)
            t1 = np.take_along_axis(t1, order[..., None], axis=1)
            ao = np.stack([2 * order, 2 * order + 1], axis=2).reshape(len(ids), -1)
            a1 = np.take_along_axis(a1, ao, axis=1)
            jo = np.concatenate(
                [(3 * order[..., None] + np.arange(3)).reshape(len(ids), -1), 3 * j + ao], axis=1
            )
            j1 = np.take_along_axis(
                np.take_along_axis(j1, jo[:, None, :], axis=2), jo[:, :, None], axis=1
            )
            theta[ids], amp[ids], rss[ids], jac[ids] = t1, a1, r1, j1
        fits.append(_Fit(theta, amp, rss, jac))
    return fits


def _quick_search_compiled(model, ys, masks, max_sources, grid, sigma2, add_threshold,
                           search_limit, deferred):
    """`_search` with ``deferred`` by `overlap_kernels.quick_search`, one call per window
    (the same fits; the grid's further time peaks, which only the exhaustive search uses,
    are not computed). ys, masks (K, 4L)."""
    K, N = ys.shape
    L = N // 4
    gt = _grid_tables(model, grid, L)
    mm = np.arange(0, L, _grid_step(model.fs))
    J = max_sources
    theta = np.empty((K, J, J, 3))
    amp = np.empty((K, J, 2 * J))
    rss = np.empty((K, J))
    gram = np.empty((K, J, 5 * J, 5 * J))
    args = _kernel_args(model)
    for k in range(K):
        deferred[k] = _kernels.quick_search(
            ys[k],
            masks[k],
            float(model.start[k]),
            float(sigma2[k]),
            float(search_limit[k]),
            float(add_threshold),
            int(max_sources),
            *args,
            LM_ITERATIONS,
            _max_rho(model.geo),
            model.tab.half_z,
            model.tab.half_res,
            gt.gain32,
            gt.rel,
            gt.norm32,
            mm,
            gt.gain,
            gt.norm,
            gt.tt,
            grid,
            int(gt.pad),
            theta[k],
            amp[k],
            rss[k],
            gram[k],
        )
    return [
        _Fit(
            theta[:, j - 1, :j].copy(),
            amp[:, j - 1, : 2 * j].copy(),
            rss[:, j - 1].copy(),
            gram[:, j - 1, : 5 * j, : 5 * j].copy(),
        )
        for j in range(1, J + 1)
    ]


def _noise_sat_fs(noise_rms_v, saturated, full_scale_v, K):
    """The compiled preparation's per-window arguments: known noise sigma (NaN: measured,
    as for non-positive values in `common.prepare`), saturation flag (-1: unknown), full
    scale (NaN: unknown)."""
    if noise_rms_v is None:
        noise = np.full(K, np.nan)
    else:
        nr = per_packet("noise_rms_v", noise_rms_v, K)
        noise = np.where(np.isfinite(nr) & (nr > 0), nr, np.nan)
    sat = (
        np.full(K, -1, np.int64)
        if saturated is None
        else per_packet("saturated", saturated, K, dtype=bool).astype(np.int64)
    )
    fsv = np.nan if full_scale_v is None else _positive("full_scale_v", full_scale_v)
    return noise, sat, fsv


def _segments_compiled(preps, m, plan, geo, analysis_s):
    """`_segments` of windows prepared by `overlap_kernels.prepare_window` (list of its
    outputs): ys, masks (n, 4L), start (n,), L."""
    nominal = plan.pre + int(math.floor(_analysis_s(geo, analysis_s) * plan.fs))
    start = np.array([min(max(int(pr[3]) - plan.pre, 0), m - 1) for pr in preps], np.int64)
    L = max(int(np.max(np.minimum(m - start, nominal), initial=8)), 8)
    ys = np.empty((len(preps), 4 * L))
    masks = np.empty((len(preps), 4 * L))
    for i, pr in enumerate(preps):
        _kernels.segment(pr[0], int(start[i]), L, pr[1], ys[i], masks[i])
    return ys, masks, start, L


def _alternatives(sub, ys, j, cs, grid, rows, t1, a1, r1, j1) -> None:
    """Joint fits of j emissions from other starting points; where one ends with a smaller
    residual it replaces rows ``rows`` of (t1, a1, r1, j1) in place."""
    t1_, a1_, r1_, j1_ = t1[rows], a1[rows], r1[rows], j1[rows]

    def take(fit):
        t2, a2, r2, j2 = fit
        b = r2 < r1_
        t1_[b], a1_[b], r1_[b], j1_[b] = t2[b], a2[b], r2[b], j2[b]

    if j == 2:
        # pairs of the first search's peaks in time (two similar emissions a few us apart
        # make a spurious single-emission optimum between them)
        for q, p in ((0, 1), (0, 2), (1, 2)):
            take(_lm(sub, ys, cs[:, [q, p]].copy()))
    # RELAX: re-start each earlier emission from the data minus the others.
    for i in range(j - 1):
        keep = [q for q in range(j) if q != i]
        cols = np.concatenate([[2 * q, 2 * q + 1] for q in keep])
        res = _residual(sub, ys, np.ascontiguousarray(t1_[:, keep]), a1_[:, cols])
        thi, _ = _grid_search(sub, res.reshape(len(rows), 4, -1), grid)
        st = t1_.copy()
        st[:, i] = thi
        take(_lm(sub, ys, st))
    # Swapped points (same emission times): the local optimum of nearly simultaneous
    # emissions of similar strength.
    for q in range(j):
        for p in range(q + 1, j):
            st = t1_.copy()
            st[:, q, :2], st[:, p, :2] = t1_[:, p, :2], t1_[:, q, :2]
            take(_lm(sub, ys, st))
    t1[rows], a1[rows], r1[rows], j1[rows] = t1_, a1_, r1_, j1_
