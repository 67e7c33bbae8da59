# SPDX-License-Identifier: Apache-2.0
"""The known pulse shape of the overlap model: the front end (Butterworth high-pass and
low-pass, optional medium loss) driven by the collision pressure, in closed form at any
sub-sample time (`PulseModel`), and its cached sample tables.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ae_tactile.geometry import LOWPASS_FAMILIES, front_end_lowpass, front_end_stages
from ae_tactile.localization.common import PRE_ONSET_S, adc_noise
from ae_tactile.localization.segments import _pre_onset_noise, _quantum2


@dataclass(frozen=True)
class PulseModel:
    """Known pulse shape h(t): front-end response to the collision pressure (paper Eq. 9).

    H(s) = P1(s) HP_n(s) LP_m(s), P1(s) = s / ((s + alpha)(s + 2 alpha)) (= 2/(s + 2 alpha)
    - 1/(s + alpha)), Butterworth HP (``highpass_hz``, order ``highpass_order``) and LP
    (``lowpass_hz``, order ``lowpass_order``; None: no low-pass). h(t) = sum_p r_p e^{p t}
    for t >= 0 (simple poles), 0 before, scaled to a peak of +1 (a touch starts positive).
    Parameters of the product's front end, not of any simulator.

    ``attenuation_db_per_m_at_1mhz`` > 0: a lossy medium, loss att l (f / 1 MHz)^2 dB over
    a path of length l, realised as one real pole per path, W_l(s) = w_a / (s + w_a) with
    10 log10(1 + (1 MHz / f_a)^2) = att l (the causal viscous law of docs/simulator.md):
    every arrival's pulse then depends on its path length.
    """

    highpass_hz: float = 100e3
    highpass_order: int = 2
    lowpass_hz: float | None = 1e6
    lowpass_order: int = 4
    alpha_1_s: float = 3000.0
    attenuation_db_per_m_at_1mhz: float = 0.0
    #: [1] frequency exponent y of the loss: 2 is the one-pole viscous law above; any
    #: other is the power law att l (f / 1 MHz)^y with its Kramers-Kronig dispersion
    #: (phase velocity c at ``attenuation_ref_hz`` [Hz]), applied per path by FFT
    attenuation_exponent: float = 2.0
    attenuation_ref_hz: float = 300e3
    #: explicit poles [rad/s] and residues of h (a pulse learnt from the device's own
    #: packets, `ae_tactile.localization.overlap.learn`); empty: the front end above
    poles_rad_s: tuple = ()
    residues: tuple = ()
    #: per-channel gain [1] and delay [s] of the device's four chains (learnt with the
    #: pulse; empty: identical channels): `correct_channels` removes them from a window
    channel_gain: tuple = ()
    channel_delay_s: tuple = ()
    #: [1] share of a single emission's energy the pulse leaves unexplained on the
    #: device's own single touches (residual energy over noise / window energy, a high
    #: quantile; learnt with the pulse, 0 for the nominal one): a further emission must
    #: explain more than this misfit of the window's energy (`decide._model_order`)
    misfit_share: float = 0.0
    #: the front end's other shapes: one first-order RC stage per corner [Hz] in place of
    #: the Butterworth high-pass (empty: the Butterworth), the low-pass family ('butter',
    #: 'bessel' with its corner at -3 dB, 'cheby1' with ``lowpass_ripple_db`` [dB] of
    #: ripple) and an amplifier pole [Hz] (None: none), as `geometry.front_end_stages`
    highpass_rc_hz: tuple = ()
    lowpass_family: str = "butter"
    lowpass_ripple_db: float = 0.5
    amplifier_pole_hz: float | None = None

    def __post_init__(self):
        if self.lowpass_family not in LOWPASS_FAMILIES:
            raise ValueError(f"lowpass_family must be one of {LOWPASS_FAMILIES}, "
                             f"got {self.lowpass_family!r}")
        if any(not (math.isfinite(f) and f > 0) for f in self.highpass_rc_hz):
            raise ValueError(f"highpass_rc_hz must hold positive corners [Hz], got "
                             f"{self.highpass_rc_hz!r}")

    def _slowest_corner_hz(self) -> float:
        """The lowest high-pass corner [Hz] (the pulse's longest time scale)."""
        return min(self.highpass_rc_hz) if self.highpass_rc_hz else self.highpass_hz

    @classmethod
    def from_poles(cls, poles_rad_s, residues) -> "PulseModel":
        """A pulse given by its poles and residues: h(t) = Re sum_p r_p e^{p t}, t >= 0
        (every complex pole with its conjugate, whose residue is the conjugate), scaled to
        a unit peak; the corner fields keep their defaults and are not used.

        Parameters
        ----------
        poles_rad_s : array_like of complex, (P,)
            Poles [rad/s], Re < 0.
        residues : array_like of complex, (P,)
            Residues [1/s].

        Returns
        -------
        PulseModel
        """
        p = np.asarray(poles_rad_s, complex).ravel()
        r = np.asarray(residues, complex).ravel()
        if p.size == 0 or p.shape != r.shape:
            raise ValueError("poles_rad_s and residues must be non-empty and of one length")
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(r)) and np.all(p.real < 0)):
            raise ValueError("poles must be finite with a negative real part")
        return cls(poles_rad_s=tuple(complex(v) for v in p),
                   residues=tuple(complex(v) for v in r))

    def correct_channels(self, windows, sample_rate_hz, noise_rms_v=None, onset_index=None):
        """Windows with the channels' own gain and delay removed (channel k advanced by
        ``channel_delay_s[k]``, a band-limited shift, and divided by ``channel_gain[k]``),
        and the noise sigma to use on them; both unchanged when the model has none.

        Parameters
        ----------
        windows : numpy.ndarray, (K, 4, M)
            Windows [V].
        sample_rate_hz : float
            Sample rate [Hz].
        noise_rms_v : float or array_like (K,), optional
            A given analog noise sigma [V]: the corrected samples are off the ADC's grid,
            so its rounding (q^2 / 12, q the apparent quantum of the raw windows), which
            the estimators add to a given sigma only on quantized data, is added here.
        onset_index : array_like of int (K,), optional
            With no sigma given: the noise is measured on the raw windows before their
            onsets (as the estimators measure it, the quantum included) and returned as the
            sigma to use: after the shift the samples are off the ADC's grid, where the
            quantum can no longer be seen (below ~1 LSB of noise the shifted samples would
            under-read it).

        Returns
        -------
        (numpy.ndarray (K, 4, M), noise_rms_v)
        """
        if not self.channel_gain and not self.channel_delay_s:
            return windows, noise_rms_v
        if noise_rms_v is None and onset_index is not None:
            noise_rms_v = raw_noise_rms(windows, onset_index, sample_rate_hz)
        elif noise_rms_v is not None:
            dif = np.abs(np.diff(windows, axis=-1))
            dif[dif == 0] = np.inf
            q = dif.min(axis=(-2, -1))
            q2 = np.where(np.isfinite(q), q * q / 12.0, 0.0)
            noise_rms_v = np.sqrt(np.asarray(noise_rms_v, float) ** 2 + q2)
        x = shift_channels(windows, sample_rate_hz, self.channel_gain or (1.0,) * 4,
                           self.channel_delay_s or (0.0,) * 4)
        return x, noise_rms_v

    @property
    def learnt(self) -> bool:
        """The pulse is given by explicit poles and residues (`from_poles`)."""
        return len(self.poles_rad_s) > 0

    @classmethod
    def from_config(cls, config) -> "PulseModel":
        """From any object with the front-end attributes of ``ae_tactile.sim.SimConfig``
        (its high-pass, low-pass family, amplifier pole and emission decay, and its medium
        loss, with the power law's exponent, when its ``attenuation`` is on): the pulse a
        device's stated front end gives."""
        att = float(getattr(config, "attenuation_db_per_m", 0.0) or 0.0)
        rc = getattr(config, "highpass_rc_hz", None)
        amp = getattr(config, "amplifier_pole_hz", None)
        return cls(
            float(config.highpass_hz),
            int(config.highpass_order),
            None if config.lowpass_hz is None else float(config.lowpass_hz),
            int(config.lowpass_order),
            float(getattr(config, "emission_alpha_1_s", 3000.0)),
            attenuation_db_per_m_at_1mhz=att,
            attenuation_exponent=(float(config.attenuation_exponent)
                                  if getattr(config, "attenuation_law", "pole") == "power"
                                  else 2.0),
            attenuation_ref_hz=float(getattr(config, "attenuation_ref_hz", 300e3)),
            highpass_rc_hz=tuple(float(f) for f in rc) if rc else (),
            lowpass_family=str(getattr(config, "lowpass_family", "butter")),
            lowpass_ripple_db=float(getattr(config, "lowpass_ripple_db", 0.5)),
            amplifier_pole_hz=None if amp is None else float(amp),
        )

    @classmethod
    def from_spec(cls, spec: str) -> "PulseModel":
        """A front end stated as text, e.g. the driver's ``front_end`` parameter:
        whitespace- or comma-separated ``name=value`` of the fields in `SPEC_FIELDS`,
        ``highpass_rc_hz`` as corners joined by '/': "highpass_hz=50e3 highpass_order=1
        lowpass_hz=800e3 lowpass_order=2", "highpass_rc_hz=60e3/69e3 lowpass_hz=600e3
        lowpass_order=6 lowpass_family=bessel". Unnamed fields keep their defaults
        (``lowpass_hz=none``: no low-pass).

        Parameters
        ----------
        spec : str

        Returns
        -------
        PulseModel
            ValueError naming the item on an unknown name, a bad value or a repeated name.
        """
        kw: dict = {}
        for item in str(spec).replace(",", " ").split():
            name, eq, value = item.partition("=")
            if not eq or name not in SPEC_FIELDS:
                raise ValueError(f"front end item {item!r}: expected name=value with a name "
                                 f"in {sorted(SPEC_FIELDS)}")
            if name in kw:
                raise ValueError(f"front end item {item!r}: {name} given twice")
            try:
                kw[name] = SPEC_FIELDS[name](value)
            except ValueError as e:
                raise ValueError(f"front end item {item!r}: {e}") from None
        try:
            return cls(**kw)
        except (TypeError, ValueError) as e:
            raise ValueError(f"front end {spec!r}: {e}") from None

    def spec(self) -> str:
        """The `from_spec` text of this front end (a learnt pulse: its pole count)."""
        if self.learnt:
            return f"learnt ({len(self.poles_rad_s)} poles)"
        out = []
        for name in SPEC_FIELDS:
            v = getattr(self, name)
            if name == "highpass_rc_hz":
                if v:
                    out.append(f"{name}=" + "/".join(f"{f:g}" for f in v))
            elif name in ("highpass_hz", "highpass_order") and self.highpass_rc_hz:
                continue
            elif v is not None or name == "lowpass_hz":
                out.append(f"{name}={v:g}" if isinstance(v, float) else f"{name}={v}")
        return " ".join(out)

    @classmethod
    def for_sample_rate(cls, sample_rate_hz: float) -> "PulseModel":
        """The product's default front end at this ADC rate: its low-pass is
        `ae_tactile.geometry.front_end_lowpass` (1 MHz, order 4; below 3.33 MS/s the
        anti-alias filter, 0.3 fs, order 8). The default wherever ``pulse`` is None."""
        lp_hz, lp_order = front_end_lowpass(float(sample_rate_hz))
        return cls(lowpass_hz=lp_hz, lowpass_order=lp_order)

    def attenuation_pole_rad_s(self, path_m):
        """w_a (rad/s) of paths of length ``path_m`` (inf when lossless)."""
        loss_db = np.asarray(path_m, float) * float(self.attenuation_db_per_m_at_1mhz)
        x = np.expm1(loss_db * (math.log(10.0) / 10.0))
        return np.where(x > 0, 2.0 * math.pi * 1e6 / np.sqrt(np.where(x > 0, x, 1.0)), np.inf)

    def poles_residues(self):
        """(poles (P,) complex, residues (P,) complex) of h, peak-normalised (cached)."""
        cache = _PR_CACHE.get(self)
        if cache is not None:
            return cache
        if self.learnt:
            poles = np.array(self.poles_rad_s, complex)
            res = np.array(self.residues, complex)
            # the slowest pole sets the span searched for the peak [s]
            span = min(20.0 / np.min(np.abs(poles.real)), 1e-3)
            t = np.linspace(0.0, span, 20001)
            h = (res[None, :] * np.exp(poles[None, :] * t[:, None])).sum(axis=1).real
            i = int(np.argmax(np.abs(h)))
            # the peak refined around the coarse one (one coarse step either side)
            t = np.linspace(t[max(i - 1, 0)], t[min(i + 1, t.size - 1)], 2001)
            h = (res[None, :] * np.exp(poles[None, :] * t[:, None])).sum(axis=1).real
            res = res / h[np.argmax(np.abs(h))]
            _PR_CACHE[self] = (poles, res)
            return poles, res
        zs = [np.zeros(1, complex)]
        ps, k = [np.array([-self.alpha_1_s, -2.0 * self.alpha_1_s])], 1.0
        for z, p, kk in front_end_stages(
                self.highpass_hz, self.highpass_order, self.highpass_rc_hz or None,
                self.lowpass_hz, self.lowpass_order, self.lowpass_family,
                self.lowpass_ripple_db, self.amplifier_pole_hz):
            zs.append(z)
            ps.append(p)
            k *= kk
        zeros = np.concatenate(zs).astype(complex)
        poles = np.concatenate(ps).astype(complex)
        # equal corners (two alike RC stages) would make a double pole: split by 1e-6
        poles = poles * (1.0 + 1e-6 * _repeats(poles))
        res = np.array(
            [
                k * np.prod(q - zeros) / np.prod(q - np.delete(poles, i))
                for i, q in enumerate(poles)
            ]
        )
        t = np.linspace(0.0, 20.0 / (2 * math.pi * self._slowest_corner_hz()), 20001)
        h = (res[None, :] * np.exp(poles[None, :] * t[:, None])).sum(axis=1).real
        res = res / h[np.argmax(np.abs(h))]
        _PR_CACHE[self] = (poles, res)
        return poles, res

    def waveform(self, t_s):
        """h(t) (unit peak) at times t_s (s, any shape)."""
        p, r = self.poles_residues()
        t = np.asarray(t_s, float)
        v = (r * np.exp(p * np.maximum(t, 0.0)[..., None])).sum(axis=-1).real
        return np.where(t >= 0, v, 0.0)


