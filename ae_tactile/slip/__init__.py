# SPDX-License-Identifier: Apache-2.0
"""Slip / texture analysis: localized emissions -> SLIP_PRECURSOR, SLIP and TEXTURE
events and a latched per-finger contact state. Pure numpy, never imports rclpy.

    from ae_tactile.slip import SlipDetector, SlipConfig, LocalizedEvent
    det = SlipDetector(SlipConfig(sliding_speed_m_s=0.02))
    outs = det.process(LocalizedEvent(time_ns, point_m, covariance_m2, polarity, amplitude_v,
                                      confidence, packet_id))
    det.advance(now_ns); det.state       # FingerState (NO_CONTACT / STICK / INCIPIENT_SLIP /
                                         # GROSS_SLIP)

Its evaluation on the simulator lives outside the product, in bench/ae_eval/slip
(bench/bench_slip.py). See docs/slip.md.
"""

from .config import SlipConfig
from .detector import SlipDetector
from .periodicity import Periodicity, periodicity
from .types import ContactInfo, FingerState, LocalizedEvent, SlipEvent

__all__ = [
    "SlipConfig",
    "SlipDetector",
    "LocalizedEvent",
    "SlipEvent",
    "ContactInfo",
    "FingerState",
    "Periodicity",
    "periodicity",
]
