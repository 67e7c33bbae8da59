# SPDX-License-Identifier: Apache-2.0
"""`PulseLearner`: the pulse learnt online from the packets accepted as isolated single
emissions (`learn.fit_pulse` on the newest of them), trusted once it explains them to the
noise, and kept per device (`calibration_state` / `load_calibration`, the protocol of
`ae_tactile.calibration.CalibrationStore`).
"""

from __future__ import annotations

import math
import pickle
import subprocess
import sys
import threading
from collections import deque
from dataclasses import replace

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization.common import validate_windows
from ae_tactile.localization.overlap.learn import (
    MIN_LEARN_POLAR_RAD,
    MIN_LEARN_SNR_DB,
    PulseFit,
    fit_pulse,
    pulse_inliers,
)
from ae_tactile.localization.overlap.pulse import PulseModel

__all__ = ["PulseLearner", "CALIBRATION_FORMAT", "MIN_LEARN_PEAK"]

#: format of `PulseLearner.calibration_state`; another one is not loaded (learnt again)
CALIBRATION_FORMAT = 1
#: [1] a candidate record's direct-wave peak over its packet's noise sigma: at least the
#: ratio of MIN_LEARN_SNR_DB (the peak exceeds the RMS the SNR is defined on, so this only
#: drops packets the fit's SNR test would)
MIN_LEARN_PEAK = 10.0 ** (MIN_LEARN_SNR_DB / 20.0)
#: [s] longest wait for a fit in its own process (a fit of 32 packets takes seconds to a
#: minute of one core; beyond this the process is ended and the fit counted as failed)
FIT_TIMEOUT_S = 900.0


