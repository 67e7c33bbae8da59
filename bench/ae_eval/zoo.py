# SPDX-License-Identifier: Apache-2.0
"""A zoo of simulated devices (issue 37): fingertips whose physics differ the way real ones
do, for the benchmarks to report their worst case beside the nominal device.

Axes (all `SimConfig` fields, `docs/simulator.md`): high-pass (Butterworth of order 1-2
at 30-150 kHz, or causal RC stages), anti-alias low-pass (Butterworth / Bessel /
Chebyshev-I, order 2-8, corner from 0.3 fs up to the PVDF band), an amplifier pole, the
emission decay alpha (1e3 .. 1e6 /s), amplifier noise through the chain, power-law loss
(f^1.5 with its dispersion), channel gain and delay mismatch, the wall echo.

    from ae_eval.zoo import ZOO, held_out
    cfg = ZOO["rc2_bessel6"].config("silicone", 5e6)
    for dev in held_out(seed=1, n=4): cfg = dev.config()

A device fixes the front end, the emission, the noise colour and the body's loss; the
benchmark chooses the medium and the sample rate of each cell (a low-pass corner given as
``lowpass_frac`` follows the rate: 0 at 0.3 fs, 1 at the PVDF band `PVDF_BAND_HZ`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ae_tactile.sim import SimConfig

__all__ = ["Device", "ZOO", "NOMINAL", "held_out", "PVDF_BAND_HZ", "LOSSY_DB_PER_M"]

#: Upper end of an anti-alias corner [Hz]: the PVDF film and amplifier band.
PVDF_BAND_HZ = 1e6
#: Loss of the lossy members at 1 MHz [dB/m]: 3 dB/cm, the issue's silicone.
LOSSY_DB_PER_M = 300.0


@dataclass(frozen=True)
class Device:
    """One simulated device.

    Parameters
    ----------
    name, description : str
    fields : dict
        `SimConfig` fields of the device (front end, alpha, noise share, mismatch, loss).
    lowpass_frac : float, optional
        Anti-alias corner between 0.3 fs (0) and `PVDF_BAND_HZ` (1), geometric; None:
        ``fields``' own (or the simulator's "auto").
    reflections : bool, optional
        Wall echo; None: the benchmark's choice.
    """

    name: str
    description: str
    fields: dict = field(default_factory=dict)
    lowpass_frac: float | None = None
    reflections: bool | None = None

    def config(self, medium: str = "water_skin", sample_rate_hz: float = 10e6,
               reflections: bool = False) -> SimConfig:
        """The device's `SimConfig` for one benchmark cell.

        Parameters
        ----------
        medium : str
            'water_skin' or 'silicone'.
        sample_rate_hz : float
        reflections : bool
            The benchmark's default, overridden by the device's ``reflections``.

        Returns
        -------
        SimConfig
        """
        kw = dict(self.fields)
        kw["sample_rate_hz"] = float(sample_rate_hz)
        kw["reflections"] = reflections if self.reflections is None else self.reflections
        if self.lowpass_frac is not None:
            lo = 0.3 * sample_rate_hz
            kw["lowpass_hz"] = float(lo * (PVDF_BAND_HZ / lo) ** self.lowpass_frac)
        return SimConfig.for_medium(medium, **kw)

    @property
    def alpha_1_s(self) -> float:
        """The device's emission decay [1/s]."""
        return float(self.fields.get("emission_alpha_1_s", 3e3))


def _lossy():
    return dict(attenuation=True, attenuation_law="power",
                attenuation_db_per_m_at_1mhz=LOSSY_DB_PER_M, attenuation_exponent=1.5)


