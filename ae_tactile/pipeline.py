# SPDX-License-Identifier: Apache-2.0
"""The fingertip's hot path: decoded packets -> contact events -> slip events (no rclpy).

One `ContactPipeline` per fingertip does, for each batch of packets the link decodes and
in the thread that decoded them:

1. per-packet validation (shape, sample rate, finite samples): a bad packet is counted by
   reason and never costs its neighbours;
2. localization: one packet alone takes the single-packet fast path, a backlog is
   localized in batches (the cost per packet falls with the batch size);
3. common-mode interference rejection (identical waveforms on the four channels, e.g. a
   motor driver's switching): such a packet has zero delays, so the localizer puts it at
   the apex; the discriminator (`ae_tactile.dsp.interference`) runs on the packets
   localized within ``APEX_POLAR_RAD`` of the apex, or with a poor fit, only (packet
   tests, the wall echo learnt from the device's touches, the timing of periodic trains);
4. contact events (TOUCH for compressions, DETOUCH for rarefactions) handed to the caller
   at once, *before* the slip step; windows that hold overlapping emissions (rejected as
   OVERLAP, or accepted with a poor fit that `suspect_overlap` finds inconsistent with one
   emission) are localized emission by emission (`ae_tactile.localization.overlap`): the
   first ``overlap_inline_max`` of a batch get the quick answer right here, after the
   batch's other contact events are out (one compiled call, about 1 ms live); the others,
   hard windows (quick answer DEFERRED: the exhaustive search, in a worker process) and
   the second window of a pair (`COVERED_TOL_S`) go to `OverlapResolver`, which hands
   their emissions over later, from its own thread, with their own stamps;
5. the slip detector: SLIP_PRECURSOR / SLIP / TEXTURE events and the finger's contact state.
   It sees the emissions in time order: while a window is with the overlap resolver, the
   slip step of contact events later than the window's earliest possible emission waits
   for its answer (at most ``OVERLAP_HOLD_MAX_S``; their contact events are out already),
   so the slip events do not depend on how fast the resolver was (a late emission
   processed after later ones can tip the detector).

The ROS driver calls it from its serial reader thread and publishes what it returns; the
separate `localizer` and `slip_detector` nodes (replaying recorded packets) use the same
`PacketLocalizer` and `SlipStage`.

Emission time of a contact event (int ns, host clock):
    t_emit = t_first_sample + emission_offset_s,
emission_offset_s being the fitted arrival at the nearest element minus the travel time
from the fitted point to it (or onset_index / fs minus that travel time when the
estimator gives no fitted arrival).
"""

from __future__ import annotations

import math
import pickle
import queue
import subprocess
import sys
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ae_tactile.dsp.coincidence import HandCoincidence
from ae_tactile.dsp.interference import (
    ECHO_LEARN_KEEP,
    TRAIN_TOL_S,
    TRAIN_TOL_SAMPLES,
    BurstTrain,
    EchoLearner,
    echo_ratio,
    packet_common_share,
)
from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import Localizer, Reason, get_estimator
from ae_tactile.localization.weak_release import (
    MIN_SNR_DB as WEAK_RELEASE_MIN_SNR_DB,
)
from ae_tactile.localization.weak_release import (
    WeakReleaseGate,
    check_min_snr_db,
    is_weak_release,
    weak_release_confidence,
)
from ae_tactile.records import (  # noqa: F401  (re-exported: the pipeline's records)
    ContactRecord,
    EventType,
    PacketView,
    slip_record,
    source_record,
)
from ae_tactile.slip import LocalizedEvent, SlipConfig, SlipDetector

#: Packets localized closer to the apex than this polar angle (rad) are checked for
#: common-mode interference (whose zero delays put it at the apex: measured within 0.1 deg
#: for bursts with 1 % channel gain mismatch; 3 deg leaves a wide margin) ...
APEX_POLAR_RAD = math.radians(3.0)
#: apex packet onsets kept for the hand's topic until taken (`ContactPipeline`)
APEX_OUT_MAX = 10_000
#: ... and so are very poorly fitting packets (a burst can also end as a bad fit elsewhere:
#: seen at confidence 0.13; real touches at 10 dB have 0.35-0.45) ...
SUSPECT_CONFIDENCE = 0.3
#: ... and every packet whose four channels are nearly one waveform: common-mode share of
#: the window's energy (noise removed) at least COMMON_SUSPECT, the discriminator's own bar
#: (bursts with a middling fit were seen localized 3 .. 25 deg off the apex at confidence
#: 0.3 .. 0.66; touches reach it only within ~11 deg of the apex: 9-14 % of touches
#: uniform over 3 .. 50 deg, which then pay the discriminator, ~40 us).
COMMON_SUSPECT = 0.9
#: Screened packets whose share is at least COMMON_IDENTICAL (the four channels one
#: waveform within the noise: bursts localized just past 3 deg scored 0.998 .. 1.000) get
#: every test, the others only the spectrum tests (a slip's window holding two emissions
#: near the apex scored 0.93 .. 0.98, and no single template explains it).
COMMON_IDENTICAL = 0.99
#: The learnt echo test (`PacketLocalizer`, `interference_echo_min` < 0) measures the echo
#: of accepted packets away from the apex with at least this confidence, at most
#: ECHO_LEARN_PER_CALL per call, and once it holds ECHO_LEARN_KEEP, in one call in
#: ECHO_LEARN_EVERY (it follows a device whose echo changes; ~40 us per measuring call).
ECHO_LEARN_CONFIDENCE = 0.5
ECHO_LEARN_PER_CALL = 4
ECHO_LEARN_EVERY = 16
#: Accepted packets below this confidence whose fit leaves more than OVERLAP_SUSPECT_EXCESS
#: of unexplained in-band energy are checked for a second emission in the window (measured
#: on the simulator: overlaps that `ml` accepted 0.1-8 mm off had confidence <= 0.53 and
#: excess 0.033-0.063; single emissions at 10-40 dB excess <= 0.025).
OVERLAP_SUSPECT_CONFIDENCE = 0.6
OVERLAP_SUSPECT_EXCESS = 0.028
#: Longest time (s) the slip step of contact events already handed out may wait while
#: more packets are waiting on the port (their contact events go out first; a slip
#: event comes at most this much later than it would alone).
SLIP_MAX_DEFER_S = 0.5e-3
#: Longest time (s) the slip step waits for the overlap resolver's answer to a window (so
#: that the slip detector sees every emission in time order, as it would offline); after
#: that the events go on without it (``slip_hold_expired``) and its emissions, when they
#: come, are processed late with their own stamps.
OVERLAP_HOLD_MAX_S = 0.1
#: Overlapping windows per batch of packets whose quick answer (`resolve_overlaps` with
#: ``exhaustive=False``: one compiled call, ~0.55 ms in a tight loop, ~0.9 ms live) comes
#: in the reader's thread, right after the batch's other contact events: their emissions
#: reach the hand soonest, while the packets that arrive meanwhile wait that long. The
#: others (0: all) get their quick answer in the resolver's thread, beside the reader;
#: DEFERRED ones the exhaustive search in the worker process. The driver's
#: `localization.overlap_inline_max`; bench_system's natural and slip cases measure both.
OVERLAP_INLINE_MAX = 2
#: A window whose trigger (its onset sample) lies within COVERED_TOL_S of the first
#: arrival of an emission resolved in the reader, or of the trigger of a window answered
#: there, holds what that window held: the second window of a pair (the same two
#: emissions; two emissions closer than 1.5 us are not resolved anyway, and a trigger
#: lags the arrival by well under 1 us). It goes to the worker, which adds, late, what the
#: first window did not hold.
COVERED_TOL_S = 2e-6
#: An emission the overlap resolver finds that was already handed out (it fell into the
#: windows of two triggers, or its own window was localized on the hot path) is the same
#: emission when its stamp is within DUPLICATE_TIME_S and its point within
#: DUPLICATE_DISTANCE_M of the earlier event's: it is dropped and counted
#: (``overlap_duplicates``). Two windows' fits of one emission agree to nanoseconds and
#: micrometres, a hot-path stamp is within 0.1 us (p99; simulator), and two emissions at
#: one spot within 1 us cannot be told apart anyway.
DUPLICATE_TIME_S = 1e-6
DUPLICATE_DISTANCE_M = 1e-3
#: Contact events are remembered for that check from the earliest possible emission of
#: the oldest window still with the resolver (or of the newest event, when none is) minus
#: this margin (ns): more than a window's pre-trigger plus its span.
RECENT_MARGIN_NS = 1_000_000


def packet_problem(samples_v, sample_rate_hz, onset_index) -> str | None:
    """Why a packet cannot be localized at all (None if it can): the per-packet check that
    keeps one bad packet from costing its neighbours."""
    x = samples_v
    if not isinstance(x, np.ndarray) or x.ndim != 2 or x.shape[0] != 4:
        return "shape"
    if x.shape[1] < 8:
        return "too_short"
    try:
        fs = float(sample_rate_hz)
    except (TypeError, ValueError):
        return "sample_rate"
    if not math.isfinite(fs) or fs <= 0:
        return "sample_rate"
    if not 0 <= int(onset_index) < x.shape[1]:
        return "onset"
    return None


