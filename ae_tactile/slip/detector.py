# SPDX-License-Identifier: Apache-2.0
"""Slip / texture detector core: localized emissions in, SLIP_PRECURSOR / SLIP / TEXTURE
events and a latched per-finger contact state out. Pure Python + numpy, no rclpy.

    det = SlipDetector(SlipConfig())
    for ev in localized_events:            # LocalizedEvent, in time order (+- reorder tolerance)
        for out in det.process(ev):        # SlipEvent list (often empty)
            publish(out)
    det.advance(now_ns)                    # time passing without events (timer)
    det.state                              # FingerState (latched)

Two readings of the emissions (docs/slip.md). The default is the fingertip model
(`ae_tactile.slip.model`: objects arrive at one point, at several or as a broad press,
are held, loaded, slide, re-stick and are released; each emission gets the event that
explains it). ``SlipDetector(model=False)`` gives the older per-emission rules, below,
which share its precursor, gross-slip, tracking and texture stages.

The rules. A held contact is silent. Under a growing tangential load Q the
Cattaneo-Mindlin slip annulus c < r < a_H, c = a_H (1 - Q/(mu P))^(1/3), spreads inward
from the contact edge and its micro-slips emit from ever more places around the edge.
The evidence is *where* emissions come from, not their sign:

* an emission far from every contact founds a contact (its founding emission: a touch,
  or the first micro-slip of a contact nobody announced);
* two emissions of a contact on one spot (within the gate of their position
  uncertainties) are a touch and its release, or repeated taps: a pair. Polarity helps
  where it is informative: a release (a rarefaction) pairs with an earlier touch (a
  compression) on its spot, never the other way round (a release comes after its touch);
  a later emission on a paired spot, or a compression on a rarefaction's, is a repeat
  (no evidence); after a touch and its release (in the contact, or in one that ended
  within ``association_radius_m``) compressions are touches, not evidence
  (``touched_compression_weight``), for ``evidence_window_s`` and until the contact's
  next compression however late, and a compression taken for a touch stays one (its
  release may be lost); a rarefaction on the founding touch's spot with nothing
  between them is its release however long the hold (the model floor kept);
  the founding emission paired ends the contact after ``release_confirm_s``;
* an emission of a contact on no other emission's spot is micro-slip evidence:
  SLIP_PRECURSOR (STICK -> INCIPIENT_SLIP) when ``precursor_min_emissions`` of them fall
  within ``evidence_window_s``. Micro-slips come from random places round the annulus;
  touches, releases and taps come from a few fixed spots. Any polarity mix is the same;
* SLIP (-> GROSS_SLIP), whether or not a precursor came first, when the latest
  emissions are more likely gross slip (a rate jump to gross_rate_min_hz ..
  gross_rate_max_hz, from the whole contact disc) than the contact's micro-slips going on
  (its own prior rate, from the slip annulus): a sequential likelihood ratio of at least
  ``gross_llr_threshold`` (`gross`); or when in the latest ``gross_window_s`` at
  least ``gross_min_events`` emissions came and either one lies inside the stick zone
  (closer than ``gross_inner_fraction`` of the contact radius to the centre fitted to its
  emissions), or their rate is a Poisson tail below ``gross_rate_alpha`` of the rate
  before them; or the contact moves;
* a contact's motion (centre and velocity along the surface) is regressed on its
  emissions over ``track_window_s``; a contact that moves significantly is predicted
  forward for association, so a dragged stylus stays one contact;
* TEXTURE while the contact's latest intervals are periodic (robust dispersion test),
  with spatial period = tracked speed x period (moving contact) or the configured sliding
  speed x period (fixed contact).

Work per event is bounded: ring buffers of ``member_history`` emissions per contact,
at most ``max_contacts`` contacts, small fits run only when their input changed.

Layout: `SlipDetector` (here: the public API, ``process`` and the latched finger state)
gathers one mixin per stage, each in its module: `tracking` (association, new contacts,
centre, radius and motion), `evidence` (an emission's membership of its contact and
SLIP_PRECURSOR), `gross` (SLIP), `texture` (TEXTURE) and `outputs` (the event records);
`contact` holds a contact's ring buffers, `fits` the small least-squares fits.
"""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.records import ContactState, Reading

