# SPDX-License-Identifier: Apache-2.0
"""Built-in scene generators: emission processes with ground truth.

Each generator turns validated parameters (SI units, see `scene_schema.py` for the schema
and defaults) into an emission process for `stream.StreamingSource`: an object with
``advance(t_ns) -> EmissionList`` and ``scene_truth() -> dict``. Static scenes are
pre-generated lists (`emission_list.StaticEmissions`); the incipient-slip scene
(`incipient_slip.py`) is a state machine that generates its emissions as time advances
and lets a controller change the normal load while it plays
(`IncipientSlipProcess.set_normal_load`). The shared pieces (seeded draws, contact
patches) are in `generator_tools.py`.

Re-exported for the generators' users: `hertz_contact_radius_m`, `stick_radius_m`,
`slip_fraction`, `IncipientSlipProcess`, `incipient_slip`, `tangent_basis`.
"""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.sim.emission import COMPRESSION, RAREFACTION
from ae_tactile.sim.emission_list import EmissionList, StaticEmissions
from ae_tactile.sim.generator_tools import (
    EventParams,
    check_patch,
    choose_polarity,
    make_emissions,
    patch_points,
    rotate_on_sphere,
    seeded_rng,
    tangent_basis,
    to_ns,
    uniform_disc,
)
from ae_tactile.sim.incipient_slip import (
    IncipientSlipProcess,
    hertz_contact_radius_m,
    incipient_slip,
    slip_fraction,
    stick_radius_m,
)
from ae_tactile.sim.interference import burst_times_s

__all__ = [
    "single_touch", "paper_positions", "three_pins", "plane_slip", "random_touches",
    "touch_hold_release", "texture", "incipient_slip", "stylus", "interference",
    "CompositeProcess", "IncipientSlipProcess", "hertz_contact_radius_m", "stick_radius_m",
    "slip_fraction", "tangent_basis",
]