_PR_CACHE: dict = {}


def raw_noise_rms(windows, onset_index, sample_rate_hz) -> np.ndarray:
    """(K,) noise sigma [V] of raw windows (K, 4, M), measured as the estimators measure
    it: the pooled variance of the samples before each onset (less the segments'
    `pre_onset_s` lead), through the quantizer's relation when they are quantized
    (`adc_noise`: sigma^2 + q^2 / 12); NaN with fewer than 4 such samples."""
    x = np.asarray(windows, float)
    on = np.broadcast_to(np.asarray(onset_index, np.int64).reshape(-1), (x.shape[0],))
    pre = max(2, int(math.ceil(PRE_ONSET_S * float(sample_rate_hz))))
    n_pre = np.clip(on - pre, 0, x.shape[2])
    sigma2, _ = _pre_onset_noise(x, n_pre)
    return np.sqrt(adc_noise(sigma2, _quantum2(x), False))


def power_law_filter(x, path_m, fs, pulse: PulseModel):
    """x (..., L) [V] through each path's power-law loss (``path_m`` (...) [m]): H(f) =
    exp(-(a(f) + j b(f)) l), a = a1 (f / 1 MHz)^y [Np/m], b = a1 tan(pi y / 2)
    [(f / 1 MHz)^y - (f / 1 MHz)(f_ref / 1 MHz)^(y - 1)] (Szabo's causal dispersion),
    by FFT over 2 L samples (the loss's short response does not wrap onto the segment)."""
    n = 2 * x.shape[-1]
    a1 = float(pulse.attenuation_db_per_m_at_1mhz) * math.log(10.0) / 20.0  # [Np/m]
    y = float(pulse.attenuation_exponent)
    f = np.fft.rfftfreq(n, 1.0 / float(fs)) / 1e6  # [MHz]
    xr = float(pulse.attenuation_ref_hz) / 1e6
    b = a1 * math.tan(math.pi * y / 2.0) * (f ** y - f * xr ** (y - 1.0))
    h = np.exp(-(a1 * f ** y + 1j * b) * np.asarray(path_m, float)[..., None])
    return np.fft.irfft(np.fft.rfft(x, n=n, axis=-1) * h, n=n, axis=-1)[..., : x.shape[-1]]


