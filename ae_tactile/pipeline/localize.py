# SPDX-License-Identifier: Apache-2.0
"""Localize: packets -> contact records (TOUCH / DETOUCH), every rejection counted by reason.

The per-packet check (`packet_problem`) keeps one bad packet from costing its neighbours;
one packet alone takes the compiled single-packet path, ``batch_min`` or more are localized
as one batch; then the screens (`screens.Screens`) drop interference, withdraw windows
holding overlapping emissions (for the overlap resolver) and gate weak releases.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections import Counter
from types import SimpleNamespace
from typing import Sequence

import numpy as np

from ae_tactile.dsp.channel_checks import CHECK_CLIPPED, CHECK_IDENTICAL, packet_checks
from ae_tactile.dsp.interference import common_mode_interference
from ae_tactile.dsp.interference import warm_up as warm_interference
from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import ChannelDelayLearner, Localizer, Reason, get_estimator
from ae_tactile.localization.front_end import FrontEndLearner, decay_family
from ae_tactile.localization.overlap import suspect_overlap
from ae_tactile.localization.overlap import warm_up as warm_overlaps
from ae_tactile.localization.overlap_worker import background_priority
from ae_tactile.localization.weak_release import WeakReleaseGate
from ae_tactile.pipeline.config import (
    APEX_POLAR_RAD,
    DELAY_LEARN_BATCH,
    DELAY_LEARN_CONFIDENCE,
    DELAY_LEARN_MAX_POLAR_RAD,
    DELAY_LEARN_MAX_RATE_HZ,
    DELAY_LEARN_STRIDE,
    DELAY_LEARN_STRIDE_CONVERGED,
    LocalizationConfig,
    front_end_pulse,
    packet_problem,
)
from ae_tactile.pipeline.screens import Screens
from ae_tactile.records import ContactRecord, EventType, PacketView, packet_record


def _gains_or_none(channel_gains):
    """Relative channel gains as a validated (4,) array, or None when all are 1 (nothing
    to apply: the per-packet path skips them). ValueError unless 4 positive finite numbers."""
    if channel_gains is None:
        return None
    g = np.asarray(channel_gains, dtype=float)
    if g.shape != (4,) or not np.all(np.isfinite(g) & (g > 0)):
        raise ValueError(f"channel_gains must be 4 positive finite numbers, got {channel_gains!r}")
    return None if np.all(g == 1.0) else g


class _Row:
    """One packet's fields of a batch `LocalizationResult` (`Screens.weak`)."""

    __slots__ = ("_res", "_j", "emission_offset_s")

    def __init__(self, res, j, offset_s):
        self._res, self._j, self.emission_offset_s = res, j, offset_s

    def __getattr__(self, name):
        return getattr(self._res, name)[self._j]


def _screen_attr(name: str) -> property:
    """A `Screens` attribute seen (and set) through the localizer."""
    return property(
        lambda self: getattr(self.screens, name),
        lambda self, v: setattr(self.screens, name, v),
        doc=f"`Screens.{name}`",
    )