class PulseLearner:
    """Online learning of the pulse from the packets accepted as isolated single emissions
    (as `ae_tactile.dsp.interference.EchoLearner` learns the wall echo).

    Candidates come by `offer` (a batch and `localize`'s answer) or `enqueue` (one packet
    the pipeline kept: a reference is kept, nothing is computed; the driver's hot path).
    They must lie at polar angle >= MIN_LEARN_POLAR_RAD (the fit checks SNR >=
    MIN_LEARN_SNR_DB itself). Once ``min_packets`` are kept, and then every
    ``refit_every`` new ones (doubling from the second fit in a row that does not
    converge, up to ``refit_converged_every``, the interval once a pulse is trusted),
    `fit_pulse` runs on the newest ``max_packets``: in the calling thread, in a thread of its own
    (``background=True``) or in a process of its own started by that thread
    (``background="process"``, the driver: the fit never holds the interpreter lock
    against the reader); one fit at a time. `pulse` is the learnt model once trusted
    (``converged``), else None: callers then use the default pulse without trusting it.
    A pulse loaded from the device's calibration file is trusted at once and checked on
    the first ``min_packets`` new candidates (`verify`): dropped when it does not explain
    them. With ``on_demand`` (the driver) candidates are kept but no fit starts before
    `want` is called (the pipeline calls it on its first window with overlapping
    emissions): a device whose emissions never overlap never pays for a fit. `state` and
    `status` report the learner for diagnostics. Thread-safe.

    Parameters
    ----------
    geometry : FingertipGeometry, optional
        The fingertip (default tip).
    min_packets, max_packets : int
        Inliers needed to trust a pulse; candidates kept (the newest).
    refit_every, refit_converged_every : int
        New candidates between fits before and after a pulse is trusted.
    background : bool or "process"
        Where the fit runs (above).
    on_demand : bool
        Fits wait for `want` (above).
    """

    def __init__(self, geometry=None, *, min_packets=12, max_packets=32, refit_every=16,
                 refit_converged_every=256, background=False, on_demand=False):
        if background not in (False, True, "process"):
            raise ValueError(f"background must be False, True or 'process', got {background!r}")
        self.geometry = FingertipGeometry() if geometry is None else geometry
        self.min_packets = int(min_packets)
        self.max_packets = int(max_packets)
        self.refit_every = int(refit_every)
        self.refit_converged_every = int(refit_converged_every)
        self.background = background
        #: fits wait for `want` (kept across `reset`: it says how the fingertip is used)
        self.wanted = not on_demand
        self._lock = threading.Lock()
        #: (samples (4, M) [V], onset, noise [V] or nan), newest last
        self._windows: deque = deque(maxlen=self.max_packets)
        self._fs: float | None = None
        self._new = 0
        self._every = self.refit_every  # new candidates before the next fit
        self._failed = 0  # fits in a row that did not converge
        self._generation = 0  # a reset or load makes a running fit's answer stale
        self._thread: threading.Thread | None = None
        self._busy = False
        self._proc = None  # the fit process under way (`close` ends it)
        self._closed = False
        self.fits = 0
        self.fit_errors = 0
        self.offered = 0
        self.last: PulseFit | None = None
        #: the trusted pulse came from the calibration file and is not checked yet
        self.loaded = False

    @property
    def pulse(self) -> PulseModel | None:
        """The trusted learnt pulse, or None before convergence."""
        last = self.last
        return last.pulse if last is not None and last.converged else None

    def pulse_at(self, sample_rate_hz: float) -> PulseModel | None:
        """The trusted pulse when it was learnt at this sample rate [Hz], else None."""
        pulse = self.pulse
        return pulse if pulse is not None and self._fs == float(sample_rate_hz) else None

    @property
    def converged(self) -> bool:
        """A learnt pulse is trusted."""
        return self.pulse is not None

    def close(self) -> None:
        """No more fits: one under way in its process is ended (its owner closes)."""
        with self._lock:
            self._closed = True
            proc = self._proc
        if proc is not None:
            proc.kill()

    def want(self) -> None:
        """Fits are needed from now on (overlapping emissions were seen): one starts at
        once when enough candidates wait. Cheap after the first call."""
        if self.wanted:
            return
        with self._lock:
            self.wanted = True
            snap = self._due_locked()
        if snap is not None:
            self._start_fit(snap)

    def reset(self) -> None:
        """Forget the candidates and the learnt pulse (a new device, a changed front end);
        a fit under way is discarded when it ends."""
        with self._lock:
            self._reset_locked()

    def _reset_locked(self) -> None:
        self._windows.clear()
        self._fs, self._new, self.last, self.loaded = None, 0, None, False
        self._every, self._failed = self.refit_every, 0
        self._generation += 1

    def _rate_locked(self, fs: float) -> None:
        """Candidates at another rate: what was learnt at the old one is forgotten."""
        if self._fs is not None and fs != self._fs:
            self._reset_locked()
        self._fs = fs

    def enqueue(self, samples_v, sample_rate_hz: float, onset_index: int, polar_rad: float,
                noise_rms_v: float = math.nan) -> bool:
        """One packet the pipeline kept as a single emission: kept by reference (never
        modified after its hand-over) when it lies away from the apex; a fit is started
        when one is due (in the background for a driver).

        Parameters
        ----------
        samples_v : numpy.ndarray, (4, M)
            The packet [V].
        sample_rate_hz : float
            Its rate [Hz] (another rate forgets what was learnt at the old one).
        onset_index : int
            Its onset [samples].
        polar_rad : float
            Its localized polar angle [rad].
        noise_rms_v : float
            Its noise sigma [V] (nan or 0: measured before the onset).

        Returns
        -------
        bool
            Kept as a candidate.
        """
        if not polar_rad >= MIN_LEARN_POLAR_RAD:
            return False
        nv = float(noise_rms_v) if noise_rms_v and noise_rms_v > 0 else math.nan
        with self._lock:
            self._rate_locked(float(sample_rate_hz))
            self._windows.append((samples_v, int(onset_index), nv))
            self._new += 1
            self.offered += 1
            snap = self._due_locked()
        if snap is not None:
            self._start_fit(snap)
        return True

    def enqueue_records(self, packets, records, min_confidence: float = 0.0) -> int:
        """`enqueue` the packets of contact records kept as single emissions: records away
        from the apex, not weak releases, of one packet each (``packet_ids[0]``, its
        sequence id), with confidence >= ``min_confidence`` and a peak of at least
        MIN_LEARN_PEAK noise sigmas (where the packet's noise is known).

        Parameters
        ----------
        packets : sequence of PacketView
            A batch.
        records : list of ContactRecord
            Its single-emission events.
        min_confidence : float
            Lowest confidence of a candidate [1].

        Returns
        -------
        int
            Candidates queued.
        """
        by_id = None
        n = 0
        for ev in records:
            if (ev.weak_release or not ev.polar_rad >= MIN_LEARN_POLAR_RAD
                    or ev.confidence < min_confidence or len(ev.packet_ids) != 1):
                continue
            if by_id is None:
                by_id = {p.sequence_id: p for p in packets}
            p = by_id.get(ev.packet_ids[0])
            nv = float(getattr(p, "noise_rms_v", 0.0) or 0.0)
            if p is None or (nv > 0 and abs(ev.amplitude_v) < MIN_LEARN_PEAK * nv):
                continue
            n += self.enqueue(p.samples_v, p.sample_rate_hz, p.onset_index, ev.polar_rad, nv)
        return n

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
        good = np.asarray(single.accepted, bool) & (
            np.asarray(single.polar_rad) >= MIN_LEARN_POLAR_RAD) & (
            np.asarray(single.snr_db_est) >= MIN_LEARN_SNR_DB)
        nr = np.full(len(on), np.nan) if noise_rms_v is None else np.broadcast_to(
            np.asarray(noise_rms_v, float), (len(on),))
        with self._lock:
            self._rate_locked(float(sample_rate_hz))
            for i in np.nonzero(good)[0]:
                self._windows.append((np.array(x[i], dtype=np.float64), int(on[i]),
                                      float(nr[i])))
            n_new = int(good.sum())
            self._new += n_new
            self.offered += n_new
            snap = self._due_locked()
        if snap is not None:
            self._start_fit(snap)
        return n_new

    def _due_locked(self):
        """The candidates of a fit that is due (enough of them, enough new ones, none
        running; marked started), else None: see `_snapshot_locked`."""
        every = self.refit_converged_every if (self.converged and not self.loaded) else (
            self._every)
        due = (not self._busy and not self._closed and len(self._windows) >= self.min_packets
               and (self.last is None or self.loaded or self._new >= every)
               and (self.wanted or self.loaded))  # a loaded pulse is checked at once
        if self.loaded and self.last is not None:
            due = due and self._new >= self.min_packets  # check it on fresh packets
        if not due:
            return None
        self._busy = True
        return self._snapshot_locked()

    def _snapshot_locked(self):
        """(candidates, rate, generation) now: the fit works on exactly these, whenever
        its thread runs."""
        self._new = 0
        return list(self._windows), self._fs, self._generation

    def _start_fit(self, snap) -> None:
        if not self.background:
            self._fit_now(snap)
            return
        self._thread = threading.Thread(target=self._fit_now, args=(snap,),
                                        name="ae_tactile_pulse", daemon=True)
        self._thread.start()

    def _fit_now(self, snap) -> None:
        try:
            self._refit_on(snap)
        finally:
            self._busy = False

    def wait(self, timeout_s: float | None = None) -> None:
        """Wait up to ``timeout_s`` [s] (None: until done) for a background fit."""
        t = self._thread
        if t is not None:
            t.join(timeout_s)

    @staticmethod
    def _candidates(snap):
        """(windows (K, 4, m) float64, onsets (K,), noise [V] or None, rate, generation)
        of a snapshot's candidates, cropped to the shortest (None: none)."""
        items, fs, gen = snap
        if not items or fs is None:
            return None
        m = min(w.shape[1] for w, _, _ in items)
        x = np.stack([np.asarray(w[:, :m], dtype=np.float64) for w, _, _ in items])
        on = np.array([min(o, m - 1) for _, o, _ in items])
        nr = np.array([n for _, _, n in items])
        return x, on, None if np.isnan(nr).any() else nr, fs, gen

    def refit(self) -> PulseFit | None:
        """Fit the pulse on the kept candidates now, in the calling thread (None when
        there are none, or the fit failed: counted in ``fit_errors``). A fit that does
        not converge never replaces a trusted pulse, except a loaded one that does not
        explain the new candidates (`verify`)."""
        with self._lock:
            snap = self._snapshot_locked()
        return self._refit_on(snap)

    def _refit_on(self, snap) -> PulseFit | None:
        got = self._candidates(snap)
        if got is None:
            return None
        x, on, nr, fs, gen = got
        if self.loaded and self.verify(x, fs, on, nr, gen):
            return self.last
        fit = self._fit(dict(windows=x, sample_rate_hz=fs, onset_index=on,
                             geometry=self.geometry, noise_rms_v=nr,
                             max_packets=self.max_packets, min_packets=self.min_packets))
        with self._lock:
            if gen != self._generation:
                return None  # reset meanwhile: the answer is for another device
            if fit is None:
                self.fit_errors += 1
                return None
            self.fits += 1
            if fit.converged or self.last is None or not self.last.converged:
                self.last, self.loaded = fit, False
            if fit.converged:
                self._failed = 0
            else:  # fewer fits where the device does not fit the model
                self._failed += 1
                self._every = min(self.refit_every << min(self._failed - 1, 16),
                                  self.refit_converged_every)
        return fit

    def verify(self, windows, sample_rate_hz, onset_index, noise_rms_v=None,
               generation=None) -> bool:
        """Check a loaded pulse on new candidates (`learn.pulse_inliers`): it must explain
        at least ``min_packets`` of them, or all when fewer, and at least the share a fit
        needs to converge (60 %). A pulse that passes is kept (no longer marked loaded);
        one that fails is dropped (untrusted).

        Parameters
        ----------
        windows : numpy.ndarray, (K, 4, M)
            Candidates [V].
        sample_rate_hz : float
            Their rate [Hz].
        onset_index : array_like of int, (K,)
            Their onsets.
        noise_rms_v : array_like (K,), optional
            Known noise sigma [V].
        generation : int, optional
            The learner's generation the candidates belong to (stale: nothing changed).

        Returns
        -------
        bool
            The loaded pulse is kept.
        """
        pulse = self.pulse
        if pulse is None:
            return False
        n, n_in = pulse_inliers(windows, sample_rate_hz, onset_index, pulse,
                                geometry=self.geometry, noise_rms_v=noise_rms_v)
        keep = n > 0 and n_in >= min(self.min_packets, n) and n_in >= 0.6 * n
        with self._lock:
            if generation is not None and generation != self._generation:
                return False
            self.loaded = False
            if not keep:
                self.last = None
            elif self.last is not None:
                self.last = replace(self.last, n_candidates=n, n_inliers=n_in)
        return keep

    def _fit(self, request: dict) -> PulseFit | None:
        """`fit_pulse` on the request, in a process of its own (``background="process"``;
        where that fails, here) or here."""
        if self.background == "process":
            proc = None
            try:
                proc = subprocess.Popen(
                    [sys.executable, "-m", "ae_tactile.localization.overlap.fit_job"],
                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                    start_new_session=True)
                with self._lock:
                    self._proc = proc
                    if self._closed:
                        proc.kill()
                out, _ = proc.communicate(
                    pickle.dumps(request, protocol=pickle.HIGHEST_PROTOCOL),
                    timeout=FIT_TIMEOUT_S)
                fit = pickle.loads(out) if out else None
            except (OSError, subprocess.SubprocessError, pickle.UnpicklingError, EOFError):
                fit = None
            finally:
                with self._lock:
                    self._proc = None
                if proc is not None and proc.poll() is None:
                    proc.kill()
                    proc.wait()
            return fit if isinstance(fit, PulseFit) else None
        try:
            return fit_pulse(**request)
        except (ValueError, np.linalg.LinAlgError):
            return None

    # ------------------------------------------------------------ the device's file
    def calibration_state(self) -> dict | None:
        """The trusted pulse as a JSON mapping for `ae_tactile.calibration.CalibrationStore`
        (None: none trusted).

        Returns
        -------
        dict or None
            {"format": 1, "sample_rate_hz", "poles_rad_s": [[re, im], ...], "residues":
            [[re, im], ...], "channel_gain": [4] or [], "channel_delay_s": [4] or [],
            "attenuation_db_per_m_at_1mhz", "attenuation_exponent", "attenuation_ref_hz"
            (the medium's power-law loss; absent in older files: lossless),
            "misfit_share" (the pulse's misfit on single touches; absent: 0),
            "n_candidates", "n_inliers", "chi2_median"}.
        """
        with self._lock:
            last, fs = self.last, self._fs
        if last is None or not last.converged or fs is None:
            return None
        p = last.pulse
        chi2 = float(last.chi2_median)
        return {
            "format": CALIBRATION_FORMAT,
            "sample_rate_hz": float(fs),
            "poles_rad_s": [[float(v.real), float(v.imag)] for v in p.poles_rad_s],
            "residues": [[float(v.real), float(v.imag)] for v in p.residues],
            "channel_gain": [float(v) for v in p.channel_gain],
            "channel_delay_s": [float(v) for v in p.channel_delay_s],
            "attenuation_db_per_m_at_1mhz": float(p.attenuation_db_per_m_at_1mhz),
            "attenuation_exponent": float(p.attenuation_exponent),
            "attenuation_ref_hz": float(p.attenuation_ref_hz),
            "misfit_share": float(p.misfit_share),
            "n_candidates": int(last.n_candidates),
            "n_inliers": int(last.n_inliers),
            "chi2_median": chi2 if math.isfinite(chi2) else -1.0,
        }

    def load_calibration(self, state: dict) -> None:
        """Start from a saved `calibration_state`: its pulse is trusted at once and
        checked on the first ``min_packets`` new candidates (`verify`).

        Parameters
        ----------
        state : dict
            As `calibration_state` wrote it.

        Returns
        -------
        None
            ValueError when it cannot be used (another format, poles not decaying,
            non-finite values, channel corrections not of 4 positive gains and delays
            under 1 us): nothing changed then.
        """
        fs, fit = _pulse_from_state(state)
        with self._lock:
            self._reset_locked()
            self._fs, self.last, self.loaded = fs, fit, True

    # ------------------------------------------------------------ diagnostics
    def state(self) -> dict:
        """Diagnostics of the learner.

        Returns
        -------
        dict
            ``pulse_candidates_offered`` / ``_kept``, ``pulse_fits``, ``pulse_fit_errors``,
            ``pulse_converged`` (0/1), ``pulse_loaded`` (0/1: from the file, not checked
            yet), ``pulse_wanted`` (0/1: fits run; see ``on_demand``), ``pulse_inliers``
            and ``pulse_chi2_median`` of the latest fit kept.
        """
        last = self.last
        return dict(
            pulse_candidates_offered=self.offered,
            pulse_candidates_kept=len(self._windows),
            pulse_fits=self.fits,
            pulse_fit_errors=self.fit_errors,
            pulse_converged=int(self.converged),
            pulse_loaded=int(self.loaded),
            pulse_wanted=int(self.wanted),
            pulse_inliers=0 if last is None else last.n_inliers,
            pulse_chi2_median=float("nan") if last is None else last.chi2_median,
        )

    def status(self) -> str:
        """The pulse in use in words (diagnostics)."""
        last, fs = self.last, self._fs
        if self.converged and fs is not None:
            how = "loaded from the device's file, checking" if self.loaded else "learnt"
            return (f"{how} at {fs / 1e6:g} MS/s: {last.n_inliers} of {last.n_candidates} "
                    f"packets explained, {self.fits} fits")
        kept = len(self._windows)
        if last is None and not self.wanted:
            return (f"nominal pulse (no overlapping emissions seen yet: not learnt; {kept} "
                    f"candidates kept)")
        if last is None:
            return (f"nominal pulse, untrusted (learning: {kept} of {self.min_packets} "
                    f"candidates)")
        return (f"nominal pulse, untrusted (latest fit explains {last.n_inliers} of "
                f"{last.n_candidates}; {self.fits} fits, {kept} candidates)")


