# SPDX-License-Identifier: Apache-2.0
"""Weak releases: a release on the spot of a touch that has not been released yet.

A release is quieter than its touch: an object leaving at v = 0.05 .. 0.2 m/s emits
about (v / 0.3 m/s)^2 of a touch's pressure, so its packet often falls below the
localizer's ``min_snr_db`` (5 dB) and is rejected, and the touch looks held for good.
The fit of such a packet is still good where it counts: its polarity and, within a few
tenths of a millimetre, its position (bench/bench_slip.py measures it on the simulator's
touch-release cycles). Windows of noise alone pass an SNR floor of -5 dB too (often at
2 MS/s, where a window has few pre-onset samples), but with a random sign and a vague,
random position: the gate's spot test and its bound on the position's uncertainty are
what keeps them out.

The gate keeps a packet rejected *only* for low SNR when

  * its polarity is a rarefaction (a release), its estimated SNR >= ``min_snr_db`` of
    the gate (default -5 dB), and
  * its position's 1-sigma (per axis) is <= ``MAX_SIGMA_M`` (0.5 mm), and
  * it lies on the spot of a touch that no release has ended, however long ago (a grasp
    is held for as long as it is held; the slip detector pairs a release with its touch
    however long the hold):
    |p - p_touch|^2 <= g^2 (var_touch + var + floor^2), g = ``GATE_SIGMA`` (4),
    floor = ``FLOOR_M`` (0.1 mm), var the per-axis position variance (m^2): the slip
    detector's same-spot gate with its default settings.

The touch it ends is forgotten (the nearest one in the gate), as is the touch an
ordinary release ends, and a touch on a remembered touch's spot replaces it (nothing
touches where something is still pressing: the earlier one was released unseen). At most
``CAPACITY`` touches are remembered, the oldest forgotten first. Touches and releases
must be fed in time order (`admit`).
"""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.jit import njit
from ae_tactile.localization.common import Reason
from ae_tactile.localization.events import confidence

#: same-spot gate radius [standard deviations of the difference of the two positions]: the
#: one definition; the slip detector's ``SlipConfig.release_gate_sigma`` defaults to it, so
#: a weak release the gate keeps pairs with its touch in the slip detector too
RELEASE_GATE_SIGMA = 4.0
#: [m] isotropic model error (bias) added to that gate; ``SlipConfig.release_floor_m``'s default
RELEASE_FLOOR_M = 0.1e-3
#: the gate's radius and floor used here (the defaults above)
GATE_SIGMA = RELEASE_GATE_SIGMA
FLOOR_M = RELEASE_FLOOR_M
#: [m] largest position 1-sigma (per axis) of a weak release: windows of noise alone that
#: pass the SNR floor at 2 MS/s come with >= 1 mm (their gate would take any touch), the
#: simulator's weak releases lie well below it (bench/bench_slip.py)
MAX_SIGMA_M = 0.5e-3
#: at most this many touches remembered (the oldest forgotten first)
CAPACITY = 32
_G2, _F2 = GATE_SIGMA * GATE_SIGMA, FLOOR_M * FLOOR_M
#: default lowest estimated SNR of a weak release (dB)
MIN_SNR_DB = -5.0


def check_min_snr_db(value) -> float:
    """The gate's SNR floor as a float; ValueError unless finite."""
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"weak_release_min_snr_db must be finite, got {value!r}")
    return v


def is_weak_release(
    reason_flags: int, polarity: int, snr_db: float, min_snr_db: float, var_m2: float
) -> bool:
    """A candidate: rejected for low SNR and nothing else, a rarefaction, SNR >= floor,
    per-axis position variance ``var_m2`` finite and <= MAX_SIGMA_M^2."""
    v = float(var_m2)
    return (
        int(reason_flags) == (1 << Reason.LOW_SNR)
        and int(polarity) < 0
        and float(snr_db) >= min_snr_db
        and math.isfinite(v)
        and 0.0 <= v <= MAX_SIGMA_M * MAX_SIGMA_M
    )


