# SPDX-License-Identifier: Apache-2.0
"""What happens at a fingertip, as the slip detector reads it: objects arrive (at one point,
at several points within milliseconds, or as a broad press), are held (silent), are loaded
(Cattaneo-Mindlin micro-slips inside their disc), slide (from the start or after a load),
are lifted or released. Each emission gets the reading that explains it:

* **touch** -- a compression while its object arrives: within `ARRIVAL_WINDOW_S` of the
  object's first emission, before any rarefaction, within association_radius_m of its
  points (a point of a multi-point object or of a broad press); a compression outside
  every held contact's patch (`PATCH_FRACTION` of association_radius_m round its touch)
  founds a contact of its own (a second object, a tap beside);
* **release** -- a rarefaction on a touch's spot (a touch and its release), or, on a
  silent held contact, anywhere on its disc (a broad object leaves where it pleases);
  further rarefactions within `RELEASE_WINDOW_S` are the same release; the contact reads
  released at once and ends when nothing follows (a micro-slip that follows shows the
  "release" was the load's first micro-slip: the contact goes on, its evidence counted);
* **slide** -- the unexplained emissions (neither touch nor release) of an object still
  arriving (no silence of `HOLD_GAP_S` since its first emission): there is no held patch to
  load, so two of them are SLIP at once (the slide's 3rd emission; see
  ``ae_eval.everyday.bounds``), never a precursor;
* **micro-slip** -- an unexplained emission inside the disc of a held contact (after a
  silence): the evidence of SLIP_PRECURSOR and the gross-slip test (`evidence`, `gross`);
* **lift** -- a sliding contact silent for `lift_quiet_s` (a few of its own intervals) is
  lifted: it reads NO_CONTACT; an emission on its disc before it ends (``quiet_s``) shows
  the slide went on; one soon after (within twice the lift quiet) founds a contact that is
  either the slide going on (emissions over the disc) or the object re-stuck and loaded
  (micro-slips on one ring): the slide decision reads which, as for an arriving object;
  one later (within ``evidence_window_s``) founds a held contact.

The constants below are the model's physical parameters (SI units)."""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.records import ContactState

from .contact import ARRIVAL, EVID, PAIRED, REPEAT
from .fits import circle_centre
from .gross import FOUNDER_SILENCE_RATIO

#: largest radius of one contact patch as a share of association_radius_m (5 mm: 2 mm):
#: micro-slips of a held contact fall within it of the touch that announced it, a
#: compression farther from every held contact is a new contact; a contact nobody
#: announced (its first emission on its ring) reaches the whole association_radius_m.
#: 0.5 (the largest Hertz contact, a_H = 2.5 mm) lets touches 2-2.5 mm beside a held one
#: in as micro-slips (docs/slip.md)
PATCH_FRACTION = 0.4
#: [s] longest spread of one object's arrival (multi-point touches 0.2-5 ms, broad presses
#: 1-10 ms, up to 20 ms held out)
ARRIVAL_WINDOW_S = 20e-3
#: [s] longest spread of one object's release
RELEASE_WINDOW_S = 20e-3
#: [s] a contact silent this long after its last emission is held (no longer arriving): a
#: grasp is held >= 50 ms before it is loaded, a slide's emissions come at >= 20 Hz
HOLD_GAP_S = 0.1
#: [s] a release off the touches' spots (or while slipping) ends its contact when nothing
#: follows for this long (a load's micro-slips follow within it; the NO_CONTACT target is
#: 0.2 s after a release)
RELEASE_WAIT_S = 0.15
#: largest relative spread (beyond 4 localization sigmas) of the distances of a load's
#: first micro-slips from its centre: its stick front at first is a thin ring (c = a (1 -
#: q)^(1/3) >= 0.97 a up to q = 0.1); wider, more slides pass for loads (the trade-off in
#: docs/slip.md)
RING_SPREAD = 0.03
#: localization sigmas (of a difference of two distances) the ring's spread may exceed
RING_SIGMAS = 2.5
#: a ring fitted to 5 or more emissions (no touch announced its centre): the largest
#: relative spread of a load (its annulus c(q) < r < a_H: c >= 0.79 a_H up to q = 0.5)
RING_SPREAD_FIT = 0.1
#: a ring fitted to 4 emissions (one beyond the circle's three parameters, so a slide's
#: 4 points often lie near some circle and a load's annulus off it): wider than this is
#: a slide at once, else the 5th emission decides
RING_SPREAD_SLIDE = 0.2
#: lift: a sliding contact silent for this many of its mean intervals ...
LIFT_INTERVALS = 5.0
#: [s] ... but at least this long and at most this long (the NO_CONTACT target is 0.2 s
#: after a lift; a 20 Hz Poisson slide has a gap of 0.15 s in 5 % of its intervals)
LIFT_QUIET_MIN_S, LIFT_QUIET_MAX_S = 0.05, 0.15
#: [ln units] spread of the strength of one kind of emission (object, speed, depth)
AMP_SPREAD_LN = 0.5
#: standard errors by which the finger's touches must be the louder (their mean ln
#: amplitude above its micro-slips') before amplitude tells one from the other
SCALE_SIGMAS = 2.0
#: share of emissions the localizer loses (missed triggers, rejected fits): the prior
#: probability that a held contact's release went unseen
P_LOST = 0.02
#: [ln units] a compression on a silent held contact is a new object's touch (the held
#: one's release lost) only when its amplitude says so by more than the prior odds
#: against a lost release, ln((1 - P_LOST) / P_LOST)
LOST_RELEASE_LLR = math.log((1.0 - P_LOST) / P_LOST)
#: weight of the finger's earlier touches (micro-slips) at each new one: its scales
#: remember ~10 of each
SCALE_DECAY = 0.9


