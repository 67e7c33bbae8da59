# SPDX-License-Identifier: Apache-2.0
"""Noise-floor tracking on the band-passed stream, per channel, in fixed blocks.

The stream is cut into blocks of B samples on the absolute sample-index grid
(block j covers indices [j B, (j + 1) B)). For each complete block and channel k:

    ms_jk  = mean of y_k^2 over the block          (y: band-passed signal, zero mean)
    pk_jk  = max  of y_k^2 over the block

A block is *bursty* (it holds a hit) when pk_jk > c^2 ms_jk on any channel (c = 6 by
default: for Gaussian noise, max of B = 1000 squared samples exceeds 36 times their
mean with probability ~2e-6, while any packet that crosses the trigger threshold pushes
the ratio far above it). A block is *missing* when it holds invalid input samples, lies
before the filter has settled after a (re)start, or is incomplete.

The noise variance used for block j is the median over the M blocks before j (default
M = 16) of ms, taken over the clean (not bursty, not missing) blocks when at least
``min_blocks`` of them are available, otherwise over all non-missing blocks (so a
persistent rise of the noise is followed instead of being rejected forever), and
undefined (the detector is blind) when fewer than ``min_blocks`` blocks are available.
The median makes the estimate robust to the few blocks that hold a weak packet too
small to be flagged bursty, and it smooths: its relative spread is about
1.25 / sqrt(M n_eff) in variance (n_eff: independent samples per block).

Everything is vectorized over the blocks of a batch: the estimate for block j depends
only on blocks before j, and only on their statistics (not on the trigger), so a
batch of any number of blocks is processed at once and the result does not depend on
how the stream was cut.
"""
from __future__ import annotations

import numpy as np


def nan_median_last(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median along the last axis ignoring NaN, and the number of non-NaN values.

    Where all values are NaN the median is NaN (no warning). Deterministic: sorts
    (NaN last) and averages the two middle elements.
    """
    s = np.sort(a, axis=-1)
    count = a.shape[-1] - np.count_nonzero(np.isnan(a), axis=-1)
    lo = np.maximum((count - 1) // 2, 0)
    hi = count // 2
    flat = s.reshape(-1, s.shape[-1])
    rows = np.arange(flat.shape[0])
    med = 0.5 * (flat[rows, lo.ravel()] + flat[rows, np.minimum(hi, s.shape[-1] - 1).ravel()])
    med = med.reshape(count.shape)
    return np.where(count > 0, med, np.nan), count


def block_stats(y: np.ndarray, block_len: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(y^2, ms, pk) for y (C, nb * B): y^2 reshaped (C, nb, B), mean and max per block (C, nb)."""
    c, n = y.shape
    nb = n // block_len
    y2 = (y * y).reshape(c, nb, block_len)
    return y2, y2.mean(axis=-1), y2.max(axis=-1)


class BlockNoiseTracker:
    """Median-of-recent-blocks noise variance per channel (see the module docstring).

    The median is re-evaluated at *epoch* starts only: every ``epoch_blocks`` blocks on
    the absolute block grid (block index divisible by epoch_blocks), and at every block
    while the estimate is still undefined (warm-up). Between epoch starts the variance is
    constant. This keeps the cost per call to a few numpy operations; the estimate lags
    the noise by at most epoch_blocks + history_blocks blocks (3.2 ms by default).
    """

    def __init__(self, n_channels: int, history_blocks: int = 16, min_blocks: int = 2,
                 burst_ratio: float = 6.0, floor_var: float = 0.0, epoch_blocks: int = 16):
        if history_blocks < 1 or min_blocks < 1 or min_blocks > history_blocks:
            raise ValueError("need 1 <= min_blocks <= history_blocks")
        if not burst_ratio > 1:
            raise ValueError("burst_ratio must be > 1")
        if epoch_blocks < 1:
            raise ValueError("epoch_blocks must be >= 1")
        self.n_channels = int(n_channels)
        self.history_blocks = int(history_blocks)
        self.min_blocks = int(min_blocks)
        self.burst_ratio2 = float(burst_ratio) ** 2
        self.floor_var = float(floor_var)
        self.epoch_blocks = int(epoch_blocks)
        self.reset()

    def reset(self) -> None:
        #: [all; clean] block means of the last M blocks, NaN = missing / excluded
        self._hist = np.full((2, self.n_channels, self.history_blocks), np.nan)
        self._var = np.full(self.n_channels, np.nan)

    @property
    def variance(self) -> np.ndarray:
        """Variance in use for the next block (C,), NaN while blind."""
        return self._var.copy()

    def _estimate(self, hist: np.ndarray) -> np.ndarray:
        med, cnt = nan_median_last(hist)
        var = np.where(cnt[1] >= self.min_blocks, med[1],
                       np.where(cnt[0] >= self.min_blocks, med[0], np.nan))
        return np.maximum(var, self.floor_var)       # NaN stays NaN

    def update(self, ms: np.ndarray, pk: np.ndarray, missing: np.ndarray, first_block: int
               ) -> tuple[np.ndarray, np.ndarray]:
        """Push the statistics of nb complete blocks with absolute indices first_block ...

        ms, pk: (C, nb) block mean and max of y^2; missing: (nb,) bool.
        Returns (var (C, nb + 1), bursty (nb,)): column j is the variance to use for the
        j-th pushed block, the last column the one for the block after them.
        """
        nb = ms.shape[1]
        m = self.history_blocks
        e = self.epoch_blocks
        with np.errstate(invalid="ignore"):
            bursty = (pk > self.burst_ratio2 * ms).any(axis=0) & ~missing
        new = np.where(np.stack([missing, missing | bursty])[:, None, :], np.nan, ms[None])
        ext = np.concatenate([self._hist, new], axis=2)
        out = np.empty((self.n_channels, nb + 1))
        var = self._var
        j = 0                       # var for block first_block + j: from ext[..., j:j + m]
        while j <= nb:
            blind = bool(np.isnan(var[0]))
            if blind:
                var = self._estimate(ext[:, :, j:j + m])
                out[:, j] = var
                j += 1
                continue
            # next epoch start at or after block first_block + j
            k = j + (-(first_block + j)) % e
            if k > j:
                kk = min(k, nb + 1)
                out[:, j:kk] = var[:, None]
                j = kk
                continue
            var = self._estimate(ext[:, :, j:j + m])
            out[:, j] = var
            j += 1
        self._hist = ext[:, :, nb:]
        self._var = var
        return out, bursty
