# SPDX-License-Identifier: Apache-2.0
"""The fingertip's hot path: decoded packets -> emissions -> contacts and slips (no rclpy).

`ContactPipeline.process` runs, for each batch of packets the link decodes and in the thread
that decoded them, the stages in order (one module each, docs/pipeline.md):

1. localize (`localize.PacketLocalizer`): per-packet check, localization (one packet alone
   on the compiled single-packet path, a backlog in batches), records;
2. screens (`screens.Screens`, called by the localizer): common-mode interference, windows
   holding overlapping emissions withdrawn, the weak-release gate;
3. hand (`hand.HandStage`): apex packets held for the hand's coincidence test;
4. slip (`slip_stage.SlipOrder`, `slip_stage.SlipStage`): the slip detector interprets
   the batch's emissions at once (before any overlapping window is fitted): a contact's
   TOUCH (its begin) and DETOUCH (its end) go to ``on_contacts``, its SLIP_PRECURSOR /
   SLIP / TEXTURE to ``on_slip``, every emission with its reading to ``on_emissions``;
5. overlaps (`overlaps.OverlapStage`): windows holding several emissions, the first few
   answered here, the others by `OverlapResolver` (its thread and worker process), later;
   emissions later than a window with the resolver are held until its answer (time
   order), then go through the slip step.

The localizer's records (a ContactRecord per emission: TOUCH for a compression, DETOUCH
for a rarefaction) go to ``on_localized`` as they come, before the slip step.

Emission time of a localized emission (int ns, host clock):
    t_emit = t_first_sample + emission_offset_s,
emission_offset_s being the fitted arrival at the nearest element minus the travel time
from the fitted point to it (or onset_index / fs minus that travel time when the
estimator gives no fitted arrival).

Threads and locks. The reader thread calls `process`; the resolver's thread hands its
answers over (`_late_from_resolver`, `OverlapStage._window_done`); a timer calls `tick`,
`release_held` and `release_coincidence`. Locks, each owned by one stage, outermost first
(a lock is only ever taken while holding locks above it in this list):

1. `HandStage.release_lock` (hand): one thread at a time hands out events while the hand
   holds some (`process` on a hand, `release_coincidence`, `enable_hand`);
2. `SlipOrder.lock` (slip, re-entrant; the step lock): held and waited-for events, one
   slip step at a time (its outputs are handed out under it); `release_coincidence`
   holds it around its hand-out;
3. `HandStage.lock` (hand): the coincidence test and its reports; and
   `OverlapStage.lock` (overlaps): the duplicate check's memory; and
   `SlipStage.lock` (slip): the detector. These three are never nested in one another.

`OverlapResolver._count_lock` and the resolver's queue are leaves. The localizer and its
screens have no lock: only the reader thread calls them.
"""

from __future__ import annotations

import time
from collections import Counter
from typing import Callable, Sequence

from ae_tactile.dsp.acoustic_model import LEARN_KEEP
from ae_tactile.dsp.coincidence import HandCoincidence
from ae_tactile.pipeline.config import COVERED_TOL_S, OVERLAP_HOLD_MAX_S, OVERLAP_INLINE_MAX
from ae_tactile.pipeline.hand import HandStage
from ae_tactile.pipeline.localize import PacketLocalizer
from ae_tactile.pipeline.overlaps import OverlapStage
from ae_tactile.pipeline.resolver import OverlapResolver
from ae_tactile.pipeline.slip_stage import SlipOrder, SlipStage
from ae_tactile.records import earliest_emission_ns


def _ignore(records: list) -> None:
    """A callback that takes nothing (no ``on_localized`` given)."""


def _stage_attr(stage: str, name: str, doc: str) -> property:
    """A stage's setting seen (and set) through the pipeline."""
    return property(
        lambda self: getattr(getattr(self, stage), name),
        lambda self, v: setattr(getattr(self, stage), name, v),
        doc=doc,
    )


