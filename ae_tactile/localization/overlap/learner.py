# SPDX-License-Identifier: Apache-2.0
"""`PulseLearner`: the pulse learnt online from the packets accepted as isolated single
emissions (`learn.fit_pulse` on the newest of them), trusted once it explains them to the
noise.
"""

from __future__ import annotations

import threading

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization.common import validate_windows
from ae_tactile.localization.overlap.learn import (
    MIN_LEARN_POLAR_RAD,
    MIN_LEARN_SNR_DB,
    PulseFit,
    fit_pulse,
)
from ae_tactile.localization.overlap.pulse import PulseModel

__all__ = ["PulseLearner"]


class PulseLearner:
    """Online learning of the pulse from the packets accepted as isolated single emissions
    (as `ae_tactile.dsp.interference.EchoLearner` learns the wall echo).

    `offer` keeps the candidates (accepted by `localize`, polar angle >=
    MIN_LEARN_POLAR_RAD, SNR >= MIN_LEARN_SNR_DB); once ``min_packets`` are kept, and then
    every ``refit_every`` new ones (every ``refit_converged_every`` once a pulse is
    trusted), `fit_pulse` runs on the newest ``max_packets``, in the calling thread or,
    with ``background``, in a thread of its own (one fit at a time). `pulse` is the learnt
    model once trusted (``converged``), else None: callers then use the default pulse
    without trusting it (one point with a count where a window is not explained). `state`
    reports the learner for diagnostics. Thread-safe.

    Parameters
    ----------
    geometry : FingertipGeometry, optional
        The fingertip (default tip).
    min_packets, max_packets : int
        Inliers needed to trust a pulse; candidates kept (the newest).
    refit_every, refit_converged_every : int
        New candidates between fits before and after a pulse is trusted.
    background : bool
        Fit in a daemon thread (a driver: the fit takes seconds) instead of in `offer`.
    """

    def __init__(self, geometry=None, *, min_packets=12, max_packets=32, refit_every=16,
                 refit_converged_every=256, background=False):
        self.geometry = FingertipGeometry() if geometry is None else geometry
        self.min_packets = int(min_packets)
        self.max_packets = int(max_packets)
        self.refit_every = int(refit_every)
        self.refit_converged_every = int(refit_converged_every)
        self.background = bool(background)
        self._lock = threading.Lock()
        self._windows: list = []  # (samples (4, M), onset, noise [V] or nan)
        self._fs: float | None = None
        self._new = 0
        self._thread: threading.Thread | None = None
        self.fits = 0
        self.offered = 0
        self.last: PulseFit | None = None

    @property
    def pulse(self) -> PulseModel | None:
        """The trusted learnt pulse, or None before convergence."""
        last = self.last
        return last.pulse if last is not None and last.converged else None

    @property
    def converged(self) -> bool:
        """A learnt pulse is trusted."""
        return self.pulse is not None

    def reset(self) -> None:
        """Forget the candidates and the learnt pulse (a new device, a changed front end)."""
        with self._lock:
            self._windows, self._fs, self._new, self.last = [], None, 0, None

    def offer(self, windows, sample_rate_hz, onset_index, single, noise_rms_v=None) -> int:
        """Keep the packets of a batch that `localize` accepted (``single``) as learning
        candidates, and refit when enough are new.

        Parameters
        ----------
        windows : array_like, (K, 4, M)
            The batch's packets [V].
        sample_rate_hz : float
            Their sample rate [Hz] (a new rate forgets what was learnt at the old one).
        onset_index : array_like of int, (K,)
            Onsets [samples].
        single : LocalizationResult
            `localize`'s answer for the batch (``accepted``, ``polar_rad``,
            ``snr_db_est``).
        noise_rms_v : float or array_like (K,), optional
            Known noise sigma [V].

        Returns
        -------
        int
            Candidates kept from this batch.
        """
        x, on = validate_windows(windows, onset_index)
        fs = float(sample_rate_hz)
        good = np.asarray(single.accepted, bool) & (
            np.asarray(single.polar_rad) >= MIN_LEARN_POLAR_RAD) & (
            np.asarray(single.snr_db_est) >= MIN_LEARN_SNR_DB)
        nr = np.full(len(on), np.nan) if noise_rms_v is None else np.broadcast_to(
            np.asarray(noise_rms_v, float), (len(on),))
        with self._lock:
            if self._fs is not None and fs != self._fs:
                self._windows, self._new, self.last = [], 0, None
            self._fs = fs
            for i in np.nonzero(good)[0]:
                self._windows.append((np.array(x[i], dtype=np.float64), int(on[i]),
                                      float(nr[i])))
            del self._windows[: -self.max_packets]
            n_new = int(good.sum())
            self._new += n_new
            self.offered += n_new
            every = self.refit_converged_every if self.converged else self.refit_every
            due = len(self._windows) >= self.min_packets and (
                self.last is None or self._new >= every)
            busy = self._thread is not None and self._thread.is_alive()
            if due and self.background and not busy:
                self._thread = threading.Thread(target=self.refit, name="ae_tactile_pulse",
                                                daemon=True)
                self._thread.start()
        if due and not self.background:
            self.refit()
        return n_new

    def wait(self, timeout_s: float | None = None) -> None:
        """Wait up to ``timeout_s`` [s] (None: until done) for a background fit."""
        t = self._thread
        if t is not None:
            t.join(timeout_s)

    def refit(self) -> PulseFit | None:
        """Fit the pulse on the kept candidates now (None when there are none). A fit that
        does not converge never replaces a trusted pulse."""
        with self._lock:
            items, fs = list(self._windows), self._fs
            self._new = 0
        if not items or fs is None:
            return None
        m = min(w.shape[1] for w, _, _ in items)
        x = np.stack([w[:, :m] for w, _, _ in items])
        on = np.array([min(o, m - 1) for _, o, _ in items])
        nr = np.array([n for _, _, n in items])
        fit = fit_pulse(x, fs, on, geometry=self.geometry,
                        noise_rms_v=None if np.isnan(nr).any() else nr,
                        max_packets=self.max_packets, min_packets=self.min_packets)
        with self._lock:
            self.fits += 1
            if fit.converged or self.last is None or not self.last.converged:
                self.last = fit
        return fit

    def state(self) -> dict:
        """Diagnostics of the learner.

        Returns
        -------
        dict
            ``pulse_candidates_offered`` / ``_kept``, ``pulse_fits``, ``pulse_converged``
            (0/1), ``pulse_inliers`` and ``pulse_chi2_median`` of the latest fit kept.
        """
        last = self.last
        return dict(
            pulse_candidates_offered=self.offered,
            pulse_candidates_kept=len(self._windows),
            pulse_fits=self.fits,
            pulse_converged=int(self.converged),
            pulse_inliers=0 if last is None else last.n_inliers,
            pulse_chi2_median=float("nan") if last is None else last.chi2_median,
        )