def shift_channels(x, fs, gain, delay_s):
    """x (..., 4, M) with channel k advanced by delay_s[k] [s] (phase ramp of the
    zero-padded spectrum: a band-limited fractional shift) and divided by gain[k]."""
    x = np.asarray(x, float)
    if not np.any(np.asarray(delay_s, float)):
        # gains alone: no transform (its rounding would hide the ADC's grid, whose quantum
        # is part of the noise the residual tests weigh)
        return x / np.asarray(gain, float)[:, None]
    m = x.shape[-1]
    n = 2 * m
    f = np.fft.rfftfreq(n, 1.0 / float(fs))
    ramp = np.exp(2j * np.pi * f[None, :] * np.asarray(delay_s, float)[:, None])  # (4, F)
    spec = np.fft.rfft(x, n=n, axis=-1) * ramp
    return np.fft.irfft(spec, n=n, axis=-1)[..., :m] / np.asarray(gain, float)[:, None]


@dataclass(frozen=True)
class _Tables:
    """Exponential tables E_p[m] = e^{p m dt} stacked [Re; Im] (2P, L) for h and h'."""

    poles: np.ndarray
    res: np.ndarray
    table: np.ndarray
    h_samples: np.ndarray  # h(m dt), m = 0..L-1 (matched filter)
    #: one pole of each conjugate pair (residue doubled: Re(c e^{pt}) + Re(c* e^{p* t}) =
    #: 2 Re(c e^{pt})) and the real poles; their tables [Re; Im]: the compiled kernels'
    half_poles: np.ndarray
    half_res: np.ndarray
    half_table: np.ndarray
    #: z_p = e^{p / f_s} of the half poles: h[m] = Re sum_p half_res_p z_p^m (the compiled
    #: matched filter's recursion)
    half_z: np.ndarray


