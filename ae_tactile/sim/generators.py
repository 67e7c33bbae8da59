# SPDX-License-Identifier: Apache-2.0
"""Built-in scene generators: emission processes with ground truth.

Each generator turns validated parameters (SI units, see `scene.py` for the schema and
defaults) into an emission process for `stream.StreamingSource`: an object with
``advance(t_ns) -> EmissionList`` and ``scene_truth() -> dict``. Static scenes are
pre-generated lists (`stream.StaticEmissions`); the incipient-slip scene is a state
machine that generates its emissions as time advances and lets a controller change the
normal load while it plays (`IncipientSlipProcess.set_normal_load`).

Contact patches: a patch point at tangent-plane offset (u, v) from a contact centre c0 on
the sphere is (c0 + u e1 + v e2) R / |c0 + u e1 + v e2| (e1, e2 orthonormal, tangent).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.sim.interference import burst_times_s
from ae_tactile.sim.stream import EmissionList, StaticEmissions

_NS = 1_000_000_000


def _ns(t_s) -> np.ndarray:
    return np.round(np.asarray(t_s, dtype=float) * _NS).astype(np.int64)


def _rng(seed, *keys) -> np.random.Generator:
    return np.random.Generator(
        np.random.PCG64(np.random.SeedSequence([int(seed), *map(int, keys)]))
    )


def tangent_basis(center_m):
    """Orthonormal tangent vectors (e1, e2) at points (..., 3) of the sphere; e1 points
    along +x projected on the tangent plane (along +y... at the poles' degenerate case)."""
    c = np.asarray(center_m, dtype=float)
    n = c / np.linalg.norm(c, axis=-1, keepdims=True)
    ref = np.broadcast_to(np.array([1.0, 0.0, 0.0]), n.shape).copy()
    par = np.abs(n[..., 0]) > 0.9
    ref[par] = np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref * n).sum(-1, keepdims=True) * n
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(n, e1)
    return e1, e2


def patch_points(geometry: FingertipGeometry, center_m, u_m, v_m) -> np.ndarray:
    """Points on the sphere at tangent-plane offsets (u, v) from one contact centre (3,)."""
    c = np.asarray(center_m, dtype=float)
    e1, e2 = tangent_basis(c)
    p = c + np.asarray(u_m, float)[..., None] * e1 + np.asarray(v_m, float)[..., None] * e2
    return p * (geometry.radius_m / np.linalg.norm(p, axis=-1, keepdims=True))


def uniform_disc(rng, n, r_in, r_out):
    """n points uniform (by area) in the annulus r_in <= r < r_out: (u, v)."""
    r = np.sqrt(rng.uniform(r_in**2, r_out**2, n))
    th = rng.uniform(0.0, 2.0 * np.pi, n)
    return r * np.cos(th), r * np.sin(th)


def _check_patch(geometry, center, radius_m, what):
    pol = math.acos(min(1.0, center[2] / geometry.radius_m))
    if pol + radius_m / geometry.radius_m > math.pi / 2:
        raise ValueError(
            f"{what}: the contact patch (radius {radius_m:.3g} m) around the contact centre"
            " reaches below the sensing hemisphere (z < 0); move it toward the apex"
        )


@dataclass(frozen=True)
class EventParams:
    speed_m_s: float
    curvature_1_m: float
    alpha_1_s: float


def _make(ctx, t_s, pts, kind, params: EventParams, polarity, ids):
    return EmissionList.create(
        _ns(t_s),
        pts,
        kind,
        polarity=polarity,
        speed_m_s=params.speed_m_s,
        curvature_1_m=params.curvature_1_m,
        alpha_1_s=params.alpha_1_s,
        density_kg_m3=ctx.config.density,
        event_id=ids,
    )


