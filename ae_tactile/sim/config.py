# SPDX-License-Identifier: Apache-2.0
"""Simulator configuration: sensor, medium, front end and effect switches (SI units).

`SimConfig` is a frozen, validated dataclass. Everything the renderers derive from it
(filter poles and residues, exponential tables) is cached on the instance, so build one
config and reuse it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from ae_tactile.geometry import MEDIA, FingertipGeometry, resolve_front_end_lowpass
from ae_tactile.sim.emission import DEFAULT_ALPHA_1_S
from ae_tactile.sim.frontend import FrontEnd


@dataclass(frozen=True)
class Medium:
    """Acoustic medium of the fingertip body.

    ``attenuation_db_per_m_at_1mhz``: amplitude loss at 1 MHz per metre of path, used only
    when the config's ``attenuation`` switch is on. The loss grows as f^2 at low
    frequency (viscous / Kelvin-Voigt law), realised causally as one real pole per path
    (see `ae_tactile.sim.propagation.attenuation_pole_rad_s`).
    """

    name: str
    sound_speed_m_s: float
    density_kg_m3: float
    attenuation_db_per_m_at_1mhz: float


#: Medium presets. Water: 0.0022 dB/cm at 1 MHz (f^2 law), i.e. negligible over 1 cm.
#: Medical silicone (the paper's Shin-Etsu lens rubber): c ~ 1000 m/s, and an ASSUMED
#: 2 dB/cm at 1 MHz (order of magnitude of silicone lens rubbers; the paper gives no
#: figure). Override with ``attenuation_db_per_m_at_1mhz``.
MEDIUM_PRESETS = {
    "water_skin": Medium("water_skin", MEDIA["water_skin"]["sound_speed_m_s"],
                         MEDIA["water_skin"]["density_kg_m3"], 0.22),
    "silicone": Medium("silicone", MEDIA["silicone"]["sound_speed_m_s"],
                       MEDIA["silicone"]["density_kg_m3"], 200.0),
}


def _pos(name, value, allow_none=False):
    if value is None and allow_none:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v


def _int_in(name, value, lo, hi):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    if not lo <= int(value) <= hi:
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    return int(value)


@dataclass(frozen=True)
class SimConfig:
    """Everything fixed about the simulated sensor. Defaults: the paper's water-skin tip.
    Validated on construction (ValueError naming the field).

    Parameters
    ----------
    geometry : FingertipGeometry
        R = 10 mm, a = 1.5 mm, c = 1480 m/s by default.
    medium : {'water_skin', 'silicone', 'custom'}
        For a preset, the geometry's sound speed must match the preset's (use
        ``SimConfig.for_medium('silicone')``); 'custom' needs ``density_kg_m3`` and
        ``attenuation_db_per_m_at_1mhz``.
    density_kg_m3 : float, optional
        rho of Eq. 10 [kg/m^3] (None: the preset's).
    attenuation_db_per_m_at_1mhz : float, optional
        Loss at 1 MHz [dB/m] (None: the preset's); used when ``attenuation`` is on.
    sensitivity_v_per_pa : float
        PVDF + amplifier gain, flat in band [V/Pa] (0.01: ~10 uV/Pa of a 28 um PVDF film
        times a 60 dB amplifier).
    highpass_hz, highpass_order : float, int
        Butterworth high-pass [Hz] (the paper's 100 kHz; order 2).
    highpass_rc_hz : tuple of float, optional
        Corners [Hz] of causal first-order RC high-pass stages, distinct, one per stage;
        given, they replace the Butterworth high-pass (a textbook coupling network:
        (60e3, 69e3) is two RC stages with -3 dB near 100 kHz). ``highpass_hz`` then only
        serves the ``lowpass_hz > highpass_hz`` check.
    lowpass_hz, lowpass_order : float or "auto" or None, int or "auto"
        Anti-alias / PVDF band limit [Hz] of family ``lowpass_family``. "auto" (default):
        ``geometry.resolve_front_end_lowpass``: (1 MHz, order 4), the PVDF/amplifier band,
        and below 3.33 MS/s the ADC's anti-alias filter (0.3 f_s, order 8).
        ``lowpass_hz=None`` disables the low-pass (an "auto" order is then 4). "auto" is
        resolved on construction; ``replace`` re-resolves it for a new sample rate.
    lowpass_family : {'butter', 'bessel', 'cheby1'}
        Low-pass family (scipy's analog designs; Bessel normalised to -3 dB at
        ``lowpass_hz``; Chebyshev-I with ``lowpass_ripple_db`` of pass-band ripple [dB],
        its edge at ``lowpass_hz``).
    amplifier_pole_hz : float, optional
        One extra real pole of the amplifier [Hz] (None: none).
    attenuation_law : {'pole', 'power'}
        'pole': the f^2 loss realised by one causal pole per path (propagation.py);
        'power': loss att_1MHz l (f / 1 MHz)^y with y = ``attenuation_exponent`` and the
        Kramers-Kronig dispersion of that law, the sound speed being the phase velocity
        at ``attenuation_ref_hz``; rendered by `render_triggered` only.
    attenuation_exponent, attenuation_ref_hz : float
        y in (0, 2], y != 1 (1.5: silicone-like rubbers) and the reference frequency of
        the sound speed [Hz] (300 kHz: where the pulse's energy lies).
    channel_gain : tuple of 4 float
        Gain of each channel relative to ``sensitivity_v_per_pa`` (mismatch; 1.0 each).
    channel_delay_s : tuple of 4 float
        Extra delay of each channel [s] (phase mismatch of the electronics; 0 each);
        the ground truth (``delays_s``) stays geometric.
    amplifier_noise_share : float
        Share in [0, 1] of the noise variance at the ADC that is amplifier noise: white
        at the amplifier's input, filtered by the whole analog chain (coloured); the
        rest is white ADC noise. 0: all white (rendered by `render_triggered` only
        when > 0).
    emission_alpha_1_s : float
        The body's emission decay alpha of Eq. 10 [1/s] (3e3), used by `render_triggered`
        when no ``alpha_1_s`` is given.
    sample_rate_hz : float
        ADC rate, an integer number of Hz (10 MS/s).
    adc_bits, adc_full_scale_v : int, float
        Codes in [-2^(b-1), 2^(b-1)-1], LSB = 2 FS / 2^b, clipping at full scale [V]
        (12 bit, +-1 V).
    attenuation : bool
        Frequency-dependent loss of the medium along each path (propagation.py).
    reflections : bool
        Specular wall echoes (propagation.py).
    reflection_coefficient, n_reflections : float, int
        Echo amplitude ratio per bounce, and the number of echoes.
    quantization : bool
        Round to ADC codes and clip (noise is on iff a level is given).
    support_rel_tol : float
        Each arrival's response is truncated once a bound on its remaining tail falls
        below this fraction of its jump |A| G.
    max_support_s : float
        Hard cap on an arrival's response length [s] (200 us).

    Each effect switched off costs nothing.
    """

    geometry: FingertipGeometry = field(default_factory=FingertipGeometry)
    medium: str = "water_skin"
    density_kg_m3: float | None = None
    attenuation_db_per_m_at_1mhz: float | None = None
    sensitivity_v_per_pa: float = 0.01
    highpass_hz: float = 100e3
    highpass_order: int = 2
    lowpass_hz: float | str | None = "auto"
    lowpass_order: int | str = "auto"
    highpass_rc_hz: tuple | None = None
    lowpass_family: str = "butter"
    lowpass_ripple_db: float = 0.5
    amplifier_pole_hz: float | None = None
    attenuation_law: str = "pole"
    attenuation_exponent: float = 1.5
    attenuation_ref_hz: float = 300e3
    channel_gain: tuple = (1.0, 1.0, 1.0, 1.0)
    channel_delay_s: tuple = (0.0, 0.0, 0.0, 0.0)
    amplifier_noise_share: float = 0.0
    emission_alpha_1_s: float = DEFAULT_ALPHA_1_S
    sample_rate_hz: float = 10e6
    adc_bits: int = 12
    adc_full_scale_v: float = 1.0
    attenuation: bool = False
    reflections: bool = False
    reflection_coefficient: float = -0.5
    n_reflections: int = 2
    quantization: bool = True
    support_rel_tol: float = 1e-6
    max_support_s: float = 200e-6

    # ---------------------------------------------------------------- validation
    def __post_init__(self) -> None:
        if not isinstance(self.geometry, FingertipGeometry):
            raise ValueError("geometry must be a FingertipGeometry, got "
                             f"{type(self.geometry).__name__}")
        if self.medium not in MEDIUM_PRESETS and self.medium != "custom":
            raise ValueError(f"unknown medium {self.medium!r}; choose one of "
                             f"{sorted(MEDIUM_PRESETS) + ['custom']}")
        if self.medium == "custom":
            if self.density_kg_m3 is None or self.attenuation_db_per_m_at_1mhz is None:
                raise ValueError("medium='custom' needs density_kg_m3 and"
                                 " attenuation_db_per_m_at_1mhz")
        else:
            preset = MEDIUM_PRESETS[self.medium]
            c = self.geometry.sound_speed_m_s
            if abs(c - preset.sound_speed_m_s) > 0.2 * preset.sound_speed_m_s:
                raise ValueError(
                    f"geometry.sound_speed_m_s={c} does not match medium {self.medium!r}"
                    f" ({preset.sound_speed_m_s} m/s); use SimConfig.for_medium({self.medium!r})"
                    " or medium='custom'")
        _pos("density_kg_m3", self.density_kg_m3, allow_none=True)
        if self.attenuation_db_per_m_at_1mhz is not None:
            v = float(self.attenuation_db_per_m_at_1mhz)
            if not math.isfinite(v) or v < 0:
                raise ValueError("attenuation_db_per_m_at_1mhz must be finite and >= 0, "
                                 f"got {self.attenuation_db_per_m_at_1mhz!r}")
        _pos("sensitivity_v_per_pa", self.sensitivity_v_per_pa)
        fs = _pos("sample_rate_hz", self.sample_rate_hz)
        if fs != round(fs):
            raise ValueError(f"sample_rate_hz must be an integer number of Hz, got {fs!r}")
        hp = _pos("highpass_hz", self.highpass_hz)
        _int_in("highpass_order", self.highpass_order, 1, 8)
        auto = {}
        for name in ("lowpass_hz", "lowpass_order"):
            v = getattr(self, name)
            if isinstance(v, str):
                if v != "auto":
                    raise ValueError(f'{name} must be a number or "auto", got {v!r}')
                auto[name] = True
        object.__setattr__(self, "_auto_fields", tuple(auto))
        hz, order = resolve_front_end_lowpass(fs, self.lowpass_hz, self.lowpass_order)
        object.__setattr__(self, "lowpass_hz", hz)
        object.__setattr__(self, "lowpass_order", order)
        lp = _pos("lowpass_hz", self.lowpass_hz, allow_none=True)
        _int_in("lowpass_order", self.lowpass_order, 1, 8)
        if hp >= fs / 2:
            raise ValueError(f"highpass_hz={hp} must be below Nyquist ({fs / 2} Hz)")
        if lp is not None and lp <= hp:
            raise ValueError(f"lowpass_hz={lp} must be above highpass_hz={hp}")
        self._validate_device(fs, lp)
        _int_in("adc_bits", self.adc_bits, 2, 24)
        _pos("adc_full_scale_v", self.adc_full_scale_v)
        for name in ("attenuation", "reflections", "quantization"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"{name} must be true or false, got {getattr(self, name)!r}")
        r = float(self.reflection_coefficient)
        if not math.isfinite(r) or abs(r) >= 1.0:
            raise ValueError("reflection_coefficient must satisfy |r| < 1, got "
                             f"{self.reflection_coefficient!r}")
        _int_in("n_reflections", self.n_reflections, 0, 16)
        tol = _pos("support_rel_tol", self.support_rel_tol)
        if tol >= 1:
            raise ValueError(f"support_rel_tol must be < 1, got {tol}")
        ms = _pos("max_support_s", self.max_support_s)
        if ms * fs < 16:
            raise ValueError(f"max_support_s={ms} is shorter than 16 samples")

    def _validate_device(self, fs, lp) -> None:
        """Checks of the device fields (front-end families, loss law, mismatch, noise)."""
        if self.highpass_rc_hz is not None:
            rc = tuple(_pos("highpass_rc_hz", v) for v in self.highpass_rc_hz)
            if not 1 <= len(rc) <= 4:
                raise ValueError("highpass_rc_hz must hold 1 to 4 corners")
            if len(set(rc)) != len(rc):
                raise ValueError(f"highpass_rc_hz corners must be distinct, got {rc}")
            if max(rc) >= fs / 2:
                raise ValueError(f"highpass_rc_hz={rc} must be below Nyquist ({fs / 2} Hz)")
            object.__setattr__(self, "highpass_rc_hz", rc)
        if self.lowpass_family not in ("butter", "bessel", "cheby1"):
            raise ValueError("lowpass_family must be 'butter', 'bessel' or 'cheby1', got"
                             f" {self.lowpass_family!r}")
        _pos("lowpass_ripple_db", self.lowpass_ripple_db)
        _pos("amplifier_pole_hz", self.amplifier_pole_hz, allow_none=True)
        if self.attenuation_law not in ("pole", "power"):
            raise ValueError(f"attenuation_law must be 'pole' or 'power', got"
                             f" {self.attenuation_law!r}")
        y = _pos("attenuation_exponent", self.attenuation_exponent)
        if y > 2.0 or abs(y - 1.0) < 1e-3:
            raise ValueError(f"attenuation_exponent must lie in (0, 2] and differ from 1, got {y}")
        _pos("attenuation_ref_hz", self.attenuation_ref_hz)
        _pos("emission_alpha_1_s", self.emission_alpha_1_s)
        for name in ("channel_gain", "channel_delay_s"):
            v = np.asarray(getattr(self, name), dtype=float)
            if v.shape != (4,) or not np.all(np.isfinite(v)):
                raise ValueError(f"{name} must hold 4 finite numbers, got {getattr(self, name)!r}")
            object.__setattr__(self, name, tuple(float(x) for x in v))
        if min(self.channel_gain) <= 0:
            raise ValueError(f"channel_gain must be positive, got {self.channel_gain}")
        if min(self.channel_delay_s) < 0 or max(self.channel_delay_s) * fs > 64:
            raise ValueError("channel_delay_s must lie in [0, 64 samples], got"
                             f" {self.channel_delay_s}")
        share = float(self.amplifier_noise_share)
        if not 0.0 <= share <= 1.0:
            raise ValueError(f"amplifier_noise_share must lie in [0, 1], got {share}")
        if share > 0 and lp is None and self.amplifier_pole_hz is None:
            raise ValueError("amplifier noise needs a low-pass or an amplifier pole (its"
                             " variance is infinite through a chain without one)")

    @property
    def streamable(self) -> bool:
        """True when the streaming renderers support every effect switched on (the power
        loss law, channel mismatch and amplifier noise are rendered by `render_triggered`
        only)."""
        return (not (self.attenuation and self.attenuation_law == "power")
                and self.channel_gain == (1.0, 1.0, 1.0, 1.0)
                and self.channel_delay_s == (0.0, 0.0, 0.0, 0.0)
                and self.amplifier_noise_share == 0.0)

    @classmethod
    def for_medium(cls, medium: str, **kwargs) -> "SimConfig":
        """A config whose geometry uses the preset medium's sound speed.

        Parameters
        ----------
        medium : str
            A preset of `MEDIUM_PRESETS`.
        **kwargs
            ``radius_m`` / ``element_offset_m`` for the geometry [m]; the rest are
            `SimConfig` fields.

        Returns
        -------
        SimConfig
        """
        if medium not in MEDIUM_PRESETS:
            raise ValueError(f"unknown medium preset {medium!r}; choose one of"
                             f" {sorted(MEDIUM_PRESETS)}")
        geo_kw = {k: kwargs.pop(k) for k in ("radius_m", "element_offset_m") if k in kwargs}
        geo = FingertipGeometry(sound_speed_m_s=MEDIUM_PRESETS[medium].sound_speed_m_s, **geo_kw)
        return cls(geometry=geo, medium=medium, **kwargs)

    def replace(self, **changes) -> "SimConfig":
        """A validated copy with some fields changed (an "auto" low-pass follows a new
        sample rate).

        Parameters
        ----------
        **changes
            `SimConfig` fields.

        Returns
        -------
        SimConfig
        """
        for name in getattr(self, "_auto_fields", ()):
            changes.setdefault(name, "auto")
        return replace(self, **changes)

    # ---------------------------------------------------------------- derived
    @property
    def density(self) -> float:
        """rho actually used [kg/m^3]."""
        if self.density_kg_m3 is not None:
            return float(self.density_kg_m3)
        return MEDIUM_PRESETS[self.medium].density_kg_m3

    @property
    def attenuation_db_per_m(self) -> float:
        """Loss at 1 MHz per metre actually used (0 when the attenuation switch is off)."""
        if not self.attenuation:
            return 0.0
        if self.attenuation_db_per_m_at_1mhz is not None:
            return float(self.attenuation_db_per_m_at_1mhz)
        return MEDIUM_PRESETS[self.medium].attenuation_db_per_m_at_1mhz

    @property
    def dt_s(self) -> float:
        """Sample period [s]."""
        return 1.0 / float(self.sample_rate_hz)

    @property
    def fs_int(self) -> int:
        """Sample rate as an integer [Hz]."""
        return int(round(self.sample_rate_hz))

    @property
    def lsb_v(self) -> float:
        """ADC step: 2 FS / 2^bits (volts)."""
        return 2.0 * self.adc_full_scale_v / (1 << self.adc_bits)

    @property
    def max_support_samples(self) -> int:
        """``max_support_s`` in samples (rounded up)."""
        return int(math.ceil(self.max_support_s * self.sample_rate_hz))

    @cached_property
    def frontend(self) -> FrontEnd:
        """Cached `ae_tactile.sim.frontend.FrontEnd` (filter poles, residues, tables)."""
        return FrontEnd(self)