def _given(prep):
    """(K,) bool: the noise sigma was given (analog: + q^2/12), not measured."""
    if prep.noise_given is None:
        return np.zeros(len(prep.sigma2), bool)
    return np.asarray(prep.noise_given, bool)


def _tables(pulse: PulseModel, fs: float, n: int) -> _Tables:
    key = (pulse, fs, n)
    t = _TAB_CACHE.get(key)
    if t is None:
        p, r = pulse.poles_residues()
        e = np.exp(p[:, None] * (np.arange(n) / fs)[None, :])
        tab = np.ascontiguousarray(np.vstack([e.real, e.imag]))
        h = (r[:, None] * e).sum(axis=0).real
        tiny = 1e-9 * np.abs(p)
        upper, real = p.imag > tiny, np.abs(p.imag) <= tiny
        if upper.sum() == (p.imag < -tiny).sum():  # every complex pole has its conjugate
            keep = upper | real
        else:
            keep = np.ones(p.size, bool)
        hp, hr, eh = p[keep], (np.where(upper, 2.0, 1.0) * r)[keep], e[keep]
        htab = np.ascontiguousarray(np.vstack([eh.real, eh.imag]))
        t = _TAB_CACHE[key] = _Tables(
            p, r, tab, h, hp.copy(), hr.copy(), htab, np.exp(hp / fs)
        )
    return t


