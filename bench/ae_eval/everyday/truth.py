# SPDX-License-Identifier: Apache-2.0
"""The ground truth of an everyday scene and its emissions in the 'events' model.

A scene is built by a family generator through `SceneBuilder`: emissions (time, point on
the cap given as tangent-plane x, y, polarity, relative amplitude, kind, contact id), the
contacts (id, object id, point, on / off times), each contact's state changes, and the
episodes a scorer needs (loads with q(t) and the time of gross slip, slides from the start,
textured strokes). `to_events` turns the emissions into ``LocalizedEvent`` s with the
localizer's error model (as ``ae_eval.slip.emission_events`` does, plus an amplitude):
packet_id = the emission's index in the truth, so a scorer can read what each event was.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.records import ContactState
from ae_tactile.slip import LocalizedEvent

NO, STICK, INC, GROSS = (
    ContactState.NO_CONTACT,
    ContactState.STICK,
    ContactState.INCIPIENT_SLIP,
    ContactState.GROSS_SLIP,
)
KINDS = ("touch", "release", "micro_slip", "slip", "texture")
#: relative first-lobe amplitude of each kind (median; lognormal spread `AMP_SPREAD`)
KIND_AMP = {"touch": 1.0, "release": 0.5, "micro_slip": 0.2, "slip": 0.3, "texture": 0.3}
AMP_SPREAD = 0.5  # [ln units] sd of the amplitude of one kind (object, speed, depth)
#: held-out scenes: a micro-slip's median amplitude relative to a touch's, drawn per scene
#: log-uniform in this range (nominal: KIND_AMP's 0.2): slip speed against approach speed
#: differs by object and material, so a reading that relies on the ratio is tested on others
HELD_OUT_MICRO_RATIO = (0.1, 1.0)
GEOMETRY = FingertipGeometry()


def draw(rng, lo, hi, log=False):
    """A value uniform (log-uniform when ``log``) in [lo, hi]."""
    if log:
        return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
    return float(rng.uniform(lo, hi))


def cap_xy(rng, r_max_m=5e-3):
    """(x, y) [m] uniform over the disc of radius r_max_m round the apex."""
    r = r_max_m * math.sqrt(rng.uniform())
    th = rng.uniform(0.0, 2.0 * math.pi)
    return r * math.cos(th), r * math.sin(th)


def around_xy(cx, cy, r_m, heading_rad, geometry=GEOMETRY):
    """(n, 2) [m] the points ``r_m`` [m] along the skin (great circles) from the surface
    point above (cx, cy), leaving it at ``heading_rad`` (0: towards +x, pi/2: towards +y,
    in its tangent plane), as in-plane (x, y). A disc or ring round a contact is then
    round on the skin: drawn in the x-y plane it would be an ellipse stretched 1 / cos
    (polar angle) along the meridian (15 % at 5 mm off the apex of a 10 mm sphere)."""
    r = np.atleast_1d(np.asarray(r_m, dtype=float))
    h = np.atleast_1d(np.asarray(heading_rad, dtype=float))
    R = geometry.radius_m
    n = geometry.surface_point_from_xy(cx, cy) / R
    e1 = np.array([1.0, 0.0, 0.0]) - n[0] * n        # +x in the tangent plane
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)                              # +y (right-handed about the normal)
    u = np.cos(h)[:, None] * e1 + np.sin(h)[:, None] * e2
    phi = (r / R)[:, None]
    p = R * (np.cos(phi) * n + np.sin(phi) * u)
    return p[:, :2]


def skin_distance_m(p, q, geometry=GEOMETRY) -> float:
    """The distance [m] along the skin between the surface points above in-plane p and q."""
    a, b = geometry.surface_point_from_xy(*p), geometry.surface_point_from_xy(*q)
    R = geometry.radius_m
    return float(R * math.acos(min(1.0, max(-1.0, float(a @ b) / (R * R)))))


def disc_xy(rng, cx, cy, r_lo, r_hi, n):
    """(n, 2) [m] points uniform by area in the annulus r_lo <= r <= r_hi [m] (along the
    skin) round the surface point above (cx, cy)."""
    r = np.sqrt(rng.uniform(r_lo**2, r_hi**2, n))
    th = rng.uniform(0.0, 2.0 * math.pi, n)
    return around_xy(cx, cy, r, th)


@dataclass
class Scene:
    """One trial's truth: emissions, contacts, state changes, episodes, duration [s]."""

    family: str
    seed: int
    held_out: bool
    params: dict
    t_s: np.ndarray
    xy_m: np.ndarray
    polarity: np.ndarray
    amplitude: np.ndarray
    kind: np.ndarray
    contact: np.ndarray
    contacts: list
    changes: list
    episodes: list
    duration_s: float

    def finger_timeline(self):
        """[(t [s], ContactState)] of the finger: the most severe state over its contacts
        (NO_CONTACT with none), one entry per change."""
        cur, out = {}, [(0.0, NO)]
        for t, cid, st in sorted(self.changes, key=lambda c: c[0]):
            if st == NO:
                cur.pop(cid, None)
            else:
                cur[cid] = st
            s = max(cur.values(), default=NO)
            if s != out[-1][1]:
                if out[-1][0] == t:
                    out[-1] = (t, s)
                else:
                    out.append((t, s))
        return out

    def kind_names(self):
        return [KINDS[k] for k in self.kind]


