# SPDX-License-Identifier: Apache-2.0
"""The pipeline's constants and settings, in one place (SI units; ns where the name says so).

`LocalizationConfig` holds the localization settings (`PacketLocalizer`, and the pipeline's
``overlap_inline_max``) with their default, unit, range and description in the field
metadata: the ROS parameter table (`ae_tactile.ros.params.localization_params`), the YAML
files and docs/parameters.md are generated from it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import numpy as np

from ae_tactile.localization.overlap.pulse import PulseModel
from ae_tactile.localization.weak_release import MIN_SNR_DB as WEAK_RELEASE_MIN_SNR_DB
from ae_tactile.localization.weak_release import check_min_snr_db

# ---------------------------------------------------------------- screens (`screens.py`)
#: [rad] packets localized closer to the apex than this are checked for common-mode
#: interference: its zero delays put it at the apex; 3 deg leaves a wide margin over the
#: spread a 1 % channel gain mismatch gives.
APEX_POLAR_RAD = math.radians(3.0)
#: [1] ... and so are packets fitting this poorly (a burst can also end as a bad fit away
#: from the apex; real touches at 10 dB SNR fit better).
SUSPECT_CONFIDENCE = 0.3
#: [1] ... and every packet whose common-mode share of the window's energy (noise removed)
#: is at least this: the discriminator's own bar (touches reach it only near the apex).
COMMON_SUSPECT = 0.9
#: [1] screened packets with at least this share (the four channels one waveform within the
#: noise) get every test, the others only the spectrum tests (a slip's window holding two
#: emissions near the apex is common-mode too, and no single template explains it).
COMMON_IDENTICAL = 0.99
#: `interference_route`: which of the discriminator's tests a packet gets
ROUTE_NONE, ROUTE_SPECTRUM, ROUTE_ALL = 0, 1, 2
#: `interference_echo_min` of a learnt echo test (`ae_tactile.dsp.interference.EchoLearner`)
ECHO_MIN_LEARN = -1.0
#: [1] the learnt echo test measures the echo of accepted packets away from the apex with
#: at least this confidence, at most ECHO_LEARN_PER_CALL per call and, once the learner
#: holds ECHO_LEARN_KEEP, in one call in ECHO_LEARN_EVERY (it follows a device whose echo
#: changes: the learners' 64 waveforms turn over in 4 measuring calls, 256 calls; a
#: measuring call costs the reflex path a few hundred us).
ECHO_LEARN_CONFIDENCE = 0.5
ECHO_LEARN_PER_CALL = 4
ECHO_LEARN_EVERY = 64
#: [1] accepted packets below this confidence whose fit leaves more than
#: OVERLAP_SUSPECT_EXCESS [1] of unexplained in-band energy are checked for a second
#: emission in the window (single emissions stay below the excess bar).
OVERLAP_SUSPECT_CONFIDENCE = 0.6
OVERLAP_SUSPECT_EXCESS = 0.028

# ---------------------------------------------------------------- channel delays (`localize.py`)
#: packets measured per learning call of the channel delays (`ChannelDelayLearner.add`)
DELAY_LEARN_BATCH = 16
#: one confident packet in this many is kept for the channel delays while a contrast is
#: not known to its tolerance, then one in DELAY_LEARN_STRIDE_CONVERGED (followed): ~0.3 ms
#: of numpy per packet measured, in a learning thread of their own (in a pipeline)
DELAY_LEARN_STRIDE = 2
DELAY_LEARN_STRIDE_CONVERGED = 16
#: [1/s] and at most this many per second of the device's time: a grasp's micro-slips at
#: 1,000/s would otherwise cost the learning thread 15 % of a core, held against the reader
DELAY_LEARN_MAX_RATE_HZ = 50.0
#: packets the channel delays learn from: confident single emissions [0..1] ...
DELAY_LEARN_CONFIDENCE = 0.3
#: ... away from the horizon [rad] (a point clamped there is no measurement)
DELAY_LEARN_MAX_POLAR_RAD = math.radians(80.0)

# ---------------------------------------------------------------- hand (`hand.py`)
#: [1] apex packet onsets kept for the hand's topic until taken (the newest)
APEX_OUT_MAX = 10_000

# ---------------------------------------------------------------- slip order (`slip_stage.py`)
#: [s] longest time the slip step waits for the overlap resolver's answer to a window (so
#: that the slip detector sees every emission in time order, as offline); then the events
#: go on without it (``slip_hold_expired``) and its emissions, when they come, are
#: processed late with their own stamps.
OVERLAP_HOLD_MAX_S = 0.1

# ---------------------------------------------------------------- overlaps (`overlaps.py`)
#: [1] overlapping windows per batch whose quick answer (one compiled call, about a
#: millisecond) comes in the reader's thread, right after the batch's other contact events:
#: their emissions reach the hand soonest, while the packets that arrive meanwhile wait
#: that long. The others (0: all) get their quick answer in the resolver's thread; DEFERRED
#: ones the exhaustive search in the worker process. The driver's
#: `localization.overlap_inline_max`.
OVERLAP_INLINE_MAX = 2
#: [s] a window whose trigger lies within this of the first arrival of an emission resolved
#: in the reader, or of the trigger of a window answered there, holds what that window held
#: (the second window of a pair; two emissions closer than 1.5 us are not resolved anyway,
#: and a trigger lags the arrival by well under 1 us): it goes to the worker, which adds,
#: late, what the first window did not hold.
COVERED_TOL_S = 2e-6
#: [s], [m] an emission the resolver finds within DUPLICATE_TIME_S and DUPLICATE_DISTANCE_M
#: of an event already handed out is that emission (two windows' fits of one emission agree
#: to nanoseconds and micrometres; two emissions at one spot within 1 us cannot be told
#: apart): dropped and counted (``overlap_duplicates``).
DUPLICATE_TIME_S = 1e-6
DUPLICATE_DISTANCE_M = 1e-3
#: [ns] contact events are remembered for that check from the earliest possible emission of
#: the oldest window still with the resolver (or of the newest event) minus this margin:
#: more than a window's pre-trigger plus its span.
RECENT_MARGIN_NS = 1_000_000
#: [1] windows waiting for the resolver at most; more are dropped (``overlap_dropped_backlog``)
OVERLAP_MAX_PENDING = 64
#: the late check (`late_check.py`): [1/s] single emissions checked per second of their
#: stamps at most (~0.1 ms of the resolver's thread each: 200/s is 2 % of a core), [1]
#: waiting at most, [1] checked per turn of the resolver's thread, [s] how often that
#: thread looks for them when it has no window to answer
LATE_CHECK_MAX_RATE_HZ = 200.0
LATE_CHECK_MAX = 64
LATE_CHECK_BATCH = 8
LATE_CHECK_POLL_S = 0.01

#: Sample rates a packet may have [Hz]: from where the localization band (100 kHz up to
#: fs/4) still has an octave (800 kHz) up to 10x the fastest front end planned (100 MHz:
#: above it one window's analysis grows past a bounded memory)
MIN_SAMPLE_RATE_HZ = 800e3
MAX_SAMPLE_RATE_HZ = 100e6
#: Longest packet localized [samples per channel] (a device packet is a few hundred; the
#: bound keeps one call's memory bounded)
MAX_PACKET_SAMPLES = 65_536


# ---------------------------------------------------------------- settings
def echo_min_setting(echo_min) -> float:
    """The echo test's setting: < 0 learnt (ECHO_MIN_LEARN), 0 off, 0 < v <= 1 fixed.
    ValueError otherwise."""
    v = float(echo_min)
    if not (math.isfinite(v) and -1.0 <= v <= 1.0):
        raise ValueError(f"interference_echo_min must be in [-1, 1], got {echo_min!r}")
    return ECHO_MIN_LEARN if v < 0.0 else v


def _setting(default, doc, unit="", lo=None, hi=None):
    """A field with its description, unit [SI] and range (the ROS parameter's)."""
    return field(default=default, metadata={"doc": doc, "unit": unit, "lo": lo, "hi": hi})


@dataclass(frozen=True)
class LocalizationConfig:
    """The localization settings, defined once.

    Parameters
    ----------
    method : str
        Delay estimator (`ae_tactile.localization.available_methods`).
    min_snr_db : float
        Reject packets below this SNR [dB].
    min_confidence : float
        Drop accepted packets below this confidence [1].
    reject_interference : bool
        Run the common-mode interference screen.
    interference_echo_min : float
        Echo test: -1 learnt, 0 off, (0, 1] fixed [1].
    interference_timing : bool
        Timing test of the apex packets.
    weak_releases : bool
        Keep weak releases on the spot of an unreleased touch.
    weak_release_min_snr_db : float
        Lowest SNR of a weak release [dB].
    resolve_overlaps : bool
        Localize each emission of a window holding several.
    front_end : str
        The device's stated front end (`PulseModel.from_spec`); refines every accepted
        point with its pulse; empty: none.
    overlap_inline_max : int
        Overlapping windows per batch answered in the reader (`ContactPipeline`).

    Returns
    -------
    LocalizationConfig
        Validated (ValueError naming the field); ``interference_echo_min`` < 0 is stored
        as -1.
    """

    method: str = _setting("ml", "Delay estimator (ml: exact-sphere maximum likelihood)")
    min_snr_db: float = _setting(
        5.0,
        "Reject packets below this SNR (docs/conventions.md): lower keeps fainter touches "
        "and more false ones from noise",
        "dB", -20.0, 80.0,
    )
    min_confidence: float = _setting(
        0.0,
        "Do not publish contact events below this localization confidence: higher drops "
        "poorly fitting events (fewer wrong points, more missed touches)",
        "", 0.0, 1.0,
    )
    reject_interference: bool = _setting(
        True,
        "Reject common-mode electrical interference (identical waveforms on the four "
        "channels)",
    )
    interference_echo_min: float = _setting(
        ECHO_MIN_LEARN,
        "Echo test of a fingertip with wall echoes: an apex packet whose echo at 2R/c is "
        "weaker than this share of the direct packet (regression coefficient) is "
        "interference (catches interference entering the amplifier's input, shaped like a "
        "touch). -1: learnt, half the echo of the device's own touches away from the apex, "
        "once 3 have shown one of >= 0.15 (none on a device without echoes); 0: no echo "
        "test; 0.25 for a wall returning half",
        "", -1.0, 1.0,
    )
    interference_timing: bool = _setting(
        True,
        "Timing test of the packets at the apex (the test a fingertip without wall echoes "
        "relies on): one whose intervals to the last 8 repeat intervals among them to < 1 us "
        "is periodic interference (rejected_INTERFERENCE_TRAIN); false for a rig that taps "
        "the apex at a crystal-timed rate",
    )
    weak_releases: bool = _setting(
        True,
        "Keep a release below min_snr_db (a rarefaction rejected only for low SNR, down to "
        "weak_release_min_snr_db) when it lies on the spot of a touch not yet released (the "
        "slip detector's same-spot gate): that touch's DETOUCH (counted as weak_releases); "
        "false: such packets stay rejected_LOW_SNR",
    )
    weak_release_min_snr_db: float = _setting(
        WEAK_RELEASE_MIN_SNR_DB,
        "Lowest estimated SNR of a weak release (windows of noise alone reach it too: the "
        "spot test and a bound of 0.5 mm on the position's 1-sigma keep them out, see "
        "docs/localization.md)",
        "dB", -20.0, 80.0,
    )
    resolve_overlaps: bool = _setting(
        True,
        "Localize each emission of a window that holds several (the first "
        "overlap_inline_max of a batch in the reader, the others beside it); false: reject "
        "such windows",
    )
    front_end: str = _setting(
        "",
        "Refine every accepted point by the one-emission fit with the pulse of the "
        "device's stated analog front end, name=value items of PulseModel.from_spec (e.g. "
        "'highpass_hz=50e3 highpass_order=1 lowpass_hz=800e3 lowpass_order=2', RC stages "
        "as highpass_rc_hz=60e3/69e3, lowpass_family=butter, bessel or cheby1): at the "
        "Cramer-Rao bound where the anti-alias filter lets the pulse alias, 0.2-0.4 ms a "
        "packet (docs/front_end.md); it is also the interference screen's model of a touch "
        "until the device's own are learnt; empty: no refinement, the nominal model",
    )
    overlap_inline_max: int = _setting(
        OVERLAP_INLINE_MAX,
        "Overlapping windows per batch whose quick fit runs in the reader (about 1 ms each: "
        "their emissions reach the hand soonest, the packets behind them that much later); "
        "the others are fitted in the resolver's thread beside it",
        "", 0, 8,
    )

    def __post_init__(self):
        for name, conv in (("min_snr_db", float), ("min_confidence", float),
                           ("interference_echo_min", echo_min_setting),
                           ("weak_release_min_snr_db", check_min_snr_db),
                           ("overlap_inline_max", int)):
            object.__setattr__(self, name, conv(getattr(self, name)))
        object.__setattr__(self, "front_end", str(self.front_end).strip())
        if self.front_end:
            PulseModel.from_spec(self.front_end)  # ValueError naming the bad item
        for f in fields(self):
            if isinstance(f.default, bool):
                object.__setattr__(self, f.name, bool(getattr(self, f.name)))

    def replace(self, **changes) -> "LocalizationConfig":
        """A validated copy with ``changes`` (TypeError on an unknown name)."""
        return replace(self, **changes)

    @classmethod
    def describe(cls) -> dict[str, dict]:
        """Per field: default, doc, unit, lo, hi (the ROS table's source)."""
        return {f.name: {"default": f.default, **f.metadata} for f in fields(cls)}


# ---------------------------------------------------------------- checks
def packet_problem(samples_v, sample_rate_hz, onset_index) -> str | None:
    """Why a packet cannot be localized at all: the per-packet check.

    Parameters
    ----------
    samples_v : numpy.ndarray
        The packet's window (4, N) [V].
    sample_rate_hz : float
        Its sample rate [Hz].
    onset_index : int
        Its onset sample.

    Returns
    -------
    str or None
        "shape", "too_short", "too_long" (over MAX_PACKET_SAMPLES), "sample_rate" (not
        finite, or outside MIN_SAMPLE_RATE_HZ .. MAX_SAMPLE_RATE_HZ) or "onset"; None if it
        can be localized.
    """
    x = samples_v
    if not isinstance(x, np.ndarray) or x.ndim != 2 or x.shape[0] != 4:
        return "shape"
    if x.shape[1] < 8:
        return "too_short"
    if x.shape[1] > MAX_PACKET_SAMPLES:
        return "too_long"
    try:
        fs = float(sample_rate_hz)
    except (TypeError, ValueError):
        return "sample_rate"
    if not (math.isfinite(fs) and MIN_SAMPLE_RATE_HZ <= fs <= MAX_SAMPLE_RATE_HZ):
        return "sample_rate"
    if not 0 <= int(onset_index) < x.shape[1]:
        return "onset"
    return None


def front_end_pulse(spec: str):
    """The pulse of a stated front end (`LocalizationConfig.front_end`); None if empty."""
    return PulseModel.from_spec(spec) if spec else None
