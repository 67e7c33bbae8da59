# SPDX-License-Identifier: Apache-2.0
"""Everyday scene families for the slip detector (issue 38): generators of ground truth
and emissions in the 'events' model, and a scorer against the issue's targets.

Families (each ``f(seed, held_out=False) -> truth.Scene``): `FAMILIES`. The truth: every
emission (time, point, polarity, amplitude, kind, contact), the contacts (id, object,
point, on / off), each contact's state changes (NO_CONTACT / STICK / INCIPIENT_SLIP /
GROSS_SLIP), loads with q(t) and the time of gross slip, slides, textured strokes.
``summary.run_trial`` runs today's ``SlipDetector`` on one; ``summary.summarize`` scores a
family (bench/bench_everyday.py).
"""

from .loaded import grasp_load, q_of_fraction, regrasp, slide_restick_ramp, slipped_fraction
from .mixed import hold, mixed_stream
from .score import score_trial
from .slides import renewal_times, slide_start, stylus
from .summary import run_trial, summarize, targets
from .touches import broad_press, multi_point, tap_beside_held, touch_beside_held
from .truth import Scene, SceneBuilder, to_events

FAMILIES = {
    "multi_point": multi_point,
    "touch_beside_held": touch_beside_held,
    "broad_press": broad_press,
    "tap_beside_held": tap_beside_held,
    "hold": hold,
    "slide_start": slide_start,
    "slide_restick_ramp": slide_restick_ramp,
    "grasp_load": grasp_load,
    "regrasp": regrasp,
    "stylus": stylus,
    "mixed": mixed_stream,
}

__all__ = [
    "FAMILIES",
    "Scene",
    "SceneBuilder",
    "broad_press",
    "grasp_load",
    "hold",
    "mixed_stream",
    "multi_point",
    "q_of_fraction",
    "regrasp",
    "renewal_times",
    "run_trial",
    "score_trial",
    "slide_restick_ramp",
    "slide_start",
    "slipped_fraction",
    "stylus",
    "summarize",
    "tap_beside_held",
    "targets",
    "to_events",
    "touch_beside_held",
]