def _interference_check():
    """The common-mode interference discriminator, where the core has it."""
    try:
        from ae_tactile.dsp.interference import common_mode_interference
    except ImportError:
        return None
    return common_mode_interference


def _gains_or_none(channel_gains):
    """Relative channel gains as a validated (4,) array, or None when all are 1 (nothing
    to apply: the per-packet path skips them). ValueError unless 4 positive finite numbers."""
    if channel_gains is None:
        return None
    g = np.asarray(channel_gains, dtype=float)
    if g.shape != (4,) or not np.all(np.isfinite(g) & (g > 0)):
        raise ValueError(f"channel_gains must be 4 positive finite numbers, got {channel_gains!r}")
    return None if np.all(g == 1.0) else g


#: `interference_echo_min` of a learnt echo test (`ae_tactile.dsp.interference.EchoLearner`)
ECHO_MIN_LEARN = -1.0


def _echo_min_setting(echo_min) -> float:
    """The echo test's setting: < 0 learnt (ECHO_MIN_LEARN), 0 off, 0 < v <= 1 fixed.
    ValueError otherwise."""
    v = float(echo_min)
    if not (math.isfinite(v) and -1.0 <= v <= 1.0):
        raise ValueError(f"interference_echo_min must be in [-1, 1], got {echo_min!r}")
    return ECHO_MIN_LEARN if v < 0.0 else v


#: `interference_route`: which of the discriminator's tests a packet gets
ROUTE_NONE, ROUTE_SPECTRUM, ROUTE_ALL = 0, 1, 2


def interference_route(polar_rad: float, confidence: float, share: float | None = None):
    """Which of the discriminator's tests the driver gives a localized packet: ROUTE_ALL
    at the apex (< APEX_POLAR_RAD), for a very poor fit (< SUSPECT_CONFIDENCE) or one
    waveform within the noise (common-mode ``share`` >= COMMON_IDENTICAL); ROUTE_SPECTRUM
    for nearly one waveform (>= COMMON_SUSPECT); else ROUTE_NONE. None when the first two
    do not decide and ``share`` is not given (the caller measures it only then)."""
    if polar_rad < APEX_POLAR_RAD or confidence < SUSPECT_CONFIDENCE:
        return ROUTE_ALL
    if share is None:
        return None
    if share >= COMMON_IDENTICAL:
        return ROUTE_ALL
    return ROUTE_SPECTRUM if share >= COMMON_SUSPECT else ROUTE_NONE


def _common_share(packets) -> list[float]:
    """`common_mode_share` of each packet (its pretrigger mean and its own noise_rms_v
    removed; compiled, ~1 us a packet)."""
    out = []
    for p in packets:
        nv = float(getattr(p, "noise_rms_v", 0.0) or 0.0)
        out.append(
            packet_common_share(p.samples_v, nv if math.isfinite(nv) else 0.0,
                                int(p.onset_index))
        )
    return out


def _packet_time_s(p) -> float:
    """A packet's onset (s) on the device's sample clock where the packet has it (exact to a
    sample), else on its host stamp."""
    fs = float(p.sample_rate_hz)
    dsi = getattr(p, "device_sample_index", None)
    if dsi is not None:
        return (int(dsi) + int(p.onset_index)) / fs
    return int(p.stamp_ns) * 1e-9 + int(p.onset_index) / fs


class _Row:
    """One packet's fields of a batch `LocalizationResult` (`PacketLocalizer._weak`)."""

    __slots__ = ("_res", "_j", "emission_offset_s")

    def __init__(self, res, j, offset_s):
        self._res, self._j, self.emission_offset_s = res, j, offset_s

    def __getattr__(self, name):
        return getattr(self._res, name)[self._j]