from .config import SlipConfig
from .contact import NAN3, SLIPPING, Contact
from .evidence import MicroSlipEvidence
from .gross import GrossSlipTest
from .model import ContactModel
from .outputs import SlipOutputs
from .texture import TextureTest
from .tracking import ContactTracking
from .types import ContactInfo, FingerState, LocalizedEvent, SlipEvent


class SlipDetector(
    ContactTracking, ContactModel, MicroSlipEvidence, GrossSlipTest, TextureTest, SlipOutputs
):
    """Stateful slip / texture detector for one finger (see the module docstring).

    Parameters
    ----------
    config : SlipConfig, optional
        Detector parameters; None: the defaults.
    contact_events : bool, optional
        ``process`` also returns a TOUCH SlipEvent when a contact begins and a DETOUCH
        when it ends; False (the default, the output of earlier versions): only
        SLIP_PRECURSOR / SLIP / TEXTURE.
    model : bool, optional
        Read the emissions with the fingertip model (`ae_tactile.slip.model`: objects
        arriving, held, loaded, sliding, lifted, released; the default). False: the
        older per-emission rules (an emission near a held contact is micro-slip
        evidence), which give a never-announced sparse load its precursor sooner at the
        cost of false alarms on multi-point touches and broad presses (docs/slip.md).

    Attributes
    ----------
    config : SlipConfig
        The parameters in use (``update_config`` changes the run-time ones).
    contacts : list of Contact
        The tracked contacts, unconfirmed candidates included.
    counts : dict of str to int
        Emissions processed, rejected (by reason) and classified, contacts created and
        dropped.
    now_ns : int or None
        Time of the newest emission or ``advance`` [ns].
    last_reading : tuple of (Reading, int)
        What the latest emission given to ``process`` was read as and the id of the
        contact it was assigned to (-1: none; (UNKNOWN, -1) for a rejected one).

    Raises
    ------
    TypeError
        When ``config`` is not a SlipConfig.
    """

    def __init__(
        self,
        config: SlipConfig | None = None,
        *,
        contact_events: bool = False,
        model: bool = True,
    ):
        if config is None:
            config = SlipConfig()
        if not isinstance(config, SlipConfig):
            raise TypeError(f"config must be a SlipConfig, got {type(config).__name__}")
        self._apply(config)
        self._speed = config.sliding_speed_m_s
        self.contacts: list[Contact] = []
        self._next_id = 1
        self.now_ns = None
        self.counts = {
            "events": 0,
            "rejected_low_confidence": 0,
            "rejected_out_of_order": 0,
            "rejected_non_finite": 0,
            "rejected_bad_type": 0,
            "releases": 0,
            "releases_cancelled": 0,
            "orphans_dropped": 0,
            "pairs": 0,
            "repeats": 0,
            "evidence": 0,
            "contacts_created": 0,
            "contacts_dropped": 0,
        }
        self._finger = FingerState(ContactState.NO_CONTACT, 0, NAN3.copy(), 0.0, 0, -1, 0, 0)
        self._fs_state, self._fs_since, self._fs_pending = ContactState.NO_CONTACT, 0, None
        self._last_end_ns = 0
        self._last_t = None
        self.contact_events = bool(contact_events)
        self._model = bool(model)
        #: TOUCH / DETOUCH events decided and not yet returned (``pop_events``)
        self._pending: list[SlipEvent] = []
        self.last_reading = (Reading.UNKNOWN, -1)
        #: (touch-release time ns, spot (3,)) of contacts that ended, at most max_contacts
        self._ended_activity = []
        #: (end time ns, centre (3,)) of contacts lifted or released off their touches
        self._lifted = []
        #: decayed sums of ln |amplitude / V| of the finger's touches (micro-slips) and
        #: their weight (`ContactModel._note_amplitude`; the device's gain: kept over a reset)
        self._touch_scale = [0.0, 0.0]
        self._micro_scale = [0.0, 0.0]

    def _apply(self, c: SlipConfig):
        """Take configuration ``c``: its windows in integer ns, squared gates [m^2] and the
        texture interval model's constants."""

        def ns(s):
            return int(round(s * 1e9))

        self.config = c
        self._w_ev, self._w_rate, self._w_track = (
            ns(c.evidence_window_s),
            ns(c.rate_window_s),
            ns(c.track_window_s),
        )
        self._confirm, self._quiet, self._report = (
            ns(c.release_confirm_s),
            ns(c.quiet_s),
            ns(c.report_interval_s),
        )
        self._reorder, self._guard = ns(c.reorder_tolerance_s), ns(c.overlap_guard_s)
        self._w_gross, self._w_hist = ns(c.gross_window_s), ns(c.gross_history_s)
        self._w_prior = ns(c.gross_prior_s)
        self._assoc2 = c.association_radius_m**2
        # interval model of a texture: k periods (k = 1, 2, 3: missed packets), sd s sqrt(k)
        km = np.arange(1, c.texture_max_multiple + 1, dtype=float)[:, None]
        prior = np.where(km == 1, 0.9, 0.1 / max(1, c.texture_max_multiple - 1))
        self._tex_k, self._tex_s = km, c.texture_interval_sd * np.sqrt(km)
        self._tex_w = np.log(prior) - 0.5 * math.log(2 * math.pi)
        self._g2 = c.release_gate_sigma**2
        self._f2 = c.release_floor_m**2
        self._model_apply()

    # ------------------------------------------------------------------ public API
    @property
    def state(self) -> FingerState:
        """Latched finger state as of the last ``process`` / ``advance``.

        Returns
        -------
        FingerState
            The most severe state over the confirmed contacts, the contact that sets it
            and since when.
        """
        return self._finger_state()

    def update_config(self, **changes) -> SlipConfig:
        """Change run-time-safe parameters at once; the whole new configuration is
        validated first.

        Parameters
        ----------
        **changes
            SlipConfig field -> new value, fields of ``SlipConfig.runtime_fields()`` only.

        Returns
        -------
        SlipConfig
            The configuration now in use.

        Raises
        ------
        ValueError
            A field that cannot change at run time, or an invalid value (nothing changed).
        """
        bad = sorted(set(changes) - set(SlipConfig.runtime_fields()))
        if bad:
            raise ValueError(
                f"SlipConfig fields {bad} cannot change at run time "
                f"(runtime fields: {', '.join(SlipConfig.runtime_fields())})"
            )
        new = self.config.replace(**changes)
        self._finger_state()  # the state as of now, under the old rate window
        self._apply(new)
        if "sliding_speed_m_s" in changes:
            self._speed = new.sliding_speed_m_s
        return new

    def set_sliding_speed(self, speed_m_s: float | None) -> None:
        """Set the sliding speed that gives fixed contacts' TEXTURE spatial periods.

        Parameters
        ----------
        speed_m_s : float or None
            Sliding speed [m/s], > 0; None: unknown (spatial period NaN unless the contact
            is tracked moving).

        Raises
        ------
        ValueError
            A speed that is not a positive finite number.
        """
        if speed_m_s is not None:
            v = float(speed_m_s)
            if not math.isfinite(v) or v <= 0:
                raise ValueError(
                    f"sliding speed must be a positive number of m/s, got {speed_m_s!r}"
                )
            speed_m_s = v
        self._speed = speed_m_s

    def contact_infos(self) -> list[ContactInfo]:
        """Snapshots of every tracked contact.

        Returns
        -------
        list of ContactInfo
            One per contact, unconfirmed candidates included, as of ``now_ns``.
        """
        now = self.now_ns if self.now_ns is not None else 0
        out = []
        for c in self.contacts:
            out.append(
                ContactInfo(
                    c.id,
                    c.state,
                    c.since_ns,
                    c.centre_at(now).copy(),
                    c.radius,
                    True,
                    c.confirmed,
                    c.pending_release_ns is not None,
                    self._rate(c, now),
                    c.precursor_count,
                    c.valid(),
                    c.last_ns,
                    c.vel.copy() if c.moving else np.zeros(3),
                    c.moving,
                )
            )
        return out

    def reset(self) -> None:
        """Forget every contact (e.g. after a gap in the data); counts are kept. Each
        contact that was reported begun gets its DETOUCH (``pop_events``)."""
        for c in list(self.contacts):
            self._end_contact(c)
        self.contacts.clear()
        self._ended_activity.clear()
        self._lifted.clear()
        self.now_ns = None
        self._last_t = None
        self._finger = FingerState(ContactState.NO_CONTACT, 0, NAN3.copy(), 0.0, 0, -1, 0, 0)
        self._fs_state, self._fs_since, self._fs_pending = ContactState.NO_CONTACT, 0, None

    def process_batch(self, events) -> list[SlipEvent]:
        """``process`` for each event in order.

        Parameters
        ----------
        events : iterable of LocalizedEvent
            Emissions in time order.

        Returns
        -------
        list of SlipEvent
            The outputs of every event, concatenated.
        """
        out = []
        for ev in events:
            out.extend(self.process(ev))
        return out

    def advance(self, now_ns: int) -> FingerState:
        """Let time pass without events (a node's timer): release confirmations,
        candidate expiry, quiet slip states falling back to STICK. A contact that ends
        here leaves its DETOUCH for ``pop_events`` (or the next ``process``'s return).

        Parameters
        ----------
        now_ns : int
            The time now [ns]; earlier than the newest time seen: nothing changes.

        Returns
        -------
        FingerState
            The latched finger state (``state``).

        Raises
        ------
        TypeError
            When ``now_ns`` is not an integer.
        """
        if isinstance(now_ns, bool) or not hasattr(now_ns, "__index__"):
            raise TypeError(f"now_ns must be an integer (ns), got {now_ns!r}")
        now = int(now_ns.__index__())
        if self.now_ns is not None and now < self.now_ns:
            return self._finger_state()
        self._expire(now)
        self._update_finger(now)
        return self._finger_state()

    def pop_events(self) -> list[SlipEvent]:
        """The TOUCH / DETOUCH events decided outside ``process`` (contacts ended by
        ``advance`` or ``reset``), oldest first; each is returned once (``process``
        returns those not popped before its own).

        Returns
        -------
        list of SlipEvent
            The pending events (often none).
        """
        out, self._pending = self._pending, []
        return out

    def _expire(self, now):
        """Advance to ``now`` [ns]: end contacts whose release is confirmed, drop
        candidates left alone for evidence_window_s, let quiet slipping contacts stick."""
        self.now_ns = now
        for c in list(self.contacts):
            wait = self._quiet if c.pending_in_slip else self._confirm
            if self._model and c.pending_in_slip:
                wait = self._rel_wait
            if c.provisional:
                wait = self._w_ev  # reads released meanwhile; a micro-slip may follow
            if c.pending_release_ns is not None and now - c.pending_release_ns >= wait:
                self._end_contact(c)
                continue
            if not c.confirmed and now - c.last_ns >= self._w_ev:
                self.contacts.remove(c)
                continue
            if c.arriving and now - c.last_ns > self._hold_gap:
                c.arriving = False
            if (
                self._model
                and (c.state == ContactState.GROSS_SLIP or c.resumed)
                and now - c.last_ns >= self._lift_min
                and now - c.last_ns >= self._lift_quiet_ns(c)
            ):
                # silent after sliding (or after a slide's lift, undecided): lifted
                # (`ContactModel`); an emission soon after a slide's lift may resume it
                c.pending_release_ns, c.pending_in_slip = c.last_ns, True
                c.pending_release_spot = None
                c.slid = c.state == ContactState.GROSS_SLIP
                self._end_contact(c)
                continue
            if c.state in SLIPPING and now - c.last_ns >= self._quiet:
                c.state = ContactState.STICK
                c.since_ns = c.last_ns + self._quiet
                c.texture_on = False
                c.texture_run = 0
                c.moving = False

    def process(self, ev: LocalizedEvent) -> list[SlipEvent]:
        """Feed one localized emission.

        Never raises on bad event data: it is rejected and counted in ``counts`` (not a
        LocalizedEvent, non-finite values, older than reorder_tolerance_s before the newest
        one seen, confidence below min_confidence).

        Parameters
        ----------
        ev : LocalizedEvent
            The emission, in time order (within reorder_tolerance_s).

        Returns
        -------
        list of SlipEvent
            The events it decided (often none): TOUCH when a contact begins (at its
            first point), DETOUCH when one ends (at its centre; those ended by time
            passing before this emission come first, as do any ``pop_events`` had not
            returned), then SLIP_PRECURSOR, SLIP and TEXTURE. ``last_reading`` tells what
            the emission was read as.
        """
        self.last_reading = (Reading.UNKNOWN, -1)
        if not isinstance(ev, LocalizedEvent):
            self.counts["rejected_bad_type"] += 1
            return self.pop_events()
        p = ev.point_m
        px, py, pz = p.tolist()
        cov = ev.covariance_m2
        cl = cov.ravel().tolist()
        tr = cl[0] + cl[4] + cl[8]
        if not (
            math.isfinite(px + py + pz)
            and math.isfinite(tr)
            and all(map(math.isfinite, cl))
            and px * px + py * py + pz * pz > 0.0
        ):
            self.counts["rejected_non_finite"] += 1
            return self.pop_events()
        t = ev.time_ns
        if self.now_ns is not None and t < self.now_ns - self._reorder:
            self.counts["rejected_out_of_order"] += 1
            return self.pop_events()
        if ev.confidence < self.config.min_confidence:
            self.counts["rejected_low_confidence"] += 1
            return self.pop_events()
        self.counts["events"] += 1
        if self.now_ns is None or t > self.now_ns:
            self._expire(t)
        out: list[SlipEvent] = []
        var = 0.5 * max(tr, 0.0)
        c = self._associate(px, py, pz, t, ev.polarity, var)
        overlap = self._last_t is not None and abs(t - self._last_t) < self._guard
        self._last_t = t if self._last_t is None else max(t, self._last_t)
        if (
            c is not None
            and not c.confirmed
            and ev.polarity > 0
            and not (c.arriving and t - c.last_ns <= self._hold_gap)
        ):
            # a touch next to a lone rarefaction (a release whose touch was missed): the
            # touch founds the contact, the orphan is forgotten
            self.contacts.remove(c)
            self.counts["orphans_dropped"] += 1
            c = None
        if c is None:
            c = self._found(ev, p, var, t, overlap)
            self.last_reading = (Reading.TOUCH if c.confirmed else Reading.UNKNOWN, c.id)
        else:
            self._member(c, ev, p, var, t, overlap, out)
        self._update_finger(self.now_ns)
        return self.pop_events() + out if self._pending else out

    # ------------------------------------------------------------------ finger state
    def _update_finger(self, t):
        """The finger's state and its start time now; the FingerState record itself is built
        when read (``state``): nothing it depends on changes before the next update."""
        if t is None:
            return
        top, top_key, n_conf = None, None, 0
        for c in self.contacts:
            if c.confirmed and not (c.provisional and c.pending_release_ns is not None):
                n_conf += 1
                key = (int(c.state), c.last_ns)
                if top is None or key > top_key:  # the first of equals, as max() picks
                    top, top_key = c, key
        if top is None:
            if self._fs_state != ContactState.NO_CONTACT:
                self._fs_since = self._last_end_ns
            self._fs_state = ContactState.NO_CONTACT
        else:
            if top.state != self._fs_state:
                self._fs_since = top.since_ns
            self._fs_state = top.state
        self._fs_pending = (top, n_conf, t)
        self._finger = None

    def _finger_state(self) -> FingerState:
        """The FingerState record of the last update (built once)."""
        if self._finger is None:
            top, n_conf, t = self._fs_pending
            if top is None:
                self._finger = FingerState(
                    ContactState.NO_CONTACT, self._fs_since, NAN3.copy(), 0.0, 0, -1, 0, t
                )
            else:
                self._finger = FingerState(
                    top.state,
                    int(self._fs_since),
                    top.centre_at(t).copy(),
                    self._rate(top, t),
                    top.precursor_count,
                    top.id,
                    n_conf,
                    t,
                )
        return self._finger
