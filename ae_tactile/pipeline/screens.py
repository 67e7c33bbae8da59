# SPDX-License-Identifier: Apache-2.0
"""The screens behind localization: common-mode interference (the packet tests, the learnt
wall echo, the apex packets' timing), overlapping emissions withdrawn from the single-
emission path, and the weak-release gate.

`Screens` holds their state (echo learner, burst train, weak-release gate, the apex packets
reported to the hand); `PacketLocalizer` owns one and calls it from the thread that
localizes, so it has no lock of its own (`learn_echo` runs in that thread too).
"""

from __future__ import annotations

import logging
import math
from types import SimpleNamespace

import numpy as np

from ae_tactile.dsp.acoustic_model import LEARN_KEEP, AcousticLearner
from ae_tactile.dsp.burst_train import TRAIN_TOL_S, TRAIN_TOL_SAMPLES, BurstTrain
from ae_tactile.dsp.interference import (
    ECHO_LEARN_KEEP,
    EchoLearner,
    common_mode_interference,
    echo_ratio,
    packet_common_share,
)
from ae_tactile.localization import Reason
from ae_tactile.localization.overlap import suspect_overlap
from ae_tactile.localization.weak_release import (
    WeakReleaseGate,
    check_min_snr_db,
    is_weak_release,
    weak_release_confidence,
)
from ae_tactile.pipeline.config import (
    APEX_POLAR_RAD,
    COMMON_IDENTICAL,
    COMMON_SUSPECT,
    ECHO_LEARN_CONFIDENCE,
    ECHO_LEARN_EVERY,
    ECHO_LEARN_PER_CALL,
    OVERLAP_SUSPECT_CONFIDENCE,
    OVERLAP_SUSPECT_EXCESS,
    ROUTE_ALL,
    ROUTE_NONE,
    ROUTE_SPECTRUM,
    SUSPECT_CONFIDENCE,
    echo_min_setting,
)
from ae_tactile.records import ContactRecord, EventType, onset_ns, packet_record

_log = logging.getLogger(__name__)

#: an interference screen that rejects more than this share of the packets it screens
#: (after UNUSUAL_MIN of them) says so once in the log: a device whose acoustic packets the
#: screen's model does not describe loses its apex touches [1]
UNUSUAL_SHARE = 0.5
UNUSUAL_MIN = 20


def interference_route(polar_rad: float, confidence: float, share: float | None = None):
    """Which of the discriminator's tests the driver gives a localized packet.

    Parameters
    ----------
    polar_rad : float
        The packet's localized polar angle [rad].
    confidence : float
        Its fit's confidence [1].
    share : float, optional
        Its common-mode share of the window's energy [1] (measured only when needed).

    Returns
    -------
    int or None
        ROUTE_ALL at the apex (< APEX_POLAR_RAD), for a very poor fit (< SUSPECT_CONFIDENCE)
        or one waveform within the noise (``share`` >= COMMON_IDENTICAL); ROUTE_SPECTRUM for
        nearly one waveform (>= COMMON_SUSPECT); else ROUTE_NONE. None when the first two do
        not decide and ``share`` is not given.
    """
    if polar_rad < APEX_POLAR_RAD or confidence < SUSPECT_CONFIDENCE:
        return ROUTE_ALL
    if share is None:
        return None
    if share >= COMMON_IDENTICAL:
        return ROUTE_ALL
    return ROUTE_SPECTRUM if share >= COMMON_SUSPECT else ROUTE_NONE


def _common_share(packets) -> list[float]:
    """`common_mode_share` of each packet (its pretrigger mean and its own noise_rms_v
    removed; compiled, about 1 us a packet)."""
    out = []
    for p in packets:
        nv = float(getattr(p, "noise_rms_v", 0.0) or 0.0)
        out.append(
            packet_common_share(p.samples_v, nv if math.isfinite(nv) else 0.0,
                                int(p.onset_index))
        )
    return out


def _packet_time_s(p) -> float:
    """A packet's onset [s] on the device's sample clock where the packet has it (exact to a
    sample), else on its host stamp."""
    fs = float(p.sample_rate_hz)
    dsi = getattr(p, "device_sample_index", None)
    if dsi is not None:
        return (int(dsi) + int(p.onset_index)) / fs
    return int(p.stamp_ns) * 1e-9 + int(p.onset_index) / fs


