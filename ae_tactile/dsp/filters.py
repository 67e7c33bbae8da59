# SPDX-License-Identifier: Apache-2.0
"""Streaming band-pass filter for the trigger path.

The detector band-passes the raw stream before it looks for packets:

    H(z) = HP_n(z) * LP_n(z),  Butterworth, order n each (default 2), as one SOS cascade

with the high-pass at ``highpass_hz`` (default 100 kHz, the paper's front-end corner: it
removes DC offsets and drift) and the low-pass at ``lowpass_hz`` (default 1.5 MHz, just
above the ~1 MHz emission band: it removes the out-of-band part of the white noise, about
5 dB of it at 10 MS/s). At low rates the low-pass corner is clipped to 0.36 fs (below
Nyquist, where a Butterworth corner is still well behaved), and dropped when that leaves
less than a factor 4 above the high-pass corner (fs below ~1.1 MS/s): the ADC's
anti-alias filter then limits the band.

The state (``zi``) is carried from call to call, so the output is bit-identical however
the stream is cut into chunks: scipy's ``sosfilt`` runs the same recursion on the same
numbers. At a (re)start the state is set to the steady state for a constant input equal
to the first sample, so a DC offset produces no start-up transient.
"""

from __future__ import annotations

import numpy as np
from scipy import signal

try:  # scipy's compiled kernel without the per-call argument handling of sosfilt
    from scipy.signal._sosfilt import _sosfilt as _sosfilt_kernel
except Exception:  # noqa: BLE001 - any scipy layout change: use the public API
    _sosfilt_kernel = None

#: The high-pass corner must lie below this fraction of fs.
LOWPASS_MAX_FRACTION = 0.4
#: The low-pass corner is clipped to this fraction of fs ...
LOWPASS_CLIP_FRACTION = 0.36
#: ... and dropped when that leaves less than this ratio to the high-pass corner.
LOWPASS_MIN_RATIO = 4.0


def design_bandpass_sos(
    sample_rate_hz: float, highpass_hz: float, lowpass_hz: float | None, order: int = 2
) -> np.ndarray:
    """SOS (n_sections, 6) of the trigger filter; see the module docstring.

    Raises ValueError when the high-pass corner is not below 0.4 fs, or when the
    low-pass corner is not above the high-pass corner.
    """
    fs = float(sample_rate_hz)
    hp = float(highpass_hz)
    if not (np.isfinite(fs) and fs > 0):
        raise ValueError(f"sample_rate_hz must be positive and finite, got {sample_rate_hz!r}")
    if not (np.isfinite(hp) and 0 < hp < LOWPASS_MAX_FRACTION * fs):
        raise ValueError(
            f"highpass_hz={highpass_hz!r} must be in (0, {LOWPASS_MAX_FRACTION} * "
            f"sample_rate_hz) = (0, {LOWPASS_MAX_FRACTION * fs:g}) Hz"
        )
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) or not 1 <= order <= 8:
        raise ValueError(f"filter order must be an integer in [1, 8], got {order!r}")
    sos = [signal.butter(int(order), hp, btype="highpass", fs=fs, output="sos")]
    if lowpass_hz is not None:
        lp = float(lowpass_hz)
        if not (np.isfinite(lp) and lp > hp):
            raise ValueError(
                f"lowpass_hz={lowpass_hz!r} must be finite and above highpass_hz={hp:g}"
            )
        lp = min(lp, LOWPASS_CLIP_FRACTION * fs)
        if lp >= LOWPASS_MIN_RATIO * hp:
            sos.append(signal.butter(int(order), lp, btype="lowpass", fs=fs, output="sos"))
    return np.ascontiguousarray(np.concatenate(sos, axis=0), dtype=np.float64)


def noise_power_gain(sos: np.ndarray, n: int = 1 << 16) -> float:
    """sum h[n]^2 of the filter's impulse response: output variance / input variance for
    white noise (so a full-band sigma maps to sigma * sqrt(gain) after the filter)."""
    imp = np.zeros(n)
    imp[0] = 1.0
    h = signal.sosfilt(sos, imp)
    return float(np.dot(h, h))


def diff_noise_ratio(sos: np.ndarray, n: int = 1 << 16) -> float:
    """var(y[n] - y[n-1]) / var(y) for white noise through the filter:
    sum (h[n] - h[n-1])^2 / sum h[n]^2 over its impulse response h."""
    imp = np.zeros(n)
    imp[0] = 1.0
    h = signal.sosfilt(sos, imp)
    dh = np.diff(np.concatenate([[0.0], h]))
    return float(np.dot(dh, dh) / np.dot(h, h))


def _kernel_works() -> bool:
    """True if scipy's private in-place kernel matches the public sosfilt bit for bit."""
    if _sosfilt_kernel is None:
        return False
    try:
        sos = signal.butter(2, [0.02, 0.3], btype="bandpass", output="sos")
        x = np.random.default_rng(0).normal(size=(2, 64))
        zi = np.random.default_rng(1).normal(size=(sos.shape[0], 2, 2))
        ref, zref = signal.sosfilt(sos, x, axis=-1, zi=zi)
        xx = x.copy()
        zz = np.ascontiguousarray(zi.transpose(1, 0, 2))
        _sosfilt_kernel(np.ascontiguousarray(sos), xx, zz)
        return bool(np.array_equal(xx, ref) and np.array_equal(zz.transpose(1, 0, 2), zref))
    except Exception:  # noqa: BLE001
        return False


_KERNEL_OK = _kernel_works()


class StreamingSOS:
    """An SOS cascade applied to a multichannel stream, state carried across calls.

    ``process(x)`` filters x (n_channels, n) float64 along the last axis. The first call
    after construction or ``reset()`` initialises the state to the steady state for a
    constant input equal to each channel's first sample. With ``inplace=True`` a
    C-contiguous float64 x is overwritten with the output (saves a copy).

    Uses scipy's compiled kernel directly when it is importable and agrees bit for bit
    with ``scipy.signal.sosfilt`` (checked once at import); otherwise ``sosfilt``.
    """

    def __init__(self, sos: np.ndarray, n_channels: int):
        self.sos = np.ascontiguousarray(sos, dtype=np.float64)
        self.n_channels = int(n_channels)
        # Steady-state state for a unit step through the whole cascade: (n_sections, 2).
        self._zi_unit = signal.sosfilt_zi(self.sos)
        self._zi: np.ndarray | None = None  # (n_channels, n_sections, 2)

    def reset(self) -> None:
        self._zi = None

    def state(self):
        """A copy of the filter state (None before the first sample)."""
        return None if self._zi is None else self._zi.copy()

    def set_state(self, zi) -> None:
        """Restore a state returned by `state`."""
        self._zi = None if zi is None else np.array(zi, dtype=np.float64, order="C", copy=True)

    def process(self, x: np.ndarray, inplace: bool = False) -> np.ndarray:
        if x.shape[-1] == 0:
            return np.zeros(x.shape, dtype=np.float64)
        if self._zi is None:
            self._zi = np.ascontiguousarray(
                self._zi_unit[None, :, :] * x[:, 0, None, None], dtype=np.float64
            )
        if _KERNEL_OK:
            if not (
                inplace and x.dtype == np.float64 and x.flags.c_contiguous and x.flags.writeable
            ):
                x = np.array(x, dtype=np.float64, order="C")
            _sosfilt_kernel(self.sos, x, self._zi)
            return x
        y, zi = signal.sosfilt(self.sos, x, axis=-1, zi=self._zi.transpose(1, 0, 2))
        self._zi = np.ascontiguousarray(zi.transpose(1, 0, 2))
        return y
