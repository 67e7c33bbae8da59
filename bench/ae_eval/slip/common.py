# SPDX-License-Identifier: Apache-2.0
"""What the slip trial families share: the time unit, randomised draws of scene
parameters, emission processes with extra emissions, and the reading of the detector's
outputs (first onset, state at a time, false-alarm counts)."""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.records import ContactState, EventType
from ae_tactile.sim.stream import EmissionList

#: nanoseconds per second
NS = 1_000_000_000
#: the 'events' pipeline's share of emissions lost at random (packets the localizer
#: rejects), strong ones included
EVENTS_DROP = 0.02
SLIP_KINDS = (EventType.SLIP_PRECURSOR, EventType.SLIP, EventType.TEXTURE)


def draw(rng, spec):
    """One value of a (lo, hi, 'log' | 'uniform') range: log-uniform or uniform."""
    lo, hi, kind = spec
    return (
        float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
        if kind == "log"
        else float(rng.uniform(lo, hi))
    )


def cap_point_xy(rng, radius_m, max_polar_deg):
    """(x, y) [m] of a point uniform by area over the cap of polar angle <= max_polar_deg
    of a sphere of radius_m."""
    cmin = math.cos(math.radians(max_polar_deg))
    th = math.acos(rng.uniform(cmin, 1.0))
    ph = rng.uniform(0.0, 2.0 * math.pi)
    return radius_m * math.sin(th) * math.cos(ph), radius_m * math.sin(th) * math.sin(ph)


def cap_xy(rng, r_max=6e-3):
    """(x, y) [m] uniform over the disc of radius r_max [m]."""
    r = r_max * math.sqrt(rng.uniform())
    th = rng.uniform(0, 2 * math.pi)
    return r * math.cos(th), r * math.sin(th)


class WithTouch:
    """An emission process plus fixed extra emissions (a touch announcing the contact)."""

    def __init__(self, process, extra: EmissionList):
        self.process = process
        self.extra = extra.sorted()
        self._h = None

    def advance(self, t_ns):
        lo = np.iinfo(np.int64).min if self._h is None else self._h
        if self._h is not None and t_ns <= self._h:
            return EmissionList.empty()
        self._h = int(t_ns)
        return EmissionList.concat(
            [self.extra.between(lo, t_ns), self.process.advance(t_ns)]
        ).sorted()

    def scene_truth(self):
        return self.process.scene_truth()


class NoEmissions:
    """An emission process that emits nothing (hand-built emission lists go beside it)."""

    def advance(self, t_ns):
        return EmissionList.empty()

    def scene_truth(self):
        return {}


def n_before(events, t_ns):
    """Localized events before t_ns (all if None): the micro-slips the detector saw."""
    return sum(1 for e in events if t_ns is None or e.time_ns < t_ns)


def first_output(outs, kind, onset=True):
    """The first output of ``kind`` (an onset one unless ``onset`` is False), or None."""
    for o in outs:
        if o.kind == kind and (o.onset or not onset):
            return o
    return None


def alarm_summary(outs):
    """Counts of slip outputs by kind and of alarm onsets (any false alarm)."""
    return {
        "n_precursor": sum(o.kind == EventType.SLIP_PRECURSOR for o in outs),
        "n_slip": sum(o.kind == EventType.SLIP for o in outs),
        "n_texture": sum(o.kind == EventType.TEXTURE for o in outs),
        "n_alarm_onsets": sum(o.onset for o in outs if o.kind in SLIP_KINDS),
    }


def state_at(trace, t):
    """The latched state of a state trace [(time ns, ContactState)] at time t [ns]."""
    s = ContactState.NO_CONTACT
    for tt, st in trace:
        if tt <= t:
            s = st
    return s