class PacketLocalizer:
    """Packets -> contact events (TOUCH / DETOUCH), counting every rejection by reason.

    ``batch_min`` packets or more in one call are localized as a batch (cheaper per
    packet under load); fewer take the single-packet path (lowest latency).
    """

    def __init__(
        self,
        method: str = "ml",
        *,
        min_snr_db: float = 5.0,
        min_confidence: float = 0.0,
        geometry: FingertipGeometry | None = None,
        channel_gains=None,
        reject_interference: bool = True,
        batch_min: int = 4,
        resolve_overlaps: bool = True,
        interference_echo_min: float = ECHO_MIN_LEARN,
        interference_timing: bool = True,
        weak_releases: bool = True,
        weak_release_min_snr_db: float = WEAK_RELEASE_MIN_SNR_DB,
    ):
        self.localizer = Localizer(method, min_snr_db=min_snr_db)
        #: weak releases (`ae_tactile.localization.weak_release`): a rarefaction rejected
        #: only for low SNR, down to weak_release_min_snr_db, on the spot of a touch not
        #: yet released is that touch's DETOUCH
        self.weak_releases = bool(weak_releases)
        self.weak_release_min_snr_db = check_min_snr_db(weak_release_min_snr_db)
        self.weak_gate = WeakReleaseGate()
        #: the interference discriminator's echo test (a device with wall echoes: an apex
        #: packet without its echo at 2R/c is interference): ECHO_MIN_LEARN (< 0) learnt
        #: from the device's own touches away from the apex, 0 off, > 0 this threshold
        self.interference_echo_min = _echo_min_setting(interference_echo_min)
        self.echo_learner = EchoLearner()
        #: the timing of the apex packets (periodic interference, `BurstTrain`); False: a
        #: rig that taps the apex at a crystal-timed rate keeps its touches
        self.burst_train = BurstTrain()
        self.interference_timing = bool(interference_timing)
        #: the hand's coincidence test (`ContactPipeline.enable_hand`): every apex packet's
        #: onset (host ns) of the last `process` call goes to ``apex_onsets_ns`` (the other
        #: fingertips' reports), and the events of those the packet tests kept where no
        #: echo test runs to ``apex_held`` [(onset ns, event)], for the pipeline to hold
        self.hand_reports = False
        self.apex_onsets_ns: list[int] = []
        self.apex_held: list[tuple[int, ContactRecord]] = []
        self._echo_calls = 0
        self._echo_pending: list = []
        #: learn the echo inside `process` (False: the caller runs `learn_echo` once the
        #: contact events are out, as `ContactPipeline` does)
        self.learn_inline = True
        self.resolve_overlaps = bool(resolve_overlaps)
        #: windows of the last `process` call that hold overlapping emissions (for the
        #: OverlapResolver; rejected as OVERLAP or withdrawn as suspects)
        self.overlap_windows: list = []
        self.method = method
        self.min_snr_db = float(min_snr_db)
        self.min_confidence = float(min_confidence)
        self.geometry = geometry or FingertipGeometry()
        self.channel_gains = _gains_or_none(channel_gains)
        self.batch_min = int(batch_min)
        self.interference = _interference_check() if reject_interference else None
        self.counts: Counter = Counter()
        self._one = getattr(self.localizer, "localize_one", None)

    # ---------------------------------------------------------------- settings
    def update(
        self,
        *,
        method: str | None = None,
        min_snr_db: float | None = None,
        min_confidence: float | None = None,
        geometry: FingertipGeometry | None = None,
        channel_gains=None,
        resolve_overlaps: bool | None = None,
        interference_echo_min: float | None = None,
        interference_timing: bool | None = None,
        weak_releases: bool | None = None,
        weak_release_min_snr_db: float | None = None,
    ) -> None:
        """Change settings at run time; takes effect at once. ValueError on a bad value
        (channel gains, echo threshold, method, SNR, confidence): nothing changed then."""
        gains = _gains_or_none(channel_gains) if channel_gains is not None else None
        weak_floor = (
            check_min_snr_db(weak_release_min_snr_db)
            if weak_release_min_snr_db is not None
            else self.weak_release_min_snr_db
        )
        echo = (
            _echo_min_setting(interference_echo_min)
            if interference_echo_min is not None
            else self.interference_echo_min
        )
        conf = float(min_confidence) if min_confidence is not None else self.min_confidence
        localizer = None
        if method is not None or min_snr_db is not None:
            m = method if method is not None else self.method
            snr = float(min_snr_db if min_snr_db is not None else self.min_snr_db)
            localizer = Localizer(m, min_snr_db=snr)
        # everything checked: apply
        if localizer is not None:
            self.localizer = localizer
            self._one = getattr(localizer, "localize_one", None)
            self.method, self.min_snr_db = m, snr
        self.interference_echo_min = echo
        self.min_confidence = conf
        if resolve_overlaps is not None:
            self.resolve_overlaps = bool(resolve_overlaps)
        if interference_timing is not None:
            self.interference_timing = bool(interference_timing)
        if weak_releases is not None and bool(weak_releases) != self.weak_releases:
            # switched: the touches remembered (or not released) meanwhile are stale
            self.weak_gate = WeakReleaseGate()
            self.weak_releases = bool(weak_releases)
        self.weak_release_min_snr_db = weak_floor
        if geometry is not None:
            if geometry != self.geometry:
                self.weak_gate = WeakReleaseGate()  # touches on the old body
                # another body, another echo: a new learner (a measurement of the old body
                # still under way in the reader's thread goes to the old one)
                self.echo_learner = EchoLearner()
                self._echo_pending = []
            self.geometry = geometry
        if channel_gains is not None:
            self.channel_gains = gains

    def set_interference(self, enabled: bool) -> None:
        """Switch the common-mode interference rejection on or off."""
        self.interference = _interference_check() if enabled else None

    def warm_up(self, sample_rate_hz: float = 10e6, n_samples: int = 400) -> None:
        """Compile / cache what the first packet would otherwise pay for."""
        warm = getattr(self.localizer, "warm_up", None)
        if warm is not None:
            warm(self.geometry, sample_rate_hz, n_samples)
        rng = np.random.default_rng(0)
        x = rng.normal(0.0, 1e-3, (4, int(n_samples))).astype(np.float32)
        view = PacketView(x, sample_rate_hz, int(n_samples) // 4, 0, -1)
        self.process([view], count=False)
        self.process([view] * self.batch_min, count=False)
        # the paths a first odd packet would take: imports, tables, compiled code
        from types import SimpleNamespace

        from ae_tactile.localization.overlap import suspect_overlap
        from ae_tactile.localization.overlap import warm_up as warm_overlaps

        w = x[None].astype(np.float64)
        on = [int(n_samples) // 4]
        with np.errstate(all="ignore"):
            if self.interference is not None:
                from ae_tactile.dsp.interference import warm_up as warm_interference

                warm_interference(sample_rate_hz, geometry=self.geometry)  # templates
                self.interference(w, sample_rate_hz, on, geometry=self.geometry)
            single = SimpleNamespace(
                accepted=np.ones(1, bool), point_m=np.array([[0.0, 0.0, self.geometry.radius_m]])
            )
            suspect_overlap(w, sample_rate_hz, on, single, geometry=self.geometry)
            warm_overlaps(self.geometry, sample_rate_hz, n_samples)
        self.overlap_windows = []

    # ---------------------------------------------------------------- packets
    def process(self, packets: Sequence, *, count: bool = True) -> list[ContactRecord]:
        """Contact events of the accepted packets, in packet order."""
        counts = self.counts if count else Counter()
        self.overlap_windows = []
        if self.apex_onsets_ns or self.apex_held:
            self.apex_onsets_ns, self.apex_held = [], []
        # the body this call localizes on, and its echo learner (`update` may switch both
        # from another thread meanwhile: the echo of these packets belongs to this one)
        body = (self.geometry, self.echo_learner)
        good = []
        for p in packets:
            counts["packets"] += 1
            why = packet_problem(p.samples_v, p.sample_rate_hz, p.onset_index)
            if why is not None:
                counts["rejected_MALFORMED_" + why] += 1
                continue
            good.append(p)
        if not good:
            return []
        weak_on = self.weak_releases  # read once: `update` may change it meanwhile
        if len(good) >= self.batch_min or self._one is None:
            out = self._batched(good, counts, weak_on)
        else:
            out = []
            for p in good:
                ev = self._single(p, counts, weak_on)
                if ev is not None:
                    out.append((p, ev))
        if self.interference is not None:
            out = self._drop_interference(out, counts)
        if self.resolve_overlaps:
            out = self._withdraw_suspects(out, counts)
        if weak_on:
            out = self._gate_weak(out, counts)
        if self.interference is not None and self.interference_echo_min < 0.0 and count:
            self._stash_echo(out, body)  # single emissions only (suspects withdrawn)
            if self.learn_inline:
                self.learn_echo()
        for _, ev in out:
            counts["events"] += 1
            counts["detouch" if ev.event_type == EventType.DETOUCH else "touch"] += 1
        return [ev for _, ev in out]

    @property
    def _overlap_threshold(self) -> float:
        """The localizer's overlap threshold (its method's default unless given)."""
        thr = self.localizer.kwargs.get("overlap_threshold")
        return get_estimator(self.method).overlap_threshold if thr is None else float(thr)

    def _gate_weak(self, found, counts):
        """The events in order through the weak-release gate: touches remembered, releases
        end them, a weak release kept only on the spot of a touch not yet released
        (counted as weak_releases; the others as rejected_LOW_SNR)."""
        gate = self.weak_gate
        kept = []
        for item in found:
            ev = item[1]
            c = ev.covariance_m2
            var = 0.5 * float(c[0, 0] + c[1, 1] + c[2, 2])
            pol = -1 if ev.event_type == EventType.DETOUCH else 1
            if gate.admit(ev.time_ns, ev.point_m, var, pol, ev.weak_release):
                kept.append(item)
                if ev.weak_release:
                    counts["weak_releases"] += 1
            else:
                counts["rejected_LOW_SNR"] += 1
        return kept

    def _weak(self, p, r, snr_db, counts, weak_on) -> ContactRecord | None:
        """A weak-release candidate's record (`_gate_weak` decides), or None: counted as
        rejected by its reason (a candidate below min_confidence: rejected_LOW_SNR)."""
        c = np.asarray(r.covariance_m2, dtype=float).reshape(3, 3)
        floor = self.weak_release_min_snr_db
        if not (
            weak_on
            and is_weak_release(
                r.reason_flags, r.polarity, snr_db, floor, 0.5 * (c[0, 0] + c[1, 1] + c[2, 2])
            )
        ):
            counts["rejected_" + Reason(int(r.reason)).name] += 1
            return None
        conf = weak_release_confidence(
            snr_db,
            floor,
            math.sqrt(max(c[0, 0] + c[1, 1], 0.0)),
            r.overlap_excess,
            self._overlap_threshold,
            r.clamped,
        )
        if conf < self.min_confidence:
            counts["rejected_LOW_SNR"] += 1
            return None
        rec = self._record(
            p,
            r.point_m,
            c,
            r.polar_rad,
            r.azimuth_rad,
            r.tau_x_s,
            r.tau_y_s,
            r.amplitude_v,
            conf,
            r.polarity,
            r.emission_offset_s,
            r.overlap_excess,
        )
        rec.weak_release = True
        return rec

    def _drop_interference(self, found, counts):
        """Drop the events whose packets the discriminator calls interference: those at the
        apex, fitting poorly, or with one waveform on the four channels."""
        near, rest = [], []
        for i, (_, ev) in enumerate(found):
            if interference_route(ev.polar_rad, ev.confidence) == ROUTE_ALL:
                near.append(i)
            else:
                rest.append(i)
        # well-fitting packets off the apex with nearly one waveform on the four channels:
        # the spectrum tests only (a window holding two emissions of a slip near the apex is
        # common-mode too, and no single template explains it: the shape and echo tests
        # would reject it; the overlap resolver is its place); one waveform within the
        # noise: every test
        screened = set()
        if rest:
            for i, c in zip(rest, _common_share([found[i][0] for i in rest])):
                route = interference_route(found[i][1].polar_rad, found[i][1].confidence, c)
                if route == ROUTE_ALL:
                    near.append(i)
                elif route == ROUTE_SPECTRUM:
                    screened.add(i)
        if not near and not screened:
            return found
        drop = set()
        groups: dict[tuple, list[int]] = {}
        for i in near + sorted(screened):
            p = found[i][0]
            groups.setdefault(
                (p.samples_v.shape[1], float(p.sample_rate_hz), i in screened), []
            ).append(i)
        for (_, fs, spectrum_only), ids in groups.items():
            w = np.stack([np.asarray(found[i][0].samples_v, dtype=np.float64) for i in ids])
            onset = np.array([int(found[i][0].onset_index) for i in ids])
            kw = (
                {"shape_min": None, "echo_min": None}
                if spectrum_only
                else {"echo_min": self.echo_min_in_use}
            )
            try:
                mask, _ = self.interference(w, fs, onset, geometry=self.geometry, **kw)
            except ValueError:
                continue
            drop.update(i for i, m in zip(ids, np.asarray(mask, bool)) if m)
        if drop:
            counts["rejected_INTERFERENCE"] += len(drop)
        # timing: every apex packet (kept or not) joins the train's history; one kept by
        # the per-packet tests whose intervals repeat the history's is a periodic burst
        train = set()
        apex = [i for i in near if found[i][1].polar_rad < APEX_POLAR_RAD]
        if self.hand_reports and apex:
            self._report_apex(found, apex, drop)
        for i in sorted(apex, key=lambda j: _packet_time_s(found[j][0])):
            p = found[i][0]
            t = _packet_time_s(p)
            if self.interference_timing and i not in drop and self.burst_train.is_member(
                t, max(TRAIN_TOL_S, TRAIN_TOL_SAMPLES / float(p.sample_rate_hz))
            ):
                train.add(i)
            self.burst_train.add(t)
        if train:
            counts["rejected_INTERFERENCE_TRAIN"] += len(train)
            drop |= train
        return [f for i, f in enumerate(found) if i not in drop]

    def _report_apex(self, found, apex, drop) -> None:
        """The apex packets' onsets for the hand, and the events of those the packet tests
        kept where nothing in one packet tells (no echo test) to hold for its decision."""
        hold = self.echo_min_in_use is None
        for i in apex:
            t = _onset_ns(found[i][0])
            if t != t:  # no host stamp: nothing to compare with the hand's
                continue
            self.apex_onsets_ns.append(int(t))
            if hold and i not in drop:
                self.apex_held.append((int(t), found[i][1]))

    @property
    def echo_min_in_use(self) -> float | None:
        """The echo test's threshold now (None: no echo test): the fixed setting, or the
        learnt one (None until the device's touches have shown an echo)."""
        v = self.interference_echo_min
        if v < 0.0:
            return self.echo_learner.echo_min
        return v if v > 0.0 else None

    def echo_test_status(self) -> str:
        """The echo test in words (diagnostics): off, fixed, learning, or what was learnt."""
        v = self.interference_echo_min
        if self.interference is None or v == 0.0:
            return "off"
        if v > 0.0:
            return f"fixed, echo >= {v:.3f}"
        r = self.echo_learner.ratio
        if r is None:
            return f"learning ({self.echo_learner.n_measured} touches measured)"
        if self.echo_learner.echo_min is None:
            return f"off: the touches' echo is {r:.3f} (no wall echo)"
        need = self.echo_learner.echo_min
        return f"learnt: touches' echo {r:.3f}, apex packets need >= {need:.3f}"

    def _stash_echo(self, found, body) -> None:
        """Keep (copies of) up to ECHO_LEARN_PER_CALL accepted, well-fitting packets away
        from the apex (never interference: its zero delays put it at the apex) for
        `learn_echo`, while the learner fills, then from one call in ECHO_LEARN_EVERY."""
        self._echo_calls += 1
        if self.echo_learner.n_measured >= ECHO_LEARN_KEEP and self._echo_calls % ECHO_LEARN_EVERY:
            return
        room = ECHO_LEARN_PER_CALL - len(self._echo_pending)
        for p, ev in found:
            if room <= 0:
                break
            if (
                ev.polar_rad >= APEX_POLAR_RAD
                and ev.confidence >= ECHO_LEARN_CONFIDENCE
                and not ev.weak_release
            ):
                self._echo_pending.append(
                    (np.array(p.samples_v, dtype=np.float64), float(p.sample_rate_hz),
                     int(p.onset_index), ev.point_m, *body)
                )
                room -= 1

    @property
    def echo_pending(self) -> bool:
        """Packets kept for `learn_echo`."""
        return bool(self._echo_pending)

    def learn_echo(self) -> None:
        """Measure the wall echo of the packets kept (`echo_ratio`, ~70 us a call) and
        teach it to the learner: run after the contact events are out (`ContactPipeline`),
        or at the end of `process` when ``learn_inline``."""
        pending, self._echo_pending = self._echo_pending, []
        groups: dict[tuple, list] = {}
        for item in pending:  # (each measured with the body it was localized on, and
            # taught to that body's learner: after a geometry change, to none)
            if item[5] is self.echo_learner:
                groups.setdefault((item[0].shape, item[1]), []).append(item)
        for (_, fs), grp in groups.items():
            geometry, learner = grp[0][4], grp[0][5]
            with np.errstate(all="ignore"):
                beta = echo_ratio(
                    np.stack([g[0] for g in grp]), fs, np.array([g[2] for g in grp]),
                    np.array([g[3] for g in grp]), geometry,
                )
            learner.add(beta)

    def _overlap(self, p, counts) -> None:
        counts["rejected_OVERLAP"] += 1
        if self.resolve_overlaps:
            self.overlap_windows.append(p)

    def _withdraw_suspects(self, found, counts):
        """Accepted packets with a poor fit whose one-emission model leaves a residual the
        noise cannot explain hold two emissions: withdrawn, for the overlap resolver."""
        low = [
            i
            for i, (_, ev) in enumerate(found)
            if ev.confidence < OVERLAP_SUSPECT_CONFIDENCE
            and ev.overlap_excess > OVERLAP_SUSPECT_EXCESS
        ]
        if not low:
            return found
        from types import SimpleNamespace

        from ae_tactile.localization.overlap import suspect_overlap

        drop = set()
        groups: dict[tuple, list[int]] = {}
        for i in low:
            p = found[i][0]
            groups.setdefault((p.samples_v.shape[1], float(p.sample_rate_hz)), []).append(i)
        for (_, fs), ids in groups.items():
            w = np.stack([np.asarray(found[i][0].samples_v, dtype=np.float64) for i in ids])
            onset = np.array([int(found[i][0].onset_index) for i in ids])
            single = SimpleNamespace(
                accepted=np.ones(len(ids), bool),
                point_m=np.array([found[i][1].point_m for i in ids]),
            )
            try:
                with np.errstate(all="ignore"):
                    mask = suspect_overlap(w, fs, onset, single, geometry=self.geometry)
            except ValueError:
                continue
            drop.update(i for i, m in zip(ids, np.asarray(mask, bool)) if m)
        for i in sorted(drop):
            self._overlap(found[i][0], counts)
            counts["overlap_suspects"] += 1
        return [f for i, f in enumerate(found) if i not in drop]

    def _single(self, p, counts, weak_on=False) -> ContactRecord | None:
        r = self._one(
            p.samples_v,
            p.sample_rate_hz,
            int(p.onset_index),
            saturated=bool(p.saturated),
            geometry=self.geometry,
            channel_gains=self.channel_gains,
        )
        if not r.accepted:
            if int(r.reason) == Reason.OVERLAP:
                self._overlap(p, counts)
                return None
            return self._weak(p, r, float(r.snr_db), counts, weak_on)
        if r.confidence < self.min_confidence:
            counts["below_min_confidence"] += 1
            return None
        return self._record(
            p,
            r.point_m,
            r.covariance_m2,
            r.polar_rad,
            r.azimuth_rad,
            r.tau_x_s,
            r.tau_y_s,
            r.amplitude_v,
            r.confidence,
            r.polarity,
            r.emission_offset_s,
            r.overlap_excess,
        )

    def _batched(self, packets, counts, weak_on=False) -> list[tuple]:
        groups: dict[tuple, list[int]] = {}
        for i, p in enumerate(packets):
            groups.setdefault((p.samples_v.shape[1], float(p.sample_rate_hz)), []).append(i)
        found: list[tuple[int, ContactRecord]] = []
        for (_, fs), ids in groups.items():
            items = [packets[i] for i in ids]
            windows = np.stack([np.asarray(p.samples_v) for p in items])
            onset = np.array([int(p.onset_index) for p in items], dtype=np.int64)
            sat = np.array([bool(p.saturated) for p in items])
            res = self.localizer(
                windows,
                fs,
                onset,
                geometry=self.geometry,
                saturated=sat,
                channel_gains=self.channel_gains,
            )
            excess = getattr(res, "overlap_excess", None)
            if excess is None:
                excess = np.zeros(len(items))
            offsets = getattr(res, "emission_offset_s", None)
            if offsets is None:
                travel = self.geometry.arrival_times_s(np.nan_to_num(res.point_m)).min(axis=-1)
                offsets = onset / fs - travel
            for j, p in enumerate(items):
                if not res.accepted[j]:
                    if int(res.reason[j]) == Reason.OVERLAP:
                        self._overlap(p, counts)
                        continue
                    row = _Row(res, j, offsets[j])
                    rec = self._weak(p, row, float(res.snr_db_est[j]), counts, weak_on)
                    if rec is not None:
                        found.append((ids[j], p, rec))
                    continue
                if res.confidence[j] < self.min_confidence:
                    counts["below_min_confidence"] += 1
                    continue
                found.append(
                    (
                        ids[j],
                        p,
                        self._record(
                            p,
                            res.point_m[j],
                            res.covariance_m2[j],
                            res.polar_rad[j],
                            res.azimuth_rad[j],
                            res.tau_x_s[j],
                            res.tau_y_s[j],
                            res.amplitude_v[j],
                            res.confidence[j],
                            res.polarity[j],
                            offsets[j],
                            excess[j],
                        ),
                    )
                )
        found.sort(key=lambda t: t[0])
        return [(p, ev) for _, p, ev in found]

    @staticmethod
    def _record(
        p, point, cov, polar, azimuth, tau_x, tau_y, amp, conf, polarity, offset_s, excess=0.0
    ) -> ContactRecord:
        kind = EventType.DETOUCH if polarity < 0 else EventType.TOUCH
        x, y, z = (float(v) for v in point)
        return ContactRecord(
            event_type=int(kind),
            time_ns=int(p.stamp_ns) + int(round(float(offset_s) * 1e9)),
            point_m=(x, y, z),
            covariance_m2=np.asarray(cov, dtype=float).reshape(3, 3),
            packet_ids=(int(p.sequence_id),),
            polar_rad=float(polar),
            azimuth_rad=float(azimuth),
            tau_x_s=float(tau_x),
            tau_y_s=float(tau_y),
            amplitude_v=float(amp),
            confidence=float(conf),
            overlap_excess=float(excess),
        )


class OverlapResolver:
    """Localizes every emission of windows that hold several (`resolve_overlaps`) and hands
    the sources to ``on_records(list[ContactRecord])`` from its own thread. Each source is
    one contact event naming the shared packet id, stamped at its own emission instant. At
    most ``max_pending`` windows wait; more are counted (``overlap_dropped_backlog``) and
    lost rather than delaying anything else.

    The quick search (one compiled call, most of it without the interpreter lock) runs in
    this object's thread, beside the reader. The exhaustive search of a window whose
    quick answer is DEFERRED (tens of milliseconds of numpy and Python, which would hold
    the lock against the thread that localizes every other packet) runs in a worker
    process (`ae_tactile.localization.overlap_worker`, started here, warmed up before the
    first window); so does the quick search where it is not compiled (no numba, a lossy
    medium). Where the process cannot run (``use_process=False``, or it failed), the
    thread does that too (``overlap_worker_unavailable``).

    ``idle`` (a driver on cores of its own): this thread and the worker run as SCHED_IDLE,
    so the reader, which shares their core, takes it the moment it wakes. Otherwise the
    worker is niced and this thread keeps the normal priority: on cores shared with other
    busy processes, an idle-class thread could wait indefinitely while it holds the
    interpreter lock or one of the pipeline's locks, and the reader with it.
    """

    def __init__(
        self,
        geometry: FingertipGeometry,
        on_records: Callable[[list], None],
        *,
        max_pending: int = 64,
        pulse=None,
        use_process: bool = True,
        on_done: Callable[[object], None] | None = None,
        idle: bool = False,
    ):
        self.geometry = geometry
        self.idle = bool(idle)
        #: what the thread's priority became ("idle", "nice" or "": as created)
        self.priority = ""
        self.on_records = on_records
        #: called with each window once it is answered (sources handed over, rejected or
        #: failed), after ``on_records``
        self.on_done = on_done
        self.pulse = pulse
        self.counts: Counter = Counter()  # written under _count_lock (two threads count)
        self._count_lock = threading.Lock()
        self._queue: queue.Queue = queue.Queue(maxsize=int(max_pending))
        self.ready = threading.Event()  # the worker has warmed up (or is not used)
        self._proc = self._start_worker() if use_process else None
        if not use_process:
            self._count("overlap_worker_unavailable")
        self._thread = threading.Thread(target=self._run, name="ae_tactile_overlaps", daemon=True)
        self._thread.start()

    def _start_worker(self):
        try:
            # its own session: a Ctrl-C at the terminal (sent to the foreground process
            # group) reaches the node, which ends the worker by closing its stdin, and
            # never interrupts the worker's imports with a traceback
            from ae_tactile.localization.overlap_worker import IDLE_FLAG

            return subprocess.Popen(
                [sys.executable, "-m", "ae_tactile.localization.overlap_worker"]
                + ([IDLE_FLAG] if self.idle else []),
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                start_new_session=True,
            )
        except OSError:
            self._count("overlap_worker_unavailable")
            return None

    def _count(self, key: str, n: int = 1) -> None:
        with self._count_lock:
            self.counts[key] += n

    def snapshot_counts(self) -> dict:
        """A consistent copy of the counts (the reader and the resolver's thread write them)."""
        with self._count_lock:
            return dict(self.counts)

    def submit(self, packets: Sequence, *, quick_first: bool = True, hard: bool = False) -> list:
        """Queue windows for the resolver (``quick_first=False``: windows whose quick
        answer was DEFERRED, for the exhaustive search only; ``hard``: the worker process
        gives the quick answer too, as for a window likely DEFERRED, so that this thread
        does no fitting beside the reader); returns those queued (the rest are counted)."""
        queued = []
        for p in packets:
            try:
                self._queue.put_nowait((p, bool(quick_first), bool(hard)))
                queued.append(p)
            except queue.Full:
                self._count("overlap_dropped_backlog")
        return queued

    #: first arrivals (host ns) of the emissions of the latest `resolve_now` answer
    arrivals_ns: list = []

    def resolve_now(self, p) -> list | None:
        """The quick answer to one window in the calling thread (the reader's; one compiled
        call, about 0.5-1 ms): its emissions' contact events ([] when it is rejected), or None
        when the worker has to answer it (DEFERRED, or the fit failed here: then `submit`
        it with ``quick_first=False``). Never raises."""
        from ae_tactile.localization.overlap import resolve_overlaps

        self.arrivals_ns = []
        try:
            with np.errstate(all="ignore"):
                res = resolve_overlaps(
                    np.asarray(p.samples_v, dtype=np.float64)[None],
                    float(p.sample_rate_hz),
                    [int(p.onset_index)],
                    geometry=self.geometry,
                    pulse=self.pulse,
                    saturated=[bool(getattr(p, "saturated", False))],
                    exhaustive=False,
                )[0]
            records = self._records(p, res)
            if records is not None:
                stamp = int(p.stamp_ns)
                self.arrivals_ns = [
                    stamp + float(np.min(src.arrival_times_s)) * 1e9 for src in res.sources
                ]
        except Exception:  # never let one window stop the reader: the worker tries it
            self._count("overlap_errors")
            return None
        if records is not None:
            self._count("overlap_answered_in_reader")
        return records

    def _records(self, p, res) -> list | None:
        """Contact events of one answer (counted), None when it is DEFERRED."""
        if res.reason == _DEFERRED:
            self._count("overlap_deferred")
            return None
        if not res.accepted:
            self._count("overlap_rejected_" + res.reason_name)
            return []
        records = [source_record(p, src) for src in res.sources]  # may raise: count after
        self._count("overlap_windows_resolved")
        self._count("overlap_sources", len(records))
        return records

    def pending(self) -> int:
        """Windows queued or being resolved: the queue's unfinished tasks (one per window
        put, done once its records are handed on), so that no moment between taking a
        window and working on it reads as idle."""
        with self._queue.mutex:
            return self._queue.unfinished_tasks

    def _quick_here(self) -> bool:
        """The quick search runs in this thread: compiled (numba, a lossless medium), it
        spends most of its ~0.5 ms without the interpreter lock, so the reader goes on
        beside it, and the answer needs no trip to the worker process."""
        from ae_tactile.localization import overlap

        pulse = self.pulse
        lossless = pulse is None or not pulse.attenuation_db_per_m_at_1mhz > 0
        return overlap._kernels.NUMBA_AVAILABLE and lossless

    def _answers(self, p, quick_first: bool = True, hard: bool = False):
        """The OverlapPackets of one window: the quick answer (computed here when compiled,
        `_quick_here`, and the window not ``hard``; else by the worker process) and, when
        it is DEFERRED, the exhaustive search's from the worker process (only the latter
        when not ``quick_first``; computed here when the process is not available)."""
        samples = np.asarray(p.samples_v, dtype=np.float64)
        fs, onset = float(p.sample_rate_hz), int(p.onset_index)
        sat = bool(getattr(p, "saturated", False))
        if quick_first and not hard and self._quick_here():
            from ae_tactile.localization.overlap import resolve_overlaps

            try:
                with np.errstate(all="ignore"):
                    res = resolve_overlaps(
                        samples[None], fs, [onset], geometry=self.geometry, pulse=self.pulse,
                        saturated=[sat], exhaustive=False,
                    )[0]
            except Exception:  # counted; the worker process answers the window instead
                self._count("overlap_errors")
            else:
                self._count("overlap_quick_in_thread")
                yield res
                if res.reason != _DEFERRED:
                    return
                quick_first = False
        proc = self._proc
        if proc is not None:
            try:
                pickle.dump(
                    (samples, fs, onset, sat, self.geometry, self.pulse, quick_first),
                    proc.stdin,
                    protocol=pickle.HIGHEST_PROTOCOL,
                )
                proc.stdin.flush()
                res = pickle.load(proc.stdout)
                if isinstance(res, str):
                    raise RuntimeError(res)
                self._count("overlap_worker_answers")
                if quick_first and res.reason == _DEFERRED:
                    yield res
                    res = pickle.load(proc.stdout)
                    if isinstance(res, str):
                        raise RuntimeError(res)
                    self._count("overlap_worker_answers")
            except (OSError, EOFError, pickle.UnpicklingError):
                self._count("overlap_worker_unavailable")
                self._stop_worker()
            else:
                yield res
                return
        from ae_tactile.localization.overlap import resolve_overlaps

        for exhaustive in (False, True) if quick_first else (True,):
            with np.errstate(all="ignore"):
                res = resolve_overlaps(
                    samples[None], fs, [onset], geometry=self.geometry, pulse=self.pulse,
                    saturated=[sat], exhaustive=exhaustive,
                )[0]
            yield res
            if res.reason != _DEFERRED:
                return

    def _done(self, p) -> None:
        if self.on_done is not None:
            try:
                self.on_done(p)
            except Exception:
                self._count("overlap_errors")

    def _run(self) -> None:
        if self.idle:  # this thread only: the reader, on the same core, comes first
            from ae_tactile.localization.overlap_worker import background_priority

            self.priority = background_priority(idle=True)
        if self._proc is not None:
            try:
                if pickle.load(self._proc.stdout) != "ready":
                    raise pickle.UnpicklingError("no ready message")
            except (OSError, EOFError, pickle.UnpicklingError):
                self._count("overlap_worker_unavailable")
                self._stop_worker()
        self.ready.set()
        while True:
            item = self._queue.get()
            if item is None:
                self._queue.task_done()
                self._stop_worker()
                return
            p, quick_first, hard = item
            told = False  # on_done called (the quick answer said DEFERRED)
            try:
                for res in self._answers(p, quick_first, hard):
                    records = self._records(p, res)
                    if records is None:
                        # a hard window: what waits for it goes on; its emissions, if
                        # any, come from the exhaustive search, late, with their stamps
                        self._done(p)
                        told = True
                        continue
                    if records:
                        self.on_records(records)
            except Exception:  # never let one window stop the resolver
                self._count("overlap_errors")
            finally:
                if not told:
                    self._done(p)
                self._queue.task_done()

    def _stop_worker(self) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        try:
            proc.stdin.close()  # EOF: the worker exits
            proc.wait(2.0)
        except (OSError, subprocess.TimeoutExpired):
            proc.kill()
            proc.wait()

    def close(self) -> None:
        """Stop the thread and the worker process (pending windows are given up)."""
        while True:
            try:
                self._queue.get_nowait()
            except queue.Empty:
                break
            self._queue.task_done()  # given up
        try:
            self._queue.put_nowait(None)
        except queue.Full:
            pass
        self._thread.join(3.0)


_DEFERRED = 10  # OverlapReason.DEFERRED (overlap is imported lazily)


def _not_in(records: list, recent) -> list:
    """The records with no row of recent (N, 4: t ns, x, y, z) within DUPLICATE_TIME_S and
    DUPLICATE_DISTANCE_M."""
    d2_max = DUPLICATE_DISTANCE_M**2
    keep = []
    for r in records:
        near = np.abs(recent[:, 0] - r.time_ns) <= DUPLICATE_TIME_S * 1e9
        if near.any():
            dp = recent[near, 1:] - np.asarray(r.point_m, dtype=float)
            if (np.einsum("ij,ij->i", dp, dp) <= d2_max).any():
                continue
        keep.append(r)
    return keep


def _onset_ns(p) -> float:
    """Host time (ns) of a window's onset sample (its trigger); NaN if it cannot be told."""
    try:
        return int(p.stamp_ns) + int(p.onset_index) * 1e9 / float(p.sample_rate_hz)
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        return math.nan


def _TIME_NS(r) -> int:
    return r.time_ns


class SlipStage:
    """Contact events -> slip events and the finger's contact state.

    Events are fed in the order they come; the detector processes an event up to
    ``SlipConfig.reorder_tolerance_s`` older than the newest one it has seen with its own
    time stamp, and counts older ones (``counts['rejected_out_of_order']``). `tick` lets
    time pass without events (quiet slip states fall back to STICK): it never advances the
    detector's clock past ``now - lag_s``, so events still in flight are not overtaken.
    Thread-safe: the reader thread feeds events, a timer thread ticks.
    """

    def __init__(self, config: SlipConfig | None = None, *, lag_s: float = 0.02):
        self.detector = SlipDetector(config or SlipConfig())
        self.lag_ns = int(lag_s * 1e9)
        self.lock = threading.Lock()
        self.counts: Counter = Counter()

    def process(self, contacts: Sequence[ContactRecord]) -> list[ContactRecord]:
        """Slip events produced by these contact events (time order)."""
        out: list[ContactRecord] = []
        with self.lock:
            for c in contacts:
                self.counts["contacts_in"] += 1
                pol = -1 if c.event_type == EventType.DETOUCH else 1
                cov = c.covariance_m2
                # the localizer's records have the stored types: the detector's cheap path
                # (it still rejects and counts non-finite values)
                ev = LocalizedEvent.trusted(
                    int(c.time_ns),
                    np.asarray(c.point_m, dtype=np.float64),
                    0.5 * (cov + cov.T),
                    pol,
                    float(c.amplitude_v),
                    min(max(float(c.confidence), 0.0), 1.0)
                    if c.confidence == c.confidence
                    else 0.0,
                    int(c.packet_ids[0]) if c.packet_ids else -1,
                )
                for s in self.detector.process(ev):
                    out.append(slip_record(s))
        self.counts["slip_events"] += len(out)
        return out

    def tick(self, now_ns: int):
        """Advance the detector to now_ns - lag; returns the finger state."""
        with self.lock:
            return self.detector.advance(int(now_ns) - self.lag_ns)

    @property
    def state(self):
        with self.lock:
            return self.detector.state

    def all_counts(self) -> dict:
        with self.lock:
            d = {f"slip_{k}": v for k, v in self.detector.counts.items()}
        d.update(self.counts)
        return d


@dataclass
class ContactPipeline:
    """Localizer and slip stage behind one call: ``process(packets, on_contacts, on_slip)``.

    ``on_contacts`` is called with the contact events of the batch before the slip step
    runs (a touch reaches the hand without waiting for slip analysis), then ``on_slip``
    with the slip events (if any).
    """

    localizer: PacketLocalizer
    slip: SlipStage | None
    counts: Counter = field(default_factory=Counter)
    overlaps: OverlapResolver | None = None
    _outputs: tuple = (None, None)  # (on_contacts, on_slip) of the latest process() call
    _slip_pending: list = field(default_factory=list)  # contacts handed out, slip step due
    _slip_pending_since: float = 0.0  # time.monotonic() of the oldest of them
    #: windows with the overlap resolver: id -> (time.monotonic() handed over, earliest
    #: possible emission stamp of theirs, ns)
    _windows_out: dict = field(default_factory=dict)
    _held: list = field(default_factory=list)  # contacts whose slip step waits for them
    #: longest wait of the slip step for the overlap resolver (s)
    overlap_hold_max_s: float = OVERLAP_HOLD_MAX_S
    #: overlapping windows per `process` call answered in the caller's thread (the rest
    #: go to the resolver's worker)
    overlap_inline_max: int = OVERLAP_INLINE_MAX
    #: `_covered` tolerance (s); 0 answers every window on its own
    overlap_covered_tol_s: float = COVERED_TOL_S
    #: the overlap resolver's thread and worker as SCHED_IDLE (`OverlapResolver` ``idle``:
    #: the driver has cores of its own)
    overlap_idle: bool = False
    _step_lock: threading.RLock = field(default_factory=threading.RLock)
    #: (stamp ns, x, y, z) of the contact events handed out that a window still with the
    #: overlap resolver could hold again (duplicate check), oldest first
    _recent: deque = field(default_factory=deque)
    #: windows with the overlap resolver: id -> earliest possible emission stamp (ns)
    _pending_ns: dict = field(default_factory=dict)
    _recent_lock: threading.Lock = field(default_factory=threading.Lock)
    _resolved_newest_ns: int = -(1 << 62)  # newest stamp the overlap resolver handed out
    #: (host ns, gave events) of the first arrivals of emissions resolved in the reader
    #: lately, and of the triggers of windows answered there (`_covered`)
    _arrivals_ns: deque = field(default_factory=lambda: deque(maxlen=16))
    #: earliest possible emission (ns) of the windows about to be fitted in the reader:
    #: `_slip_before` goes on with what is older
    _inline_horizon_ns: int | None = None
    #: the coincidence test of the fingertips of one hand (`enable_hand`); None: off
    hand: HandCoincidence | None = None
    _hand_lock: threading.Lock = field(default_factory=threading.Lock)
    #: one thread at a time hands out events while the hand holds some (the reader's
    #: `process`, `release_coincidence` from the reader or a timer): they go out in order
    _release_lock: threading.Lock = field(default_factory=threading.Lock)
    _apex_out: list = field(default_factory=list)  # apex onsets (ns) to report to the hand

    def __post_init__(self) -> None:
        self.localizer.learn_inline = False  # `process` learns once the events are out

    def start_overlaps(self, wait_s: float = 0.0) -> None:
        """Start the overlap resolver (and its worker process) now, not at the first
        overlapping window, and wait up to wait_s for the worker to be warm; the driver
        calls this while warming up, before acquisition."""
        if self.overlaps is None:
            self.overlaps = OverlapResolver(
                self.localizer.geometry, self._late_from_resolver, on_done=self._window_done,
                idle=self.overlap_idle,
            )
        if wait_s > 0:
            self.overlaps.ready.wait(wait_s)

    # ------------------------------------------------------------ the hand
    def enable_hand(self, window_s: float | None = None, wait_s: float | None = None) -> None:
        """Take part in the coincidence test of the fingertips of one hand
        (`ae_tactile.dsp.coincidence`): `take_apex_onsets` gives this fingertip's apex
        packets for the others, `hand_reports` takes theirs, and an apex packet the packet
        tests kept where no echo test runs is held until `release_coincidence` decides it
        (ValueError on bad settings: nothing changed then)."""
        kw = {k: v for k, v in (("window_s", window_s), ("wait_s", wait_s)) if v is not None}
        hand = HandCoincidence(**kw)  # checks the settings
        # never in the middle of a hand-out (the same lock order as `process`)
        with self._release_lock, self._hand_lock:
            if self.hand is not None:  # the reports, held packets and counts stay
                hand = self.hand.with_settings(hand.window_ns * 1e-9, hand.wait_ns * 1e-9)
            self.hand = hand
        self.localizer.hand_reports = True

    def _hold_apex(self, contacts: list) -> list:
        """Hold the events of apex packets the localizer left to the hand, and behind them
        every later event of this fingertip (a release never overtakes its touch); the
        rest go on."""
        loc = self.localizer
        if loc.apex_onsets_ns:
            with self._hand_lock:
                if self.hand is not None:
                    self.hand.add_own(loc.apex_onsets_ns)
                self._apex_out.extend(loc.apex_onsets_ns)
                if len(self._apex_out) > APEX_OUT_MAX:  # nobody takes them: the newest
                    del self._apex_out[:-APEX_OUT_MAX]
        if self.hand is None or not (loc.apex_held or self.hand.pending):
            return contacts
        held = {id(rec): t for t, rec in loc.apex_held}
        keep = []
        with self._hand_lock:
            hand = self.hand
            for rec in contacts:
                t = held.get(id(rec))
                if t is not None and hand.hold(t, rec):
                    held[id(rec)] = None  # held
            bar = hand.held_min(_TIME_NS)  # the earliest held event
            for rec in contacts:
                if held.get(id(rec), 0) is None:
                    continue
                if bar is not None and rec.time_ns >= bar:
                    hand.follow(rec)
                else:
                    keep.append(rec)
        return keep

    def take_apex_onsets(self) -> list:
        """This fingertip's apex packet onsets (host ns) not reported yet."""
        if not self._apex_out:
            return []
        with self._hand_lock:
            out, self._apex_out = self._apex_out, []
        return out

    def hand_reports(self, onsets_ns, source: str = "", now_ns: int | None = None) -> None:
        """Another fingertip's (``source``) apex packet onsets (host ns); ``now_ns``: this
        fingertip's host time (stamps far from it are counted and dropped)."""
        with self._hand_lock:
            if self.hand is not None:
                self.hand.add_others(onsets_ns, source, now_ns)

    def release_coincidence(
        self,
        now_ns: int,
        *,
        flush: bool = False,
        blocking: bool = True,
        timeout_s: float | None = None,
    ) -> bool:
        """Decide the held apex packets whose wait is over at host time ``now_ns``
        (``flush``: all of them, with the reports at hand): those another fingertip saw
        too are interference (``rejected_INTERFERENCE_HAND``), the others are handed out
        with the events behind them, in time order, and go through the slip step after
        the earlier events' put-off one. ``blocking`` False: nothing if another thread is
        handing out events (``timeout_s``: waiting at most that long). True if any was
        handed out."""
        hand = self.hand
        if hand is None or not (hand.pending or hand.unpaired):
            return False
        wait = -1 if timeout_s is None else max(0.0, float(timeout_s))
        if not (self._release_lock.acquire(True, wait) if blocking else
                self._release_lock.acquire(False)):
            return False
        try:
            # the slip stage's clock (`tick`, a timer) waits until what is decided here
            # has been through the slip step: it never runs past a released event
            with self._step_lock:
                with self._hand_lock:
                    hand = self.hand
                    kept, rejected = hand.due(int(now_ns), _TIME_NS, flush)
                if rejected:
                    self.counts["rejected_INTERFERENCE_HAND"] += len(rejected)
                on_contacts, on_slip = self._outputs
                if kept and on_contacts is not None:
                    self.run_pending_slip()  # earlier events first, in the slip stage too
                    self.late(self._claim(kept, resolved=False), on_contacts, on_slip)
            return bool(kept)
        finally:
            self._release_lock.release()

    def _late_from_resolver(self, records: list) -> None:
        on_contacts, on_slip = self._outputs
        if on_contacts is None:
            return
        self.late(self._claim(records, resolved=True), on_contacts, on_slip)

    def _claim(self, records: list, *, resolved: bool) -> list:
        """The records whose emission was not handed out already (none earlier within
        DUPLICATE_TIME_S and DUPLICATE_DISTANCE_M: |dt| <= T and |dp| <= D), remembered
        for as long as a window with the resolver could hold their emissions; the others
        are counted (``overlap_duplicates``). One step under the lock: the reader and the
        resolver's thread can never both hand out one emission. ``resolved``: the
        resolver's answers (checked always; the hot path's events only when the resolver
        already handed out emissions that recent, i.e. the reader fell behind)."""
        if not records:
            return records
        with self._recent_lock:
            rec = self._recent
            fresh = records
            if rec and (
                resolved
                or min(r.time_ns for r in records)
                <= self._resolved_newest_ns + DUPLICATE_TIME_S * 1e9
            ):
                fresh = _not_in(records, np.array(rec, dtype=float))
                if len(fresh) < len(records):
                    self.counts["overlap_duplicates"] += len(records) - len(fresh)
            if not fresh:
                return fresh
            if resolved:
                newest = max(r.time_ns for r in fresh)
                self._resolved_newest_ns = max(self._resolved_newest_ns, newest)
            rec.extend((r.time_ns, *r.point_m) for r in fresh)
            pending = self._pending_ns
            keep_from = (min(pending.values()) if pending else rec[-1][0]) - RECENT_MARGIN_NS
            # (stamps may go back, e.g. after a device reset: never more than all of them)
            while rec and rec[0][0] < keep_from:
                rec.popleft()
        return fresh

    def _window_done(self, p) -> None:
        """The resolver answered a window: the slip step of what waited for it runs."""
        with self._recent_lock:
            self._pending_ns.pop(id(p), None)
        with self._step_lock:
            self._windows_out.pop(id(p), None)
            self._slip_step([])

    def _slip_step(self, contacts: list) -> None:
        """The slip step of these contact events, in time order with those held back: held
        while a window is with the overlap resolver (at most ``OVERLAP_HOLD_MAX_S``)."""
        if self.slip is None:
            return
        with self._step_lock:
            self._held.extend(contacts)
            horizon = self._inline_horizon_ns
            if self._windows_out:
                out = self._windows_out.values()
                if time.monotonic() - min(t for t, _ in out) < self.overlap_hold_max_s:
                    oldest = min(e for _, e in out)  # nothing the windows hold is older
                    horizon = oldest if horizon is None else min(horizon, oldest)
                else:
                    self.counts["slip_hold_expired"] += len(self._windows_out)
                    self._windows_out.clear()
            if horizon is None:
                batch, self._held = self._held, []
            else:
                batch = [c for c in self._held if c.time_ns < horizon]
                if not batch:
                    return
                self._held = [c for c in self._held if c.time_ns >= horizon]
            if not batch:
                return
            if len(batch) > 1:
                batch.sort(key=_TIME_NS)  # stable: packet order where stamps tie
            slips = self.slip.process(batch)
            on_slip = self._outputs[1]
            if slips and on_slip is not None:
                on_slip(slips)

    def idle(self) -> bool:
        """No window with the overlap resolver and no slip step waiting for one."""
        with self._step_lock:
            if self._windows_out or self._held or self._slip_pending:
                return False
        if self.hand is not None and self.hand.pending:
            return False
        return self.overlaps is None or not self.overlaps.pending()

    def wait_idle(self, timeout_s: float) -> bool:
        """Wait (up to timeout_s) until `idle`; True if so (offline replay and tests; never
        on the hot path)."""
        deadline = time.monotonic() + float(timeout_s)
        while not self.idle():
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.001)
        return True

    def release_held(self) -> None:
        """Run the slip step of held events whose wait has expired (a timer calls this)."""
        if self._held:
            self._slip_step([])

    def tick(self, now_ns: int):
        """Let time pass in the slip stage (`SlipStage.tick`), never past a held event;
        returns the finger state."""
        with self._step_lock:
            if self._held:
                now_ns = min(int(now_ns), min(r.time_ns for r in self._held) + self.slip.lag_ns)
            hand = self.hand
            due = hand.next_due_ns() if hand is not None else None
            if due is not None:  # never past an event the hand still holds
                now_ns = min(int(now_ns), due - hand.wait_ns + self.slip.lag_ns)
            return self.slip.tick(now_ns)

    def process(
        self,
        packets: Sequence,
        on_contacts: Callable[[list], None],
        on_slip: Callable[[list], None] | None = None,
        more_waiting: Callable[[], bool] | None = None,
    ) -> None:
        """Localize, hand out the contact events, then run the slip step on them.

        more_waiting: asked after the contact events are out (e.g. the link's
        `bytes_waiting`); while it says more packets are already waiting, the slip step
        is put off, at most ``SLIP_MAX_DEFER_S``, so that their contact events go out
        first; `run_pending_slip` (the link's idle call) or a later `process` runs it.
        On a hand (`enable_hand`), one thread at a time hands out events (the held
        packets' release waits for this batch, or a timer's is skipped).
        """
        if self.hand is None:
            self._process(packets, on_contacts, on_slip, more_waiting)
            return
        with self._release_lock:
            self._process(packets, on_contacts, on_slip, more_waiting)

    def _process(self, packets, on_contacts, on_slip, more_waiting) -> None:
        self._outputs = (on_contacts, on_slip)
        loc = self.localizer
        if loc.echo_pending and loc.echo_learner.ratio is None:
            # the echo test is still being learnt (its first 3 touches, ~70 us each, once):
            # what the last batch's touches teach judges this batch's packets, however far
            # behind the reader is (later measurements wait for a moment without packets)
            loc.learn_echo()
        contacts = loc.process(packets)
        if self.localizer.hand_reports:
            contacts = self._hold_apex(contacts)
        windows = self.localizer.overlap_windows
        if windows:
            # registered before anything of this batch is remembered: the duplicate check
            # keeps every event a window could hold until the window is answered
            self._register(windows)
        contacts = self._claim(contacts, resolved=False)
        if windows:
            if contacts:  # out before the overlapping windows are resolved
                on_contacts(contacts)
            if self._slip_pending:
                self._slip_before(windows)
            contacts = contacts + self._overlapping(windows, on_contacts)
        elif contacts:
            on_contacts(contacts)
        if more_waiting is None or self.slip is None:
            self._slip_step(contacts)
            if self.localizer.echo_pending:
                self.localizer.learn_echo()
            return
        if contacts:
            if not self._slip_pending:
                self._slip_pending_since = time.monotonic()
            self._slip_pending.extend(contacts)
        if self._slip_pending and (
            time.monotonic() - self._slip_pending_since >= SLIP_MAX_DEFER_S or not more_waiting()
        ):
            self.run_pending_slip()
        if self.localizer.echo_pending and not more_waiting():
            self.localizer.learn_echo()  # else when the link is idle (`run_idle_work`)

    def _slip_before(self, windows: list) -> None:
        """Before the overlapping ``windows`` are fitted in this thread (about a millisecond
        each): the slip step put off while they arrived (earlier packets' contact events),
        so that a slip precursor those decide does not wait for the fits. What is not older
        than the windows' earliest possible emission is held until a later slip step (time
        order, as offline). This batch's own contact events wait as before: running their
        slip step here would delay the windows' events."""
        pending, self._slip_pending = self._slip_pending, []
        with self._step_lock:
            self._inline_horizon_ns = min(self._earliest_ns(p) for p in windows)
            try:
                self._slip_step(pending)
            finally:
                self._inline_horizon_ns = None

    def _earliest_ns(self, p) -> int:
        """Earliest possible emission stamp of a window (ns): its emissions are at most one
        sphere diameter's travel time older than its first sample."""
        g = self.localizer.geometry
        return int(p.stamp_ns) - int(math.ceil(2.0 * g.radius_m / g.sound_speed_m_s * 1e9))

    def _register(self, windows: list) -> None:
        """Windows for the resolver: their earliest possible emission stamps keep the
        duplicate check's memory until they are answered."""
        with self._recent_lock:
            self._pending_ns.update((id(p), self._earliest_ns(p)) for p in windows)

    def _overlapping(self, windows: list, on_contacts) -> list:
        """Windows holding several emissions (registered): the first
        ``overlap_inline_max`` of the batch get the quick answer here, in the reader's
        thread (their emissions reach the hand soonest, in time for the slip step); the
        others, those whose quick answer is DEFERRED, and a window triggered by an emission
        (or whose trigger matches a window) just answered here, the second window of a
        pair, go to the resolver. Returns the contact events handed out here."""
        self.start_overlaps()
        self.overlaps.geometry = self.localizer.geometry
        found: list = []
        later: list = []  # (window, quick_first, slip step waits for it, hard)
        inline = 0
        for p in windows:
            covered = self._covered(p)
            if covered is not None:
                # the second window of a pair; hard when the first one gave no events here
                # (DEFERRED): the worker process gives both its answers
                self.counts["overlap_covered"] += 1
                later.append((p, True, covered, covered))
                continue
            if inline >= self.overlap_inline_max:
                later.append((p, True, True, False))
                continue
            inline += 1
            records = self.overlaps.resolve_now(p)
            produced = bool(records)
            self._arrivals_ns.append((_onset_ns(p), produced))
            if records is None:  # DEFERRED (or failed here): the worker's exhaustive search
                later.append((p, False, False, True))
                continue
            self._arrivals_ns.extend((t, True) for t in self.overlaps.arrivals_ns)
            fresh = self._claim(records, resolved=True)
            with self._recent_lock:
                self._pending_ns.pop(id(p), None)
            if fresh:
                on_contacts(fresh)
                found.extend(fresh)
        if later:
            self._to_worker(later)
        return found

    def _covered(self, p) -> bool | None:
        """None, unless the window's trigger (within ``overlap_covered_tol_s``) is the first
        arrival of an emission resolved in the reader or the trigger of a window answered
        there; then whether the slip step must wait for it (that window gave no events)."""
        if not self._arrivals_ns or self.overlap_covered_tol_s <= 0:
            return None
        onset_ns = _onset_ns(p)
        tol = self.overlap_covered_tol_s * 1e9
        match = [produced for t, produced in self._arrivals_ns if abs(onset_ns - t) <= tol]
        return None if not match else not any(match)

    def _to_worker(self, later: list) -> None:
        """Hand (window, quick_first, hold, hard) to the resolver (registered already for
        the duplicate check); the slip step waits for the ``hold`` ones, registered before
        the worker can answer."""
        windows = [p for p, _, _, _ in later]
        held = [p for p, _, hold, _ in later if hold]
        if self.slip is not None and held:
            with self._step_lock:
                now = time.monotonic()
                self._windows_out.update((id(p), (now, self._earliest_ns(p))) for p in held)
        queued = []
        # quick answers first: the slip step may wait for them (a pair's hard second
        # window too); exhaustive searches of windows DEFERRED here (nothing waits) last
        for quick_first, hard in ((True, False), (True, True), (False, True)):
            ws = [p for p, q, _, h in later if q == quick_first and h == hard]
            if ws:
                queued += self.overlaps.submit(ws, quick_first=quick_first, hard=hard)
        if len(queued) < len(windows):
            lost = {id(p) for p in windows} - {id(p) for p in queued}
            with self._recent_lock:
                for k in lost:
                    self._pending_ns.pop(k, None)
            with self._step_lock:
                for k in lost:
                    self._windows_out.pop(k, None)

    @property
    def slip_pending(self) -> bool:
        """Contact events handed out whose slip step is still due."""
        return bool(self._slip_pending)

    def run_pending_slip(self) -> None:
        """The slip step of contact events handed out while more packets were waiting."""
        with self._step_lock:  # the reader's idle call and a hand-out from a timer
            pending, self._slip_pending = self._slip_pending, []
            if pending:
                self._slip_step(pending)

    def run_idle_work(self) -> bool:
        """What waits for a moment without packets: the slip step put off, then the echo
        test's learning. True when it published slip or state changes may have come."""
        slip = self.slip_pending
        if slip:
            self.run_pending_slip()
        if self.localizer.echo_pending:
            self.localizer.learn_echo()
        return slip

    def late(
        self,
        contacts: list,
        on_contacts: Callable[[list], None],
        on_slip: Callable[[list], None] | None = None,
    ) -> None:
        """Contact events (from the hot path, or later from the overlap resolver): handed
        out, then through the slip stage."""
        if contacts:
            on_contacts(contacts)
            self._slip_step(contacts)

    def all_counts(self) -> Counter:
        """Every count of the pipeline (a copy; safe beside the reader and resolver)."""
        # dict.copy is one C call: a consistent copy while other threads count
        c = Counter(dict.copy(self.localizer.counts))
        c.update(dict.copy(self.counts))
        hand = self.hand
        if hand is not None:
            c.update({f"hand_{k}": v for k, v in dict.copy(hand.counts).items()})
        if self.overlaps is not None:
            c.update(self.overlaps.snapshot_counts())
        return c

    def close(self) -> None:
        if self.overlaps is not None:
            self.overlaps.close()
