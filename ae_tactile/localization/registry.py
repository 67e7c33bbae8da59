# SPDX-License-Identifier: Apache-2.0
"""The registry of delay estimators (pyroomacoustics' doa/ algorithms dict is the model):
each estimator lives in its own module (`ml`, `gradient`, `gcc`, `xcorr_farfield`) and is
registered here by name with its description and default overlap threshold;
`get_estimator` looks one up. Also the default analysis band.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ae_tactile.localization import gcc, gradient, ml, xcorr_farfield

#: Default signal band (Hz): the front end's 100 kHz high-pass to its 1 MHz low-pass,
#: the upper edge lowered to fs/4 at low sample rates (see `default_band_hz`).
DEFAULT_BAND_HZ = (100e3, 1e6)


#: Candidate band of the data-driven edge (``ml`` with ``band_hz=None``): 100 kHz to
#: min(0.45 fs, 4 MHz); the edge then follows each packet's spectrum (`common.band_edge_hz`).
AUTO_BAND_MAX_HZ = 4e6


def auto_band_hz(sample_rate_hz):
    """Candidate band (lo, hi) of the data-driven edge."""
    return (DEFAULT_BAND_HZ[0], min(AUTO_BAND_MAX_HZ, 0.45 * float(sample_rate_hz)))


def default_band_hz(sample_rate_hz):
    """(100 kHz, min(1 MHz, fs/4)): above fs/4 a 1 MHz front end aliases at low rates, and
    aliased content does not shift like the rest of the waveform (bias, not noise)."""
    return (DEFAULT_BAND_HZ[0], min(DEFAULT_BAND_HZ[1], 0.25 * float(sample_rate_hz)))


@dataclass(frozen=True)
class EstimatorInfo:
    """A registered delay estimator."""

    name: str
    function: Callable
    description: str
    #: Default overlap threshold on the excess misfit (calibrated, see docs/localization.md).
    overlap_threshold: float


ESTIMATORS: dict[str, EstimatorInfo] = {}


def register_estimator(name, function, description, overlap_threshold=0.1):
    """Add an estimator ``function(prepared, plan, **options) -> core dict`` to the registry."""
    if not isinstance(name, str) or not name:
        raise ValueError("estimator name must be a non-empty string")
    ESTIMATORS[name] = EstimatorInfo(name, function, description, float(overlap_threshold))


def available_methods() -> list[str]:
    return sorted(ESTIMATORS)


def get_estimator(name) -> EstimatorInfo:
    try:
        return ESTIMATORS[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown localization method {name!r}; choose one of {available_methods()}"
        ) from None


# Overlap thresholds: the excess misfit of single clean packets stays below ~0.055 (ML,
# gradient, GCC) and ~0.1 (far-field baseline, whose biased delays leave some misfit) at
# 5-10 dB SNR, 2-20 MS/s, polar angles up to 90 deg (docs/localization.md).
register_estimator(
    "ml",
    ml.estimate,
    "maximum likelihood on the exact sphere: steered response power over (s_x, s_y), "
    "Newton from a cross-correlation start",
    overlap_threshold=0.07,
)
register_estimator(
    "gradient",
    gradient.estimate,
    "the paper's gradient method (ref. [8]) iterated with re-alignment, band-limited derivative",
    overlap_threshold=0.07,
)
register_estimator(
    "gcc_phat",
    gcc.estimate_gcc_phat,
    "GCC-PHAT over the 6 pairs, PHAT in band only, Newton sub-sample peak, LS, exact inversion",
    overlap_threshold=0.07,
)
register_estimator(
    "xcorr_farfield",
    xcorr_farfield.estimate_xcorr_farfield,
    "paper baseline: plain cross-correlation peaks of channel sums, far-field Eq. 2 inversion",
    overlap_threshold=0.12,
)
