# SPDX-License-Identifier: Apache-2.0
"""Per-channel delay offsets learnt from the device's own touches (`ChannelDelayLearner`).

A real front end's four channels never have equal group delays: channel k adds d_k to
every arrival, t_k = |s - e_k| / c + T0 + d_k. Only differences matter (a common part
shifts the emission instant T0), so d is kept with sum(d) = 0 and written in the three
contrasts of the 2 x 2 array (unit vectors over the channels 11, 1-1, -11, -1-1):
x = (1, 1, -1, -1) / 2, y = (1, -1, 1, -1) / 2, xy = (1, -1, -1, 1) / 2.

One packet has four arrivals and three unknowns (s_x, s_y, T0): its fit leaves one
residual, the arrivals' projection on the unit vector n(s) orthogonal to 1 and to
d t / d s_x, d t / d s_y at the fitted point. d is seen only through it: n . d. n is the
xy contrast (within 0.3 %) tilted by +-7 % towards x and y as the point moves over the
fingertip, so from touches at unknown points the xy offset is learnt at once and the x
and y offsets ~15x more slowly (per packet, 1 / 0.066 of the information): hundreds of
touches fix the twist, thousands the x and y parts.

Measurement (off the hot path, a batch of kept packets at a time): the numpy ``ml`` fit
with the offsets in use, then the four channels' own shifts that maximise the steered
response power from the fit (Newton on the free arrival shifts, the common shift fixed),
y = n . (shift + offsets in use), its variance n^T F^+ n from the arrival Fisher matrix.
The offsets are the weighted least squares over the last ``keep`` packets of
y_i = (B n_i) . beta (beta the three contrasts), with packets whose normalised residual
lies beyond 4 robust sigma dropped; each contrast's standard error comes from the
normal equations scaled by the residuals' own spread. A contrast is applied once its
standard error is below ``tolerance`` times the delay noise of the best-measured tenth
of the packets (a bias it could leave is then small beside any packet's noise), or once
it lies 3 standard errors or more from zero (taking it out leaves less bias than it
removes), with at least ``min_count`` packets in: before that the localizer is unchanged.

The same residuals test the localizer's noise model: with its delay noise right they are
y_i ~ N(n_i . d, var_i). A device whose delay noise is larger shows it there, and
`fit_delay_noise` fits the two ways it is larger, a scale of var_i (coloured noise) and an
error of each channel's own at any SNR (aliasing). Once that fit explains the residuals
better by `DELAY_NOISE_DEVIANCE`, the localizer's covariances carry it (``applied_noise``,
`Localizer.set_channel_delays`): a point's covariance then covers its error on such a
device instead of claiming the white-noise bound. A bias the four arrivals share (one
that moves every channel alike, e.g. a lossy body's dispersion) leaves no residual and is
not seen.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import ml
from ae_tactile.localization.common import adc_noise, validate_windows
from ae_tactile.localization.covariance import arrival_fisher
from ae_tactile.localization.estimators import _plan
from ae_tactile.localization.segments import prepare

#: the contrasts x, y, xy of the 2 x 2 array as unit vectors over the channels (3, 4)
CONTRASTS = np.array([[1.0, 1.0, -1.0, -1.0], [1.0, -1.0, 1.0, -1.0], [1.0, -1.0, -1.0, 1.0]]) / 2
#: packets kept by default (the x and y contrasts need thousands)
DELAY_KEEP = 4096
#: packets before any contrast is applied
DELAY_MIN_COUNT = 64
#: a contrast is applied once its standard error is below this share of the best-measured
#: tenth of the packets' delay noise
DELAY_TOLERANCE = 0.3
#: a contrast this many standard errors from zero is applied whatever its precision
DELAY_SIGNIFICANT = 3.0
#: normalised residuals beyond this many robust sigma are dropped from the fit
DELAY_TRIM_SIGMA = 4.0
#: largest offset difference taken as a channel delay [s]: beyond, a wiring or model fault
MAX_OFFSET_S = 1e-6
#: the residuals' own noise model (`fit_delay_noise`) is applied once it explains them
#: better than the localizer's by this deviance (chi^2 of 2 degrees of freedom, p = 0.003)
DELAY_NOISE_DEVIANCE = 11.8
#: largest noise scale taken (a larger one is a fault of the model, not of the noise)
MAX_NOISE_SCALE = 100.0
_FORMAT = 1


def free_shifts(zb, w_rad_s, iterations: int = 3):
    """The four channels' own shifts [s] (K, 4), mean 0, that maximise the steered response
    power sum_f |sum_k zb_k e^{j w delta_k}|^2 from zb (the aligned spectra of a fit).

    Parameters
    ----------
    zb : ndarray, (K, 4, nb) complex
        Band bins of the four channels aligned by the fit.
    w_rad_s : ndarray, (nb,)
        Their angular frequencies [rad/s].
    iterations : int
        Newton steps.

    Returns
    -------
    ndarray, (K, 4)
        The shifts [s] (each step capped at a quarter period of the top bin).
    """
    k = zb.shape[0]
    delta = np.zeros((k, 4))
    w2 = w_rad_s * w_rad_s
    cap = 0.25 * 2 * np.pi / max(float(np.max(w_rad_s)), 1e-300)
    idx = np.arange(4)
    proj = np.eye(4) - 0.25
    for _ in range(iterations):
        z = zb * np.exp(1j * w_rad_s * delta[..., None])
        cb = np.conj(z.sum(axis=1))[:, None, :] * z
        g = -2.0 * (w_rad_s * cb.imag).sum(axis=2)
        h = 2.0 * np.einsum("kaf,kbf,f->kab", z, np.conj(z), w2).real
        h[:, idx, idx] -= 2.0 * (w2 * cb.real).sum(axis=2)
        # the common shift leaves P unchanged: solve on the sum-zero subspace
        step = -np.einsum("kab,kb->ka", np.linalg.pinv(proj @ h @ proj), g @ proj)
        step = np.clip(np.nan_to_num(step), -cap, cap)
        delta += step - step.mean(axis=1, keepdims=True)
    return delta


def fit_delay_noise(r, var):
    """The noise model the residuals ``r`` [s] (K,) of packets whose delay noise the
    localizer puts at ``var`` [s^2] (K,) show: r_k ~ N(0, scale var_k + sd^2), maximum
    likelihood, ``scale`` >= 1, ``sd`` >= 0.

    ``scale``: the delay noise is that many times the white-noise model's (coloured
    amplifier noise through the front end; it grows with the noise). ``sd``: each channel's
    arrival carries an error of its own of that size at any SNR (a sampled waveform that is
    no exact delayed copy of the others': aliasing behind a weak anti-alias filter, a
    front end that rings differently per channel). A residual is one unit combination of
    the four arrivals, so it carries sd^2 in full; tau_x and tau_y (a quarter of a sum of
    four arrivals) carry sd^2 / 4 each (`delay_noise_covariance`).

    Parameters
    ----------
    r, var : ndarray, (K,)

    Returns
    -------
    tuple
        (scale, sd [s], deviance: 2 ln L(scale, sd) - 2 ln L(1, 0) >= 0).
    """
    from scipy.optimize import minimize  # lazy: a learner's thread only, not every import

    r2 = np.asarray(r, float) ** 2
    v = np.asarray(var, float)
    v0 = float(np.median(v))

    def nll(q):
        tot = q[0] * v + q[1] * v0
        return float(np.sum(np.log(tot) + r2 / tot))

    base = nll((1.0, 0.0))
    best = None
    for start in ((1.0, 0.0), (max(1.0, float(np.mean(r2 / v))), 0.0),
                  (1.0, max(0.0, float(np.mean(r2)) / v0 - 1.0))):
        res = minimize(nll, start, method="L-BFGS-B",
                       bounds=[(1.0, MAX_NOISE_SCALE), (0.0, (0.99 * MAX_OFFSET_S) ** 2 / v0)])
        if np.isfinite(res.fun) and (best is None or res.fun < best.fun):
            best = res
    if best is None or not best.fun < base:
        return 1.0, 0.0, 0.0
    return float(best.x[0]), math.sqrt(float(best.x[1]) * v0), 2.0 * (base - float(best.fun))


def residual_normals(geometry: FingertipGeometry, point_m):
    """Unit vectors n (K, 4) orthogonal to 1 and to d t_k / d(s_x, s_y) at the points: the
    one combination of the four arrivals a fit leaves (sign: n . xy > 0).

    Parameters
    ----------
    geometry : FingertipGeometry
    point_m : ndarray, (K, 3)

    Returns
    -------
    ndarray, (K, 4)
    """
    _, dt, _ = geometry.arrival_time_derivatives(point_m[:, 0], point_m[:, 1])
    a = np.concatenate([np.ones(dt.shape[:2] + (1,)), dt / np.abs(dt).max()], axis=2)
    q, _ = np.linalg.qr(a, mode="complete")  # (K, 4, 4): last column spans the rest
    n = q[:, :, 3]
    n *= np.sign(n @ CONTRASTS[2])[:, None]
    return n


def measure(windows, sample_rate_hz, onset_index, geometry=None, channel_delays_s=None,
            channel_gains=None):
    """The delay residual of each packet (see the module docstring).

    Parameters
    ----------
    windows : array_like, (K, 4, M)
        Accepted single-emission packets [V].
    sample_rate_hz : float
    onset_index : array_like of int, (K,)
    geometry : FingertipGeometry, optional
    channel_delays_s : array_like (4,), optional
        The offsets in use [s] (the fit is made with them).
    channel_gains : array_like (4,), optional

    Returns
    -------
    tuple of ndarray
        (u (K, 3): B n, the contrasts' weights; y (K,): n . (shift + offsets in use) [s];
        var (K,): its variance [s^2]; ok (K,) bool: a usable measurement).
    """
    geo = geometry or FingertipGeometry()
    d = ml._delays_arg(channel_delays_s)
    x, on = validate_windows(windows, onset_index)
    plan = _plan(float(sample_rate_hz), geo, x.shape[2], None, 1e-6, 0.3e-6, "ml")
    with np.errstate(all="ignore"):
        prep = prepare(x, on, plan, channel_gains=channel_gains)
        core = ml.estimate(prep, plan, channel_delays_s=d)
        given = np.zeros(len(on), bool)
        s2 = adc_noise(prep.sigma2, prep.quant2, given)
        zb = core["zb"]
        f = arrival_fisher(zb, plan.w_al, s2, core["count"], plan.n_fft_al, core["n_bins"],
                           noise_by_noise=True)
        shift = free_shifts(zb, plan.w_al)
        n = residual_normals(geo, core["point"])
        y = np.einsum("ka,ka->k", n, shift + d)
        var = np.einsum("ka,kab,kb->k", n, np.linalg.pinv(f), n)
    ok = (np.isfinite(y) & np.isfinite(var) & (var > 0) & np.isfinite(s2) & ~core["clamped"]
          & (np.abs(y) < MAX_OFFSET_S))
    return n @ CONTRASTS.T, y, var, ok


class ChannelDelayLearner:
    """Per-channel delay offsets from accepted single packets (module docstring).

    Parameters
    ----------
    keep : int
        Packets kept (the last ones).
    min_count : int
        Packets before any contrast is applied.
    tolerance : float
        A contrast is applied once its standard error is below this share of the delay
        noise of the best-measured tenth of the packets.

    Returns
    -------
    ChannelDelayLearner
        ``applied_delays_s``: the offsets to take out of the arrivals (None until a
        contrast has converged).
    """

    def __init__(self, keep: int = DELAY_KEEP, min_count: int = DELAY_MIN_COUNT,
                 tolerance: float = DELAY_TOLERANCE):
        if not (int(keep) >= 8 and int(min_count) >= 4 and tolerance > 0):
            raise ValueError("keep >= 8, min_count >= 4 and tolerance > 0 needed")
        self.keep, self.min_count, self.tolerance = int(keep), int(min_count), float(tolerance)
        #: called with ``applied_delays_s`` and ``applied_noise`` whenever they may have
        #: changed (a refit, a load, a reset): the owner hands them to its
        #: `Localizer.set_channel_delays`
        self.on_update = None
        self._lock = threading.RLock()  # a learning thread, the store's saves and loads
        self.reset()

    def reset(self) -> None:
        """Forget every packet (another body, or a reset of the device's calibration)."""
        with self._lock:
            self._reset_locked()

    def _reset_locked(self) -> None:
        self._u = np.zeros((0, 3))
        self._y = np.zeros(0)
        self._var = np.zeros(0)
        #: estimated offsets [s] (4,), sum 0 (None: too few packets)
        self.delays_s = None
        #: standard errors of the x, y, xy contrasts [s] (3,)
        self.stderr_s = np.full(3, np.inf)
        #: which contrasts are applied (3,)
        self.converged = np.zeros(3, bool)
        #: which contrasts are known to the tolerance (3,): learning may slow down
        self.precise = np.zeros(3, bool)
        #: the offsets to take out of the arrivals [s] (4,) or None
        self.applied_delays_s = None
        #: packets used by the last fit (after trimming)
        self.n_used = 0
        #: the delay noise the residuals show (`fit_delay_noise`): scale of the localizer's
        #: white-noise variance, per-channel timing error [s], deviance over the localizer's
        self.noise_scale, self.timing_sd_s, self.noise_deviance = 1.0, 0.0, 0.0
        #: (scale, sd [s]) applied to the localizer's covariances: (1, 0) until the
        #: residuals show their own noise by DELAY_NOISE_DEVIANCE
        self.applied_noise = (1.0, 0.0)
        self._notify()

    def _notify(self) -> None:
        if self.on_update is not None:
            self.on_update(*self.applied)

    @property
    def applied(self) -> tuple:
        """(``applied_delays_s``, ``applied_noise``): `Localizer.set_channel_delays`'s
        arguments."""
        return self.applied_delays_s, self.applied_noise

    @property
    def all_converged(self) -> bool:
        """Every contrast applied."""
        return bool(self.converged.all())

    @property
    def all_precise(self) -> bool:
        """Every contrast known to the tolerance (not merely clearly non-zero)."""
        return bool(self.precise.all())

    @property
    def n_packets(self) -> int:
        """Packets kept."""
        return len(self._y)

    def add(self, windows, sample_rate_hz, onset_index, geometry=None, channel_gains=None) -> int:
        """Measure accepted single-emission packets (`measure`, with the offsets in use)
        and refit.

        Parameters
        ----------
        windows : array_like, (K, 4, M)
        sample_rate_hz : float
        onset_index : array_like of int, (K,)
        geometry : FingertipGeometry, optional
        channel_gains : array_like (4,), optional

        Returns
        -------
        int
            Packets taken.
        """
        u, y, var, ok = measure(windows, sample_rate_hz, onset_index, geometry,
                                self.applied_delays_s, channel_gains)
        self.add_measurements(u[ok], y[ok], var[ok])
        return int(ok.sum())

    def add_measurements(self, u, y, var) -> None:
        """Append `measure`'s rows (u (K, 3), y (K,) [s], var (K,) [s^2]) and refit."""
        with self._lock:
            self._u = np.concatenate([self._u, np.asarray(u, float)])[-self.keep:]
            self._y = np.concatenate([self._y, np.asarray(y, float)])[-self.keep:]
            self._var = np.concatenate([self._var, np.asarray(var, float)])[-self.keep:]
            self._fit()

    def _fit(self) -> None:
        """Trimmed weighted least squares of the contrasts; what is applied."""
        n = len(self._y)
        if n < max(self.min_count, 8):
            self.delays_s, self.applied_delays_s = None, None
            self.converged[:] = False
            self.precise[:] = False
            self.stderr_s[:] = np.inf
            self.n_used = 0
            self.noise_scale, self.timing_sd_s, self.noise_deviance = 1.0, 0.0, 0.0
            self.applied_noise = (1.0, 0.0)
            self._notify()
            return
        u, y, w = self._u, self._y, 1.0 / self._var
        keep = np.ones(n, bool)
        for _ in range(3):
            a = (u[keep] * w[keep, None]).T @ u[keep]
            beta = np.linalg.lstsq(a, (u[keep] * w[keep, None]).T @ y[keep], rcond=None)[0]
            z = (y - u @ beta) * np.sqrt(w)
            mad = 1.4826 * np.median(np.abs(z[keep] - np.median(z[keep])))
            new = np.abs(z) <= DELAY_TRIM_SIGMA * max(mad, 1e-12)
            if (new == keep).all() or new.sum() < 8:
                break
            keep = new
        # the residuals' own noise model, and the offsets weighted by it
        self.noise_scale, self.timing_sd_s, self.noise_deviance = fit_delay_noise(
            (y - u @ beta)[keep], self._var[keep])
        noisy = self.noise_deviance >= DELAY_NOISE_DEVIANCE
        self.applied_noise = (self.noise_scale, self.timing_sd_s) if noisy else (1.0, 0.0)
        if noisy:
            w = 1.0 / (self.noise_scale * self._var + self.timing_sd_s**2)
            a = (u[keep] * w[keep, None]).T @ u[keep]
            beta = np.linalg.lstsq(a, (u[keep] * w[keep, None]).T @ y[keep], rcond=None)[0]
            z = (y - u @ beta) * np.sqrt(w)
        m = int(keep.sum())
        a = (u[keep] * w[keep, None]).T @ u[keep]
        chi2 = float(np.sum(z[keep] ** 2)) / max(m - 3, 1)
        cov = np.linalg.pinv(a) * chi2
        self.stderr_s = np.sqrt(np.maximum(np.diag(cov), 0.0))
        self.delays_s = CONTRASTS.T @ beta
        scale, sd = self.applied_noise
        noise = math.sqrt(float(np.quantile(scale * self._var[keep] + sd * sd, 0.1)))
        # precise beside the packets' noise, or clearly not zero (taking it out then
        # leaves less bias than it removes)
        self.precise = self.stderr_s <= self.tolerance * noise
        self.converged = self.precise | (np.abs(beta) >= DELAY_SIGNIFICANT * self.stderr_s)
        self.n_used = m
        applied = CONTRASTS.T @ np.where(self.converged, beta, 0.0)
        # an offset of a microsecond is a wiring or model fault, never applied
        sane = np.isfinite(applied).all() and np.abs(applied).max() < MAX_OFFSET_S
        self.applied_delays_s = applied if self.converged.any() and sane else None
        self._notify()

    # ------------------------------------------------------------ persistence
    def calibration_state(self) -> dict | None:
        """The kept measurements as a JSON mapping for `ae_tactile.calibration.CalibrationStore`
        (None: nothing learnt).

        Returns
        -------
        dict or None
            {"format": 1, "u": [[x, y, xy], ...], "y_s": [...], "var_s2": [...]}.
        """
        with self._lock:
            if not len(self._y):
                return None
            return {"format": _FORMAT, "u": self._u.tolist(), "y_s": self._y.tolist(),
                    "var_s2": self._var.tolist()}

    def load_calibration(self, state: dict) -> None:
        """Start from a saved `calibration_state`.

        Parameters
        ----------
        state : dict
            As `calibration_state` wrote it.

        Returns
        -------
        None
            ValueError when it cannot be used (another format, unequal lengths, rows that
            are not unit-norm contrasts, non-finite or out-of-range values): nothing
            changed then.
        """
        if not isinstance(state, dict) or state.get("format") != _FORMAT:
            raise ValueError("channel delays: unknown format")
        try:
            u = np.array(state["u"], dtype=float)
            y = np.array(state["y_s"], dtype=float)
            var = np.array(state["var_s2"], dtype=float)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"channel delays: malformed ({exc})") from None
        if not (u.ndim == 2 and u.shape[1:] == (3,) and y.shape == (len(u),)
                and var.shape == (len(u),) and np.isfinite(u).all() and np.isfinite(y).all()
                and np.isfinite(var).all() and (var > 0).all()
                and (np.abs(y) < MAX_OFFSET_S).all()
                and np.allclose(np.linalg.norm(u, axis=1), 1.0, atol=1e-6)):
            raise ValueError("channel delays: values out of range")
        with self._lock:
            self._reset_locked()
            self._u, self._y, self._var = u[-self.keep:], y[-self.keep:], var[-self.keep:]
            self._fit()

    #: the name of the task's protocol (`load_calibration` is the store's)
    load_calibration_state = load_calibration

    def status(self) -> str:
        """The offsets in words (diagnostics)."""
        with self._lock:
            return self._status_locked()

    def _status_locked(self) -> str:
        if self.delays_s is None:
            return f"learning ({self.n_packets} of {self.min_count} packets)"
        d = " / ".join(f"{v * 1e9:+.1f}" for v in self.delays_s)
        se = " / ".join(f"{v * 1e9:.1f}" for v in self.stderr_s)
        on = ",".join(n for n, c in zip(("x", "y", "xy"), self.converged) if c) or "none"
        scale, sd = self.applied_noise
        noise = (f"delay noise {scale:.2f} x the model's + {sd * 1e9:.1f} ns per channel"
                 if (scale, sd) != (1.0, 0.0) else "delay noise as modelled")
        return (f"offsets {d} ns (x/y/xy se {se} ns) from {self.n_used} packets; "
                f"applied: {on}; {noise}")