_TAB_CACHE: dict = {}


def _repeats(poles) -> np.ndarray:
    """Per pole, how many earlier poles equal it (within 1e-9 relative): 0 for simple."""
    out = np.zeros(poles.size)
    for i in range(1, poles.size):
        out[i] = np.sum(np.abs(poles[:i] - poles[i]) <= 1e-9 * abs(poles[i]))
    return out


def _opt_hz(value: str):
    """A corner [Hz] or 'none'."""
    return None if value.lower() == "none" else _hz(value)


def _hz(value: str) -> float:
    """A positive finite number (a frequency [Hz], a rate [1/s], a ripple [dB])."""
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"must be positive and finite, got {value}")
    return v


def _order(value: str) -> int:
    v = int(value)
    if not 1 <= v <= 12:
        raise ValueError(f"order must be 1 .. 12, got {value}")
    return v


#: The fields a stated front end names (`PulseModel.from_spec`) and their parsers.
SPEC_FIELDS = {
    "highpass_hz": _hz,
    "highpass_order": _order,
    "highpass_rc_hz": lambda v: tuple(_hz(f) for f in v.split("/")),
    "lowpass_hz": _opt_hz,
    "lowpass_order": _order,
    "lowpass_family": str,
    "lowpass_ripple_db": _hz,
    "amplifier_pole_hz": _opt_hz,
    "alpha_1_s": _hz,
}
