# SPDX-License-Identifier: Apache-2.0
"""The demo's truth for the contact state, and the scores of a run against it (no rclpy).

A simulated scene knows what touched the fingertip: its ground-truth emissions (each with
its kind: touch, release, micro-slip, slip, texture; time; point) and, per part, its
gross-slip intervals. `truth_contacts` turns them into the contacts a hand would name and
their states, with one physical reading of each kind:

- a touch begins a contact at its point (a touch within ``SAME_SPOT_M`` of an open
  contact is that contact touching again: a re-touch, not a second object);
- a release ends the nearest open contact within ``CONTACT_RADIUS_M``;
- a micro-slip makes the nearest open contact (within ``CONTACT_RADIUS_M``; else a contact
  of its own) INCIPIENT_SLIP: Cattaneo-Mindlin slip at the edge of a held, loaded contact;
- a part of the scene that names its contact's centre (``contact_center_m``: an object
  held from the part's start, e.g. the incipient-slip scene, whose first emissions are
  micro-slips) begins that contact at the part's start;
- a slip emission makes it GROSS_SLIP (it sticks again ``QUIET_S`` after its last one, as
  a slide that stopped), and so does a gross-slip interval of the scene's truth (the
  contact nearest the part's contact centre, until the interval's end or the scene's);
- texture emissions are a stylus sliding: one moving contact, GROSS_SLIP from its first to
  its last emission (runs ``QUIET_S`` apart are two strokes), then lifted.

The finger's true state is the most severe over its open contacts (NO_CONTACT: none), as
the driver's ContactState. `score_run` compares a run with it: the share of time the
reported state equals the truth (``SETTLE_S`` after each change of the truth excepted),
each SLIP_PRECURSOR / SLIP / TEXTURE true or false (backed by a slip state of the truth
within ``GRACE_S`` before it), SLIP timing against each gross slip, the precursor's lead,
contacts begun and ended against the truth's. The same conventions as the benchmark's
everyday-scene scorer (bench/ae_eval/everyday/score.py), restated here so that the
installed demo needs no evaluation code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ae_tactile.records import ContactState, EventType

NS = 1_000_000_000
#: [m] a touch this close to an open contact is that contact touching again
SAME_SPOT_M = 0.5e-3
#: [m] a release or micro-slip belongs to an open contact this close (about the largest
#: Hertz contact radius of a fingertip's loads, with the localization error)
CONTACT_RADIUS_M = 3e-3
#: [s] a contact that slid sticks again this long after its last slip emission (the
#: driver's own fall-back time, SlipConfig.quiet_s)
QUIET_S = 0.3
#: [s] after each change of the true state, the reported state is not scored (the time a
#: detector needs to see a change through its emissions)
SETTLE_S = 0.1
#: [s] an alarm this long after the truth left a slip state is still backed
GRACE_S = 0.3
#: [s] step of the state comparison
GRID_S = 1e-3
#: [s] an output may precede its emission's true time by the time stamp error
STAMP_S = 1e-6

NO, STICK, INC, GROSS = (int(s) for s in ContactState)


@dataclass
class TruthContact:
    """One contact of the scene's truth: its changes of state [(time ns, ContactState)]
    (NO_CONTACT last when it ended)."""

    contact_id: int
    point_m: tuple
    changes: list = field(default_factory=list)
    last_slip_ns: int | None = None
    moving: bool = False

    @property
    def state(self) -> int:
        return int(self.changes[-1][1]) if self.changes else NO

    def set(self, t_ns: int, state: int) -> None:
        if self.state != state:
            self.changes.append((int(t_ns), int(state)))


def _nearest(contacts, point, radius_m):
    best, best_d = None, radius_m
    for c in contacts:
        d = math.dist(c.point_m, point)
        if d <= best_d:
            best, best_d = c, d
    return best


def truth_contacts(truth_events, scene_truth: dict | None = None, end_ns: int | None = None):
    """The scene's contacts and their states (see the module docstring).

    Parameters
    ----------
    truth_events : iterable of (int, int, tuple)
        Ground-truth emissions as (time ns, EventType of their kind: TOUCH touch, DETOUCH
        release, SLIP_PRECURSOR micro-slip, SLIP slip, TEXTURE texture, point (3,) [m]),
        e.g. the simulated fingertip's ``sim/ground_truth``, captured or not.
    scene_truth : dict, optional
        The scene's truth (``sim/scene_truth``'s "truth": a part or a composite's
        "parts", with ``gross_slip_intervals_ns`` and ``contact_center_m``), same clock.
    end_ns : int, optional
        End of the scene [ns] (open gross slips last until then).

    Returns
    -------
    list of TruthContact
        In order of their beginning.
    """
    events = sorted(((int(t), int(k), tuple(float(v) for v in p)) for t, k, p in truth_events),
                    key=lambda e: e[0])
    intervals = _gross_intervals(scene_truth)
    marks = [(a, "gross_on", c, b) for a, b, c in intervals] + [
        (t, "held", c, None) for t, c in _held_parts(scene_truth)]
    timeline = sorted([(t, "event", k, p) for t, k, p in events] + marks, key=lambda x: x[0])
    all_c: list[TruthContact] = []
    open_c: list[TruthContact] = []
    stroke: TruthContact | None = None
    for t, what, a, b in timeline:
        _quiet(open_c, t)
        if stroke is not None and t - stroke.last_slip_ns > QUIET_S * NS:
            _end(stroke, stroke.last_slip_ns, open_c)
            stroke = None
        if what == "held":
            if _nearest(open_c, a, SAME_SPOT_M) is None:
                _new(all_c, open_c, t, a, STICK)
            continue
        if what == "gross_on":
            c = _nearest(open_c, a, CONTACT_RADIUS_M) or _new(all_c, open_c, t, a, GROSS)
            c.set(t, GROSS)
            c.last_slip_ns = None if b is None else int(b)
            c.moving = b is None  # sliding until the interval's end: never quiet
            continue
        kind, p = a, b
        if kind == EventType.TEXTURE:
            if stroke is None:
                stroke = _new(all_c, open_c, t, p, GROSS)
                stroke.moving = True  # ends at its last emission, never sticks
            stroke.point_m, stroke.last_slip_ns = p, t
            continue
        near = _nearest(open_c, p, CONTACT_RADIUS_M)
        if kind == EventType.TOUCH:
            if _nearest(open_c, p, SAME_SPOT_M) is None:
                _new(all_c, open_c, t, p, STICK)
        elif kind == EventType.DETOUCH:
            if near is not None:
                _end(near, t, open_c)
        elif kind == EventType.SLIP_PRECURSOR:
            c = near or _new(all_c, open_c, t, p, INC)
            if c.state == STICK:
                c.set(t, INC)
        elif kind == EventType.SLIP:
            c = near or _new(all_c, open_c, t, p, GROSS)
            c.set(t, GROSS)
            if not c.moving:
                c.last_slip_ns = t
    if end_ns is not None:
        _quiet(open_c, int(end_ns))
        if stroke is not None and int(end_ns) - stroke.last_slip_ns > QUIET_S * NS:
            _end(stroke, stroke.last_slip_ns, open_c)
    return all_c


def _gross_intervals(scene_truth) -> list:
    """[(start ns, end ns or None, contact centre (3,))] of the scene's gross slips."""
    if not scene_truth:
        return []
    out = []
    for part in scene_truth.get("parts", [scene_truth]):
        centre = tuple(part.get("contact_center_m") or (math.nan,) * 3)
        for a, b in part.get("gross_slip_intervals_ns") or []:
            if a is not None:
                out.append((int(a), None if b is None else int(b), centre))
    return out


