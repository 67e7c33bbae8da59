# SPDX-License-Identifier: Apache-2.0
"""The medium's loss in the learnt pulse: a power law att l (f / 1 MHz)^y over each
path of length l with its Kramers-Kronig dispersion (`pulse.power_law_filter`), two
physical parameters (att [dB/m at 1 MHz], y) fitted with the pulse's poles by
`learn.fit_pulse`: in a lossy body each channel's pulse depends on its path length, which
no common pulse can represent.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ae_tactile.localization.overlap.pulse import PulseModel, power_law_filter

#: [dB/m] unit of the loss parameter in the pole fit's vector (near the poles' log
#: parameters in size: one step of the fit's difference quotient is a fraction of a dB/m)
LOSS_UNIT_DB_PER_M = 100.0
#: [dB/m] largest medium loss at 1 MHz learnt (30 dB/cm: ten times a lossy silicone)
MAX_LOSS_DB_PER_M = 3000.0
#: [dB/m] start of the loss in the fit when the initial pulse has none: a small loss, so
#: the fit sees the gradient of both signs (a lossless medium is its lower bound)
LOSS_START_DB_PER_M = 30.0
#: [1] range and start of the loss's frequency exponent y (water 2, soft solids and
#: tissue 1-2; y = 2 itself has no causal dispersion of this form, y = 1 a singular one)
LOSS_EXPONENT_RANGE = (1.05, 1.95)
LOSS_EXPONENT_START = 1.5
#: learn the medium's loss where the lossless pulse is not trusted (`learn._fit`)
LEARN_LOSS = True
#: [1] share of the lossless pulse's median excess misfit (chi^2 ratio - 1) the loss
#: must remove to be kept: a clear margin over a front-end error it could stand in for
LOSS_MIN_EXCESS_DROP = 0.5


def _with_loss(v, bounds, init: PulseModel):
    """The pole parameters v with the medium's power-law loss appended: its value at
    1 MHz (units of LOSS_UNIT_DB_PER_M; start ``init``'s, else LOSS_START_DB_PER_M;
    0 .. MAX_LOSS_DB_PER_M) and its exponent y (LOSS_EXPONENT_RANGE)."""
    start = float(init.attenuation_db_per_m_at_1mhz) or LOSS_START_DB_PER_M
    hi = MAX_LOSS_DB_PER_M / LOSS_UNIT_DB_PER_M
    y0, y1 = LOSS_EXPONENT_RANGE
    y = init.attenuation_exponent if y0 < init.attenuation_exponent < y1 else \
        LOSS_EXPONENT_START
    v = np.append(v, [min(start / LOSS_UNIT_DB_PER_M, hi - 1e-6), y])
    return v, (np.append(bounds[0], [0.0, y0]), np.append(bounds[1], [hi, y1]))


def _loss_of(v) -> PulseModel:
    """A PulseModel carrying only the power-law loss of v's last two entries."""
    return PulseModel(attenuation_db_per_m_at_1mhz=float(v[-2]) * LOSS_UNIT_DB_PER_M,
                      attenuation_exponent=float(v[-1]))


def _lossy(basis, path_m, fs, loss: PulseModel):
    """A basis (..., L, P) through the power-law loss of its paths ``path_m`` (...)."""
    out = power_law_filter(np.moveaxis(basis, -1, -2), path_m[..., None], fs, loss)
    return np.moveaxis(out, -2, -1)


def _learnt(poles, res, v, with_loss=True):
    """The learnt PulseModel of poles and residues with the power-law loss of v (none
    unless ``with_loss``)."""
    pulse = PulseModel.from_poles(poles, res)
    if not with_loss:
        return pulse
    loss = _loss_of(v)
    if loss.attenuation_db_per_m_at_1mhz <= 0:
        return pulse
    return replace(pulse, attenuation_db_per_m_at_1mhz=loss.attenuation_db_per_m_at_1mhz,
                   attenuation_exponent=loss.attenuation_exponent)


def _keep_loss(ratio0, limit0, ratio1, limit1) -> bool:
    """Model selection between the lossless pulse (chi^2 ratios ``ratio0`` of the
    candidates, limits ``limit0``) and the pulse with the medium's loss (``ratio1``,
    ``limit1``): the loss is kept when it passes at least as many candidates' residual
    test and removes at least LOSS_MIN_EXCESS_DROP of the lossless pulse's median excess
    misfit (chi^2 ratio - 1). An information criterion cannot decide it: its penalty
    for two parameters (2 ln N, N ~ 1e4 samples) is ~20 sigma^2 against a systematic
    misfit of thousands, so any front-end error would buy a loss; a loss standing in for
    the front end lowers the misfit a little, a body's loss (a pulse changing with the
    path, which no common pulse can follow) removes most of it."""
    if not (np.all(np.isfinite(ratio1)) and np.isfinite(ratio0).any()):
        return False
    ex0 = max(float(np.nanmedian(ratio0)) - 1.0, 0.0)
    ex1 = max(float(np.median(ratio1)) - 1.0, 0.0)
    more = int(np.sum(ratio1 <= limit1)) >= int(np.sum(ratio0 <= limit0))
    return bool(more and ex1 <= (1.0 - LOSS_MIN_EXCESS_DROP) * ex0)
