# SPDX-License-Identifier: Apache-2.0
"""The device's stated front end, calibrated on its own packets: the filter families and
orders as the device states them (`PulseModel.from_spec`), the corners and the emission
decay from its accepted single touches.

A stated corner is a component's nominal value: capacitors and resistors of 5-10 %
tolerance move it that much, and the refinement (`refine`) needs the pulse to better than
5 % at 40 dB (a pulse 5 % off fails the residual test there and the packet keeps ml's
answer; at 20 dB one 10 % off passes and is no better than ml). So the corners are fitted:
one factor k_hp on every high-pass corner, one k_lp on the low-pass corner and the
emission decay alpha (a property of the body and the object, not of the electronics),
minimising the summed residual of the one-emission fits (3 Levenberg-Marquardt steps from
each packet's matched-filter time, as `calibrate_pulse`) by Nelder-Mead, from alpha =
3e3, 1e5 and 1e6 /s; then each chain's gain (a few % apart in any real amplifier: the
median least-squares scale of the fitted model per channel), kept where it explains
more packets. The calibration is trusted (``converged``) when the pulse explains at
least FRONT_END_MIN_INLIERS packets to the noise and FRONT_END_MIN_INLIER_SHARE of them
(the resolver's residual test, `pulse_inliers`); the factors stay within
MAX_CORNER_FACTOR of the statement (beyond, the statement is wrong, not its tolerance).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, replace

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization.common import make_plan, validate_windows
from ae_tactile.localization.estimators import localize
from ae_tactile.localization.overlap.learn import (
    MIN_LEARN_POLAR_RAD,
    MIN_LEARN_SNR_DB,
    pulse_inliers,
)
from ae_tactile.localization.overlap.model import _lm, _Model
from ae_tactile.localization.overlap.pulse import _PR_CACHE, _TAB_CACHE, PulseModel
from ae_tactile.localization.overlap.search import _segments
from ae_tactile.localization.overlap.suspect import _time_search
from ae_tactile.localization.segments import prepare

__all__ = ["FrontEndFit", "FrontEndLearner", "calibrate_front_end", "FRONT_END_PACKETS"]

#: [1] packets one calibration uses (some 2e4 samples for three parameters)
FRONT_END_PACKETS = 24
#: [1] packets the calibrated pulse must explain, and their share of the candidates: the
#: device's own family explains all but the odd packet (24 of 24 in the zoo); a family
#: near it, but not it (a 6th-order Bessel for a 2nd-order Butterworth), 13-18 of 24, and
#: its refined points are 1.4x the bound at 20 dB
FRONT_END_MIN_INLIERS = 12
FRONT_END_MIN_INLIER_SHARE = 0.9
#: [1] calibrated corners within this factor of the stated ones
MAX_CORNER_FACTOR = 1.5
#: [1/s] starts of the emission decay (its decades in real bodies: 1e3 .. 1e6)
ALPHA_STARTS_1_S = (3e3, 1e5, 1e6)
#: [1/s] emission decays the interference screen's templates span while the decay is
#: unknown (a statement does not give it): its range in real bodies, a step per ~half
#: decade (adjacent pulses then correlate above the shape test's 0.94)
ALPHA_SPAN_1_S = (3e3, 3e4, 1e5, 3e5, 1e6)
#: [1] how far a stated corner may be off (the components' tolerance: 5-10 % parts)
STATED_CORNER_TOLERANCE = 0.1


def decay_family(stated: PulseModel | None) -> tuple | None:
    """The pulses the stated front end may give: over the decays an emission may have
    (`ALPHA_SPAN_1_S`), its high-pass and low-pass corners each at their stated value and
    +-`STATED_CORNER_TOLERANCE` off; the interference screen's templates and spectrum
    limits before the calibration measures the device (None: no statement)."""
    if stated is None:
        return None
    out = []
    for k_hp in (1.0 - STATED_CORNER_TOLERANCE, 1.0, 1.0 + STATED_CORNER_TOLERANCE):
        for k_lp in (1.0 - STATED_CORNER_TOLERANCE, 1.0, 1.0 + STATED_CORNER_TOLERANCE):
            out.extend(scaled_front_end(stated, (math.log(k_hp), math.log(k_lp), math.log(a)))
                       for a in ALPHA_SPAN_1_S)
    return tuple(out)
#: objective evaluations per start
CALIBRATION_MAXFEV = 60
#: [1] chains' gains within this of alike are not corrected (below what the fits see)
MIN_CHANNEL_GAIN = 3e-3
#: [1] untrusted calibrations before the learner stops trying (the statement does not
#: describe the device: a lossy body, another family); a new statement starts again
MAX_ATTEMPTS = 3
_FORMAT = 1  # of `FrontEndLearner.calibration_state`


@dataclass
class FrontEndFit:
    """One calibration: the pulse (the stated one with the fitted factors and decay, and
    the chains' own gains where they differ),
    the factors k_hp, k_lp [1] and decay [1/s], the candidates offered and the packets
    it explains (``n_inliers``), and whether it is trusted (``converged``)."""

    pulse: PulseModel
    highpass_factor: float
    lowpass_factor: float
    alpha_1_s: float
    n_candidates: int
    n_inliers: int
    converged: bool

    def describe(self) -> str:
        """The calibration in words (diagnostics)."""
        g = self.pulse.channel_gain
        gains = ", chain gains " + "/".join(f"{v:.3f}" for v in g) if g else ""
        return (f"corners x{self.highpass_factor:.3f} (high-pass) x{self.lowpass_factor:.3f} "
                f"(low-pass) of the stated, emission decay {self.alpha_1_s:.3g} /s{gains}: "
                f"{self.n_inliers} of {self.n_candidates} packets explained")


def scaled_front_end(stated: PulseModel, v) -> PulseModel:
    """``stated`` with its high-pass corners times exp(v[0]), its low-pass corner times
    exp(v[1]) and the emission decay exp(v[2]) [1/s]."""
    k_hp, k_lp, alpha = (float(math.exp(x)) for x in v)
    return replace(
        stated,
        highpass_hz=stated.highpass_hz * k_hp,
        highpass_rc_hz=tuple(f * k_hp for f in stated.highpass_rc_hz),
        lowpass_hz=None if stated.lowpass_hz is None else stated.lowpass_hz * k_lp,
        alpha_1_s=alpha,
    )


def calibrate_front_end(windows, sample_rate_hz, onset_index, stated, *, geometry=None,
                        noise_rms_v=None, max_packets=FRONT_END_PACKETS) -> FrontEndFit:
    """Fit the stated front end's corners and the emission decay to single touches.

    Parameters
    ----------
    windows : array_like, (K, 4, M)
        Packets [V]; those `localize` accepts away from the apex with SNR >=
        MIN_LEARN_SNR_DB are the candidates, the first ``max_packets`` used.
    sample_rate_hz : float
        Sample rate [Hz].
    onset_index : array_like of int, (K,)
        Onsets [samples].
    stated : PulseModel
        The device's front end as stated (not a learnt pulse).
    geometry : FingertipGeometry, optional
        The fingertip (default tip).
    noise_rms_v : float or array_like (K,), optional
        Known noise sigma [V]; default measured before the onset.
    max_packets : int
        Candidates used at most.

    Returns
    -------
    FrontEndFit
        ``converged`` False (and the stated pulse) when there are too few candidates.
    """
    from scipy.optimize import minimize  # lazy: only a calibration needs the optimizer

    if not isinstance(stated, PulseModel) or stated.learnt:
        raise TypeError("stated must be a PulseModel of a front end (not a learnt pulse)")
    geo = FingertipGeometry() if geometry is None else geometry
    fs = float(sample_rate_hz)
    x, on = validate_windows(windows, onset_index)
    with np.errstate(all="ignore"):
        ml = localize(x, fs, on, geometry=geo, noise_rms_v=noise_rms_v)
    ids = np.nonzero(ml.accepted & (ml.polar_rad >= MIN_LEARN_POLAR_RAD)
                     & (ml.snr_db_est >= MIN_LEARN_SNR_DB))[0][: int(max_packets)]
    v0 = np.array([0.0, 0.0, math.log(stated.alpha_1_s)])
    if ids.size < FRONT_END_MIN_INLIERS:
        return FrontEndFit(stated, 1.0, 1.0, stated.alpha_1_s, int(ids.size), 0, False)
    data = _calibration_data(x[ids], on[ids], fs, geo, ml.point_m[ids, :2])
    lim = math.log(MAX_CORNER_FACTOR)

    def cost(v):
        if abs(v[0]) > lim or abs(v[1]) > lim or not 5.0 < v[2] < 15.0:
            return math.inf  # outside the tolerance, or alpha outside 150 /s .. 3e6 /s
        return _rss(scaled_front_end(stated, v), data)

    best = None
    for a in ALPHA_STARTS_1_S:
        s = np.array([0.0, 0.0, math.log(a)])
        r = minimize(cost, s, method="Nelder-Mead", options=dict(
            xatol=1e-3, fatol=1e-12, maxfev=CALIBRATION_MAXFEV,
            initial_simplex=[s, s + [0.08, 0, 0], s + [0, 0.08, 0], s + [0, 0, 1.0]]))
        if best is None or r.fun < best.fun:
            best = r
    v = best.x if best is not None and math.isfinite(best.fun) else v0
    nr = None if noise_rms_v is None else np.broadcast_to(
        np.asarray(noise_rms_v, float), (len(on),))[ids]
    pulse = scaled_front_end(stated, v)
    n_cand, n_in = pulse_inliers(x[ids], fs, on[ids], pulse, geometry=geo, noise_rms_v=nr)
    gains = _channel_gains(pulse, data)
    if gains is not None:  # the chains' own gains, kept where they explain more packets
        with_gains = replace(pulse, channel_gain=gains)
        n2 = pulse_inliers(x[ids], fs, on[ids], with_gains, geometry=geo, noise_rms_v=nr)[1]
        if n2 > n_in:
            pulse, n_in = with_gains, n2
    ok = n_in >= FRONT_END_MIN_INLIERS and n_in >= FRONT_END_MIN_INLIER_SHARE * n_cand
    k_hp, k_lp, alpha = (float(math.exp(c)) for c in v)
    return FrontEndFit(pulse, k_hp, k_lp, alpha, int(n_cand), int(n_in), bool(ok))


def _channel_gains(pulse, data) -> tuple | None:
    """Each chain's gain [1] (mean 1) from the one-emission fits with ``pulse``: per
    packet and channel the least-squares scale of the fitted model to the samples, the
    median over the packets; None where every gain is within MIN_CHANNEL_GAIN of 1."""
    geo, fs, start, length, inside, seg, pts, y = data
    with np.errstate(all="ignore"):
        model = _Model(geo, fs, start, length, pulse, True, inside)
        th, amp, _, _ = _lm(model, y, _time_search(model, seg, pts)[:, None, :], iterations=5)
        phi, _ = model.evaluate(th)
    m = np.einsum("kj,kjn->kn", amp, phi).reshape(seg.shape)  # (K, 4, L)
    g = np.median(np.einsum("kcl,kcl->kc", seg, m) / np.einsum("kcl,kcl->kc", m, m), axis=0)
    if not np.all(np.isfinite(g)) or np.any(g <= 0):
        return None
    g = g / g.mean()
    return None if np.max(np.abs(g - 1.0)) < MIN_CHANNEL_GAIN else tuple(float(v) for v in g)


def _calibration_data(x, on, fs, geo, pts):
    """The candidates' fit segments (`calibrate_pulse`'s): (geo, fs, start, length,
    inside, seg, pts, y)."""
    plan = make_plan(fs, geo, x.shape[2], (100e3, 1e6))
    with np.errstate(all="ignore"):
        prep = prepare(x, on, plan, spectra=False)
        seg, start, length, inside = _segments(prep, plan, geo, plan.fs, None)
    return geo, plan.fs, start, length, inside, seg, pts, seg.reshape(len(on), -1)


def _rss(pm, data) -> float:
    """Summed residual [V^2 scaled] of the one-emission fits with pulse ``pm``."""
    geo, fs, start, length, inside, seg, pts, y = data
    with np.errstate(all="ignore"):
        model = _Model(geo, fs, start, length, pm, True, inside)
        th0 = _time_search(model, seg, pts)
        _, _, rss, _ = _lm(model, y, th0[:, None, :], iterations=3)
    _TAB_CACHE.pop((pm, fs, length), None)  # each trial pulse is used once
    _PR_CACHE.pop(pm, None)
    total = float(np.sum(rss))
    return total if math.isfinite(total) else math.inf


class FrontEndLearner:
    """The stated front end calibrated online: `add` the device's accepted touches; once
    FRONT_END_PACKETS candidates of one sample rate and window length are in, one
    calibration runs (`calibrate_front_end`); trusted, its pulse goes to ``on_update``
    (the localizer refines with it from then on). Untrusted, the next packets try again,
    MAX_ATTEMPTS times in all (the status says so); nothing is refined meanwhile.
    Thread-safe."""

    def __init__(self, stated: PulseModel | None = None):
        self._lock = threading.Lock()
        #: called with the calibrated pulse (or None when the statement is withdrawn)
        self.on_update = None
        self.set_stated(stated)

    def set_stated(self, stated: PulseModel | None) -> None:
        """A new statement (None: none): the calibration starts afresh."""
        with self._lock:
            self.stated = stated
            self.fit: FrontEndFit | None = None  # the latest calibration
            self.pulse: PulseModel | None = None  # the trusted one, in use
            self.attempts = 0
            self._pending: dict = {}
        if self.on_update is not None:
            self.on_update(None)

    @property
    def wanted(self) -> bool:
        """A statement is set, not yet calibrated, and not given up on."""
        return self.stated is not None and self.pulse is None and self.attempts < MAX_ATTEMPTS

    def add(self, windows, sample_rate_hz, onset_index, geometry=None) -> None:
        """Offer accepted single-emission packets (K, 4, M) [V]; calibrates when enough
        are in (in the caller's thread: seconds of numpy, so a background one)."""
        with self._lock:
            if not self.wanted:
                return
            x = np.asarray(windows, np.float64)
            key = (float(sample_rate_hz), x.shape[-1], id(geometry))
            got = self._pending.setdefault(key, ([], [], geometry))
            got[0].extend(x)
            got[1].extend(int(o) for o in np.atleast_1d(onset_index))
            if len(got[0]) < FRONT_END_PACKETS:
                return
            del self._pending[key]
            stated = self.stated
        fit = calibrate_front_end(np.stack(got[0]), key[0], got[1], stated, geometry=got[2])
        with self._lock:
            if stated is not self.stated:
                return  # a new statement meanwhile: this calibration is of the old one
            self.fit, self.attempts = fit, self.attempts + 1
            if fit.converged:
                self.pulse = fit.pulse
        if fit.converged and self.on_update is not None:
            self.on_update(fit.pulse)

    def calibration_state(self) -> dict | None:
        """The trusted calibration as a JSON mapping for
        `ae_tactile.calibration.CalibrationStore` (None: none yet): the statement it is of,
        the factors, the decay and how many packets it explained."""
        with self._lock:
            if self.pulse is None:
                return None
            f = self.fit
            return {"format": _FORMAT, "stated": self.stated.spec(),
                    "highpass_factor": f.highpass_factor, "lowpass_factor": f.lowpass_factor,
                    "alpha_1_s": f.alpha_1_s, "n_candidates": f.n_candidates,
                    "n_inliers": f.n_inliers, "channel_gain": list(self.pulse.channel_gain)}

    def load_calibration(self, state: dict) -> None:
        """Start from a saved `calibration_state` of the same statement.

        Returns
        -------
        None
            ValueError when it cannot be used (another format or statement, values out of
            range): nothing changed then.
        """
        if not isinstance(state, dict) or state.get("format") != _FORMAT:
            raise ValueError("front end: unknown format")
        try:
            stated = PulseModel.from_spec(str(state["stated"]))
            v = [math.log(float(state["highpass_factor"])),
                 math.log(float(state["lowpass_factor"])), math.log(float(state["alpha_1_s"]))]
            n_cand, n_in = int(state["n_candidates"]), int(state["n_inliers"])
            gains = tuple(float(g) for g in state.get("channel_gain", ()))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"front end: malformed ({exc})") from None
        lim = math.log(MAX_CORNER_FACTOR)
        if not (abs(v[0]) <= lim and abs(v[1]) <= lim and 5.0 < v[2] < 15.0) or (
                gains and (len(gains) != 4 or not all(0.5 < g < 2.0 for g in gains))):
            raise ValueError("front end: factors, decay or gains out of range")
        with self._lock:
            if self.stated is None or stated != self.stated:
                raise ValueError("front end: calibrated for another statement "
                                 f"({state['stated']!r})")
            pulse = replace(scaled_front_end(stated, v), channel_gain=gains)
            self.fit = FrontEndFit(pulse, *(math.exp(c) for c in v), n_cand, n_in, True)
            self.pulse = pulse
        if self.on_update is not None:
            self.on_update(pulse)

    def status(self) -> str:
        """In words, for diagnostics."""
        with self._lock:
            if self.stated is None:
                return "none stated (no refinement)"
            if self.pulse is not None:
                return "calibrated: " + self.fit.describe()
            n = max((len(v[0]) for v in self._pending.values()), default=0)
            if self.attempts >= MAX_ATTEMPTS:
                return (f"not trusted after {self.attempts} calibrations, the last "
                        + self.fit.describe() + ": the statement does not describe this "
                        "device (no refinement)")
            line = f"calibrating ({n} of {FRONT_END_PACKETS} packets)"
            if self.fit is not None:
                line += (f"; {self.attempts} calibration(s) not trusted, the last "
                         + self.fit.describe() + " (no refinement meanwhile)")
            return line