def _held_parts(scene_truth) -> list:
    """[(start ns, contact centre (3,))] of the scene's parts that hold an object from
    their start (they name its centre)."""
    if not scene_truth:
        return []
    out = []
    for part in scene_truth.get("parts", [scene_truth]):
        c = part.get("contact_center_m")
        if c is not None and part.get("start_time_ns") is not None:
            out.append((int(part["start_time_ns"]), tuple(float(v) for v in c)))
    return out


def _new(all_c, open_c, t, p, state) -> TruthContact:
    c = TruthContact(len(all_c) + 1, tuple(p))
    c.set(t, state)
    all_c.append(c)
    open_c.append(c)
    return c


def _end(c, t, open_c) -> None:
    c.set(t, NO)
    if c in open_c:
        open_c.remove(c)


def _quiet(open_c, t) -> None:
    """Contacts that slid stick again QUIET_S after their last slip emission."""
    for c in open_c:
        if c.state == GROSS and c.last_slip_ns is not None and not c.moving \
                and t - c.last_slip_ns > QUIET_S * NS:
            c.set(c.last_slip_ns + int(QUIET_S * NS), STICK)


def finger_timeline(contacts) -> list:
    """The finger's true state [(time ns, ContactState value)] from each change on: the
    most severe over the open contacts.

    Parameters
    ----------
    contacts : list of TruthContact
        `truth_contacts`.

    Returns
    -------
    list of (int, int)
        Time-ordered changes (the first: NO_CONTACT at the first contact's beginning).
    """
    marks = sorted({t for c in contacts for t, _ in c.changes})
    out = []
    for t in marks:
        st = max((_state_at_changes(c.changes, t) for c in contacts), default=NO)
        if not out or out[-1][1] != st:
            out.append((int(t), int(st)))
    return out