@njit(cache=True, nogil=True)
def _nearest_spot(t_ns, xyz, var, n, t, x, y, z, v, g2, f2):  # pragma: no cover - compiled
    """Index of the nearest of the first ``n`` remembered touches (oldest first) on the
    spot of (x, y, z) with variance v, touched no later than t (the oldest on a tie);
    -1: none."""
    best = -1
    best_d2 = np.inf
    for i in range(n):
        dx = x - xyz[i, 0]
        dy = y - xyz[i, 1]
        dz = z - xyz[i, 2]
        d2 = dx * dx + dy * dy + dz * dz
        if d2 <= g2 * (var[i] + v + f2) and d2 < best_d2 and t_ns[i] <= t:
            best = i
            best_d2 = d2
    return best


class WeakReleaseGate:
    """The touches not yet released (time ns, point m, per-axis variance m^2), bounded:
    arrays in the order fed (the oldest first), searched by a compiled kernel."""

    def __init__(self):
        self._t = np.zeros(CAPACITY + 1, np.int64)
        self._xyz = np.zeros((CAPACITY + 1, 3))
        self._var = np.zeros(CAPACITY + 1)
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def clear(self) -> None:
        self._n = 0

    def _delete(self, i: int) -> None:
        n = self._n
        for a in (self._t, self._xyz, self._var):
            a[i:n - 1] = a[i + 1:n]
        self._n = n - 1

    def admit(self, time_ns: int, point_m, var_m2: float, polarity: int, weak: bool) -> bool:
        """Feed one event in time order; True when it is kept. A touch (polarity >= 0, the
        localizer's TOUCH) is remembered and kept; a release ends the nearest remembered
        touch in the gate and is kept; a weak release (``weak``) is kept only if it ended
        one; a weak touch never is."""
        if weak and polarity >= 0:
            return False  # a weak touch stays rejected
        t = int(time_ns)
        x, y, z = (float(v) for v in point_m)
        var = float(var_m2)
        if not (math.isfinite(x + y + z + var) and var >= 0.0):
            return not weak
        if weak and var > MAX_SIGMA_M * MAX_SIGMA_M:
            return False  # too vague a spot to be any touch's
        best = _nearest_spot(self._t, self._xyz, self._var, self._n, t, x, y, z, var,
                             _G2, _F2)
        if best >= 0:
            self._delete(best)  # released, or replaced by a touch on its spot
        if polarity >= 0:
            n = self._n
            self._t[n], self._xyz[n], self._var[n] = t, (x, y, z), var
            self._n = n + 1
            if self._n > CAPACITY:
                self._delete(0)
            return True
        return best >= 0 or not weak


def kept_with_weak_releases(
    res, time_ns, min_snr_db: float = MIN_SNR_DB, gate=None, usable=None
):
    """(kept (K,) bool, weak (K,) bool) of a `LocalizationResult` whose packets come at
    ``time_ns`` (K,): the accepted packets and the weak releases the gate keeps (fed in
    time order; ``gate`` carries the touches from earlier calls; packets not ``usable``
    (K,) bool are neither kept nor fed)."""
    gate = WeakReleaseGate() if gate is None else gate
    k = len(res.accepted)
    kept = np.zeros(k, bool)
    weak = np.zeros(k, bool)
    var = 0.5 * np.trace(res.covariance_m2, axis1=1, axis2=2)
    for i in np.argsort(np.asarray(time_ns), kind="stable"):
        if usable is not None and not usable[i]:
            continue
        w = not res.accepted[i] and is_weak_release(
            res.reason_flags[i], res.polarity[i], res.snr_db_est[i], min_snr_db, var[i]
        )
        if res.accepted[i] or w:
            kept[i] = gate.admit(int(time_ns[i]), res.point_m[i], var[i], int(res.polarity[i]), w)
            weak[i] = w and kept[i]
    return kept, weak


def weak_release_confidence(
    snr_db, min_snr_db, sigma_pos_m, overlap_excess, overlap_threshold, clamped
) -> float:
    """The localizer's confidence (localization/events.py: c_snr c_fit c_pos c_clamp) of a
    weak release, with the gate's SNR floor in place of min_snr_db."""
    return float(
        confidence(True, float(snr_db), float(min_snr_db), float(overlap_excess),
                   float(overlap_threshold), float(sigma_pos_m), bool(clamped))
    )
