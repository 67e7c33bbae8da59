# SPDX-License-Identifier: Apache-2.0
"""The contact pipeline, one module per stage along the data flow (docs/pipeline.md):

- `localize` (`PacketLocalizer`): per-packet check, localization, records;
- `screens` (`Screens`): interference, overlap suspects, weak releases;
- `hand` (`HandStage`): the hand's coincidence test;
- `overlaps` (`OverlapStage`, `OverlapResolver`): windows holding several emissions;
- `slip_stage` (`SlipOrder`, `SlipStage`): the slip step in time order;
- `config`: the constants and `LocalizationConfig`;
- `core` (`ContactPipeline`): the stages in order, and which lock each owns.
"""

from ae_tactile.pipeline.config import (
    APEX_OUT_MAX,
    APEX_POLAR_RAD,
    COMMON_IDENTICAL,
    COMMON_SUSPECT,
    COVERED_TOL_S,
    DUPLICATE_DISTANCE_M,
    DUPLICATE_TIME_S,
    ECHO_LEARN_CONFIDENCE,
    ECHO_LEARN_EVERY,
    ECHO_LEARN_PER_CALL,
    ECHO_MIN_LEARN,
    OVERLAP_HOLD_MAX_S,
    OVERLAP_INLINE_MAX,
    OVERLAP_SUSPECT_CONFIDENCE,
    OVERLAP_SUSPECT_EXCESS,
    RECENT_MARGIN_NS,
    ROUTE_ALL,
    ROUTE_NONE,
    ROUTE_SPECTRUM,
    SUSPECT_CONFIDENCE,
    LocalizationConfig,
)
from ae_tactile.pipeline.core import ContactPipeline
from ae_tactile.pipeline.hand import HandStage
from ae_tactile.pipeline.localize import PacketLocalizer, packet_problem
from ae_tactile.pipeline.overlaps import OverlapStage
from ae_tactile.pipeline.resolver import OverlapResolver
from ae_tactile.pipeline.screens import Screens, interference_route
from ae_tactile.pipeline.slip_stage import SlipOrder, SlipStage
from ae_tactile.records import (
    ContactRecord,
    EventType,
    PacketView,
    packet_record,
    slip_record,
    source_record,
)

__all__ = [
    "APEX_OUT_MAX",
    "APEX_POLAR_RAD",
    "COMMON_IDENTICAL",
    "COMMON_SUSPECT",
    "COVERED_TOL_S",
    "DUPLICATE_DISTANCE_M",
    "DUPLICATE_TIME_S",
    "ECHO_LEARN_CONFIDENCE",
    "ECHO_LEARN_EVERY",
    "ECHO_LEARN_PER_CALL",
    "ECHO_MIN_LEARN",
    "OVERLAP_HOLD_MAX_S",
    "OVERLAP_INLINE_MAX",
    "OVERLAP_SUSPECT_CONFIDENCE",
    "OVERLAP_SUSPECT_EXCESS",
    "RECENT_MARGIN_NS",
    "ROUTE_ALL",
    "ROUTE_NONE",
    "ROUTE_SPECTRUM",
    "SUSPECT_CONFIDENCE",
    "ContactPipeline",
    "ContactRecord",
    "EventType",
    "HandStage",
    "LocalizationConfig",
    "OverlapResolver",
    "OverlapStage",
    "PacketLocalizer",
    "PacketView",
    "Screens",
    "SlipOrder",
    "SlipStage",
    "interference_route",
    "packet_problem",
    "packet_record",
    "slip_record",
    "source_record",
]