@dataclass
class SceneBuilder:
    """Collects a scene's emissions, contacts, state changes and episodes."""

    family: str
    seed: int
    held_out: bool
    rng: np.random.Generator
    params: dict = field(default_factory=dict)
    rows: list = field(default_factory=list)
    contacts: list = field(default_factory=list)
    changes: list = field(default_factory=list)
    episodes: list = field(default_factory=list)
    micro_ratio: float = KIND_AMP["micro_slip"]

    def __post_init__(self):
        if self.held_out:  # own stream: the scene's other draws stay as they were
            self.micro_ratio = draw(np.random.default_rng([49001, int(self.seed)]),
                                    *HELD_OUT_MICRO_RATIO, log=True)

    def emit(self, t_s, x, y, pol, kind, cid):
        """One emission at t_s [s], (x, y) [m], polarity +-1, kind (a name of KINDS)."""
        median = self.micro_ratio if kind == "micro_slip" else KIND_AMP[kind]
        amp = median * math.exp(self.rng.normal(0.0, AMP_SPREAD))
        self.rows.append((float(t_s), float(x), float(y), int(pol), amp, KINDS.index(kind),
                          int(cid)))

    def emit_many(self, t_s, xy, pol, kind, cid):
        for t, (x, y), p in zip(t_s, xy, np.broadcast_to(pol, len(t_s))):
            self.emit(t, x, y, p, kind, cid)

    def contact(self, x, y, t_on, t_off, obj=0, touch=True, release=True, state=STICK):
        """A contact at (x, y) [m] from t_on to t_off [s] in ``state``; its touch
        (compression) and release (rarefaction) emissions unless told otherwise. Returns
        its id."""
        cid = len(self.contacts)
        self.contacts.append({"id": cid, "object": obj, "x_m": x, "y_m": y,
                              "t_on_s": t_on, "t_off_s": t_off})
        if touch:
            self.emit(t_on, x, y, +1, "touch", cid)
        if release:
            self.emit(t_off, x, y, -1, "release", cid)
        self.changes.append((t_on, cid, state))
        if t_off > t_on:  # else the family ends it later (`state`)
            self.changes.append((t_off, cid, NO))
        return cid

    def state(self, t_s, cid, st):
        self.changes.append((float(t_s), cid, st))

    def build(self, tail_s=0.5):
        """The Scene; its duration ends ``tail_s`` [s] after the last emission or change."""
        rows = sorted(self.rows, key=lambda r: r[0])
        a = np.array(rows, dtype=float).reshape(-1, 7)
        t_end = max([a[:, 0].max() if len(a) else 0.0] + [c[0] for c in self.changes])
        return Scene(self.family, self.seed, self.held_out, dict(self.params), a[:, 0],
                     a[:, 1:3], a[:, 3].astype(int), a[:, 4], a[:, 5].astype(int),
                     a[:, 6].astype(int), self.contacts, self.changes, self.episodes,
                     float(t_end + tail_s))


def to_events(scene: Scene, rng, *, sigma_m=None, drop=0.02, time_sigma_s=100e-9,
              amp_noise=0.1, geometry=GEOMETRY):
    """The 'events' pipeline: LocalizedEvents (time order) of a scene's emissions with the
    localizer's error model: Gaussian position error ``sigma_m`` [m] per tangent axis
    (None: log-uniform 5 .. 40 um per trial, as ae_eval.slip.scene_events), Gaussian time
    error, a share ``drop`` lost, the amplitude with a relative error ``amp_noise``.
    packet_id is the emission's index in the scene."""
    n = scene.t_s.size
    if n == 0:
        return []
    if sigma_m is None:
        sigma_m = draw(rng, 5e-6, 40e-6, log=True)
    P = geometry.surface_point_from_xy(scene.xy_m[:, 0], scene.xy_m[:, 1])
    nrm = P / np.linalg.norm(P, axis=1, keepdims=True)
    ref = np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = ref - (ref * nrm).sum(1, keepdims=True) * nrm
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(nrm, e1)
    z = rng.normal(0.0, sigma_m, (n, 2))
    Q = P + z[:, :1] * e1 + z[:, 1:] * e2
    Q *= geometry.radius_m / np.linalg.norm(Q, axis=1, keepdims=True)
    cov = sigma_m**2 * (e1[:, :, None] * e1[:, None, :] + e2[:, :, None] * e2[:, None, :])
    t = np.round(scene.t_s * 1e9 + rng.normal(0.0, time_sigma_s * 1e9, n)).astype(np.int64)
    amp = scene.polarity * scene.amplitude * (1.0 + rng.normal(0.0, amp_noise, n))
    keep = rng.uniform(0.0, 1.0, n) >= drop
    out = [LocalizedEvent(int(t[i]), Q[i], cov[i], int(scene.polarity[i]), float(amp[i]), 0.9,
                          int(i)) for i in np.flatnonzero(keep)]
    out.sort(key=lambda e: e.time_ns)
    return out
