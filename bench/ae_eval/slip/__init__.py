# SPDX-License-Identifier: Apache-2.0
"""Evaluation of the slip detector on the simulator's scenes (bench/bench_slip.py,
test/test_slip_eval.py).

The real pipeline at core level, per trial: a scene with its own seed and randomised
parameters -> the simulator's triggered source (windows cut from the stream around each
emission, as the device's trigger cuts them: overlaps, noise and quantization included)
-> ``ae_tactile.localization.localize`` (default estimator, accepted packets only, time
stamp = onset time - travel time from the fitted point, as the localizer node stamps
events) -> ``SlipDetector``. Nothing of the ground truth reaches the detector
(`pipelines`).

Trials (each function takes a seed and returns a JSON-able dict):
  incipient_slip_trial   Cattaneo-Mindlin incipient slip (optionally announced by a touch
                         at the contact centre): precursor before gross slip, lead time,
                         load fraction q = Q/(mu P) at detection, SLIP delay (`incipient`)
  gross_slip_bound_trial the same scene (never announced, 'events'): the Bayes posterior
                         that gross slip has begun, given truth no detector has (the
                         bound a SLIP decision can reach) (`bound`)
  closed_loop_trial      the same scene, P raised (grip reflex) once SLIP_PRECURSOR arrives:
                         was gross slip averted (`incipient`)
  touch_hold_release_trial, random_touches_trial, tapping_trial, cycles_trial,
  grasp_cycles_trial     false alarms (any SLIP_PRECURSOR / SLIP / TEXTURE) and the
                         latched state (`alarms`)
  stylus_trial, texture_trial
                         spatial period error of TEXTURE, detection time (`texture`)
  drift_slip_trial       plane slip drifting along x: SLIP delay and direction error
  interference_trial, hand_interference_trial
                         common-mode interference on one fingertip and across a hand
                         (`interference`, `hand`)
``run_evaluation`` runs the main families and summarises them (`summary`).
"""

from .alarms import (
    GRASP_CYCLES,
    cycles_packets,
    cycles_trial,
    grasp_cycles_trial,
    noise_window_snr_db,
    random_touches_trial,
    tapping_trial,
    touch_hold_release_trial,
    weak_release_trial,
)
from .bound import BOUND_THRESHOLDS, gross_slip_bound_trial, summarize_gross_slip_bound
from .common import EVENTS_DROP, NS, SLIP_KINDS
from .hand import hand_interference_trial, link_clock
from .incipient import (
    INCIPIENT_RANGES,
    closed_loop_trial,
    incipient_slip_scene,
    incipient_slip_trial,
)
from .interference import (
    apex_touch_packets,
    interference_finger,
    interference_outcome,
    interference_packet_rates,
    interference_trial,
    learnt_echo_min,
)
from .pipelines import (
    emission_events,
    localized_events,
    run_detector,
    scene_events,
    stream_localized_events,
    streaming_source,
    triggered_source,
)
from .summary import (
    run_evaluation,
    summarize_alarms,
    summarize_closed_loop,
    summarize_drift,
    summarize_incipient,
    summarize_texture,
)
from .texture import drift_slip_trial, stylus_events, stylus_trial, texture_trial

__all__ = [
    "BOUND_THRESHOLDS",
    "EVENTS_DROP",
    "GRASP_CYCLES",
    "INCIPIENT_RANGES",
    "NS",
    "SLIP_KINDS",
    "apex_touch_packets",
    "closed_loop_trial",
    "cycles_packets",
    "cycles_trial",
    "drift_slip_trial",
    "emission_events",
    "grasp_cycles_trial",
    "gross_slip_bound_trial",
    "hand_interference_trial",
    "incipient_slip_scene",
    "incipient_slip_trial",
    "interference_finger",
    "interference_outcome",
    "interference_packet_rates",
    "interference_trial",
    "learnt_echo_min",
    "link_clock",
    "localized_events",
    "noise_window_snr_db",
    "random_touches_trial",
    "run_detector",
    "run_evaluation",
    "scene_events",
    "stream_localized_events",
    "streaming_source",
    "stylus_events",
    "stylus_trial",
    "summarize_alarms",
    "summarize_closed_loop",
    "summarize_drift",
    "summarize_gross_slip_bound",
    "summarize_incipient",
    "summarize_texture",
    "tapping_trial",
    "texture_trial",
    "touch_hold_release_trial",
    "triggered_source",
    "weak_release_trial",
]
