# SPDX-License-Identifier: Apache-2.0
"""Contact localization from the four PVDF channels. Pure numpy/scipy, no rclpy.

    from ae_tactile.localization import localize, available_methods
    res = localize(windows (K, 4, M), sample_rate_hz, onset_index (K,), method="ml")
    res.point_m, res.covariance_m2, res.accepted, res.reason, res.polarity, res.confidence

Methods (registry ``ESTIMATORS``, pick by name): ``ml`` (exact-sphere maximum
likelihood), ``gradient`` (the paper's gradient method, iterated), ``gcc_phat``,
``xcorr_farfield`` (the paper's one-shot Eq. 2 baseline); one module each, registered in
`registry`. Overlapping emissions: `overlap`. Cramer-Rao bounds are evaluation code
(``ae_eval.crlb`` in bench/).

Per-packet hot path (compiled with numba when available, `fast.py`):

    loc = Localizer("ml").warm_up(geometry, fs, n_samples)
    r = loc.localize_one(window (4, M), fs, onset)   # PacketLocation: accepted, point_m, ...

The channels' own delays, learnt from touches (`ChannelDelayLearner`), are taken out of
the arrivals with ``Localizer.set_channel_delays``. See docs/localization.md.
"""

from ae_tactile.localization.channel_delays import ChannelDelayLearner
from ae_tactile.localization.common import REASON_DESCRIPTIONS, Reason
from ae_tactile.localization.estimators import localize, localize_packets
from ae_tactile.localization.fast import NUMBA_AVAILABLE
from ae_tactile.localization.localizer import Localizer
from ae_tactile.localization.registry import (
    DEFAULT_BAND_HZ,
    ESTIMATORS,
    EstimatorInfo,
    available_methods,
    default_band_hz,
    get_estimator,
    register_estimator,
)
from ae_tactile.localization.result import LocalizationResult, PacketLocation

__all__ = [
    "localize",
    "localize_packets",
    "Localizer",
    "LocalizationResult",
    "Reason",
    "REASON_DESCRIPTIONS",
    "ESTIMATORS",
    "EstimatorInfo",
    "available_methods",
    "get_estimator",
    "register_estimator",
    "DEFAULT_BAND_HZ",
    "default_band_hz",
    "PacketLocation",
    "NUMBA_AVAILABLE",
    "ChannelDelayLearner",
]