class ContactPipeline:
    """The stages behind one call: ``process(packets, on_localized, on_slip, ...,
    on_contacts=..., on_emissions=...)``.

    The slip step runs for a batch's emissions at once: ``on_contacts`` gets a contact's
    TOUCH when it begins and its DETOUCH when it ends (also from `tick`), ``on_slip`` its
    SLIP_PRECURSOR / SLIP / TEXTURE, ``on_emissions`` every emission with its reading
    (`ae_tactile.records.EmissionRecord`); ``on_localized`` the localizer's records as
    they come, before the slip step. Without a slip stage, ``on_emissions`` gets each
    emission at once with the reading UNKNOWN.

    Parameters
    ----------
    localizer : PacketLocalizer
        The localize stage (and its screens).
    slip : SlipStage or None
        The slip stage (None: contact events only).
    counts : collections.Counter, optional
        The pipeline's own counters (the stages after the localizer count into it).
    overlaps : OverlapResolver, optional
        A resolver already running (default: started at the first overlapping window or
        by `start_overlaps`).
    overlap_hold_max_s : float
        Longest wait of the slip step for the overlap resolver [s].
    overlap_inline_max : int
        Overlapping windows per `process` call answered in the caller's thread.
    overlap_covered_tol_s : float
        Tolerance [s] of the second window of a pair; 0 answers every window on its own.
    overlap_idle : bool
        The resolver's thread and worker as SCHED_IDLE (the driver has cores of its own).
    hand : HandCoincidence, optional
        The hand's coincidence test (default: off until `enable_hand`).

    Returns
    -------
    ContactPipeline
    """

    def __init__(
        self,
        localizer: PacketLocalizer,
        slip: SlipStage | None,
        counts: Counter | None = None,
        overlaps: OverlapResolver | None = None,
        overlap_hold_max_s: float = OVERLAP_HOLD_MAX_S,
        overlap_inline_max: int = OVERLAP_INLINE_MAX,
        overlap_covered_tol_s: float = COVERED_TOL_S,
        overlap_idle: bool = False,
        hand: HandCoincidence | None = None,
    ):
        self.localizer = localizer
        self.slip = slip
        self.counts = Counter() if counts is None else counts
        #: on_localized of the latest process() (None: none given); False: no process() yet
        self._on_localized: Callable[[list], None] | None | bool = False
        self.slip_order = SlipOrder(slip, self.counts, overlap_hold_max_s)
        so = self.slip_order
        self.overlap_stage = OverlapStage(
            self.counts, self._late_from_resolver, so.window_done, so.hold_windows,
            so.unhold_windows, inline_max=overlap_inline_max,
            covered_tol_s=overlap_covered_tol_s, idle=overlap_idle, resolver=overlaps,
        )
        # the overlap fits use the channel delays the localizer applies once learnt, and
        # their covariances carry its delay noise
        self.overlap_stage.channel_delays = lambda: self.localizer.localizer.channel_delays_s
        self.overlap_stage.delay_noise = lambda: self.localizer.localizer.delay_noise
        self.hand_stage = HandStage(self.counts, hand)
        #: on a hand: called right after a batch's apex packets are known, before the slip
        #: step (the driver reports them to the other fingertips then: their wait for this
        #: report does not include this fingertip's slip step)
        self.on_apex: Callable[[], None] | None = None
        self.localizer.learn_inline = False  # `process` learns once the events are out

    overlaps = _stage_attr("overlap_stage", "resolver", "The `OverlapResolver` (or None).")
    overlap_inline_max = _stage_attr("overlap_stage", "inline_max", "`OverlapStage.inline_max`")
    overlap_covered_tol_s = _stage_attr(
        "overlap_stage", "covered_tol_s", "`OverlapStage.covered_tol_s` [s]")
    overlap_idle = _stage_attr("overlap_stage", "idle", "`OverlapStage.idle`")
    overlap_hold_max_s = _stage_attr("slip_order", "hold_max_s", "`SlipOrder.hold_max_s` [s]")
    hand = _stage_attr("hand_stage", "hand", "The `HandCoincidence` (None: off).")

    # ------------------------------------------------------------ the batch
    def process(
        self,
        packets: Sequence,
        on_localized: Callable[[list], None] | None = None,
        on_slip: Callable[[list], None] | None = None,
        more_waiting: Callable[[], bool] | None = None,
        *,
        on_contacts: Callable[[list], None] | None = None,
        on_emissions: Callable[[list], None] | None = None,
    ) -> None:
        """Localize the batch, run the slip step on its emissions, hand out what it gives.

        Parameters
        ----------
        packets : sequence of PacketView
            One batch, in arrival order.
        on_localized : callable, optional
            Called with each list of the localizer's records (ContactRecord per emission,
            TOUCH: compression, DETOUCH: rarefaction), before their slip step.
        on_slip : callable, optional
            Called with each list of SLIP_PRECURSOR / SLIP / TEXTURE records.
        more_waiting : callable, optional
            Asked after the batch (e.g. the link's `bytes_waiting`): while more packets
            wait, the echo test's learning waits for `run_idle_work`.
        on_contacts : callable, optional
            Called with each list of a contact's TOUCH (begin) / DETOUCH (end) records.
        on_emissions : callable, optional
            Called with each list of `EmissionRecord` (every emission, its reading).

        Returns
        -------
        None
            On a hand (`enable_hand`), one thread at a time hands out events (the held
            packets' release waits for this batch, or a timer's is skipped).
        """
        self.set_outputs(on_localized, on_slip, on_contacts=on_contacts,
                         on_emissions=on_emissions)
        stage = self.overlap_stage
        stage.reader_active = True  # the late check waits (`OverlapStage._late_turn`)
        try:
            if self.hand_stage.hand is None:
                self._process(packets, on_localized, more_waiting)
                return
            with self.hand_stage.release_lock:
                self._process(packets, on_localized, more_waiting)
        finally:
            stage.reader_active = False

    def set_outputs(self, on_localized=None, on_slip=None, *, on_contacts=None,
                    on_emissions=None) -> None:
        """Where the outputs go (as `process`'s callbacks), e.g. before the first batch so
        that `tick`'s DETOUCHes and the resolver's late answers have a destination."""
        self._on_localized = on_localized
        so = self.slip_order
        so.on_slip, so.on_contacts, so.on_emissions = on_slip, on_contacts, on_emissions

    def _process(self, packets, on_localized, more_waiting) -> None:
        """The stages in order (`process`)."""
        loc = self.localizer
        self._learn_echo_first()
        contacts = loc.process(packets)  # localize, screens
        if loc.hand_reports:
            contacts = self.hand_stage.hold_apex(contacts, loc.apex_onsets_ns, loc.apex_held)
            if self.on_apex is not None:
                self.on_apex()
        windows = loc.overlap_windows
        if windows:
            # registered before anything of this batch is remembered: the duplicate check
            # keeps every event a window could hold until the window is answered
            self.overlap_stage.register(windows, loc.geometry)
        contacts = self.overlap_stage.claim(contacts, resolved=False)
        if contacts and on_localized:
            on_localized(contacts)
        if windows:
            self._overlaps(contacts, windows, on_localized)
        else:
            self.slip_order.after_batch(contacts)
        if loc.echo_pending and (more_waiting is None or self.slip is None or not more_waiting()):
            loc.learn_echo()  # else when the link is idle (`run_idle_work`)
        if contacts and loc.resolve_overlaps:  # the overlap pulse's candidates: queued only
            self.overlap_stage.offer_singles(packets, contacts, loc.geometry)
            self.overlap_stage.check_later(packets, contacts)  # a late second emission?

    def _learn_echo_first(self) -> None:
        """While the echo test or the device's acoustic packet is still being learnt (its
        first touches), what the last batch's touches teach judges this batch's packets,
        however far behind the reader is (later measurements wait for a moment without
        packets)."""
        loc = self.localizer
        if loc.echo_pending and (loc.echo_learner.ratio is None
                                 or loc.screens.acoustic.n_learnt < LEARN_KEEP):
            loc.learn_echo()

    def _overlaps(self, contacts: list, windows: list, on_localized) -> None:
        """The slip step of the batch's emissions older than the overlapping windows'
        earliest one (their TOUCHes out before the fits), then the windows (their
        emissions to ``on_localized`` as they come), then the slip step of the rest."""
        g = self.localizer.geometry
        self.slip_order.step_before(contacts, min(earliest_emission_ns(p, g) for p in windows))
        found = self.overlap_stage.overlapping(windows, on_localized or _ignore, g)
        self.slip_order.after_batch(found)

    def late(self, contacts: list) -> None:
        """Localized emissions that come late (the overlap resolver's, the hand's held
        ones): to ``on_localized``, then through the slip step (outputs as `process`'s)."""
        if contacts:
            if self._on_localized:
                self._on_localized(contacts)
            self.slip_order.step(contacts)

    def _late_from_resolver(self, records: list) -> None:
        if self._on_localized is False:  # no process() yet: nowhere to hand them
            return
        self.late(self.overlap_stage.claim(records, resolved=True))

    # ------------------------------------------------------------ overlaps
    def start_overlaps(self, wait_s: float = 0.0) -> None:
        """Start the overlap resolver (and its worker process) now, not at the first
        overlapping window, and wait up to wait_s [s] for the worker to be warm; the driver
        calls this while warming up, before acquisition."""
        self.overlap_stage.start(self.localizer.geometry, wait_s)

    # ------------------------------------------------------------ the hand
    def enable_hand(self, window_s: float | None = None, wait_s: float | None = None) -> None:
        """Take part in the coincidence test of the fingertips of one hand
        (`ae_tactile.dsp.coincidence`): `take_apex_onsets` gives this fingertip's apex
        packets for the others, `hand_reports` takes theirs, and an apex packet the packet
        tests kept where no echo test runs is held until `release_coincidence` decides it
        (ValueError on bad settings: nothing changed then)."""
        self.hand_stage.enable(window_s, wait_s)
        self.localizer.hand_reports = True

    def take_apex_onsets(self) -> list:
        """This fingertip's apex packet onsets (host ns) not reported yet."""
        return self.hand_stage.take_apex_onsets()

    def hand_reports(self, onsets_ns, source: str = "", now_ns: int | None = None) -> None:
        """Another fingertip's (``source``) apex packet onsets (host ns); ``now_ns``: this
        fingertip's host time (stamps far from it are counted and dropped)."""
        self.hand_stage.reports(onsets_ns, source, now_ns)

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
        if not self.hand_stage.waiting():
            return False
        lock = self.hand_stage.release_lock
        wait = -1 if timeout_s is None else max(0.0, float(timeout_s))
        if not (lock.acquire(True, wait) if blocking else lock.acquire(False)):
            return False
        try:
            # the slip stage's clock (`tick`, a timer) waits until what is decided here
            # has been through the slip step: it never runs past a released event
            with self.slip_order.lock:
                kept = self.hand_stage.decide(now_ns, flush)
                if kept and self._on_localized is not False:
                    self.late(self.overlap_stage.claim(kept, resolved=False))
            return bool(kept)
        finally:
            lock.release()

    # ------------------------------------------------------------ time and idle work
    def tick(self, now_ns: int):
        """Let time pass in the slip stage (`SlipStage.tick`), never past a held event;
        contacts that end meanwhile go to ``on_contacts`` (their DETOUCH); returns the
        finger state."""
        return self.slip_order.tick(now_ns, self.hand_stage.limit_ns)

    def release_held(self) -> None:
        """Run the slip step of held events whose wait has expired (a timer calls this)."""
        self.slip_order.release_held()

    @property
    def slip_pending(self) -> bool:
        """Emissions whose slip step was put off: never (it runs at once)."""
        return self.slip_order.pending

    def run_pending_slip(self) -> None:
        """Nothing to do: the slip step runs at once (kept for the idle-work callers)."""
        self.slip_order.run_pending()

    def run_idle_work(self) -> bool:
        """What waits for a moment without packets: the echo test's learning. True when
        slip or state changes may have come (never: the slip step runs at once)."""
        if self.localizer.echo_pending:
            self.localizer.learn_echo()
        return False

    def idle(self) -> bool:
        """No window with the overlap resolver and no slip step waiting for one."""
        if self.slip_order.busy() or self.hand_stage.pending():
            return False
        return not self.overlap_stage.pending()

    def wait_idle(self, timeout_s: float) -> bool:
        """Wait (up to timeout_s [s]) until `idle`; True if so (offline replay and tests;
        never on the hot path)."""
        deadline = time.monotonic() + float(timeout_s)
        while not self.idle():
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.001)
        return True

    def calibration_learners(self) -> dict:
        """Section name -> learner of what the stages learn about the device (the screens'
        acoustic packet and wall echo; the overlap stage's pulse, ``overlap_pulse``): what
        `ae_tactile.calibration.CalibrationStore` loads and saves.

        Returns
        -------
        dict
        """
        out = dict(self.localizer.calibration_learners())
        out["overlap_pulse"] = self.overlap_stage.pulse_learner
        return out

    def all_counts(self) -> Counter:
        """Every count of the pipeline (a copy; safe beside the reader and resolver)."""
        # dict.copy is one C call: a consistent copy while other threads count
        c = Counter(dict.copy(self.localizer.counts))
        c.update(dict.copy(self.counts))
        c.update(self.hand_stage.all_counts())
        if self.overlaps is not None:
            c.update(self.overlaps.snapshot_counts())
        return c

    def close(self) -> None:
        """Stop the overlap resolver's thread and worker process."""
        self.overlap_stage.close()
