# SPDX-License-Identifier: Apache-2.0
"""The per-packet hot path: `Localizer`, an estimator with its settings fixed and its tables
warmed up, localizing one window at a time (`localize_one`, compiled with numba where
available) or a batch (`__call__`, the same as `localize`).
"""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.dsp.channel_checks import identical_channels, packet_identical
from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import fast
from ae_tactile.localization.common import Reason, per_packet, validate_windows
from ae_tactile.localization.estimators import (
    _gains_arg,
    _iterations,
    _noise_arg,
    _plan,
    _positive_arg,
    _reject_identical,
    delay_noise_arg,
    localize,
    resolve_engine,
)
from ae_tactile.localization.registry import get_estimator
from ae_tactile.localization.result import PacketLocation, _result_from_kernel

#: the `__call__` keywords the compiled batch with channel delays takes (others: numpy)
_DELAYED_BATCH_KEYS = frozenset({"geometry", "saturated", "channel_gains", "noise_rms_v"})
#: the input types `localize_one` takes without conversion
_FLOATS = (np.dtype(np.float64), np.dtype(np.float32))
_REALS = (int, np.integer, float, np.floating)



class Localizer:
    """A configured `localize` (what the ROS node holds):
    ``Localizer(method='ml', ...)(windows, fs, onset)``.

    ``localize_one(window (4, M), fs, onset)`` is the per-packet hot path: with numba and
    ``ml`` one compiled call per packet (plans and tables cached per (fs, M, geometry));
    ``warm_up(geometry, fs, n_samples)`` compiles and caches it before acquisition.

    Parameters
    ----------
    method : str
        A name in `available_methods()` (default ``"ml"``).
    **kwargs
        The keyword arguments of `localize` (``geometry``, ``band_hz``, ``min_snr_db``,
        ``overlap_threshold``, ``full_scale_v``, ``engine``, estimator options...), held
        for every call; a call's own keywords override them.

    Returns
    -------
    Localizer
        Calling it returns the `LocalizationResult` of `localize`; `localize_one` a
        `PacketLocation`.

    Raises
    ------
    ValueError
        Unknown method, non-finite ``min_snr_db`` or non-positive ``overlap_threshold``.
    """

    _ONE_KEYS = frozenset(
        {
            "band_hz",
            "min_snr_db",
            "overlap_threshold",
            "pre_onset_s",
            "echo_guard_s",
            "full_scale_v",
            "engine",
            "iterations",
            "geometry",
        }
    )

    def __init__(self, method="ml", **kwargs):
        info = get_estimator(method)
        self.method = method
        self.kwargs = kwargs
        opts = {
            k: v
            for k, v in kwargs.items()
            if k not in self._ONE_KEYS and k not in ("noise_rms_v", "saturated", "channel_gains")
        }
        if "iterations" in kwargs:
            opts["iterations"] = kwargs["iterations"]
        self._one_engine = resolve_engine(kwargs.get("engine"), method, opts)
        if self._one_engine == "numba":
            self._iterations = _iterations(kwargs)
            self._min_snr_db = float(kwargs.get("min_snr_db", 5.0))
            thr = kwargs.get("overlap_threshold")
            self._thr = info.overlap_threshold if thr is None else float(thr)
            fsv = kwargs.get("full_scale_v")
            self._full_scale = np.nan if fsv is None else _positive_arg("full_scale_v", fsv)
            if not (np.isfinite(self._min_snr_db) and np.isfinite(self._thr) and self._thr > 0):
                raise ValueError("min_snr_db must be finite and overlap_threshold positive")
        self._plans = {}
        self._default_geometry = kwargs.get("geometry") or FingertipGeometry()
        #: the channels' own delays taken out of the arrivals (`set_channel_delays`) [s]
        self.channel_delays_s = None
        #: the device's delay noise the covariances carry (`set_channel_delays`): (scale,
        #: per-channel timing sd [s]), None: the white-noise model's
        self.delay_noise = None
        self._cnoise = fast.noise_args(None)
        #: the device's pulse that refines every accepted point (`set_front_end`); None:
        #: the estimator's answer as it is
        self.front_end = None

    def set_channel_delays(self, channel_delays_s, delay_noise=None) -> None:
        """Model each channel's arrival as t_k(s) + d_k from now on (``ml`` only; the other
        estimators ignore it): the front end's per-channel delay, e.g. a
        `ae_tactile.localization.ChannelDelayLearner`'s ``applied_delays_s``; and the
        delay noise its residuals show (its ``applied_noise``), carried by every
        covariance from now on (every method).

        Parameters
        ----------
        channel_delays_s : array_like (4,) or None
            d_k [s], finite, |d_k| < 1 us (a common part only shifts the emission
            instant); None: no correction.
        delay_noise : (float, float) or None
            (scale >= 1 of the model's delay covariance, each channel's own timing error
            [s], 0 <= sd < 1 us); None: the model's.

        Returns
        -------
        None
            ValueError on a bad value (nothing changed then).
        """
        dn = delay_noise_arg(delay_noise)
        if channel_delays_s is None:
            d = None
        else:
            d = np.array(channel_delays_s, dtype=np.float64).reshape(-1)
            if d.shape != (4,) or not np.isfinite(d).all() or np.abs(d).max() >= 1e-6:
                raise ValueError(
                    "channel_delays_s must be 4 finite delays below 1 us [s], got "
                    f"{channel_delays_s!r}"
                )
        self.channel_delays_s = d if d is not None and d.any() else None
        self.delay_noise, self._cnoise = dn, fast.noise_args(dn)

    def set_front_end(self, pulse) -> None:
        """Refine every accepted point from now on by the one-emission fit with the
        device's pulse (`ae_tactile.localization.refine`): the estimate that stays at the
        Cramer-Rao bound behind an anti-alias filter that lets the pulse alias, at
        0.2-0.4 ms a packet. A packet whose fit fails its residual test keeps the
        estimator's answer (``refined`` False).

        Parameters
        ----------
        pulse : PulseModel or None
            The device's front end (`PulseModel.from_spec` of what it states,
            `PulseModel.from_config`, or one learnt); None: no refinement.

        Returns
        -------
        None
            TypeError on anything else.
        """
        from ae_tactile.localization.overlap.pulse import PulseModel  # lazy: cycle

        if pulse is not None and not isinstance(pulse, PulseModel):
            raise TypeError(f"pulse must be a PulseModel or None, got {type(pulse).__name__}")
        self.front_end = pulse

    def _refined(self, res, windows, sample_rate_hz, onset_index, kw):
        """``res`` with its accepted points refined with `front_end` (unchanged without
        one)."""
        if self.front_end is None:
            return res
        from ae_tactile.localization.refine import refine_result  # lazy: cycle

        return refine_result(res, windows, sample_rate_hz, onset_index, self.front_end,
                             geometry=kw.get("geometry") or self._default_geometry,
                             noise_rms_v=kw.get("noise_rms_v"),
                             channel_delays_s=self.channel_delays_s)[0]

    def __call__(self, windows, sample_rate_hz, onset_index, **overrides):
        res = self._call(windows, sample_rate_hz, onset_index, **overrides)
        if self.front_end is None:
            return res
        kw = dict(self.kwargs)
        kw.update(overrides)
        return self._refined(res, windows, sample_rate_hz, onset_index, kw)

    def _call(self, windows, sample_rate_hz, onset_index, **overrides):
        kw = dict(self.kwargs)
        kw.update(overrides)
        kw.setdefault("delay_noise", self.delay_noise)
        d = self.channel_delays_s
        if d is None or self.method != "ml":
            return localize(windows, sample_rate_hz, onset_index, method=self.method, **kw)
        if self._one_engine == "numba" and set(overrides) <= _DELAYED_BATCH_KEYS:
            return self._batch_delayed(windows, sample_rate_hz, onset_index, kw, d)
        return localize(windows, sample_rate_hz, onset_index, method=self.method,
                        channel_delays_s=d, **kw)

    def _batch_delayed(self, windows, sample_rate_hz, onset_index, kw, d):
        """`localize` through the compiled kernel with the channels' own delays ``d``
        (the settings this localizer was built with, which its compiled path holds;
        overrides: geometry, saturated, channel_gains, noise_rms_v)."""
        geo = kw.get("geometry") or FingertipGeometry()
        fs = _positive_arg("sample_rate_hz", sample_rate_hz)
        x, onset = validate_windows(windows, onset_index, copy=False)
        k = x.shape[0]
        if k == 0:
            return localize(x, fs, onset, method=self.method, **kw)
        noise = _noise_arg(kw.get("noise_rms_v"), k)
        sat = kw.get("saturated")
        sat = (np.full(k, -1, np.int8) if sat is None
               else per_packet("saturated", sat, k, dtype=bool).astype(np.int8))
        out, pt, cov, ctau = fast.run_batch(
            x, onset, self._tables(fs, x.shape[2], geo), noise_rms=noise, sat=sat,
            full_scale=self._full_scale, gains=_gains_arg(kw.get("channel_gains")),
            iterations=self._iterations, min_snr_db=self._min_snr_db, thr=self._thr,
            channel_delays_s=d, delay_noise=self.delay_noise,
        )
        res = _result_from_kernel(self.method, {"iterations": self._iterations}, out, pt, cov,
                                  ctau)
        return _reject_identical(res, identical_channels(x, onset, noise))

    def _tables(self, fs, m, geometry):
        key = (fs, m, geometry)
        hit = self._plans.get(key)
        if hit is None:
            plan = _plan(
                fs,
                geometry,
                m,
                self.kwargs.get("band_hz"),
                self.kwargs.get("pre_onset_s", 1e-6),
                self.kwargs.get("echo_guard_s", 0.3e-6),
                self.method,
            )
            hit = fast.tables_for(plan)
            if len(self._plans) > 32:
                self._plans.clear()
            self._plans[key] = hit
        return hit

    def localize_one(
        self,
        samples_v,
        sample_rate_hz,
        onset_index,
        *,
        noise_rms_v=None,
        saturated=False,
        geometry=None,
        channel_gains=None,
        check_identical=True,
    ) -> PacketLocation:
        """Localize one window: the per-packet hot path.

        Never raises on the data (NaN, zeros, clipping: a rejection with its reason).

        Parameters
        ----------
        samples_v : ndarray, (4, M)
            The window [V], float32 or float64 (other real dtypes are converted).
        sample_rate_hz : float
            Sample rate [Hz], > 0.
        onset_index : int
            First sample at/after the earliest arrival, in the window.
        noise_rms_v : float, optional
            Known noise sigma [V], > 0; None or NaN: measured before the onset.
        saturated : bool or None
            Upstream clip flag; None: the flat-top heuristic decides.
        geometry : FingertipGeometry, optional
            Default: the one given at construction, else the default tip.
        channel_gains : array_like (4,), optional
            Relative gains of the 4 channels (divided out).
        check_identical : bool
            Reject four identical channels (`packet_identical`, reason NO_SIGNAL); False
            only where the caller has just checked the window (the pipeline does).

        Returns
        -------
        PacketLocation
            accepted, reason, point_m, covariance_m2, polarity, confidence, ... as floats.

        Raises
        ------
        ValueError, TypeError
            Bad arguments (shape, dtype, non-positive rate, non-integer onset).
        """
        geo = self._default_geometry if geometry is None else geometry
        if self._one_engine != "numba":
            return self._one_numpy(samples_v, sample_rate_hz, onset_index, geo, noise_rms_v,
                                   saturated, channel_gains)
        x, fs, on, nr = _one_args(samples_v, sample_rate_hz, onset_index, noise_rms_v)
        sat = -1 if saturated is None else int(bool(saturated))
        if not isinstance(geo, FingertipGeometry):
            raise TypeError(f"geometry must be a FingertipGeometry, got {type(geo).__name__}")
        tb = self._tables(fs, x.shape[1], geo)
        gains = None if channel_gains is None else _gains_arg(channel_gains)
        out = np.empty(fast.N_SCALAR_OUT)
        pt = np.empty(3)
        cov = np.empty((3, 3))
        ctau = np.empty((2, 2))
        fast.run_one(x, on, nr, sat, self._full_scale, gains, tb, self._iterations,
                     self._min_snr_db, self._thr, out, pt, cov, ctau, self.channel_delays_s,
                     self._cnoise)
        loc = PacketLocation(out, pt, cov, ctau)
        if check_identical and packet_identical(x, on, nr):
            _reject_identical_one(loc)
        if loc.accepted and self.front_end is not None:
            self._refine_one(loc, x, fs, on, nr, geo)
        return loc

    def _refine_one(self, loc, x, fs, on, nr, geo) -> None:
        """`localize_one`'s answer refined in place with `front_end` (`set_front_end`)."""
        from ae_tactile.localization.refine import refine_points  # lazy: cycle

        got = refine_points(x[None], fs, [on], loc.point_m[None], [loc.emission_offset_s],
                            self.front_end, geometry=geo,
                            noise_rms_v=None if not math.isfinite(nr) else nr,
                            channel_delays_s=self.channel_delays_s)
        if not got.refined[0]:
            return
        p = got.point_m[0]
        loc.point_m, loc.covariance_m2 = p, got.covariance_m2[0]
        loc.emission_offset_s = float(got.emission_offset_s[0])
        polar, azimuth = geo.angles_from_points(p[None])
        loc.polar_rad, loc.azimuth_rad = float(polar[0]), float(azimuth[0])
        loc.tau_x_s, loc.tau_y_s = (float(v) for v in geo.exact_delays_s(p))
        loc.refined = True

    def _one_numpy(self, samples_v, sample_rate_hz, onset_index, geo, noise_rms_v, saturated,
                   channel_gains) -> PacketLocation:
        """`localize_one` through `localize` (engine numpy, or a method other than ml)."""
        kw = dict(self.kwargs)
        kw.update(
            geometry=geo,
            noise_rms_v=noise_rms_v,
            channel_gains=channel_gains,
            saturated=None if saturated is None else [bool(saturated)],
        )
        x = np.asarray(samples_v)
        if x.ndim != 2:
            raise ValueError(f"samples_v must have shape (4, M), got {x.shape}")
        if self.channel_delays_s is not None and self.method == "ml":
            kw.pop("geometry")
            res = self(x[None], sample_rate_hz, [onset_index], geometry=geo, **kw)
        else:
            res = localize(x[None], sample_rate_hz, [onset_index], method=self.method,
                           delay_noise=self.delay_noise, **kw)
            res = self._refined(res, x[None], sample_rate_hz, [onset_index], kw)
        return PacketLocation.from_result(res, 0)

    def warm_up(self, geometry=None, sample_rate_hz=10e6, n_samples=400):
        """Compile and cache the kernels (float32 and float64 windows) and the plan for this
        (geometry, fs, M) so that the first packet is fast. Returns self."""
        geo = self._default_geometry if geometry is None else geometry
        fs = _positive_arg("sample_rate_hz", sample_rate_hz)
        m = int(n_samples)
        rng = np.random.default_rng(0)
        x = rng.standard_normal((4, m)) * 1e-3
        for dt in (np.float64, np.float32):
            self.localize_one(x.astype(dt), fs, m // 4, geometry=geo)
            self(x.astype(dt)[None], fs, [m // 4], geometry=geo)
        return self


def _reject_identical_one(loc: PacketLocation) -> None:
    """The entry check of `Localizer.localize_one` (as `localize`'s): four channels that
    are one signal (`ae_tactile.dsp.channel_checks.packet_identical`) are rejected as
    NO_SIGNAL, confidence 0, polarity 0."""
    loc.reason_flags = int(loc.reason_flags) | (1 << int(Reason.NO_SIGNAL))
    first = next(r for r in Reason if r and loc.reason_flags & (1 << int(r)))
    loc.reason = Reason(first)
    loc.accepted = False
    loc.confidence = 0.0
    loc.polarity = 0


def _one_args(samples_v, sample_rate_hz, onset_index, noise_rms_v):
    """The checked arguments of the compiled `Localizer.localize_one`: (x (4, M) float
    C-contiguous, fs [Hz], onset int, noise sigma [V] or NaN); TypeError / ValueError."""
    x = samples_v
    if not (type(x) is np.ndarray and x.dtype in _FLOATS and x.flags.c_contiguous):
        x = np.asarray(x)
        if x.dtype == object or not (
            np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)
        ):
            raise TypeError(f"samples_v must be a real numeric array, got dtype {x.dtype}")
        x = np.ascontiguousarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] != 4 or x.shape[1] < 4:
        raise ValueError(f"samples_v must have shape (4, M) with M >= 4, got {x.shape}")
    fs = sample_rate_hz
    if type(fs) is not float:
        fs = _positive_arg("sample_rate_hz", fs)
    elif not (fs > 0 and fs < np.inf):
        raise ValueError(
            f"sample_rate_hz must be a positive finite number, got {sample_rate_hz!r}"
        )
    on = onset_index
    if type(on) is not int:
        if isinstance(on, (bool, np.bool_)) or not isinstance(on, _REALS):
            raise TypeError(f"onset_index must be an integer sample index, got {on!r}")
        if not (np.isfinite(on) and on == int(on)):
            raise ValueError(f"onset_index must be an integer sample index, got {on!r}")
        on = int(on)
    if noise_rms_v is None:
        nr = np.nan
    else:
        nr = float(noise_rms_v)
        if not (nr > 0 and nr < np.inf) and not math.isnan(nr):
            raise ValueError(
                f"noise_rms_v must be positive and finite (NaN: unknown), got {noise_rms_v!r}"
            )
    return x, fs, on, nr