def amp_ln(ev):
    """ln |amplitude_v / 1 V| of an emission, or None when it carries none."""
    a = abs(ev.amplitude_v)
    return math.log(a) if a > 0.0 and math.isfinite(a) else None


def touch_llr(x, mu_touch, mu_micro, n_touch=math.inf, n_micro=math.inf):
    """Log-likelihood ratio of an emission of ln-amplitude ``x`` being a new object's touch
    (drawn round ``mu_touch``, the mean ln-amplitude of ``n_touch`` touches of the finger)
    against being the next micro-slip of a held contact (round ``mu_micro``, of
    ``n_micro`` micro-slips); Gaussian in ln amplitude with AMP_SPREAD_LN for either.
    0 (no evidence) when one is unknown (None) or the touches are not the louder by
    SCALE_SIGMAS standard errors of the two means (scales alike, or not yet told apart).

    A source's strength is rho v^2 / a_c (the paper's eq. 11), v the speed at which the
    surface moves: a touch moves at the object's approach speed, a micro-slip at the local
    slip speed of an annulus element of a contact already formed. How the two compare is
    learnt, not assumed. The sensor sits at the centre of the spherical tip, every surface
    point at the same distance R from it, and the device's gain is common to both, so the
    two scales compare without any absolute amplitude."""
    if x is None or mu_touch is None or mu_micro is None:
        return 0.0
    d = mu_touch - mu_micro
    if d <= SCALE_SIGMAS * AMP_SPREAD_LN * math.sqrt(1.0 / n_touch + 1.0 / n_micro):
        return 0.0
    return d * (x - 0.5 * (mu_touch + mu_micro)) / (2.0 * AMP_SPREAD_LN**2)