def _complex_list(values, name: str) -> np.ndarray:
    a = np.asarray(values, dtype=float)
    if a.ndim != 2 or a.shape[1] != 2 or a.shape[0] == 0 or not np.isfinite(a).all():
        raise ValueError(f"overlap pulse: {name} must be non-empty [[re, im], ...]")
    return a[:, 0] + 1j * a[:, 1]


def _pulse_from_state(state):
    """(sample rate [Hz], PulseFit of the saved pulse) of a saved state; ValueError if
    unusable."""
    if not isinstance(state, dict) or state.get("format") != CALIBRATION_FORMAT:
        raise ValueError("overlap pulse: unknown format")
    try:
        fs = float(state["sample_rate_hz"])
        poles = _complex_list(state["poles_rad_s"], "poles_rad_s")
        res = _complex_list(state["residues"], "residues")
        gain = np.asarray(state.get("channel_gain", []), dtype=float).reshape(-1)
        delay = np.asarray(state.get("channel_delay_s", []), dtype=float).reshape(-1)
        n_cand, n_in = int(state["n_candidates"]), int(state["n_inliers"])
        chi2 = float(state.get("chi2_median", -1.0))
        loss = float(state.get("attenuation_db_per_m_at_1mhz", 0.0))  # [dB/m]
        y = float(state.get("attenuation_exponent", 2.0))
        ref_hz = float(state.get("attenuation_ref_hz", 300e3))
        misfit = float(state.get("misfit_share", 0.0))  # [1]
    except (KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"overlap pulse: malformed ({exc})") from None
    if not (math.isfinite(fs) and fs > 0 and 0 <= n_in <= n_cand):
        raise ValueError("overlap pulse: sample rate or counts out of range")
    if gain.size not in (0, 4) or not (np.isfinite(gain).all() and (gain > 0).all()):
        raise ValueError("overlap pulse: channel_gain must be 4 positive numbers or none")
    if delay.size not in (0, 4) or not (np.abs(delay) < 1e-6).all():
        raise ValueError("overlap pulse: channel_delay_s must be 4 delays under 1 us or none")
    if not (math.isfinite(loss) and loss >= 0 and 0 < y <= 2 and ref_hz > 0):
        raise ValueError("overlap pulse: loss >= 0, exponent in (0, 2], reference > 0")
    if not (math.isfinite(misfit) and 0 <= misfit < 1):
        raise ValueError("overlap pulse: misfit_share must be in [0, 1)")
    pulse = PulseModel.from_poles(poles, res)  # ValueError: not decaying, not finite
    pulse = replace(pulse, channel_gain=tuple(map(float, gain)),
                    channel_delay_s=tuple(map(float, delay)),
                    attenuation_db_per_m_at_1mhz=loss, attenuation_exponent=y,
                    attenuation_ref_hz=ref_hz, misfit_share=misfit)
    return fs, PulseFit(pulse, True, n_cand, n_in, chi2 if chi2 >= 0 else float("nan"))
