# SPDX-License-Identifier: Apache-2.0
"""One tracked contact of the slip detector: ring buffers of its emissions (time, point,
variance, polarity, packet id, member flags) and its state (founder, pending release,
fitted centre and radius, motion track, texture run)."""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.records import ContactState

# member flags; FOUNDER: the emission that founded the contact; EVID: micro-slip evidence
# (on no other emission's spot); PAIRED: a touch / release pair; REPEAT: on an earlier
# emission's spot; OVERLAP: may share a trigger window with another emission;
# SLIP_EMISSION: came while the contact slipped or moved; TOUCHED: a compression that came
# during touch-release activity (a touch, for as long as it counts); ARRIVAL: a touch of
# the arriving object (a point of a multi-point object or of a broad press)
FOUNDER, EVID, PAIRED, REPEAT, OVERLAP, SLIP_EMISSION, TOUCHED = 1, 2, 4, 8, 16, 32, 64
ARRIVAL = 128
TOUCH_POINT = FOUNDER | ARRIVAL
TRACKED = EVID | REPEAT
SLIPPING = (ContactState.INCIPIENT_SLIP, ContactState.GROSS_SLIP)
#: (3,) of NaN: an unknown point or direction (copied before it is handed out)
NAN3 = np.full(3, np.nan)


class Contact:
    """One tracked contact: ring buffers of its emissions and its state.

    Parameters
    ----------
    cid : int
        Tracker id.
    t_ns : int
        Time of the founding emission [ns].
    history : int
        Emissions kept (ring buffer length, member_history).
    confirmed : bool
        Confirmed (a touch founded it, or a second emission joined).
    """

    def __init__(self, cid, t_ns, history, confirmed):
        H = history
        self.id = cid
        self.H = H
        self.t = np.zeros(H, np.int64)
        self.p = np.zeros((H, 3))
        self.var = np.zeros(H)  # per-axis position variance (m^2)
        self.pol = np.zeros(H, np.int8)
        self.pid = np.zeros(H, np.int64)
        self.flags = np.zeros(H, np.uint8)
        self.tlist = [0] * H  # self.t as Python ints (cheap per-element reads)
        self.flist = [0] * H  # self.flags as Python ints
        self.n_fit_members = 0  # valid members with EVID set and OVERLAP clear
        # the box holding every compression the contact ever had (m, grown only) and their
        # largest per-axis variance: a cheap test for a far release's touch
        self.touch_box = [math.inf, math.inf, math.inf, -math.inf, -math.inf, -math.inf]
        self.touch_var = 0.0
        self.n = 0
        self.state = ContactState.STICK
        self.since_ns = t_ns
        self.created_ns = t_ns
        self.last_ns = t_ns
        self.confirmed = confirmed
        self.pending_release_ns = None
        self.pending_in_slip = False  # a release-like emission while slipping
        self.pending_release_spot = None  # (point, variance) of the founder's release
        self.touch_release_ns = None  # latest touch-release pair
        self.touch_release_open = False  # no compression came since it (the next is a touch)
        self.founder = None  # (point, variance, polarity) of the founder
        self.founder_ns = t_ns  # its time
        self.founder_n = 0  # its index among the contact's emissions (c.n when added)
        self.founder_paired = False  # an emission paired with the founder (its release)
        self.last_p = None  # latest emission's point
        self.precursor_count = 0
        self.last_report = {}
        self.texture_on = False
        self.texture_run = 0
        self._centre = None
        self.centre_xyz = None  # self.centre as a tuple of floats (association)
        self.fitted = False  # centre from a circle fit to micro-slips
        self.radius = 0.0
        self.n_evid_fit = -1  # evidence count at the last circle fit
        self.rings = []  # (time ns, centre, radius) of the latest circle fits
        self.moving = False
        self.vel = np.zeros(3)
        self.track_t = 0.0  # reference time (s) of the motion fit
        self.track_c = None  # centre at track_t
        self.track_se = math.inf  # standard error of the speed (m/s)
        self.events_since_track = 0
        self.rate_key = None
        self.rate_val = 0.0
        self.arriving = True  # no silence of HOLD_GAP_S since its first emission
        self.saw_rarefaction = False  # a rarefaction came (the arrival is over)
        self.slid = False  # it slid (a lift of it may be a re-stick)
        self.resumed = False  # founded soon after a slide's lift: slide or re-stick
        self.release_gap_ns = 0  # [ns] silence before its pending release (`model`)
        self.release_iv_ns = 0.0  # [ns] mean of its latest intervals before it
        self.provisional = False  # its pending release is off its touches (`model`)
        # sums and counts of ln |amplitude / V| of its touches and of its micro-slips
        # (`model.touch_llr`: a new object's touch against its next micro-slip)
        self.touch_ln = [0.0, 0]
        self.micro_ln = [0.0, 0]

    @property
    def centre(self):
        """Centre (3,) of a fixed contact (m); ``centre_xyz`` holds the same as floats."""
        return self._centre

    @centre.setter
    def centre(self, value):
        self._centre = value
        self.centre_xyz = (
            None if value is None else (float(value[0]), float(value[1]), float(value[2]))
        )

    # -------------------------------------------------------------- buffers
    def add(self, t, p, var, pol, pid, flags):
        """Store an emission (time [ns], point (3,) [m], per-axis variance [m^2], polarity,
        packet id, member flags) in the next slot, overwriting the oldest once full;
        returns the slot."""
        i = self.n % self.H
        if self.n >= self.H and (int(self.flags[i]) & (EVID | OVERLAP)) == EVID:
            self.n_fit_members -= 1  # the overwritten slot leaves the fit set
        if (flags & (EVID | OVERLAP)) == EVID:
            self.n_fit_members += 1
        self.tlist[i] = int(t)
        self.flist[i] = flags
        self.t[i] = t
        self.p[i] = p
        self.var[i] = var
        self.pol[i] = pol
        self.pid[i] = pid
        self.flags[i] = flags
        self.n += 1
        if pol > 0:
            b = self.touch_box
            x, y, z = float(p[0]), float(p[1]), float(p[2])
            if x < b[0]:
                b[0] = x
            if x > b[3]:
                b[3] = x
            if y < b[1]:
                b[1] = y
            if y > b[4]:
                b[4] = y
            if z < b[2]:
                b[2] = z
            if z > b[5]:
                b[5] = z
            if var > self.touch_var:
                self.touch_var = float(var)
        if t >= self.last_ns:
            self.last_ns = t
            self.last_p = (float(p[0]), float(p[1]), float(p[2]))
        return i

    def valid(self):
        """Number of valid slots (the first ``k`` slots)."""
        return self.n if self.n < self.H else self.H

    def centre_at(self, t_ns):
        """Centre (3,) [m] at ``t_ns``: predicted along the track of a moving contact."""
        if self.moving and self.track_c is not None:
            return self.track_c + self.vel * (t_ns * 1e-9 - self.track_t)
        return self.centre