class ContactModel:
    """The readings of an emission of a contact that is arriving, held or released, the
    slide-from-the-start decision and the lift of a sliding contact.

    Methods of `SlipDetector` (`ae_tactile.slip.detector`), which holds the state they
    use: ``config``, ``counts``, ``contacts`` and the windows in ns set by ``_apply``.
    """

    def _model_apply(self):
        """Windows of the model in integer ns, the patch gate squared [m^2] (from the
        configuration's association_radius_m)."""
        self._w_arrive = int(round(ARRIVAL_WINDOW_S * 1e9))
        self._w_release = int(round(RELEASE_WINDOW_S * 1e9))
        self._hold_gap = int(round(HOLD_GAP_S * 1e9))
        self._patch2 = (PATCH_FRACTION * self.config.association_radius_m) ** 2
        self._rel_wait = int(round(RELEASE_WAIT_S * 1e9))
        #: [ns] no lift is possible sooner (`_lift_quiet_ns` >= it): skips its work
        self._lift_min = int(LIFT_QUIET_MIN_S * 1e9)

    def _note_amplitude(self, c, x, touch):
        """An emission of ln-amplitude ``x`` (or None) of contact ``c``, a touch or a
        micro-slip (``touch`` False): the contact's scale and the finger's (a decayed mean
        over its recent ones, the device's gain in it)."""
        if x is None:
            return
        own, fin = (c.touch_ln, self._touch_scale) if touch else (c.micro_ln, self._micro_scale)
        own[0] += x
        own[1] += 1
        fin[0] = SCALE_DECAY * fin[0] + x
        fin[1] = SCALE_DECAY * fin[1] + 1.0

    def _touch_llr(self, c, x):
        """`touch_llr` of a compression (ln-amplitude ``x``) on held contact ``c``: a new
        object's touch round the finger's touches (the contact's own before the finger
        has one), its micro-slip round its own micro-slips when two or more came, else
        round the finger's once it has two."""
        ft, fm = self._touch_scale, self._micro_scale
        st, nt = c.touch_ln
        if ft[1] >= 1.0:
            mu_t, n_t = ft[0] / ft[1], ft[1]
        else:
            mu_t, n_t = (st / nt, nt) if nt else (None, 1)
        sm, nm = c.micro_ln
        if nm >= 2:
            mu_m, n_m = sm / nm, nm
        else:
            mu_m, n_m = (fm[0] / fm[1], fm[1]) if fm[1] >= 2.0 else (None, 1)
        return touch_llr(x, mu_t, mu_m, n_t, n_m)

    def _arrival_flags(self, c, ev, t):
        """Flags of an emission of a held (not slipping) contact that the arrival or the
        release of its object explains, or None: ARRIVAL for a touch of the arriving
        object, REPEAT for a rarefaction of a release under way."""
        if c.arriving and t - c.last_ns > self._hold_gap:
            c.arriving = False
        if ev.polarity < 0:
            c.saw_rarefaction = True
            if c.pending_release_ns is not None and t - c.pending_release_ns <= self._w_release:
                self.counts["release_burst"] = self.counts.get("release_burst", 0) + 1
                return REPEAT
            return None
        if (
            ev.polarity > 0
            and c.arriving
            and not c.saw_rarefaction
            and t - c.founder_ns <= self._w_arrive
        ):
            return ARRIVAL
        return None

    def _silent(self, c, t):
        """No micro-slip evidence of the contact within evidence_window_s before ``t``."""
        k = c.valid()
        m = ((c.flags[:k] & EVID) != 0) & (c.t[:k] > t - self._w_ev)
        return int(m.sum()) == 0

    def _provisional_release(self, c, ev, t):
        """A rarefaction on the disc of a silent held contact: read as its release (the
        contact reads released; it ends after quiet_s unless an emission follows)."""
        if ev.polarity < 0 and not c.arriving and c.state == ContactState.STICK:
            if c.pending_release_ns is None and self._silent(c, t):
                c.pending_release_ns, c.pending_in_slip = t, True
                c.provisional = True
                c.pending_release_spot = (ev.point_m.copy(), 0.0)
                self.counts["releases"] += 1
                return True
        return False

    def _slide_decision(self, c, ev, t, out):
        """Slide or load, for an arriving object's unexplained emissions: on one ring (the
        stick front of a load, round the touch that announced it or fitted) they are
        micro-slips (the contact is held and loaded: the precursor decides); spread over
        a disc they are a slide from the start: SLIP at once. Round an announcing touch:
        decided at the 3rd unexplained emission (the 4th of the object), at the 2nd when
        they are clearly off one ring. A fitted ring (no touch announced it) has one
        emission beyond the circle's three parameters at the 4th: only a clear slide
        (`RING_SPREAD_SLIDE`) is decided there, the rest from the 5th on
        (`RING_SPREAD_FIT`)."""
        if c.state == ContactState.GROSS_SLIP:
            return
        k = c.valid()
        F = c.flags[:k]
        free = (F & PAIRED) == 0
        n = int((((F & (EVID | ARRIVAL)) != 0) & free).sum())  # arrival touches too
        if n < 2:
            return
        ring, fitted = self._ring_spread(c, k, F, free)
        if ring is None or (n == 2 and ring <= 2.0 * RING_SPREAD):
            return  # not decided yet
        if fitted and int(free.sum()) <= 4 and ring <= RING_SPREAD_SLIDE:
            return  # a 4-point fit: wait for the 5th emission
        c.resumed = False  # decided: a load or a slide
        if ring <= (RING_SPREAD_FIT if fitted else RING_SPREAD):
            c.arriving = False  # a held contact being loaded: its micro-slips
            self._precursor_decision(c, ev, ev.point_m, t, out)
            return
        c.state, c.since_ns = ContactState.GROSS_SLIP, t
        c.slid = True
        out.append(self._slip_event(c, ev, 7, onset=True))

    def _ring_spread(self, c, k, F, free):
        """(relative spread, fitted) of the ring the contact's unpaired emissions lie on:
        (max - min) / mean of their distances, less RING_SIGMAS localization sigmas, from
        the touch that announced it (a compression followed by a pause of more than
        ARRIVAL_WINDOW_S: its centre) or, unless that pause is much longer than the
        intervals after it (`gross.FOUNDER_SILENCE_RATIO`: surely a touch) and when they
        are not on a ring round it (the "touch" may be the load's first micro-slip), from
        the circle fitted to them (4 or more; ``fitted``); the thinner ring is taken. The
        spread None: not enough emissions to tell, or all on a short arc (any ring passes
        through them)."""
        P = c.p[:k][free]
        sig = RING_SIGMAS * math.sqrt(2.0 * float(c.var[:k][free].max()))
        fp, _, fpol = c.founder
        ann = None
        if fpol > 0 and len(P) > 2 and not c.resumed:
            T = np.sort(c.t[:k][free])
            if T[1] - c.founder_ns > self._w_arrive:
                # the pause after it much longer than the intervals after it: surely a
                # touch (the same test as the activity's onset, `gross`), else maybe the
                # load's first micro-slip
                nx = T[2:6]
                sure = T[1] - T[0] > FOUNDER_SILENCE_RATIO * float(nx[-1] - T[1]) / len(nx)
                D = P - fp
                d = np.sqrt(np.einsum("ij,ij->i", D, D))
                d = d[d > sig]  # the touch itself
                ann = self._spread(d, sig) if len(d) >= 2 else None
                if ann is not None and (ann <= RING_SPREAD or sure):
                    return ann, False
        if len(P) < 4:
            return None, True
        centre = circle_centre(P)
        if centre is None:
            # on a line: a stylus or a drag passes along it in time order (no ring); a
            # load's micro-slips on a short arc of its ring come in any order: not decided
            return (math.inf if self._in_line_order(c, k, free, P) else None), True
        D = P - centre
        fit = self._spread(np.sqrt(np.einsum("ij,ij->i", D, D)), sig)
        if ann is not None and ann < fit:
            return ann, False
        return fit, True

    @staticmethod
    def _in_line_order(c, k, free, P):
        """Do the points ``P`` (the contact's unpaired emissions) follow each other along
        the line from the first to the last in time order?"""
        order = np.argsort(c.t[:k][free], kind="stable")
        Q = P[order]
        x = (Q - Q[0]) @ (Q[-1] - Q[0])
        dx = np.diff(x)
        return bool((dx > 0).all())

    @staticmethod
    def _spread(d, sig):
        """Relative spread (max - min - ``sig``) / mean of distances ``d`` [m] (0 at
        least; inf for a zero mean)."""
        mean = float(d.mean())
        return max(float(d.max() - d.min()) - sig, 0.0) / mean if mean > 0 else math.inf

    def _lift_quiet_ns(self, c):
        """How long a sliding contact may stay silent before it reads lifted [ns]: a few
        of its mean intervals over the latest member_history emissions."""
        k = c.valid()
        if k >= 3:
            tl = c.tlist[:k] if k < c.H else c.tlist  # [ns] Python ints: no array per call
            iv = float(max(tl) - min(tl)) / (k - 1) * 1e-9
        else:
            iv = LIFT_QUIET_MAX_S / LIFT_INTERVALS
        q = min(max(LIFT_INTERVALS * iv, LIFT_QUIET_MIN_S), LIFT_QUIET_MAX_S)
        return int(q * 1e9)

    def _near_lifted(self, p, t):
        """The (end time ns, centre, lift quiet ns or 0) of a contact lifted after a slide
        or released off its touches within evidence_window_s before ``t``, within
        the patch radius of ``p`` (a slide going on, a re-stuck object, a load's micro-slips
        after its first), or None. (Prunes the list.)"""
        lst = self._lifted
        if not lst:
            return None
        lst[:] = [a for a in lst if t - a[0] <= self._w_ev]
        for a in reversed(lst):
            d = a[1] - p
            if float(d @ d) <= self._patch2:
                return a
        return None

    def _resume(self, c, lifted, t):
        """A contact founded on the disc of a contact that ended: not an arriving object.
        Within twice its lift quiet of a lifted slide it is either the slide going on
        (emissions over the disc) or the object re-stuck and loaded (micro-slips on the
        stick front's ring): the slide decision reads which (`_slide_decision`, a ring
        fitted to its emissions: its first one is no touch announcing a centre)."""
        c.arriving = False
        if lifted[2] and t - lifted[0] <= 2 * lifted[2]:
            c.arriving, c.resumed = True, True


def lift_bound(rate_hz, quiet_s, intervals):
    """P(a Poisson slide at ``rate_hz`` shows no gap of ``quiet_s`` [s] in ``intervals``
    intervals): how often a slide is not taken for lifted before it ends."""
    return (1.0 - math.exp(-rate_hz * quiet_s)) ** intervals
