# SPDX-License-Identifier: Apache-2.0
"""What an acoustic packet looks like on THIS device, learnt from its own touches: the
interference screen's model of an acoustic packet (`ae_tactile.dsp.interference`).

The screen tells common-mode interference from a touch at the apex by what only an
acoustic packet has: its spectrum inside the front end's band (little energy at DC, little
above the anti-alias corner) and its waveform, the front end's response to the emission.
Both depend on the device (front-end filters, emission decay, the body's loss), and the
nominal front end's model rejects every apex touch of a device whose front end differs.
Every accepted touch away from the apex is an acoustic packet of this device measured
through its own front end, on four channels (interference is never there: its zero delays
put it at the apex). `AcousticLearner` keeps, per sample rate:

  waveforms  each channel's direct wave from one sample before its arrival (the onset
             plus the localized delay) to the first wall echo (the geometry's echo-free
             duration), baseline removed, unit norm: the templates of the shape test
             (their sub-sample phases and path lengths vary from touch to touch, as an
             apex touch's may);
  low, high  each channel's share of energy at DC and its high-frequency index over
             the analysis window from its arrival (the statistics of the spectrum tests,
             noise removed): the screen's limits become LEARN_MARGIN times the largest
             the device's own touches gave, never below the nominal limits.

Only channels whose direct wave is at least ECHO_LEARN_SNR above the noise in the echo-free
span are kept (a noisy template would fit noise). The model is used once LEARN_MIN
waveforms are held at the packet's rate; until then the nominal front end's.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from ae_tactile.geometry import resolve_front_end_lowpass

#: waveforms (channels) kept per sample rate: the most recent (a device that changes,
#: a new body, is followed)
LEARN_KEEP = 64
#: waveforms needed before the learnt model replaces the nominal one (4 touches)
LEARN_MIN = 16
#: the spectrum tests' limits: this many times the largest statistic of the device's
#: touches (an apex touch's common mode averages four channels: its noise is lower)
LEARN_MARGIN = 1.5
#: the nominal front end's templates describe the device while they leave at most this
#: share of its touches' waveforms unexplained [1] (half the mismatch the shape test
#: allows an acoustic packet, 1 - SHAPE_MIN)
NOMINAL_FIT_MAX = 0.03
#: a channel's direct wave must exceed the noise's energy in its span this many times
LEARN_SNR = 100.0


def channel_arrivals(points_m, onset_index, sample_rate_hz, geometry) -> np.ndarray:
    """Each channel's arrival sample (K, 4) float (NaN where the point is not finite):
    the onset (the first arrival, sample index) plus the delay of the element's path
    over the nearest element's for the localized ``points_m`` (K, 3) [m]."""
    pts = np.asarray(points_m, dtype=float).reshape(-1, 3)
    on = np.asarray(onset_index, dtype=float).reshape(-1)
    d = np.linalg.norm(pts[:, None, :] - geometry.element_positions_m[None], axis=2)
    return on[:, None] + (d - d.min(axis=1, keepdims=True)) / geometry.sound_speed_m_s * float(
        sample_rate_hz)


def spectrum_stats(x, nv, f_top_hz, sample_rate_hz):
    """The spectrum tests' statistics of signals ``x`` (N, W) with noise variance ``nv``
    per sample (scalar or (N,)) [V^2]: (low (N,): share of energy at DC, high (N,): energy
    of the first difference over a tone's at ``f_top_hz``), noise removed, as
    `ae_tactile.dsp.interference.common_mode_interference` computes them."""
    x = np.asarray(x, dtype=float)
    w = x.shape[1]
    nv = np.asarray(nv, dtype=float).reshape(-1) if np.ndim(nv) else float(nv)
    e = np.einsum("nw,nw->n", x, x) - w * nv
    mean = x.sum(axis=1) / w
    tiny = 1e-30
    low = np.maximum((mean * mean * w - nv) / np.maximum(e, tiny), 0.0)
    d = np.diff(x, axis=1)
    band = 2.0 * (1.0 - math.cos(2.0 * math.pi * f_top_hz / float(sample_rate_hz)))
    e_d = np.einsum("nw,nw->n", d, d) - (w - 1) * 2.0 * nv
    high = np.maximum(e_d / np.maximum(e * band, tiny), 0.0)
    return low, high