def _state_at_changes(changes, t) -> int:
    st = NO
    for tc, s in changes:
        if tc > t:
            break
        st = s
    return st


def _state_at(t_arr, s_arr, t):
    i = np.searchsorted(t_arr, t, side="right") - 1
    return np.where(i >= 0, s_arr[np.maximum(i, 0)], NO)


def score_run(truth_events, reported_states, outputs, scene_truth: dict | None = None,
              contact_events=(), end_ns: int | None = None) -> dict:
    """Score a run's contact state and alarms against the scene's truth.

    Parameters
    ----------
    truth_events : iterable of (int, int, tuple)
        Ground-truth emissions (`truth_contacts`).
    reported_states : iterable of (int, int)
        The reported finger state from each time on [(time ns, ContactState value)], e.g.
        ContactState's (state_since, state).
    outputs : iterable of (int, int)
        The run's SLIP_PRECURSOR / SLIP / TEXTURE as (time ns, EventType value).
    scene_truth : dict, optional
        The scene's truth (gross-slip intervals, parts).
    contact_events : iterable of (int, int)
        The run's contact TOUCH / DETOUCH as (time ns, EventType value).
    end_ns : int, optional
        End of the scene [ns]; default: the last truth emission + SETTLE_S.

    Returns
    -------
    dict
        JSON-able: "state_right_share", "state_scored_s", "false_alarms" (count and each
        as [time s from the first truth, kind]), "true_alarms", "gross_slips" (per gross
        slip: SLIP delay [ms], negative when early, its q unknown here; precursor lead
        [ms]), "contacts" (truth begun / ended, TOUCH / DETOUCH received), "truth_timeline"
        and "reported_timeline" (time s from the first truth, state name).
    """
    truth_events = list(truth_events)
    if not truth_events:
        return {}
    t0 = min(int(t) for t, _, _ in truth_events)
    end = int(end_ns) if end_ns is not None else (
        max(int(t) for t, _, _ in truth_events) + int(SETTLE_S * NS))
    contacts = truth_contacts(truth_events, scene_truth, end)
    tl = finger_timeline(contacts)
    tt = np.array([t for t, _ in tl], dtype=np.int64)
    ts = np.array([s for _, s in tl], dtype=int)
    rep = sorted((int(t), int(s)) for t, s in reported_states)
    rt = np.array([t for t, _ in rep], dtype=np.int64)
    rs = np.array([s for _, s in rep], dtype=int)
    grid = np.arange(t0, end, int(GRID_S * NS), dtype=np.int64)
    truth = _state_at(tt, ts, grid)
    got = _state_at(rt, rs, grid) if rt.size else np.full(grid.size, NO)
    mask = np.ones(grid.size, bool)
    for t in tt[1:]:
        mask[(grid >= t) & (grid < t + int(SETTLE_S * NS))] = False
    n = int(mask.sum())
    right = int(np.sum((truth == got) & mask))
    out = {"state_right_share": right / n if n else None, "state_scored_s": n * GRID_S}
    out.update(_alarms(outputs, tt, ts, t0))
    backed = [(int(t), int(k)) for t, k in outputs if _backed(int(t), int(k), tt, ts)]
    out["gross_slips"] = _gross(outputs, backed, scene_truth)
    ce = [(int(t), int(k)) for t, k in contact_events]
    out["contacts"] = {
        "truth_begun": len(contacts),
        "truth_ended": sum(1 for c in contacts if c.state == NO),
        "touch_events": sum(1 for _, k in ce if k == EventType.TOUCH),
        "detouch_events": sum(1 for _, k in ce if k == EventType.DETOUCH),
    }
    names = {int(s): s.name for s in ContactState}
    out["truth_timeline"] = [((t - t0) / NS, names[s]) for t, s in tl]
    out["reported_timeline"] = [((t - t0) / NS, names.get(s, str(s))) for t, s in rep]
    out["t0_ns"] = t0
    return out