# ---------------------------------------------------------------------- static scenes
def single_touch(ctx, p):
    geo = ctx.config.geometry
    pt = geo.surface_point_from_xy(p["x_m"], p["y_m"])
    ev = EventParams(p["speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
    em = make_emissions(ctx, [p["time_s"]], pt[None, :], "touch", ev, COMPRESSION, [0])
    return StaticEmissions(em, {"generator": "single_touch"})


def _released(ctx, p, touches, t, pts):
    """The touches, and each one's release hold_s [s] after it (opposite polarity,
    separation speed release_speed_m_s) when hold_s > 0 and releases emit."""
    if not p["hold_s"] > 0 or not ctx.effects["release_emissions"]:
        return touches
    evr = EventParams(p["release_speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
    n = len(t)
    rel = make_emissions(ctx, np.asarray(t) + p["hold_s"], pts, "release", evr, RAREFACTION,
                         np.arange(n, 2 * n))
    return EmissionList.concat([touches, rel])


def paper_positions(ctx, p):
    """The paper's Fig. 7: touches at x = 0, 2.5, 5 mm (y = 0), one every interval_s; each
    released hold_s after it (0: held to the end)."""
    geo = ctx.config.geometry
    xs = np.asarray(p["xs_m"], dtype=float)
    pts = geo.surface_point_from_xy(xs, np.zeros_like(xs))
    t = p["start_s"] + p["interval_s"] * np.arange(xs.size)
    ev = EventParams(p["speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
    touches = make_emissions(ctx, t, pts, "touch", ev, COMPRESSION, np.arange(xs.size))
    return StaticEmissions(_released(ctx, p, touches, t, pts), {"generator": "paper_positions"})


def three_pins(ctx, p):
    """The paper's Fig. 8: a plate with three pins touching within ~2 ms; each pin released
    hold_s after its touch (0: held to the end)."""
    geo = ctx.config.geometry
    xy = np.asarray(p["points_xy_m"], dtype=float)
    t = np.asarray(p["times_s"], dtype=float)
    if xy.shape != (t.size, 2):
        raise ValueError(
            "params.points_xy_m must be a list of [x, y] pairs, one per entry of times_s"
        )
    pts = geo.surface_point_from_xy(xy[:, 0], xy[:, 1])
    ev = EventParams(p["speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
    touches = make_emissions(ctx, t, pts, "touch", ev, COMPRESSION, np.arange(t.size))
    return StaticEmissions(_released(ctx, p, touches, t, pts), {"generator": "three_pins"})


def plane_slip(ctx, p):
    """The paper's Fig. 9: a flat plate slipping along x over the tip. Slip emissions at
    Poisson rate rate_hz from points uniform over the contact disc, whose centre moves
    along x at drift_m_s from (x_m, y_m) (zero drift: the tip stays under the plate)."""
    geo = ctx.config.geometry
    rng = seeded_rng(ctx.seed, 31)
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
        make_emissions(ctx, t, pts, "slip", ev, pol, np.arange(n)), {"generator": "plane_slip"}
    )


def random_touches(ctx, p):
    """Poisson touches (rate_hz) uniform by area over the cap of polar angle <= max_polar_deg,
    speeds uniform in [speed_min_m_s, speed_max_m_s]; each is released after a hold time
    uniform in [hold_min_s, hold_max_s] (a release emission when release_emissions is on)."""
    geo = ctx.config.geometry
    rng = seeded_rng(ctx.seed, 41)
    n = rng.poisson(p["rate_hz"] * ctx.duration_s)
    t = np.sort(rng.uniform(0.0, ctx.duration_s, n))
    cmin = math.cos(math.radians(p["max_polar_deg"]))
    th = np.arccos(rng.uniform(cmin, 1.0, n))
    ph = rng.uniform(0, 2 * np.pi, n)
    pts = geo.surface_point_from_angles(th, ph)
    v = rng.uniform(p["speed_min_m_s"], p["speed_max_m_s"], n)
    lists = [
        EmissionList.create(
            to_ns(t),
            pts,
            "touch",
            polarity=COMPRESSION,
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
                to_ns(tr[ok]),
                pts[ok],
                "release",
                polarity=RAREFACTION,
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
    lists = [make_emissions(ctx, [p["time_s"]], pt, "touch", ev, COMPRESSION, [0])]
    t_rel = p["time_s"] + p["hold_s"]
    if ctx.effects["release_emissions"]:
        evr = EventParams(p["release_speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
        lists.append(make_emissions(ctx, [t_rel], pt, "release", evr, RAREFACTION, [1]))
    return StaticEmissions(
        EmissionList.concat(lists),
        {"generator": "touch_hold_release", "release_time_ns": int(to_ns(t_rel))},
    )


def texture(ctx, p):
    """Sliding at speed_m_s over a texture of spatial period period_m: emissions at the
    mean rate v / lambda, the n-th at t0 + n lambda / v + jitter (Gaussian, std
    jitter_fraction of the period), from points uniform in the contact patch."""
    geo = ctx.config.geometry
    rng = seeded_rng(ctx.seed, 51)
    rate = p["slide_speed_m_s"] / p["period_m"]
    t0, t1 = p["start_s"], min(ctx.duration_s, p["start_s"] + p["slide_duration_s"])
    n = max(0, int(math.floor((t1 - t0) * rate)))
    t = t0 + np.arange(n) / rate + rng.normal(0.0, p["jitter_fraction"] / rate, n)
    keep = (t >= 0) & (t < ctx.duration_s)
    c = geo.surface_point_from_xy(p["x_m"], p["y_m"])
    check_patch(geo, c, p["contact_radius_m"], "texture")
    u, v = uniform_disc(rng, n, 0.0, p["contact_radius_m"])
    pts = patch_points(geo, c, u, v)
    ev = EventParams(p["speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
    pol = rng.choice([-1.0, 1.0], n) if p["random_polarity"] else np.ones(n)
    em = make_emissions(ctx, t[keep], pts[keep], "texture", ev, pol[keep], np.arange(n)[keep])
    return StaticEmissions(em, {"generator": "texture", "emission_rate_hz": rate})

# ---------------------------------------------------------------------- moving contact
def stylus(ctx, p):
    """A stylus dragged over the tip: it touches at (x_m, y_m) at start_s (a touch
    emission), slides along the great circle heading ``heading_deg`` (from +x toward +y in
    the tangent plane) at ``slide_speed_m_s`` for ``path_m``, then lifts off (a release,
    when release_emissions is on). While it slides over a texture of spatial period
    ``period_m`` it emits at arc lengths n lambda (times n lambda / v + Gaussian jitter,
    std ``jitter_fraction`` of the period), from points uniform in a patch of radius
    ``contact_radius_m`` around the moving centre; a fraction ``miss_fraction`` of the
    ridges stays silent. Polarity: 'random', 'compression' or 'rarefaction'. Truth: the
    track (start and end times, start point, direction and speed, from which the centre and
    velocity follow at any time), the period and the emission rate."""
    geo = ctx.config.geometry
    rng = seeded_rng(ctx.seed, 71)
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
        check_patch(geo, q, p["contact_radius_m"], "stylus")
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
    pol = choose_polarity(rng.choice([-1.0, 1.0], n), p["polarity"])
    lists = [make_emissions(ctx, t[keep], pts[keep], "texture", ev, pol[keep],
                            2 + np.arange(n)[keep])]
    if t0 < ctx.duration_s:
        lists.append(
            make_emissions(
                ctx,
                [t0],
                p0[None, :],
                "touch",
                EventParams(p["touch_speed_m_s"], p["curvature_1_m"], p["alpha_1_s"]),
                COMPRESSION,
                [0],
            )
        )
    t_end = t0 + dur
    if ctx.effects["release_emissions"] and t_end < ctx.duration_s:
        lists.append(
            make_emissions(
                ctx,
                [t_end],
                rotate_on_sphere(p0, d, [p["path_m"] / R]),
                "release",
                EventParams(p["touch_speed_m_s"] * 0.5, p["curvature_1_m"], p["alpha_1_s"]),
                RAREFACTION,
                [1],
            )
        )
    truth = {
        "generator": "stylus",
        "start_time_ns": int(to_ns(t0)),
        "end_time_ns": int(to_ns(t_end)),
        "slide_speed_m_s": v,
        "period_m": lam,
        "emission_rate_hz": v / lam,
        "start_point_m": [float(x) for x in p0],
        "direction": [float(x) for x in d],
        "n_texture_emissions": int(keep.sum()),
    }
    return StaticEmissions(EmissionList.concat(lists), truth)

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
    rng = seeded_rng(ctx.seed, 81)
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
        "burst_times_ns": [] if p["shared_clock"] else [int(x) for x in to_ns(t)],
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
            burst_start_time_ns=int(to_ns(p["start_s"])),
            burst_end_time_ns=int(to_ns(end)),
        )
    lists = []
    n_taps = int(p["taps_before"])
    if n_taps:
        geo = ctx.config.geometry
        rng_t = seeded_rng(ctx.seed, 82)
        pol = np.radians(rng_t.uniform(10.0, 45.0, n_taps))
        az = rng_t.uniform(0.0, 2.0 * math.pi, n_taps)
        pts = geo.surface_point_from_xy(geo.radius_m * np.sin(pol) * np.cos(az),
                                        geo.radius_m * np.sin(pol) * np.sin(az))
        t_tap = 0.005 + 0.03 * np.arange(n_taps)
        ev = EventParams(p["speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
        ids = 100 + 2 * np.arange(n_taps)
        lists.append(make_emissions(ctx, t_tap, pts, "touch", ev, COMPRESSION, ids))
        if ctx.effects["release_emissions"]:
            evr = EventParams(p["release_speed_m_s"], p["curvature_1_m"], p["alpha_1_s"])
            lists.append(make_emissions(ctx, t_tap + 0.01, pts, "release", evr, RAREFACTION,
                                        ids + 1))
    if p["hold_s"] > 0:
        # a held touch (touch_hold_release) under the interference: the false-alarm scene
        sub = touch_hold_release(ctx, {**p, "time_s": p["touch_time_s"]})
        lists.append(sub.emissions)
        truth.update(
            {
                "touch_time_ns": int(to_ns(p["touch_time_s"])),
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
