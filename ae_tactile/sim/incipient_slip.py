# SPDX-License-Identifier: Apache-2.0
"""The incipient-slip scene: a held object under a growing tangential load
(Cattaneo-Mindlin), generated as time advances, its normal load changeable while it plays.
"""
from __future__ import annotations

import math

import numpy as np

from ae_tactile.sim.emission_list import EmissionList
from ae_tactile.sim.generator_tools import (
    NS_PER_S,
    EventParams,
    check_patch,
    choose_polarity,
    seeded_rng,
    tangent_basis,
)


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
        self.step_ns = int(round(p["step_s"] * NS_PER_S))
        self.t_start_ns = int(round(p["start_s"] * NS_PER_S))
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
        check_patch(
            self.geometry,
            self.center,
            self.contact_radius(max(P for _, P in self.loads)),
            "incipient_slip",
        )

    # ------------------------------------------------------------------ mechanics
    def contact_radius(self, P):
        return float(hertz_contact_radius_m(P, self.r_eff, self.E, self.nu))

    def tangential_load(self, t_ns):
        t = (np.asarray(t_ns, float) - self.t_start_ns) / NS_PER_S
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
        return self.t_start_ns + (Q - self.q0) / self.qdot * NS_PER_S

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
        check_patch(self.geometry, self.center, self.contact_radius(P), "incipient_slip")
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
        rng = seeded_rng(self.seed, 61, step, key, (a - step * self.step_ns))
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
                    t = self.t_start_ns + (q * self.mu * P - self.q0) / self.qdot * NS_PER_S
                else:
                    t = np.full(n, float(a))
                times.append(np.clip(t, a, stick_end - 1))
                kinds += ["micro_slip"] * n
            bg = self.p["background_rate_hz"]
            fseg = float(slip_fraction(min(qe, 1.0)))
            if bg > 0 and fseg > 0:  # background events by thinning
                n = rng.poisson(bg * fseg * (stick_end - a) / NS_PER_S)
                t = rng.uniform(a, stick_end, n)
                f_t = slip_fraction(self.tangential_load(t) / (self.mu * P))
                ok = rng.uniform(0, 1, n) * fseg < f_t
                times.append(t[ok])
                kinds += ["micro_slip"] * int(ok.sum())
        slide_from = a if sliding else onset
        if sliding_new and slide_from is not None and b > slide_from:
            n = rng.poisson(self.p["slip_rate_hz"] * (b - slide_from) / NS_PER_S)
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
        pol = choose_polarity(
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