class AcousticLearner:
    """The device's acoustic packets (the module docstring): `add` accepted touches away
    from the apex; `templates`, `low_max`, `high_max` give the screen the device's own
    model once `ready`.

    Parameters
    ----------
    keep : int
        Waveforms kept per sample rate.
    """

    def __init__(self, keep: int = LEARN_KEEP):
        self.keep = int(keep)
        self._waves: dict[float, deque] = {}
        self._low: dict[float, deque] = {}
        self._high: dict[float, deque] = {}
        self._cache: dict[tuple, np.ndarray] = {}
        self._fresh = 0  # waveforms learnt since the cache was built
        #: channel waveforms accepted so far (all rates)
        self.n_learnt = 0

    def reset(self) -> None:
        """Forget everything learnt (another body, or a reset of the device's model)."""
        self.__init__(self.keep)

    def ready(self, sample_rate_hz: float) -> bool:
        """Whether the learnt model is used at this rate (>= LEARN_MIN waveforms)."""
        return len(self._waves.get(float(sample_rate_hz), ())) >= LEARN_MIN

    def span(self, sample_rate_hz: float) -> int:
        """Samples of the learnt waveforms at this rate (0: none)."""
        w = self._waves.get(float(sample_rate_hz))
        return len(w[0]) if w else 0

    def add(self, windows, sample_rate_hz, onset_index, points_m, geometry, *,
            window_s: float = 20e-6, f_top_hz: float | None = None) -> int:
        """Learn from accepted packets away from the apex.

        Parameters
        ----------
        windows : array_like, (K, 4, M)
            The packets [V].
        sample_rate_hz : float
            Their rate [Hz].
        onset_index : array_like of int, (K,)
            Their onsets.
        points_m : array_like, (K, 3)
            Where they were localized [m].
        geometry : FingertipGeometry
            The body (element positions, sound speed, echo-free duration).
        window_s : float
            The spectrum tests' analysis length [s].
        f_top_hz : float, optional
            The spectrum tests' top frequency [Hz] (default: theirs, the nominal front
            end's low-pass corner at this rate, at most the Nyquist frequency).

        Returns
        -------
        int
            Channel waveforms learnt.
        """
        x = np.asarray(windows, dtype=float)
        fs = float(sample_rate_hz)
        if x.ndim != 3 or x.shape[1] != 4 or x.shape[0] == 0:
            return 0
        k, _, m = x.shape
        on = np.asarray(onset_index, dtype=np.int64).reshape(-1)
        arr = channel_arrivals(points_m, on, fs, geometry)
        n_span = int(geometry.echo_free_duration_s * fs)  # one before + echo-free - 1
        w = max(4, int(round(window_s * fs)))
        npre = int(on.min()) - 2
        if n_span < 8 or npre < 8 or not np.isfinite(arr).all():
            return 0
        pre = x[:, :, :npre]
        base = pre.mean(axis=2, keepdims=True)
        nv = pre.var(axis=2)  # (K, 4)
        st = np.rint(arr).astype(np.int64) - 1
        ok = (st >= npre) & (st + max(n_span, w) <= m)
        rows, chans = np.nonzero(ok)
        if rows.size == 0:
            return 0
        seg = x[rows, chans][:, None, :] - base[rows, chans][:, :, None]
        seg = seg[:, 0, :]
        idx = st[rows, chans][:, None]
        direct = np.take_along_axis(seg, idx + np.arange(n_span)[None, :], axis=1)
        e = np.einsum("nw,nw->n", direct, direct)
        good = e > LEARN_SNR * n_span * nv[rows, chans]
        if not good.any():
            return 0
        anal = np.take_along_axis(seg, idx + np.arange(w)[None, :], axis=1)[good]
        if f_top_hz is None:
            lp, _ = resolve_front_end_lowpass(fs, "auto", "auto")
            f_top_hz = 0.5 * fs if lp is None else min(float(lp), 0.5 * fs)
        low, high = spectrum_stats(anal, nv[rows, chans][good], f_top_hz, fs)
        waves = direct[good] / np.sqrt(e[good])[:, None]
        filling = False
        for name, new in (("_waves", list(waves)), ("_low", low), ("_high", high)):
            store = getattr(self, name).setdefault(fs, deque(maxlen=self.keep))
            if name == "_waves" and store and len(store[0]) != n_span:
                store.clear()  # another body: another echo-free span
            filling |= len(store) < self.keep
            store.extend(new)
        self._fresh += int(good.sum())
        # templates, limits and the nominal fit are built anew while the model fills, then
        # once its waveforms have all been replaced (a rebuild costs a screened packet
        # hundreds of us; a device drifts over minutes)
        if filling or self._fresh >= self.keep:
            self._cache, self._fresh = {}, 0
        self.n_learnt += int(good.sum())
        return int(good.sum())

    def templates(self, sample_rate_hz: float, n_samples: int, n_lags: int) -> np.ndarray:
        """The shape test's templates from the learnt waveforms, (n_lags * J, n_samples):
        for each lag l < n_lags each waveform's first n_samples - l samples behind l zeros,
        unit norm (n_samples <= `span`)."""
        fs = float(sample_rate_hz)
        key = (fs, int(n_samples), int(n_lags))
        out = self._cache.get(key)
        if out is None:
            waves = np.array(self._waves[fs])
            rows = []
            for lag in range(int(n_lags)):
                t = waves[:, : int(n_samples) - lag]
                t = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-30)
                rows.append(np.pad(t, ((0, 0), (lag, 0))))
            out = np.concatenate(rows)
            out.setflags(write=False)
            self._cache[key] = out
        return out

    def nominal_misfit(self, sample_rate_hz: float, front_end, residual) -> bool:
        """Whether the nominal model misses the device's touches at this rate: the share
        of a learnt waveform the nominal templates leave unexplained (``residual(waves,
        fs, front_end)`` (J,) [1]) exceeds NOMINAL_FIT_MAX in more than a tenth of them.
        Where the nominal front end describes the device, its templates stay in use (the
        learnt ones would only add the touches' noise)."""
        fs = float(sample_rate_hz)
        key = ("nominal", fs, front_end)  # a tuple or a PulseModel: both hashable
        out = self._cache.get(key)
        if out is None:
            r = residual(np.array(self._waves[fs]), fs, front_end)
            out = bool(np.quantile(r, 0.9) > NOMINAL_FIT_MAX)
            self._cache[key] = out
        return out

    def low_max(self, sample_rate_hz: float, nominal: float) -> float:
        """The low-frequency test's limit at this rate: LEARN_MARGIN x the largest share
        of DC the device's touches gave, at least ``nominal``."""
        return max(nominal, self._largest("_low", float(sample_rate_hz)))

    def high_max(self, sample_rate_hz: float, nominal: float) -> float:
        """The high-frequency test's limit at this rate (as `low_max`)."""
        return max(nominal, self._largest("_high", float(sample_rate_hz)))

    def _largest(self, name: str, fs: float) -> float:
        """LEARN_MARGIN x the largest statistic ``name`` of the touches at rate ``fs``
        (0: none), kept with the templates."""
        key = (name, fs)
        out = self._cache.get(key)
        if out is None:
            v = getattr(self, name).get(fs)
            out = self._cache[key] = LEARN_MARGIN * float(np.max(v)) if v else 0.0
        return out

    def calibration_state(self) -> dict | None:
        """The learnt model as a JSON mapping for `ae_tactile.calibration.CalibrationStore`
        (None: nothing learnt).

        Returns
        -------
        dict or None
            {"format": 1, "rates": {fs [Hz] as text: {"waves": [[...]], "low": [...],
            "high": [...]}}}.
        """
        if not self._waves:
            return None
        rates = {repr(fs): {"waves": [list(map(float, w)) for w in self._waves[fs]],
                            "low": [float(v) for v in self._low.get(fs, ())],
                            "high": [float(v) for v in self._high.get(fs, ())]}
                 for fs in self._waves}
        return {"format": 1, "rates": rates}

    def load_calibration(self, state: dict) -> None:
        """Start from a saved `calibration_state`.

        Parameters
        ----------
        state : dict
            As `calibration_state` wrote it.

        Returns
        -------
        None
            ValueError when it cannot be used (another format, waveforms of unequal
            length, non-finite or not unit-norm values): nothing changed then.
        """
        if not isinstance(state, dict) or state.get("format") != 1:
            raise ValueError("acoustic model: unknown format")
        waves, low, high = {}, {}, {}
        try:
            for key, r in dict(state["rates"]).items():
                fs = float(key)
                w = np.array(r["waves"], dtype=float)
                lo = np.array(r["low"], dtype=float).reshape(-1)
                hi = np.array(r["high"], dtype=float).reshape(-1)
                if not (math.isfinite(fs) and fs > 0 and w.ndim == 2 and w.shape[1] >= 8
                        and np.isfinite(w).all() and np.isfinite(lo).all()
                        and np.isfinite(hi).all() and (lo >= 0).all() and (hi >= 0).all()
                        and np.allclose(np.linalg.norm(w, axis=1), 1.0, atol=1e-6)):
                    raise ValueError("acoustic model: values out of range")
                waves[fs] = deque(w, maxlen=self.keep)
                low[fs] = deque(lo, maxlen=self.keep)
                high[fs] = deque(hi, maxlen=self.keep)
        except (KeyError, TypeError, AttributeError) as exc:
            raise ValueError(f"acoustic model: malformed ({exc})") from None
        self._waves, self._low, self._high, self._cache, self._fresh = waves, low, high, {}, 0
        self.n_learnt = sum(len(w) for w in waves.values())

    def status(self) -> str:
        """The model in words (diagnostics)."""
        if not self._waves:
            return f"nominal front end (learning: 0 of {LEARN_MIN} waveforms)"
        parts = []
        for fs, w in self._waves.items():
            state = "learnt" if len(w) >= LEARN_MIN else f"learning {len(w)} of {LEARN_MIN}"
            parts.append(f"{fs / 1e6:g} MS/s {state}")
        return "device's own touches: " + ", ".join(parts)