def _backed(t: int, k: int, tt, ts) -> bool:
    """An output at ``t`` [ns] of kind ``k`` is backed by the truth: a precursor by a slip
    state (INCIPIENT_SLIP or GROSS_SLIP), a SLIP / TEXTURE by GROSS_SLIP, within GRACE_S
    before it (STAMP_S after)."""
    lo = np.searchsorted(tt, t - int(GRACE_S * NS), side="right") - 1
    hi = np.searchsorted(tt, t + int(STAMP_S * NS), side="right")
    worst = int(ts[max(lo, 0):max(hi, lo + 1)].max()) if tt.size and hi > 0 else NO
    return worst >= INC if k == EventType.SLIP_PRECURSOR else worst == GROSS


def _alarms(outputs, tt, ts, t0) -> dict:
    """Each SLIP_PRECURSOR / SLIP / TEXTURE backed by the truth or not."""
    false, true = [], 0
    for t, k in outputs:
        t, k = int(t), int(k)
        if _backed(t, k, tt, ts):
            true += 1
        else:
            false.append([(t - t0) / NS, EventType(k).name])
    return {"false_alarms": len(false), "false_alarm_list": false, "true_alarms": true}


def _gross(outputs, backed, scene_truth) -> list:
    """Per gross slip of the scene: the first SLIP's delay after it [ms] (negative: early,
    any SLIP from its part's start on) and the lead before it [ms] of the first precursor
    the truth backs (``backed``: the outputs that are), from its part's start."""
    out = []
    if not scene_truth:
        return out
    for part in scene_truth.get("parts", [scene_truth]):
        g = part.get("gross_slip_time_ns")
        if g is None:
            continue
        start = int(part.get("start_time_ns", 0) or 0)
        slips = [int(t) for t, k in outputs if k == EventType.SLIP and int(t) >= start]
        pre = [t for t, k in backed if k == EventType.SLIP_PRECURSOR and start <= t < int(g)]
        out.append({
            "part": part.get("name", ""),
            "slip_delay_ms": (min(slips) - int(g)) / 1e6 if slips else None,
            "precursor_lead_ms": (int(g) - min(pre)) / 1e6 if pre else None,
        })
    return out