def _by_shape(found, ids, extra=None) -> dict:
    """Indices of ``found`` grouped by (window length, sample rate[, extra(i)])."""
    groups: dict[tuple, list[int]] = {}
    for i in ids:
        p = found[i][0]
        key = (p.samples_v.shape[1], float(p.sample_rate_hz))
        groups.setdefault(key if extra is None else key + (extra(i),), []).append(i)
    return groups


def _stack(found, ids):
    """Windows (n, 4, N) [V] as float64 and onsets (n,) of ``found[ids]``."""
    w = np.stack([np.asarray(found[i][0].samples_v, dtype=np.float64) for i in ids])
    return w, np.array([int(found[i][0].onset_index) for i in ids])


class Screens:
    """Interference, overlap-suspect and weak-release screens of localized packets.

    Parameters
    ----------
    reject_interference : bool
        Run the common-mode interference discriminator.
    interference_echo_min : float
        Echo test: < 0 learnt from the device's touches, 0 off, (0, 1] fixed threshold [1].
    interference_timing : bool
        Reject apex packets whose timing repeats a periodic train (False: a rig tapping the
        apex at a crystal-timed rate keeps its touches).
    weak_releases : bool
        Keep weak releases on the spot of a touch not yet released.
    weak_release_min_snr_db : float
        Lowest SNR of a weak release [dB].
    """

    def __init__(
        self,
        *,
        reject_interference: bool,
        interference_echo_min: float,
        interference_timing: bool,
        weak_releases: bool,
        weak_release_min_snr_db: float,
    ):
        #: weak releases (`ae_tactile.localization.weak_release`): a rarefaction rejected
        #: only for low SNR, down to weak_release_min_snr_db, on the spot of a touch not
        #: yet released is that touch's DETOUCH
        self.weak_releases = bool(weak_releases)
        self.weak_release_min_snr_db = check_min_snr_db(weak_release_min_snr_db)
        self.weak_gate = WeakReleaseGate()
        #: the discriminator's echo test (a device with wall echoes: an apex packet without
        #: its echo at 2R/c is interference)
        self.interference_echo_min = echo_min_setting(interference_echo_min)
        self.echo_learner = EchoLearner()
        #: the device's own acoustic packets (templates and spectrum limits of the
        #: discriminator), learnt from its accepted touches away from the apex
        self.acoustic = AcousticLearner()
        #: the device's front end (`PulseModel`, stated or calibrated; None: the nominal
        #: one): the discriminator's templates until its own packets are learnt
        self.pulse = None
        #: packets the discriminator judged and rejected (the unusual-share warning)
        self.screened = 0
        self.screened_rejected = 0
        self._warned = False
        #: the timing of the apex packets (periodic interference)
        self.burst_train = BurstTrain()
        self.interference_timing = bool(interference_timing)
        self.interference = common_mode_interference if reject_interference else None
        #: the hand's coincidence test (`ContactPipeline.enable_hand`): every apex packet's
        #: onset [host ns] of the last call goes to ``apex_onsets_ns`` (the other
        #: fingertips' reports), and the events of those the packet tests kept where no
        #: echo test runs to ``apex_held`` [(onset ns, event)], for the hand to hold
        self.hand_reports = False
        self.apex_onsets_ns: list[int] = []
        self.apex_held: list[tuple[int, ContactRecord]] = []
        self._echo_calls = 0
        self._echo_pending: list = []

    def new_call(self) -> None:
        """Forget the apex packets of the previous call."""
        if self.apex_onsets_ns or self.apex_held:
            self.apex_onsets_ns, self.apex_held = [], []

    def new_body(self) -> None:
        """Another body: touches and echo of the old one are stale (a measurement of the old
        body still under way goes to the old learner)."""
        self.weak_gate = WeakReleaseGate()
        self.echo_learner = EchoLearner()
        self.acoustic = AcousticLearner()
        self._echo_pending = []

    def set_weak_releases(self, enabled: bool) -> None:
        """Switch weak releases; switched, the touches remembered meanwhile are stale."""
        if bool(enabled) != self.weak_releases:
            self.weak_gate = WeakReleaseGate()
            self.weak_releases = bool(enabled)

    # ------------------------------------------------------------ weak releases
    def weak(self, p, r, snr_db, counts, weak_on, overlap_threshold, min_confidence):
        """A weak-release candidate's record (`gate_weak` decides), or None: counted as
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
            snr_db, floor, math.sqrt(max(c[0, 0] + c[1, 1], 0.0)), r.overlap_excess,
            overlap_threshold, r.clamped,
        )
        if conf < min_confidence:
            counts["rejected_LOW_SNR"] += 1
            return None
        rec = packet_record(
            p, r.point_m, c, r.polar_rad, r.azimuth_rad, r.tau_x_s, r.tau_y_s, r.amplitude_v,
            conf, r.polarity, r.emission_offset_s, r.overlap_excess,
        )
        rec.weak_release = True
        return rec

    def gate_weak(self, found, counts):
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

    # ------------------------------------------------------------ overlap suspects
    def withdraw_suspects(self, found, geometry):
        """Accepted packets with a poor fit whose one-emission model leaves a residual the
        noise cannot explain hold two emissions. Returns (the rest, the packets withdrawn
        for the overlap resolver)."""
        low = [
            i
            for i, (_, ev) in enumerate(found)
            if ev.confidence < OVERLAP_SUSPECT_CONFIDENCE
            and ev.overlap_excess > OVERLAP_SUSPECT_EXCESS
        ]
        if not low:
            return found, []
        drop = set()
        for (_, fs), ids in _by_shape(found, low).items():
            w, onset = _stack(found, ids)
            single = SimpleNamespace(
                accepted=np.ones(len(ids), bool),
                point_m=np.array([found[i][1].point_m for i in ids]),
            )
            try:
                with np.errstate(all="ignore"):
                    mask = suspect_overlap(w, fs, onset, single, geometry=geometry)
            except ValueError:
                continue
            drop.update(i for i, m in zip(ids, np.asarray(mask, bool)) if m)
        withdrawn = [found[i][0] for i in sorted(drop)]
        return [f for i, f in enumerate(found) if i not in drop], withdrawn

    # ------------------------------------------------------------ interference
    def _routes(self, found):
        """(indices for every test, indices for the spectrum tests only) of ``found``."""
        near, rest = [], []
        for i, (_, ev) in enumerate(found):
            if interference_route(ev.polar_rad, ev.confidence) == ROUTE_ALL:
                near.append(i)
            else:
                rest.append(i)
        # well-fitting packets off the apex with nearly one waveform on the four channels:
        # the spectrum tests only (the overlap resolver is the place of a window holding two
        # emissions near the apex); one waveform within the noise: every test
        screened = set()
        if rest:
            for i, c in zip(rest, _common_share([found[i][0] for i in rest])):
                route = interference_route(found[i][1].polar_rad, found[i][1].confidence, c)
                if route == ROUTE_ALL:
                    near.append(i)
                elif route == ROUTE_SPECTRUM:
                    screened.add(i)
        return near, screened

    def drop_interference(self, found, counts, geometry):
        """Drop the events whose packets the discriminator calls interference: those at the
        apex, fitting poorly, or with one waveform on the four channels; then the apex
        packets whose timing repeats a periodic train."""
        near, screened = self._routes(found)
        if not near and not screened:
            return found
        drop = set()
        groups = _by_shape(found, near + sorted(screened), lambda i: i in screened)
        for (_, fs, spectrum_only), ids in groups.items():
            w, onset = _stack(found, ids)
            kw = (
                {"shape_min": None, "echo_min": None}
                if spectrum_only
                else {"echo_min": self.echo_min_in_use}
            )
            try:
                mask, _ = self.interference(w, fs, onset, geometry=geometry,
                                            acoustic=self.acoustic, pulse=self.pulse, **kw)
            except ValueError:
                continue
            drop.update(i for i, m in zip(ids, np.asarray(mask, bool)) if m)
        self._count_screened(counts, len(near) + len(screened), len(drop))
        apex = [i for i in near if found[i][1].polar_rad < APEX_POLAR_RAD]
        if self.hand_reports and apex:
            self._report_apex(found, apex, drop)
        train = self._train(found, apex, drop)
        if train:
            counts["rejected_INTERFERENCE_TRAIN"] += len(train)
            drop |= train
        return [f for i, f in enumerate(found) if i not in drop]

    def _count_screened(self, counts, n_screened: int, n_rejected: int) -> None:
        """Count the discriminator's packets (``interference_screened``) and rejections
        (``rejected_INTERFERENCE``); warn once when it rejects an unusual share of them."""
        counts["interference_screened"] += n_screened
        if n_rejected:
            counts["rejected_INTERFERENCE"] += n_rejected
        self.screened += n_screened
        self.screened_rejected += n_rejected
        if (not self._warned and self.screened >= UNUSUAL_MIN
                and self.screened_rejected > UNUSUAL_SHARE * self.screened):
            self._warned = True
            _log.warning(
                "the interference screen rejected %d of the %d packets it judged (%s): "
                "either a source of interference, or a device whose touches the screen's "
                "model does not describe yet (apex touches lost)", self.screened_rejected,
                self.screened, self.acoustic.status())

    def _train(self, found, apex, drop) -> set:
        """Timing: every apex packet (kept or not) joins the train's history; one kept by
        the per-packet tests whose intervals repeat the history's is a periodic burst."""
        train = set()
        for i in sorted(apex, key=lambda j: _packet_time_s(found[j][0])):
            p = found[i][0]
            t = _packet_time_s(p)
            if self.interference_timing and i not in drop and self.burst_train.is_member(
                t, max(TRAIN_TOL_S, TRAIN_TOL_SAMPLES / float(p.sample_rate_hz))
            ):
                train.add(i)
            self.burst_train.add(t)
        return train

    def _report_apex(self, found, apex, drop) -> None:
        """The apex packets' onsets for the hand, and the events of those the packet tests
        kept where nothing in one packet tells (no echo test) to hold for its decision."""
        hold = self.echo_min_in_use is None
        for i in apex:
            t = onset_ns(found[i][0])
            if t != t:  # no host stamp: nothing to compare with the hand's
                continue
            self.apex_onsets_ns.append(int(t))
            if hold and i not in drop:
                self.apex_held.append((int(t), found[i][1]))

    # ------------------------------------------------------------ the wall echo
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

    @property
    def learning_echo(self) -> bool:
        """The learnt echo test is on (interference rejection with a learnt threshold)."""
        return self.interference is not None and self.interference_echo_min < 0.0

    @property
    def learning(self) -> bool:
        """The discriminator is on: it learns the device's acoustic packets (and the echo
        when `learning_echo`)."""
        return self.interference is not None

    def calibration_learners(self) -> dict:
        """The screens' learners by section name, for
        `ae_tactile.calibration.CalibrationStore` (load_into / save): the device's acoustic
        packet and its wall echo."""
        return {"interference_acoustic": self.acoustic, "interference_echo": self.echo_learner}

    def acoustic_model_status(self) -> str:
        """The discriminator's model of an acoustic packet in words (diagnostics)."""
        if self.interference is None:
            return "off"
        return (f"{self.acoustic.status()}; screened {self.screened}, rejected "
                f"{self.screened_rejected}")

    def stash_echo(self, found, body) -> None:
        """Keep (copies of) up to ECHO_LEARN_PER_CALL accepted, well-fitting packets away
        from the apex (never interference: its zero delays put it at the apex) for
        `learn_echo`, while the learners fill, then from one call in ECHO_LEARN_EVERY.
        ``body``: (geometry, echo learner, acoustic learner) the packets were localized
        with."""
        self._echo_calls += 1
        full = (self.echo_learner.n_measured >= ECHO_LEARN_KEEP or not self.learning_echo) and (
            self.acoustic.n_learnt >= LEARN_KEEP)
        if full and self._echo_calls % ECHO_LEARN_EVERY:
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
        """Measure the wall echo (`echo_ratio`, when the echo is learnt) and the acoustic
        packet (`AcousticLearner.add`) of the packets kept, tens of us a call, and teach
        them to the learners of the body each was localized on (after a geometry change,
        to none)."""
        pending, self._echo_pending = self._echo_pending, []
        groups: dict[tuple, list] = {}
        for item in pending:
            if item[5] is self.echo_learner:
                groups.setdefault((item[0].shape, item[1]), []).append(item)
        for (_, fs), grp in groups.items():
            geometry, learner, acoustic = grp[0][4], grp[0][5], grp[0][6]
            w = np.stack([g[0] for g in grp])
            onset = np.array([g[2] for g in grp])
            pts = np.array([g[3] for g in grp])
            with np.errstate(all="ignore"):
                if self.learning_echo:
                    learner.add(echo_ratio(w, fs, onset, pts, geometry))
                acoustic.add(w, fs, onset, pts, geometry)