class PacketLocalizer:
    """Packets -> contact events (TOUCH / DETOUCH), counting every rejection by reason.

    ``batch_min`` packets or more in one call are localized as a batch (cheaper per
    packet under load); fewer take the single-packet path (lowest latency).

    Parameters
    ----------
    method : str, optional
        Localization estimator (`ae_tactile.localization.get_estimator`); default the
        config's.
    config : LocalizationConfig, optional
        The settings (default: `LocalizationConfig()`).
    geometry : FingertipGeometry, optional
        The fingertip's body (default: `FingertipGeometry()`).
    channel_gains : array_like, optional
        Relative gains of the four channels (4 positive numbers).
    batch_min : int
        Packets per call from which the batch path is taken.
    **settings
        Fields of `LocalizationConfig` replacing the config's (``min_snr_db=10.0``, ...).

    Returns
    -------
    PacketLocalizer
        `process(packets)` gives the contact records of a batch.
    """

    def __init__(
        self,
        method: str | None = None,
        *,
        config: LocalizationConfig | None = None,
        geometry: FingertipGeometry | None = None,
        channel_gains=None,
        batch_min: int = 4,
        **settings,
    ):
        if method is not None:
            settings["method"] = method
        cfg = (config or LocalizationConfig()).replace(**settings)
        #: the settings in use (`update` replaces it)
        self.config = cfg
        self.localizer = Localizer(cfg.method, min_snr_db=cfg.min_snr_db)
        self.screens = Screens(
            reject_interference=cfg.reject_interference,
            interference_echo_min=cfg.interference_echo_min,
            interference_timing=cfg.interference_timing,
            weak_releases=cfg.weak_releases,
            weak_release_min_snr_db=cfg.weak_release_min_snr_db,
        )
        #: learn the echo inside `process` (False: the caller runs `learn_echo` once the
        #: contact events are out, as `ContactPipeline` does)
        self.learn_inline = True
        self.resolve_overlaps = cfg.resolve_overlaps
        #: windows of the last `process` call that hold overlapping emissions (for the
        #: overlap stage; rejected as OVERLAP or withdrawn as suspects)
        self.overlap_windows: list = []
        self.method = cfg.method
        self.min_snr_db = cfg.min_snr_db
        self.min_confidence = cfg.min_confidence
        self.geometry = geometry or FingertipGeometry()
        self.channel_gains = _gains_or_none(channel_gains)
        self.batch_min = int(batch_min)
        self.counts: Counter = Counter()
        self._one = getattr(self.localizer, "localize_one", None)
        #: ids of this call's packets found clipped in their samples (`_checked`)
        self._clipped: set = set()
        #: the channels' own delays, learnt from accepted touches and taken out of the
        #: arrivals once converged (`ChannelDelayLearner`; persisted as "channel_delays")
        self.delay_learner = ChannelDelayLearner()
        self._delay_pending: list = []
        self._delay_seen, self._delay_last_ns = 0, -(1 << 62)  # [1], [ns] last one kept
        self._delay_thread: threading.Thread | None = None  # `_hand_off_delays`
        self._delay_done: threading.Event | None = None  # the learning call under way
        self._delays_next: tuple | None = None  # (offsets,) it learnt, not yet in use
        self._deferring = False  # learning inline: offsets wait for the next hand-off
        self.delay_learner.on_update = self._set_delays
        #: the stated front end (``front_end``) calibrated on the same kept packets; its
        #: pulse refines every accepted point once trusted (`_set_front_end`)
        self.front_end_learner = FrontEndLearner(front_end_pulse(cfg.front_end))
        self._front_next: list = []  # a calibrated pulse not yet in use (from the thread)
        self.front_end_learner.on_update = self._set_front_end
        self.screens.pulse = decay_family(self.front_end_learner.stated)

    weak_releases = _screen_attr("weak_releases")
    weak_release_min_snr_db = _screen_attr("weak_release_min_snr_db")
    weak_gate = _screen_attr("weak_gate")
    interference = _screen_attr("interference")
    interference_echo_min = _screen_attr("interference_echo_min")
    interference_timing = _screen_attr("interference_timing")
    echo_learner = _screen_attr("echo_learner")
    burst_train = _screen_attr("burst_train")
    hand_reports = _screen_attr("hand_reports")
    apex_onsets_ns = _screen_attr("apex_onsets_ns")
    apex_held = _screen_attr("apex_held")
    echo_min_in_use = _screen_attr("echo_min_in_use")
    echo_pending = _screen_attr("echo_pending")

    def echo_test_status(self) -> str:
        """`Screens.echo_test_status`."""
        return self.screens.echo_test_status()

    def learn_echo(self) -> None:
        """`Screens.learn_echo`: run once the contact events are out."""
        self.screens.learn_echo()

    def calibration_learners(self) -> dict:
        """`Screens.calibration_learners` and the channel delays (``channel_delays``):
        section name -> learner of what the localize stage learns about the device (for
        `ae_tactile.calibration.CalibrationStore`)."""
        out = dict(self.screens.calibration_learners())
        out["channel_delays"] = self.delay_learner
        out["front_end"] = self.front_end_learner
        return out

    def _set_front_end(self, pulse) -> None:
        """The calibrated pulse to the localizer (the learner's ``on_update``); from the
        learning thread it waits for the next hand-off, as the delays do."""
        if self._deferring or threading.current_thread() is self._delay_thread:
            self._front_next = [pulse]
        else:
            self._use_front_end(pulse)

    def _use_front_end(self, pulse) -> None:
        """The calibrated pulse (None: not calibrated) refines the points; the screen's
        templates are its pulse, else the stated front end's over the emission decays
        (else the nominal front end's)."""
        self.localizer.set_front_end(pulse)
        self.screens.pulse = (pulse if pulse is not None
                              else decay_family(self.front_end_learner.stated))

    def front_end_status(self) -> str:
        """`FrontEndLearner.status`: the stated front end's calibration, in words."""
        return self.front_end_learner.status()

    def _set_delays(self, delays_s, noise=None) -> None:
        """The learner's offsets and delay noise to the localizer (its ``on_update``); from
        the learning thread they wait for the next hand-off (`_hand_off_delays`)."""
        if self._deferring or threading.current_thread() is self._delay_thread:
            self._delays_next = (delays_s, noise)
        else:
            self.localizer.set_channel_delays(delays_s, noise)

    def stash_delays(self, found) -> None:
        """Keep (copies of) the confident single emissions of a call for `_hand_off_delays`:
        one in DELAY_LEARN_STRIDE until every contrast is precise, then in ..._CONVERGED;
        at most DELAY_LEARN_MAX_RATE_HZ by their stamps."""
        learner = self.delay_learner
        for p, ev in found:
            if len(self._delay_pending) >= 4 * DELAY_LEARN_BATCH:
                return
            # not at the apex: interference lands there, and packets the hand must judge
            if (ev.weak_release or ev.confidence < DELAY_LEARN_CONFIDENCE
                    or not APEX_POLAR_RAD <= ev.polar_rad < DELAY_LEARN_MAX_POLAR_RAD):
                continue
            self._delay_seen += 1
            stride = DELAY_LEARN_STRIDE_CONVERGED if learner.all_precise else DELAY_LEARN_STRIDE
            if self._delay_seen % stride or (
                    ev.time_ns - self._delay_last_ns < 1e9 / DELAY_LEARN_MAX_RATE_HZ):
                continue
            self._delay_last_ns = ev.time_ns
            self._delay_pending.append((np.array(p.samples_v, dtype=np.float64),
                                        float(p.sample_rate_hz), int(p.onset_index),
                                        self.geometry, self.channel_gains))

    def _hand_off_delays(self) -> None:
        """Measure the kept packets at once (``learn_inline``) or, in a pipeline, in a niced
        thread (milliseconds of numpy the reflex path must not wait for); what a call learnt
        is used from the next hand-off on, which waits for it: never timing-dependent."""
        if self._delay_done is not None:
            self._delay_done.wait()
        if self._delays_next is not None:
            self.localizer.set_channel_delays(*self._delays_next)
            self._delays_next = None
        if self._front_next:
            self._use_front_end(self._front_next.pop())
        if self.learn_inline:
            self._deferring = True
            try:
                self.learn_delays()
            finally:
                self._deferring = False
            return
        if self._delay_thread is None:
            self._delay_queue: queue.SimpleQueue = queue.SimpleQueue()
            self._delay_thread = threading.Thread(target=self._delay_work, daemon=True,
                                                  name="ae_tactile_channel_delays")
            self._delay_thread.start()
        self._delay_done = threading.Event()
        self._delay_queue.put((self._delay_pending, self._delay_done))
        self._delay_pending = []

    def _delay_work(self) -> None:
        background_priority(False)
        while True:
            pending, done = self._delay_queue.get()
            try:
                self.learn_delays(pending)
            except Exception:  # the learner's bug must not end the learning
                logging.getLogger("ae_tactile.pipeline").exception("channel delay learning")
            finally:
                done.set()

    def learn_delays(self, pending: list | None = None) -> None:
        """Measure the kept packets (``pending``, default those kept now) with
        `ChannelDelayLearner.add` (numpy, ~0.3 ms a packet), one call per (rate, window
        length, body); the learner's offsets reach the localizer through ``on_update``."""
        if pending is None:
            pending, self._delay_pending = self._delay_pending, []
        groups: dict = {}
        for item in pending:
            if item[3] is self.geometry:  # packets of an earlier body are dropped
                key = (item[1], item[0].shape[1], id(item[4]))
                groups.setdefault(key, []).append(item)
        for items in groups.values():
            fs, gains = items[0][1], items[0][4]
            with np.errstate(all="ignore"):
                self.delay_learner.add(np.stack([it[0] for it in items]), fs,
                                       [it[2] for it in items], self.geometry, gains)
            if self.front_end_learner.wanted and gains is None:
                self.front_end_learner.add(np.stack([it[0] for it in items]), fs,
                                           [it[2] for it in items], self.geometry)

    def interference_model_status(self) -> str:
        """`Screens.acoustic_model_status`: the interference screen's model of an acoustic
        packet (the nominal front end's until the device's own is learnt) and how many
        packets it judged and rejected, in words for diagnostics."""
        return self.screens.acoustic_model_status()

    # ---------------------------------------------------------------- settings
    def update(
        self,
        *,
        geometry: FingertipGeometry | None = None,
        channel_gains=None,
        **settings,
    ) -> None:
        """Change settings at run time; takes effect at once.

        Parameters
        ----------
        geometry : FingertipGeometry, optional
            Another body (its touches and echo start afresh).
        channel_gains : array_like, optional
            Relative gains of the four channels.
        **settings
            Fields of `LocalizationConfig` (None: unchanged).

        Returns
        -------
        None
            ValueError on a bad value (channel gains, echo threshold, method, SNR,
            confidence): nothing changed then.
        """
        sc = self.screens
        gains = _gains_or_none(channel_gains) if channel_gains is not None else None
        given = {k: v for k, v in settings.items() if v is not None}
        cfg = self.config.replace(**given)
        localizer = None
        if "method" in given or "min_snr_db" in given:
            localizer = Localizer(cfg.method, min_snr_db=cfg.min_snr_db)
        # everything checked: apply what was given
        if localizer is not None:
            localizer.set_channel_delays(*self.delay_learner.applied)
            localizer.set_front_end(self.localizer.front_end)
            self.localizer = localizer
            self._one = getattr(localizer, "localize_one", None)
            self.method, self.min_snr_db = cfg.method, cfg.min_snr_db
        for name in given:
            self._apply(name, getattr(cfg, name))
        self.config = cfg
        if geometry is not None:
            if geometry != self.geometry:
                sc.new_body()
                self.delay_learner.reset()  # its measurements are of the old body
            self.geometry = geometry
        if channel_gains is not None:
            self.channel_gains = gains

    def _apply(self, name: str, value) -> None:
        """One validated setting (not method / min_snr_db: the localizer's) at work."""
        sc = self.screens
        if name == "min_confidence":
            self.min_confidence = value
        elif name == "front_end":
            self.front_end_learner.set_stated(front_end_pulse(value))
        elif name == "resolve_overlaps":
            self.resolve_overlaps = value
        elif name == "weak_releases":
            sc.set_weak_releases(value)
        elif name == "reject_interference":
            sc.interference = common_mode_interference if value else None
        elif name in ("interference_echo_min", "interference_timing", "weak_release_min_snr_db"):
            setattr(sc, name, value)

    def set_interference(self, enabled: bool) -> None:
        """Switch the common-mode interference rejection on or off."""
        self.screens.interference = common_mode_interference if enabled else None
        self.config = self.config.replace(reject_interference=bool(enabled))

    def warm_up(self, sample_rate_hz: float = 10e6, n_samples: int = 400) -> None:
        """Compile / cache what the first packet would otherwise pay for.

        Parameters
        ----------
        sample_rate_hz : float
            Sample rate of the packets to come [Hz].
        n_samples : int
            Their window length.

        Returns
        -------
        None
        """
        warm = getattr(self.localizer, "warm_up", None)
        if warm is not None:
            warm(self.geometry, sample_rate_hz, n_samples)
        rng = np.random.default_rng(0)
        x = rng.normal(0.0, 1e-3, (4, int(n_samples))).astype(np.float32)
        view = PacketView(x, sample_rate_hz, int(n_samples) // 4, 0, -1)
        self.process([view], count=False)
        self.process([view] * self.batch_min, count=False)
        # the paths a first odd packet would take: tables, compiled code
        w = x[None].astype(np.float64)
        on = [int(n_samples) // 4]
        with np.errstate(all="ignore"):
            if self.interference is not None:
                warm_interference(sample_rate_hz, geometry=self.geometry)  # templates
                self.interference(w, sample_rate_hz, on, geometry=self.geometry)
            single = SimpleNamespace(
                accepted=np.ones(1, bool), point_m=np.array([[0.0, 0.0, self.geometry.radius_m]])
            )
            suspect_overlap(w, sample_rate_hz, on, single, geometry=self.geometry)
            warm_overlaps(self.geometry, sample_rate_hz, n_samples)
        # the weak-release gate's search (a noise packet never reaches it)
        WeakReleaseGate().admit(0, (0.0, 0.0, self.geometry.radius_m), 1e-10, -1, False)
        self.overlap_windows = []

    # ---------------------------------------------------------------- packets
    def process(self, packets: Sequence, *, count: bool = True) -> list[ContactRecord]:
        """Contact events of the accepted packets, in packet order.

        Parameters
        ----------
        packets : sequence of PacketView
            One batch, in arrival order.
        count : bool
            Count into ``counts`` and learn (False: a warm-up call).

        Returns
        -------
        list of ContactRecord
            TOUCH / DETOUCH records of the packets kept; the windows holding overlapping
            emissions are in ``overlap_windows`` after the call.
        """
        counts = self.counts if count else Counter()
        self.overlap_windows = []
        sc = self.screens
        sc.new_call()
        # the body this call localizes on, and its echo learner (`update` may switch both
        # from another thread meanwhile: the echo of these packets belongs to this one)
        body = (self.geometry, sc.echo_learner, sc.acoustic)
        good = self._checked(packets, counts)
        if not good:
            return []
        weak_on = sc.weak_releases  # read once: `update` may change it meanwhile
        if len(good) >= self.batch_min or self._one is None:
            out = self._batched(good, counts, weak_on)
        else:
            out = []
            for p in good:
                ev = self._single(p, counts, weak_on)
                if ev is not None:
                    out.append((p, ev))
        if sc.interference is not None:
            out = sc.drop_interference(out, counts, self.geometry)
        if self.resolve_overlaps:
            out, withdrawn = sc.withdraw_suspects(out, self.geometry)
            for p in withdrawn:
                self._overlap(p, counts)
                counts["overlap_suspects"] += 1
        if weak_on:
            out = sc.gate_weak(out, counts)
        if sc.learning and count:
            sc.stash_echo(out, body)  # single emissions only (suspects withdrawn)
            if self.learn_inline:
                sc.learn_echo()
        if count:
            self.stash_delays(out)
            if len(self._delay_pending) >= DELAY_LEARN_BATCH:
                self._hand_off_delays()
        for _, ev in out:
            counts["events"] += 1
            counts["detouch" if ev.event_type == EventType.DETOUCH else "touch"] += 1
        return [ev for _, ev in out]

    def _checked(self, packets, counts) -> list:
        """The packets `packet_problem` passes (the others counted by reason), less those
        whose four channels are one signal (`packet_identical`: rejected_IDENTICAL_CHANNELS,
        never four sensors' view of an emission); a packet whose samples show a flat top at
        a rail (`packet_clipped`) without the device's flag is marked saturated
        (``clipped_from_samples``; the localizer rejects it as SATURATED). Both tests run
        in one compiled call (`packet_checks`)."""
        good = []
        self._clipped = set()
        for p in packets:
            counts["packets"] += 1
            why = packet_problem(p.samples_v, p.sample_rate_hz, p.onset_index)
            if why is not None:
                counts["rejected_MALFORMED_" + why] += 1
                continue
            nv = float(getattr(p, "noise_rms_v", 0.0) or 0.0)
            check = packet_checks(p.samples_v, int(p.onset_index), nv, p.sample_rate_hz,
                                  bool(p.saturated))
            if check == CHECK_IDENTICAL:
                counts["rejected_IDENTICAL_CHANNELS"] += 1
                continue
            if check == CHECK_CLIPPED:
                counts["clipped_from_samples"] += 1
                self._clipped.add(id(p))
            good.append(p)
        return good

    def _saturated(self, p) -> bool:
        """The device's saturation flag, or a flat top found in the samples this call."""
        return bool(p.saturated) or id(p) in self._clipped

    @property
    def _overlap_threshold(self) -> float:
        """The localizer's overlap threshold (its method's default unless given)."""
        thr = self.localizer.kwargs.get("overlap_threshold")
        return get_estimator(self.method).overlap_threshold if thr is None else float(thr)

    def _overlap(self, p, counts) -> None:
        counts["rejected_OVERLAP"] += 1
        if self.resolve_overlaps:
            self.overlap_windows.append(p)

    def _weak(self, p, r, snr_db, counts, weak_on) -> ContactRecord | None:
        return self.screens.weak(
            p, r, snr_db, counts, weak_on, self._overlap_threshold, self.min_confidence
        )

    def _single(self, p, counts, weak_on=False) -> ContactRecord | None:
        """The single-packet path: one compiled call."""
        r = self._one(
            p.samples_v,
            p.sample_rate_hz,
            int(p.onset_index),
            saturated=self._saturated(p),
            geometry=self.geometry,
            channel_gains=self.channel_gains,
            check_identical=False,  # `_checked` did, for every packet it passed
        )
        if not r.accepted:
            if int(r.reason) == Reason.OVERLAP:
                self._overlap(p, counts)
                return None
            return self._weak(p, r, float(r.snr_db), counts, weak_on)
        if r.confidence < self.min_confidence:
            counts["below_min_confidence"] += 1
            return None
        if self.localizer.front_end is not None:
            counts["refined" if r.refined else "refine_failed"] += 1
        return packet_record(
            p, r.point_m, r.covariance_m2, r.polar_rad, r.azimuth_rad, r.tau_x_s, r.tau_y_s,
            r.amplitude_v, r.confidence, r.polarity, r.emission_offset_s, r.overlap_excess,
        )

    def _batched(self, packets, counts, weak_on=False) -> list[tuple]:
        """The batch path: one call per (window length, sample rate) group; (packet, record)
        pairs in packet order."""
        groups: dict[tuple, list[int]] = {}
        for i, p in enumerate(packets):
            groups.setdefault((p.samples_v.shape[1], float(p.sample_rate_hz)), []).append(i)
        found: list[tuple[int, PacketView, ContactRecord]] = []
        for (_, fs), ids in groups.items():
            items = [packets[i] for i in ids]
            found += self._batch_group(items, ids, fs, counts, weak_on)
        found.sort(key=lambda t: t[0])
        return [(p, ev) for _, p, ev in found]

    def _batch_group(self, items, ids, fs, counts, weak_on) -> list[tuple]:
        """(index, packet, record) of one group of equal windows."""
        windows = np.stack([np.asarray(p.samples_v) for p in items])
        onset = np.array([int(p.onset_index) for p in items], dtype=np.int64)
        sat = np.array([self._saturated(p) for p in items])
        res = self.localizer(
            windows, fs, onset, geometry=self.geometry, saturated=sat,
            channel_gains=self.channel_gains,
        )
        excess = getattr(res, "overlap_excess", None)
        if excess is None:
            excess = np.zeros(len(items))
        offsets = getattr(res, "emission_offset_s", None)
        if offsets is None:
            travel = self.geometry.arrival_times_s(np.nan_to_num(res.point_m)).min(axis=-1)
            offsets = onset / fs - travel
        found = []
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
            if self.localizer.front_end is not None:
                counts["refined" if res.refined[j] else "refine_failed"] += 1
            rec = packet_record(
                p, res.point_m[j], res.covariance_m2[j], res.polar_rad[j], res.azimuth_rad[j],
                res.tau_x_s[j], res.tau_y_s[j], res.amplitude_v[j], res.confidence[j],
                res.polarity[j], offsets[j], excess[j],
            )
            found.append((ids[j], p, rec))
        return found