_MEMBERS = [
    Device("nominal", "the simulator's default device (Butterworth 2 x 100 kHz high-pass,"
           " Butterworth 4 x 1 MHz / 8 x 0.3 fs low-pass, alpha 3e3 /s, white noise)"),
    Device("rc2_bessel6", "issue 37 ex. 1: two RC high-pass stages (60, 69 kHz) and a"
           " 6th-order Bessel anti-alias", dict(highpass_rc_hz=(60e3, 69e3),
                                                lowpass_family="bessel", lowpass_order=6)),
    Device("hp1_50k_lp2_800k", "issue 37 ex. 2: 1st-order 50 kHz high-pass, 2nd-order"
           " 800 kHz low-pass", dict(highpass_hz=50e3, highpass_order=1, lowpass_hz=800e3,
                                      lowpass_order=2)),
    Device("alpha_1e6", "issue 37 ex. 3: nominal front end, emission decay 1e6 /s",
           dict(emission_alpha_1_s=1e6)),
    Device("alpha_1e3", "emission decay 1e3 /s", dict(emission_alpha_1_s=1e3)),
    Device("alpha_3e4", "emission decay 3e4 /s", dict(emission_alpha_1_s=3e4)),
    Device("hp2_150k", "Butterworth 2 x 150 kHz high-pass", dict(highpass_hz=150e3)),
    Device("hp1_30k", "Butterworth 1 x 30 kHz high-pass", dict(highpass_hz=30e3,
                                                              highpass_order=1)),
    Device("cheby8", "8th-order Chebyshev-I (1 dB) anti-alias at the PVDF band",
           dict(lowpass_family="cheby1", lowpass_order=8, lowpass_ripple_db=1.0),
           lowpass_frac=1.0),
    Device("butter8_03fs", "8th-order Butterworth anti-alias at 0.3 fs",
           dict(lowpass_order=8), lowpass_frac=0.0),
    Device("amp_pole", "nominal plus an amplifier pole at 1.5 MHz",
           dict(amplifier_pole_hz=1.5e6)),
    Device("amp_noise", "all noise from the amplifier, coloured by the chain",
           dict(amplifier_noise_share=1.0)),
    Device("amp_noise_half", "half the noise variance from the amplifier",
           dict(amplifier_noise_share=0.5)),
    Device("lossy", "power-law loss 3 dB/cm at 1 MHz, f^1.5, with its dispersion", _lossy()),
    Device("gain_mismatch", "channel gains 1.00 / 1.04 / 0.97 / 1.02",
           dict(channel_gain=(1.0, 1.04, 0.97, 1.02))),
    Device("delay_mismatch", "channel delays 0 / 30 / 10 / 50 ns",
           dict(channel_delay_s=(0.0, 30e-9, 10e-9, 50e-9))),
    Device("wall_echo", "nominal with the wall echo", reflections=True),
    Device("no_echo", "nominal without the wall echo", reflections=False),
    Device("textbook", "RC 60/69 kHz + Bessel-6, alpha 1e4, amplifier noise, 3 % gain"
           " mismatch, lossy", dict(highpass_rc_hz=(60e3, 69e3), lowpass_family="bessel",
                                     lowpass_order=6, emission_alpha_1_s=1e4,
                                     amplifier_noise_share=1.0,
                                     channel_gain=(1.0, 1.03, 0.98, 1.01), **_lossy())),
]

#: The named members, by name.
ZOO: dict[str, Device] = {d.name: d for d in _MEMBERS}
#: The nominal device.
NOMINAL = ZOO["nominal"]


def _draw(g: np.random.Generator, i: int) -> Device:
    f: dict = {}
    if g.random() < 0.5:
        f["highpass_hz"] = float(math.exp(g.uniform(math.log(30e3), math.log(150e3))))
        f["highpass_order"] = int(g.integers(1, 3))
    else:
        k = int(g.integers(1, 3))
        f["highpass_rc_hz"] = tuple(sorted(float(x) for x in g.uniform(30e3, 150e3, k)))
    family = str(g.choice(["butter", "bessel", "cheby1"]))
    f["lowpass_family"] = family
    f["lowpass_order"] = int(g.integers(2, 9))
    if family == "cheby1":
        f["lowpass_ripple_db"] = float(g.uniform(0.1, 1.0))
    if g.random() < 0.3:
        f["amplifier_pole_hz"] = float(g.uniform(1.2e6, 5e6))
    f["emission_alpha_1_s"] = float(math.exp(g.uniform(math.log(1e3), math.log(1e6))))
    if g.random() < 0.5:
        f["amplifier_noise_share"] = float(g.uniform(0.2, 1.0))
    if g.random() < 0.5:
        f.update(_lossy())
        f["attenuation_db_per_m_at_1mhz"] = float(g.uniform(50.0, 400.0))
    if g.random() < 0.5:
        f["channel_gain"] = tuple(float(x) for x in 1.0 + g.uniform(-0.05, 0.05, 4))
        f["channel_delay_s"] = tuple(float(x) for x in g.uniform(0.0, 50e-9, 4))
    refl = bool(g.random() < 0.5)
    return Device(f"held_out_{i}", "random draw from the zoo's ranges", f,
                  lowpass_frac=float(g.uniform(0.0, 1.0)), reflections=refl)


def held_out(seed: int, n: int = 8) -> list[Device]:
    """``n`` random devices drawn from the zoo's ranges (continuous draws: never a named
    member; checked).

    Parameters
    ----------
    seed : int
    n : int

    Returns
    -------
    list of Device
    """
    g = np.random.default_rng([37, int(seed)])
    out = []
    while len(out) < n:
        d = _draw(g, len(out))
        if all(d.fields != m.fields or d.lowpass_frac != m.lowpass_frac for m in _MEMBERS):
            out.append(d)
    return out