# ---------------------------------------------------------------------- static scenes
def single_touch(ctx, p):
    geo = ctx.config.geometry
    pt = geo.surface_point_from_xy(p["x_m"], p["y_m"])
    ev = EventParams(p["speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
    em = _make(ctx, [p["time_s"]], pt[None, :], "touch", ev, 1, [0])
    return StaticEmissions(em, {"generator": "single_touch"})


def paper_positions(ctx, p):
    """The paper's Fig. 7: touches at x = 0, 2.5, 5 mm (y = 0), one every interval_s."""
    geo = ctx.config.geometry
    xs = np.asarray(p["xs_m"], dtype=float)
    pts = geo.surface_point_from_xy(xs, np.zeros_like(xs))
    t = p["start_s"] + p["interval_s"] * np.arange(xs.size)
    ev = EventParams(p["speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
    return StaticEmissions(
        _make(ctx, t, pts, "touch", ev, 1, np.arange(xs.size)), {"generator": "paper_positions"}
    )


def three_pins(ctx, p):
    """The paper's Fig. 8: a plate with three pins touching within ~2 ms."""
    geo = ctx.config.geometry
    xy = np.asarray(p["points_xy_m"], dtype=float)
    t = np.asarray(p["times_s"], dtype=float)
    if xy.shape != (t.size, 2):
        raise ValueError(
            "params.points_xy_m must be a list of [x, y] pairs, one per entry of times_s"
        )
    pts = geo.surface_point_from_xy(xy[:, 0], xy[:, 1])
    ev = EventParams(p["speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
    return StaticEmissions(
        _make(ctx, t, pts, "touch", ev, 1, np.arange(t.size)), {"generator": "three_pins"}
    )


def plane_slip(ctx, p):
    """The paper's Fig. 9: a flat plate slipping along x over the tip. Slip emissions at
    Poisson rate rate_hz from points uniform over the contact disc, whose centre moves
    along x at drift_m_s from (x_m, y_m) (zero drift: the tip stays under the plate)."""
    geo = ctx.config.geometry
    rng = _rng(ctx.seed, 31)
    t0, t1 = p["start_s"], min(p["start_s"] + p["slip_duration_s"], ctx.duration_s)
    n = rng.poisson(p["rate_hz"] * max(0.0, t1 - t0))
    t = np.sort(rng.uniform(t0, t1, n))
    pts = np.zeros((n, 3))
    for i in range(n):
        cx = p["x_m"] + p["drift_m_s"] * (t[i] - t0)
        c = geo.surface_point_from_xy(cx, p["y_m"])
        u, v = uniform_disc(rng, 1, 0.0, p["contact_radius_m"])
        pts[i] = patch_points(geo, c, u, v)[0]
    if n and np.any(pts[:, 2] < 0):
        raise ValueError("plane_slip: the contact reaches below the sensing hemisphere")
    ev = EventParams(p["speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
    pol = rng.choice([-1.0, 1.0], n)
    return StaticEmissions(
        _make(ctx, t, pts, "slip", ev, pol, np.arange(n)), {"generator": "plane_slip"}
    )


def random_touches(ctx, p):
    """Poisson touches (rate_hz) uniform by area over the cap of polar angle <= max_polar_deg,
    speeds uniform in [speed_min_m_s, speed_max_m_s]; each is released after a hold time
    uniform in [hold_min_s, hold_max_s] (a release emission when release_emissions is on)."""
    geo = ctx.config.geometry
    rng = _rng(ctx.seed, 41)
    n = rng.poisson(p["rate_hz"] * ctx.duration_s)
    t = np.sort(rng.uniform(0.0, ctx.duration_s, n))
    cmin = math.cos(math.radians(p["max_polar_deg"]))
    th = np.arccos(rng.uniform(cmin, 1.0, n))
    ph = rng.uniform(0, 2 * np.pi, n)
    pts = geo.surface_point_from_angles(th, ph)
    v = rng.uniform(p["speed_min_m_s"], p["speed_max_m_s"], n)
    lists = [
        EmissionList.create(
            _ns(t),
            pts,
            "touch",
            polarity=1,
            speed_m_s=v,
            curvature_1_m=p["curvature_1_m"],
            alpha_1_s=p["alpha_1_s"],
            density_kg_m3=ctx.config.density,
            event_id=2 * np.arange(n),
        )
    ]
    if ctx.effects["release_emissions"]:
        hold = rng.uniform(p["hold_min_s"], p["hold_max_s"], n)
        tr = t + hold
        ok = tr < ctx.duration_s
        lists.append(
            EmissionList.create(
                _ns(tr[ok]),
                pts[ok],
                "release",
                polarity=-1,
                speed_m_s=v[ok] * p["release_speed_ratio"],
                curvature_1_m=p["curvature_1_m"],
                alpha_1_s=p["alpha_1_s"],
                density_kg_m3=ctx.config.density,
                event_id=2 * np.arange(n)[ok] + 1,
            )
        )
    return StaticEmissions(EmissionList.concat(lists), {"generator": "random_touches"})


def touch_hold_release(ctx, p):
    """A touch at time_s, held for hold_s, then released (opposite polarity, separation
    speed release_speed_m_s) when release_emissions is on."""
    geo = ctx.config.geometry
    pt = geo.surface_point_from_xy(p["x_m"], p["y_m"])[None, :]
    ev = EventParams(p["speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
    lists = [_make(ctx, [p["time_s"]], pt, "touch", ev, 1, [0])]
    t_rel = p["time_s"] + p["hold_s"]
    if ctx.effects["release_emissions"]:
        evr = EventParams(p["release_speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
        lists.append(_make(ctx, [t_rel], pt, "release", evr, -1, [1]))
    return StaticEmissions(
        EmissionList.concat(lists),
        {"generator": "touch_hold_release", "release_time_ns": int(_ns(t_rel))},
    )


def texture(ctx, p):
    """Sliding at speed_m_s over a texture of spatial period period_m: emissions at the
    mean rate v / lambda, the n-th at t0 + n lambda / v + jitter (Gaussian, std
    jitter_fraction of the period), from points uniform in the contact patch."""
    geo = ctx.config.geometry
    rng = _rng(ctx.seed, 51)
    rate = p["slide_speed_m_s"] / p["period_m"]
    t0, t1 = p["start_s"], min(ctx.duration_s, p["start_s"] + p["slide_duration_s"])
    n = max(0, int(math.floor((t1 - t0) * rate)))
    t = t0 + np.arange(n) / rate + rng.normal(0.0, p["jitter_fraction"] / rate, n)
    keep = (t >= 0) & (t < ctx.duration_s)
    c = geo.surface_point_from_xy(p["x_m"], p["y_m"])
    _check_patch(geo, c, p["contact_radius_m"], "texture")
    u, v = uniform_disc(rng, n, 0.0, p["contact_radius_m"])
    pts = patch_points(geo, c, u, v)
    ev = EventParams(p["speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
    pol = rng.choice([-1.0, 1.0], n) if p["random_polarity"] else np.ones(n)
    em = _make(ctx, t[keep], pts[keep], "texture", ev, pol[keep], np.arange(n)[keep])
    return StaticEmissions(em, {"generator": "texture", "emission_rate_hz": rate})


def _polarity(drawn, mode):
    """Emission polarities: the random draw (kept so the random stream never changes),
    or all compressions / all rarefactions."""
    if mode == "compression":
        return np.ones_like(drawn)
    if mode == "rarefaction":
        return -np.ones_like(drawn)
    return drawn


# ---------------------------------------------------------------------- incipient slip
def hertz_contact_radius_m(load_n, radius_m, youngs_modulus_pa, poisson_ratio=0.5):
    """Hertz: a_H = (3 P R / (4 E*))^(1/3), rigid object on an elastic tip:
    E* = E / (1 - nu^2) (= 4E/3 for nu = 0.5). ``radius_m``: effective radius."""
    e_star = youngs_modulus_pa / (1.0 - poisson_ratio**2)
    return (3.0 * np.asarray(load_n, float) * radius_m / (4.0 * e_star)) ** (1.0 / 3.0)


def stick_radius_m(a_h_m, q_load_n, mu, p_load_n):
    """Cattaneo-Mindlin stick radius c = a_H (1 - Q/(mu P))^(1/3) (0 at gross slip)."""
    q = np.clip(np.asarray(q_load_n, float) / (mu * np.asarray(p_load_n, float)), 0.0, 1.0)
    return np.asarray(a_h_m, float) * (1.0 - q) ** (1.0 / 3.0)


def slip_fraction(q):
    """Slipping area fraction 1 - (1 - q)^(2/3), q = Q/(mu P) in [0, 1]."""
    q = np.clip(np.asarray(q, float), 0.0, 1.0)
    return 1.0 - (1.0 - q) ** (2.0 / 3.0)


class IncipientSlipProcess:
    """Incipient slip of a held object under a growing tangential load (Cattaneo-Mindlin).

    Loads: normal P(t) (piecewise constant, changed by ``set_normal_load``), tangential
    Q(t) = min(Q0 + Qdot t, Q_max). With q = Q / (mu P): Hertz radius a_H(P), stick
    radius c = a_H (1 - q)^(1/3), slipping fraction f(q) = 1 - (1 - q)^(2/3).

    Emissions while sticking (q < 1), all 'micro_slip', uniform by area in the annulus
    c < r < a_H at their time:
      * front events: each newly slipping area emits, density ``front_density_per_m2``:
        their number in [t_a, t_b) is Poisson(rho_A pi a_H^2 (f_hi - f_lo)) over the part
        of f above its running maximum (the slip front only advances into stuck area);
        since df/dq = (2/3)(1 - q)^(-1/3), the rate grows as the stick zone shrinks;
      * background events at rate ``background_rate_hz`` f(q) (ongoing micro-slip in the
        slipping annulus).
    ``micro_slip_count`` (optional) replaces the density: the front then emits that many on
    average over a whole ramp (q from 0 to 1), whatever the contact's size.
    ``micro_slip_polarity``: 'random' (each emission +1 or -1), 'compression' (+1),
    'rarefaction' (-1); it applies to gross-slip emissions too.
    Gross slip once q reaches 1 (Q = mu P): the time goes in the truth
    (``gross_slip_time_ns``), and while q >= 1 'slip' emissions come at ``slip_rate_hz``
    from the whole contact disc. Raising P so that q < 1 again re-sticks the contact
    (the front memory restarts at the current f). Mindlin-Deresiewicz load-history
    effects are not modelled.

    Randomness is drawn per fixed time step (``step_s``) from a generator keyed by
    (seed, step, load-change index), so the emissions do not depend on how time is
    chunked, and a load change only redraws the future.
    """

    def __init__(self, ctx, p):
        self.geometry = ctx.config.geometry
        self.density = ctx.config.density
        self.seed = int(ctx.seed)
        self.p = dict(p)
        self.mu = p["friction_coefficient"]
        self.q0 = p["tangential_load_start_n"]
        self.qdot = p["tangential_load_rate_n_per_s"]
        self.qmax = (
            p["tangential_load_max_n"] if p["tangential_load_max_n"] is not None else np.inf
        )
        r_obj = p["object_radius_m"]
        rf = self.geometry.radius_m
        self.r_eff = rf if r_obj is None else 1.0 / (1.0 / rf + 1.0 / r_obj)
        self.E = p["youngs_modulus_pa"]
        self.nu = p["poisson_ratio"]
        self.center = self.geometry.surface_point_from_xy(p["x_m"], p["y_m"])
        self._e1, self._e2 = tangent_basis(self.center)
        self.step_ns = int(round(p["step_s"] * _NS))
        self.t_start_ns = int(round(p["start_s"] * _NS))
        # load history: list of (time_ns, P); index = load-change key
        self.loads = [(0, float(p["normal_load_n"]))]
        self.event_params = {
            "micro_slip": EventParams(
                p["micro_slip_speed_m_s"], p["curvature_1_m"], p["alpha_1_s"]
            ),
            "slip": EventParams(p["slip_speed_m_s"], p["curvature_1_m"], p["alpha_1_s"]),
        }
        self.horizon_ns = 0  # everything before has been returned
        self._pending = EmissionList.empty()
        self._gen_ns = 0  # events generated (pending or returned) up to here
        self._fmax = 0.0  # running max of f at _gen_ns
        self._sliding = False
        _check_patch(
            self.geometry,
            self.center,
            self.contact_radius(max(P for _, P in self.loads)),
            "incipient_slip",
        )

    # ------------------------------------------------------------------ mechanics
    def contact_radius(self, P):
        return float(hertz_contact_radius_m(P, self.r_eff, self.E, self.nu))

    def tangential_load(self, t_ns):
        t = (np.asarray(t_ns, float) - self.t_start_ns) / _NS
        return np.minimum(self.q0 + self.qdot * np.maximum(t, 0.0), self.qmax)

    def normal_load(self, t_ns) -> float:
        P = self.loads[0][1]
        for t, v in self.loads:
            if t <= t_ns:
                P = v
        return P

    def state_at(self, t_ns) -> dict:
        """Loads and contact state at time t_ns (SI units)."""
        P = self.normal_load(t_ns)
        Q = float(self.tangential_load(t_ns))
        a = self.contact_radius(P)
        q = Q / (self.mu * P)
        return {
            "normal_load_n": P,
            "tangential_load_n": Q,
            "load_ratio": q,
            "hertz_radius_m": a,
            "stick_radius_m": float(stick_radius_m(a, Q, self.mu, P)),
            "slip_fraction": float(slip_fraction(q)),
            "gross_slip": q >= 1.0,
        }

    def _time_of_q(self, q, P):
        """Time (ns, float) at which Q(t) = q mu P on the ramp (inf if never)."""
        Q = q * self.mu * P
        if Q > self.qmax:
            return np.inf
        if self.qdot <= 0:
            return -np.inf if Q <= self.q0 else np.inf
        return self.t_start_ns + (Q - self.q0) / self.qdot * _NS

    # ------------------------------------------------------------------ control
    def set_normal_load(self, load_n: float, at_time_ns: int) -> None:
        """Change the normal load P to ``load_n`` from ``at_time_ns`` on (not in the past:
        at_time_ns must be >= the time already handed out by ``advance``)."""
        P = float(load_n)
        if not math.isfinite(P) or P <= 0:
            raise ValueError(f"normal load must be positive, got {load_n!r}")
        t = int(at_time_ns)
        if t < self.horizon_ns:
            raise ValueError(
                f"cannot change the normal load at {t} ns: emissions up to "
                f"{self.horizon_ns} ns have already been produced"
            )
        _check_patch(self.geometry, self.center, self.contact_radius(P), "incipient_slip")
        # drop pending events from t on and roll the generator back to t
        self._pending = self._pending.between(np.iinfo(np.int64).min, t)
        if self._gen_ns > t:
            self._gen_ns = t
            self._fmax, self._sliding = self._state_before(t)
        self.loads.append((t, P))
        self.loads.sort(key=lambda x: x[0])

    def _state_before(self, t_ns):
        """(fmax, sliding) at time t_ns, recomputed from the load history (deterministic)."""
        fmax, sliding = 0.0, False
        bounds = self._segments(0, t_ns)
        for a, b, P, _ in bounds:
            fmax, sliding, _, _ = self._advance_state(a, b, P, fmax, sliding)
        return fmax, sliding

    def _segments(self, t_a, t_b):
        """Constant-P pieces of [t_a, t_b) cut at steps and load changes: (a, b, P, key)."""
        cuts = sorted(
            {
                t_a,
                t_b,
                *[t for t, _ in self.loads if t_a < t < t_b],
                *range((t_a // self.step_ns + 1) * self.step_ns, t_b, self.step_ns),
            }
        )
        out = []
        for a, b in zip(cuts[:-1], cuts[1:]):
            key = max(i for i, (t, _) in enumerate(self.loads) if t <= a)
            out.append((a, b, self.loads[key][1], key))
        return out

    def _advance_state(self, a, b, P, fmax, sliding):
        """State after [a, b) at constant P: (fmax, sliding, onset_ns or None, restuck).

        q is non-decreasing inside a constant-P piece, so the contact can only re-stick at
        its start (after P was raised) and slip grossly at most once inside it."""
        qa = float(self.tangential_load(a)) / (self.mu * P)
        qb = float(self.tangential_load(b)) / (self.mu * P)
        restuck = False
        if sliding and qa < 1.0:  # re-stuck: the front memory restarts here
            sliding, fmax, restuck = False, float(slip_fraction(qa)), True
        if qb >= 1.0:
            onset = None
            if not sliding:
                onset = a if qa >= 1.0 else max(a, int(math.ceil(self._time_of_q(1.0, P))))
            return 1.0, True, onset, restuck
        return max(fmax, float(slip_fraction(qb))), False, None, restuck

    # ------------------------------------------------------------------ generation
    def _generate(self, a, b, P, key, fmax, sliding):
        step = a // self.step_ns
        rng = _rng(self.seed, 61, step, key, (a - step * self.step_ns))
        aH = self.contact_radius(P)
        fmax_new, sliding_new, onset, restuck = self._advance_state(a, b, P, fmax, sliding)
        if restuck:
            sliding, fmax = (
                False,
                float(slip_fraction(float(self.tangential_load(a)) / (self.mu * P))),
            )
        times, kinds = [], []
        stick_end = b if onset is None else onset
        if not sliding and stick_end > a:
            qa = float(self.tangential_load(a)) / (self.mu * P)
            qe = float(self.tangential_load(stick_end)) / (self.mu * P)
            f_lo = max(fmax, float(slip_fraction(qa)))
            f_hi = float(slip_fraction(min(qe, 1.0)))
            if f_hi > f_lo:  # front events, uniform in f
                count = self.p.get("micro_slip_count")
                n_full = (
                    count
                    if count is not None
                    else self.p["front_density_per_m2"] * math.pi * aH * aH
                )
                n = rng.poisson(n_full * (f_hi - f_lo))
                u = rng.uniform(f_lo, f_hi, n)
                q = 1.0 - (1.0 - u) ** 1.5
                if self.qdot > 0:
                    t = self.t_start_ns + (q * self.mu * P - self.q0) / self.qdot * _NS
                else:
                    t = np.full(n, float(a))
                times.append(np.clip(t, a, stick_end - 1))
                kinds += ["micro_slip"] * n
            bg = self.p["background_rate_hz"]
            fseg = float(slip_fraction(min(qe, 1.0)))
            if bg > 0 and fseg > 0:  # background events by thinning
                n = rng.poisson(bg * fseg * (stick_end - a) / _NS)
                t = rng.uniform(a, stick_end, n)
                f_t = slip_fraction(self.tangential_load(t) / (self.mu * P))
                ok = rng.uniform(0, 1, n) * fseg < f_t
                times.append(t[ok])
                kinds += ["micro_slip"] * int(ok.sum())
        slide_from = a if sliding else onset
        if sliding_new and slide_from is not None and b > slide_from:
            n = rng.poisson(self.p["slip_rate_hz"] * (b - slide_from) / _NS)
            times.append(rng.uniform(slide_from, b, n))
            kinds += ["slip"] * n
        if not kinds:
            return None, fmax_new, sliding_new
        t = np.floor(np.concatenate(times)).astype(np.int64)
        code = np.where(np.array(kinds) == "micro_slip", 0, 1)
        # positions: micro-slip in the annulus c(t) < r < a_H, slip anywhere in the disc
        Q = self.tangential_load(t)
        c = stick_radius_m(aH, Q, self.mu, P)
        r_in = np.where(code == 0, c, 0.0)
        rr = np.sqrt(rng.uniform(0, 1, t.size) * (aH**2 - r_in**2) + r_in**2)
        th = rng.uniform(0, 2 * np.pi, t.size)
        pts = (
            self.center
            + (rr * np.cos(th))[:, None] * self._e1
            + (rr * np.sin(th))[:, None] * self._e2
        )
        pts *= self.geometry.radius_m / np.linalg.norm(pts, axis=1, keepdims=True)
        pol = _polarity(
            rng.choice([-1.0, 1.0], t.size), self.p.get("micro_slip_polarity", "random")
        )
        ids = (step << 24) + (key << 16) + np.arange(t.size)
        return (t, code, pts, pol, ids), fmax_new, sliding_new

    def _to_list(self, parts) -> EmissionList:
        if not parts:
            return EmissionList.empty()
        t, code, pts, pol, ids = (np.concatenate(x) for x in zip(*parts))
        lists = []
        for c, kind in enumerate(("micro_slip", "slip")):
            m = code == c
            if m.any():
                ev = self.event_params[kind]
                lists.append(
                    EmissionList.create(
                        t[m],
                        pts[m],
                        kind,
                        polarity=pol[m],
                        speed_m_s=ev.speed_m_s,
                        curvature_1_m=ev.curvature_1_m,
                        alpha_1_s=ev.alpha_1_s,
                        density_kg_m3=self.density,
                        event_id=ids[m],
                    )
                )
        return EmissionList.concat(lists)

    def advance(self, t_ns: int) -> EmissionList:
        """Emissions with horizon <= time < t_ns (generated step by step, deterministically)."""
        t_ns = int(t_ns)
        if t_ns <= self.horizon_ns:
            return EmissionList.empty()
        if t_ns > self._gen_ns:
            end = (-(-t_ns // self.step_ns)) * self.step_ns  # whole steps
            parts = []
            for a, b, P, key in self._segments(self._gen_ns, end):
                raw, self._fmax, self._sliding = self._generate(
                    a, b, P, key, self._fmax, self._sliding
                )
                if raw is not None:
                    parts.append(raw)
            self._pending = EmissionList.concat([self._pending, self._to_list(parts)])
            self._gen_ns = end
        out = self._pending.between(self.horizon_ns, t_ns)
        self._pending = self._pending.between(t_ns, np.iinfo(np.int64).max)
        self.horizon_ns = t_ns
        return out

    def gross_slip_intervals(self, until_ns: int | None = None) -> list[list]:
        """[[start_ns, end_ns or None], ...] of gross slip up to ``until_ns`` (default: the
        time generated so far), from the load history."""
        end = self._gen_ns if until_ns is None else int(until_ns)
        out, fmax, sliding = [], 0.0, False
        for a, b, P, _ in self._segments(0, end) if end > 0 else []:
            fmax, sliding, onset, restuck = self._advance_state(a, b, P, fmax, sliding)
            if restuck and out:
                out[-1][1] = int(a)
            if onset is not None:
                out.append([int(onset), None])
        return out

    def scene_truth(self, until_ns: int | None = None) -> dict:
        iv = self.gross_slip_intervals(until_ns)
        onset = iv[0][0] if iv else None
        P0 = self.loads[0][1]
        return {
            "generator": "incipient_slip",
            "gross_slip_time_ns": onset,
            "gross_slip_intervals_ns": iv,
            "predicted_gross_slip_time_ns": (
                None
                if not np.isfinite(self._time_of_q(1.0, P0))
                else int(math.ceil(self._time_of_q(1.0, P0)))
            ),
            "normal_load_changes": [[int(t), float(P)] for t, P in self.loads],
            "hertz_radius_m": self.contact_radius(P0),
            "effective_radius_m": self.r_eff,
            "friction_coefficient": self.mu,
            "contact_center_m": [float(x) for x in self.center],
        }


def incipient_slip(ctx, p):
    return IncipientSlipProcess(ctx, p)


# ---------------------------------------------------------------------- moving contact
def rotate_on_sphere(p0_m, direction, angle_rad):
    """Points (n, 3): p0 (3,) rotated by ``angle_rad`` (n,) about the axis p0 x direction,
    i.e. moved along the great circle through p0 heading along ``direction`` (tangent)."""
    p0 = np.asarray(p0_m, float)
    k = np.cross(p0, np.asarray(direction, float))
    k /= np.linalg.norm(k)
    a = np.asarray(angle_rad, float)[:, None]
    return p0 * np.cos(a) + np.cross(k, p0) * np.sin(a) + k * (k @ p0) * (1 - np.cos(a))


def stylus(ctx, p):
    """A stylus dragged over the tip: it touches at (x_m, y_m) at start_s (a touch
    emission), slides along the great circle heading ``heading_deg`` (from +x toward +y in
    the tangent plane) at ``slide_speed_m_s`` for ``path_m``, then lifts off (a release,
    when release_emissions is on). While it slides over a texture of spatial period
    ``period_m`` it emits at arc lengths n lambda (times n lambda / v + Gaussian jitter,
    std ``jitter_fraction`` of the period), from points uniform in a patch of radius
    ``contact_radius_m`` around the moving centre; a fraction ``miss_fraction`` of the
    ridges stays silent. Polarity: 'random', 'compression' or 'rarefaction'. Truth: the
    track (centre and velocity at any time), the period and the speed."""
    geo = ctx.config.geometry
    rng = _rng(ctx.seed, 71)
    R = geo.radius_m
    p0 = geo.surface_point_from_xy(p["x_m"], p["y_m"])
    e1, e2 = tangent_basis(p0)
    h = math.radians(p["heading_deg"])
    d = math.cos(h) * e1 + math.sin(h) * e2
    v, lam = p["slide_speed_m_s"], p["period_m"]
    t0 = p["start_s"]
    dur = p["path_m"] / v
    end = rotate_on_sphere(p0, d, [p["path_m"] / R])[0]
    for q in (p0, end):
        _check_patch(geo, q, p["contact_radius_m"], "stylus")
    n = int(math.floor(p["path_m"] / lam))
    k = np.arange(1, n + 1)
    t = t0 + k * lam / v + rng.normal(0.0, p["jitter_fraction"] * lam / v, n)
    keep = (
        (rng.uniform(0, 1, n) >= p["miss_fraction"])
        & (t > t0)
        & (t < min(t0 + dur, ctx.duration_s))
    )
    centres = rotate_on_sphere(p0, d, v * (t - t0) / R)
    u, w = uniform_disc(rng, n, 0.0, p["contact_radius_m"])
    f1, f2 = tangent_basis(centres) if n else (np.zeros((0, 3)), np.zeros((0, 3)))
    pts = centres + u[:, None] * f1 + w[:, None] * f2
    pts *= R / np.linalg.norm(pts, axis=1, keepdims=True) if n else 1.0
    ev = EventParams(p["speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
    pol = _polarity(rng.choice([-1.0, 1.0], n), p["polarity"])
    lists = [_make(ctx, t[keep], pts[keep], "texture", ev, pol[keep], 2 + np.arange(n)[keep])]
    if t0 < ctx.duration_s:
        lists.append(
            _make(
                ctx,
                [t0],
                p0[None, :],
                "touch",
                EventParams(p["touch_speed_m_s"], p["curvature_1_m"], p["alpha_1_s"]),
                1,
                [0],
            )
        )
    t_end = t0 + dur
    if ctx.effects["release_emissions"] and t_end < ctx.duration_s:
        lists.append(
            _make(
                ctx,
                [t_end],
                rotate_on_sphere(p0, d, [p["path_m"] / R]),
                "release",
                EventParams(p["touch_speed_m_s"] * 0.5, p["curvature_1_m"], p["alpha_1_s"]),
                -1,
                [1],
            )
        )
    truth = {
        "generator": "stylus",
        "start_time_ns": int(_ns(t0)),
        "end_time_ns": int(_ns(t_end)),
        "slide_speed_m_s": v,
        "period_m": lam,
        "emission_rate_hz": v / lam,
        "start_point_m": [float(x) for x in p0],
        "direction": [float(x) for x in d],
        "n_texture_emissions": int(keep.sum()),
    }
    return StaticEmissions(EmissionList.concat(lists), truth)


def stylus_track(truth: dict, radius_m: float, t_ns):
    """(centre (n, 3), velocity (n, 3)) of a stylus scene's contact at times t_ns (n,)."""
    t = (np.atleast_1d(np.asarray(t_ns, float)) - truth["start_time_ns"]) * 1e-9
    t = np.clip(t, 0.0, (truth["end_time_ns"] - truth["start_time_ns"]) * 1e-9)
    p0, d, v = (
        np.asarray(truth["start_point_m"]),
        np.asarray(truth["direction"]),
        truth["slide_speed_m_s"],
    )
    c = rotate_on_sphere(p0, d, v * t / radius_m)
    c2 = rotate_on_sphere(p0, d, v * (t + 1e-6) / radius_m)
    return c, (c2 - c) / 1e-6


# ---------------------------------------------------------------------- interference
def interference(ctx, p):
    """Common-mode electrical interference bursts (a switching motor driver, ESD): no
    acoustic emission; the burst times and waveform options go in the scene truth, for
    `ae_tactile.sim.interference.InterferenceSource` to render as packets (the acoustic
    renderer cannot). Bursts at ``rate_hz`` from ``start_s`` for ``burst_duration_s``,
    periodic (jitter ``jitter_s``) or Poisson. With ``hold_s`` > 0 a touch at (x_m, y_m)
    at ``touch_time_s`` is held that long under the bursts and released. ``taps_before``
    taps (touch, release 10 ms later, every 30 ms from 5 ms) at random points 10 .. 45 deg
    from the apex come first: the everyday touches from which the driver learns the wall
    echo (end them before ``start_s``). ``shared_clock``: the bursts lie on the host's
    monotonic clock (`shared_clock_burst_times_ns`, drawn from ``shared_seed``), the same
    for every simulated fingertip of the machine playing a scene with that seed: the
    fingertips of one hand under one source; the truth has no burst list then."""
    rng = _rng(ctx.seed, 81)
    end = min(ctx.duration_s, p["start_s"] + p["burst_duration_s"])
    t = burst_times_s(
        end,
        p["rate_hz"],
        periodic=p["periodic"],
        jitter_s=p["jitter_s"],
        start_s=p["start_s"],
        rng=rng,
    )
    truth = {
        "generator": "interference",
        "burst_times_ns": [] if p["shared_clock"] else [int(x) for x in _ns(t)],
        "kind": p["kind"],
        "coupling": p["coupling"],
        "amplitude_snr_db": p["amplitude_snr_db"],
        "seed": int(ctx.seed),
    }
    if p["shared_clock"]:
        truth.update(
            shared_clock=True,
            shared_seed=int(p["shared_seed"]),
            rate_hz=float(p["rate_hz"]),
            periodic=bool(p["periodic"]),
            jitter_s=float(p["jitter_s"]),
            burst_start_time_ns=int(_ns(p["start_s"])),
            burst_end_time_ns=int(_ns(end)),
        )
    lists = []
    n_taps = int(p["taps_before"])
    if n_taps:
        geo = ctx.config.geometry
        rng_t = _rng(ctx.seed, 82)
        pol = np.radians(rng_t.uniform(10.0, 45.0, n_taps))
        az = rng_t.uniform(0.0, 2.0 * math.pi, n_taps)
        pts = geo.surface_point_from_xy(geo.radius_m * np.sin(pol) * np.cos(az),
                                        geo.radius_m * np.sin(pol) * np.sin(az))
        t_tap = 0.005 + 0.03 * np.arange(n_taps)
        ev = EventParams(p["speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
        ids = 100 + 2 * np.arange(n_taps)
        lists.append(_make(ctx, t_tap, pts, "touch", ev, 1, ids))
        if ctx.effects["release_emissions"]:
            evr = EventParams(p["release_speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
            lists.append(_make(ctx, t_tap + 0.01, pts, "release", evr, -1, ids + 1))
    if p["hold_s"] > 0:
        # a held touch (touch_hold_release) under the interference: the false-alarm scene
        sub = touch_hold_release(ctx, {**p, "time_s": p["touch_time_s"]})
        lists.append(sub.emissions)
        truth.update(
            {
                "touch_time_ns": int(_ns(p["touch_time_s"])),
                "release_time_ns": sub.truth["release_time_ns"],
            }
        )
    em = EmissionList.concat(lists) if lists else EmissionList.empty()
    return StaticEmissions(em, truth)


# ---------------------------------------------------------------------- composite
class CompositeProcess:
    """Several emission processes played at time offsets on one timeline (a showcase scene).

    Part i's emissions are shifted by its offset and get event ids ``(i << 40) + id``, so
    ids stay unique. ``set_normal_load`` reaches every part that has one (the incipient
    slip part), with the time shifted into the part's own timeline; the scene truth lists
    each part's truth with times shifted onto the common timeline.
    """

    ID_SHIFT = 40

    def __init__(self, parts):
        self.parts = [(int(off_ns), proc, str(name)) for off_ns, proc, name in parts]

    def advance(self, t_ns: int) -> EmissionList:
        out = []
        for i, (off, proc, _) in enumerate(self.parts):
            if t_ns <= off:
                continue
            em = proc.advance(int(t_ns) - off)
            if len(em):
                out.append(
                    EmissionList(
                        em.time_ns + off,
                        em.point_m,
                        em.kind,
                        em.strength_pa_m,
                        em.speed_m_s,
                        em.curvature_1_m,
                        em.alpha_1_s,
                        em.event_id + (i << self.ID_SHIFT),
                    )
                )
        return EmissionList.concat(out)

    def set_normal_load(self, load_n: float, at_time_ns: int) -> None:
        done = False
        for off, proc, _ in self.parts:
            if hasattr(proc, "set_normal_load") and at_time_ns >= off:
                proc.set_normal_load(load_n, int(at_time_ns) - off)
                done = True
        if not done:
            raise ValueError("no part of this scene has a normal load to change (yet)")

    def scene_truth(self) -> dict:
        parts = []
        for off, proc, name in self.parts:
            truth = dict(proc.scene_truth())
            for k, v in list(truth.items()):
                if k.endswith("_time_ns") and v is not None:
                    truth[k] = int(v) + off
                elif k.endswith("_intervals_ns") and v:
                    truth[k] = [[a + off, None if b is None else b + off] for a, b in v]
            parts.append({"name": name, "offset_ns": off, "start_time_ns": off, **truth})
        return {"generator": "composite", "parts": parts}
