# SPDX-License-Identifier: Apache-2.0
"""Overlapping emissions: localize two or three emissions that share one packet window.

Several touches within microseconds (three pins, a plate landing, slip bursts) put two or
three emissions from different points into one window. The single-source estimators
(`localize`) reject them (OVERLAP) or, when the second emission arrives late in the
echo-free segment, accept a wrong point. This module fits them jointly.

Model (white Gaussian noise sigma^2 per sample, per channel): J emissions, source j at
the surface point s_j = (s_x, s_y, sqrt(R^2 - s_x^2 - s_y^2)), emission time T_j, direct
amplitude A_j (signed: touch > 0) and first-echo amplitude B_j:

    y_k(t) = sum_j [ A_j (R / d_jk) h(t - T_j - d_jk / c) + B_j h(t - T_j - e_jk / c) ] + n_k(t)

    d_jk = |s_j - e_k| (direct path),  e_jk = 2R + |s_j + e_k| (first wall echo: the
    hemisphere on its base acts, by the mirror image in the base plane, as a full sphere;
    the concave wall refocuses the echo, so its amplitude is the same on all elements).

h(t) is the *known pulse shape*: the response of the front end (Butterworth high-pass and
anti-alias low-pass, `PulseModel`) to the collision pressure of the paper's Eq. 9,
P1(s) = 2/(s + 2 alpha) - 1/(s + alpha) (a step for omega >> alpha), evaluated in closed
form at any sub-sample time (partial fractions) and normalised to a unit peak. Unknowns
per emission: (s_x, s_y, T_j) nonlinear, (A_j, B_j) linear: 5 per emission.

Fit over the window from 1 us before the onset to before the *second* wall echo of the
earliest emission (4R/c - 2 sqrt(2) a / c after it: 24 us in water), so that an emission
arriving up to ~10 us after the first is still seen whole; the first echoes of every
emission are part of the model. Search (RELAX, cyclic superimposed-signal estimation):

  1. matched-filter grid: per channel correlation with h, summed over channels along the
     travel times of a 1 mm grid of surface points; the three best points at distinct
     times are kept, the best starts the Levenberg-Marquardt fit of one emission;
  2. emission 2 is searched only when the one-emission residual is not noise: joint LM
     from (emission 1, best grid point of the residual); where that still leaves more
     than noise, also from each pair of the three time peaks of step 1, from emission 1
     re-searched on the data minus emission 2 (RELAX), and with the points swapped; the
     best residual wins. A third emission likewise;
  3. model order: J + 1 emissions only if the residual energy falls by more than
     ``add_threshold`` sigma^2 (a generalised likelihood-ratio test, so that single-source
     packets stay single);
  4. the final residual must be consistent with noise (chi^2 per degree of freedom below
     ``max_chi2_ratio``) and no two emissions closer than ``min_separation_s``, else the
     packet is rejected (a wrong or missing emission leaves its energy in the residual);
  5. covariance of each point: the (s_x, s_y) block of the inverse Fisher matrix of the
     joint model, F = J^T J / sigma^2 (all 5J parameters), inflated by the chi^2 ratio
     when it exceeds 1; an emission whose in-plane 1-sigma exceeds ``max_sigma_m`` is not
     reported (counted in ``n_dropped``).

`suspect_overlap` is the cheap test for packets `localize` accepted as single: the
emission time by the matched filter along the accepted point's travel times, one linear
LS on [h, h'] (direct wave and echo), chi^2 per degree of freedom against the same limit.
`localize_with_overlaps` chains the fast path, the test and the overlap fit.
`calibrate_pulse` fits the front-end corners of `PulseModel` to single touches;
`fit_pulse` / `PulseLearner` learn the whole pulse (emission decay and the front end's
poles) from the device's own single-emission packets (`learn`). The LM
fits and the grid run as compiled kernels where numba is present (`overlap_kernels`).

Modules: `pulse` (the pulse shape), `learn` (the pulse learnt from the device's data),
`model` (results, the J-emission model, the LM fit),
`search` (grid and RELAX search), `decide` (order, residual test, covariance), `suspect`
(`suspect_overlap`), `api` (the public calls).
"""

# the compiled kernels stay reachable as `overlap._kernels` (the pipeline asks NUMBA_AVAILABLE)
from ae_tactile.localization import overlap_kernels as _kernels  # noqa: F401
from ae_tactile.localization.overlap.api import (
    calibrate_pulse,
    localize_with_overlaps,
    resolve_overlaps,
    warm_up,
)
from ae_tactile.localization.overlap.learn import PulseFit, fit_pulse
from ae_tactile.localization.overlap.learner import PulseLearner
from ae_tactile.localization.overlap.model import OverlapPacket, OverlapReason, OverlapSource
from ae_tactile.localization.overlap.pulse import PulseModel
from ae_tactile.localization.overlap.suspect import suspect_overlap

__all__ = [
    "PulseModel",
    "PulseLearner",
    "PulseFit",
    "fit_pulse",
    "OverlapReason",
    "OverlapSource",
    "OverlapPacket",
    "resolve_overlaps",
    "suspect_overlap",
    "calibrate_pulse",
    "localize_with_overlaps",
    "warm_up",
]
