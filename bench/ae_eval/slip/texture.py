# SPDX-License-Identifier: Apache-2.0
"""Moving and periodic contacts: a stylus dragged over a texture (TEXTURE from the
tracked speed), sliding over a texture at a known speed, and plane slip drifting along x
(the SLIP direction)."""

from __future__ import annotations

import math

import numpy as np

from ae_eval.sim_truth import stylus_track
from ae_tactile.records import EventType
from ae_tactile.sim.scene import load_scene
from ae_tactile.slip import SlipConfig

from .common import NS, cap_point_xy, first_output
from .pipelines import localized_events, run_detector, scene_events


def stylus_events(
    seed: int,
    *,
    pipeline: str = "triggered",
    jitter: tuple = (0.0, 0.2),
    period_m: tuple = (0.2e-3, 0.6e-3),
):
    """(scene, its scene spec, localized events (time order), number of true emissions,
    end_ns) of `stylus_trial`'s slide ``seed``: speed 5 .. 50 mm/s and period (m) log-uniform,
    timing jitter uniform in ``jitter`` (fraction of the period), a great-circle stroke of
    40 periods (8 .. 14 mm)."""
    rng = np.random.default_rng([7023, int(seed)])
    v = float(math.exp(rng.uniform(math.log(0.005), math.log(0.05))))
    lam = float(math.exp(rng.uniform(math.log(period_m[0]), math.log(period_m[1]))))
    jit = float(rng.uniform(*jitter))
    path = float(min(14e-3, max(8e-3, 40 * lam)))
    heading = float(rng.uniform(0, 360))
    h = math.radians(heading)
    x0, y0 = -0.5 * path * math.cos(h), -0.5 * path * math.sin(h)
    medium = "silicone" if rng.uniform() < 0.5 else "water_skin"
    dur = 0.01 + path / v + 0.1
    spec = {
        "generator": "stylus",
        "duration_s": dur,
        "seed": int(seed) + 8000,
        "sensor": {"medium": medium},
        "effects": {"attenuation": medium == "silicone"},
        "noise": {"snr_db": float(rng.uniform(25, 35))},
        "params": {
            "x_m": x0,
            "y_m": y0,
            "heading_deg": heading,
            "slide_speed_m_s": v,
            "period_m": lam,
            "path_m": path,
            "jitter_fraction": jit,
            "contact_radius_m": float(rng.uniform(0.1e-3, 0.4e-3)),
            "polarity": str(rng.choice(["random", "compression", "rarefaction"])),
        },
    }
    scene = load_scene(spec)
    end_ns = int(round(dur * NS))
    events, n_em = scene_events(scene, None, end_ns, pipeline)
    return scene, spec, events, n_em, end_ns


def stylus_trial(
    seed: int,
    config: SlipConfig | None = None,
    *,
    pipeline: str = "triggered",
    jitter: tuple = (0.0, 0.2),
    period_m: tuple = (0.2e-3, 0.6e-3),
) -> dict:
    """A stylus dragged over the tip (the stylus scene, `stylus_events`): one tracked
    contact, TEXTURE with the spatial period from the tracked speed (no sliding speed
    given), its error, the time to the first TEXTURE, the number of contacts the emissions
    were split into."""
    scene, spec, events, n_em, end_ns = stylus_events(
        seed, pipeline=pipeline, jitter=jitter, period_m=period_m
    )
    v, lam = spec["params"]["slide_speed_m_s"], spec["params"]["period_m"]
    jit, path = spec["params"]["jitter_fraction"], spec["params"]["path_m"]
    det, outs, trace = run_detector(events, config, end_ns)
    truth = scene.process.scene_truth()
    tex = [o for o in outs if o.kind == EventType.TEXTURE]
    lam_est = np.array([o.spatial_period_m for o in tex])
    first = tex[0] if tex else None
    # contacts that raised an alarm (the TOUCH / DETOUCH of short-lived ones are no alarm)
    ids = {o.contact_id for o in outs if o.kind in (EventType.SLIP, EventType.TEXTURE)}
    dir_err = []
    for o in outs:
        if o.kind in (EventType.SLIP, EventType.TEXTURE) and np.all(
            np.isfinite(o.slip_direction)
        ):
            _, vel = stylus_track(truth, scene.config.geometry.radius_m, [o.time_ns])
            u = vel[0] / np.linalg.norm(vel[0])
            dir_err.append(math.degrees(math.acos(float(np.clip(o.slip_direction @ u, -1, 1)))))
    return {
        "seed": int(seed),
        "slide_speed_m_s": v,
        "period_m": lam,
        "jitter_fraction": jit,
        "path_m": path,
        "polarity": spec["params"]["polarity"],
        "n_emissions": n_em,
        "n_events": len(events),
        "n_contacts_reporting": len(ids),
        "n_texture": len(tex),
        "texture_delay_ms": None
        if first is None
        else (first.time_ns - truth["start_time_ns"]) / 1e6,
        "rel_error_first": None if first is None else float(first.spatial_period_m / lam - 1.0),
        "rel_error_median": None if not tex else float(np.nanmedian(lam_est) / lam - 1.0),
        "rel_error_max": None if not tex else float(np.nanmax(np.abs(lam_est / lam - 1.0))),
        "direction_error_deg_median": None if not dir_err else float(np.median(dir_err)),
        "n_precursor": sum(o.kind == EventType.SLIP_PRECURSOR for o in outs),
    }


def texture_trial(
    seed: int, config: SlipConfig | None = None, *, speed_known: bool = True
) -> dict:
    """Sliding at v (5-50 mm/s) over a texture with emission rate v/lambda in 10-150 Hz."""
    rng = np.random.default_rng([7004, int(seed)])
    v = float(math.exp(rng.uniform(math.log(0.005), math.log(0.05))))
    rate = float(math.exp(rng.uniform(math.log(10.0), math.log(150.0))))
    lam = v / rate
    x, y = cap_point_xy(rng, 0.01, 50.0)
    dur = max(1.0, 40.0 / rate)
    spec = {
        "generator": "texture",
        "duration_s": dur,
        "seed": int(seed) + 4000,
        "sensor": {"medium": "silicone"},
        "effects": {"attenuation": True},
        "noise": {"snr_db": float(rng.uniform(25, 35))},
        "params": {
            "x_m": x,
            "y_m": y,
            "slide_speed_m_s": v,
            "period_m": lam,
            "jitter_fraction": float(rng.uniform(0.02, 0.08)),
            "contact_radius_m": float(rng.uniform(0.5e-3, 1.5e-3)),
        },
    }
    scene = load_scene(spec)
    end_ns = int(round(dur * NS))
    pk = scene.triggered_source().next_packets(1 << 30, horizon_ns=end_ns)
    events = localized_events(pk, scene.config.geometry)
    det, outs, trace = run_detector(
        events, config, end_ns, sliding_speed_m_s=v if speed_known else None
    )
    tex = [o for o in outs if o.kind == EventType.TEXTURE]
    first = tex[0] if tex else None
    lam_est = np.array([o.spatial_period_m for o in tex])
    out = {
        "seed": int(seed),
        "slide_speed_m_s": v,
        "period_m": lam,
        "rate_hz": rate,
        "jitter_fraction": spec["params"]["jitter_fraction"],
        "n_emissions": int(len(pk.emissions)),
        "n_events": len(events),
        "n_texture": len(tex),
        "texture_time_ms": None if first is None else first.time_ns / 1e6,
        "period_first_m": None if first is None else float(first.spatial_period_m),
        "period_median_m": None if not tex else float(np.median(lam_est)),
        "rate_first_hz": None if first is None else float(first.emission_rate_hz),
        "rel_error_first": None if first is None else float(first.spatial_period_m / lam - 1.0),
        "rel_error_median": None if not tex else float(np.median(lam_est) / lam - 1.0),
        "rel_error_max": None if not tex else float(np.max(np.abs(lam_est / lam - 1.0))),
        "final_state": int(det.state.state),
    }
    out.update(
        {
            "n_precursor": sum(o.kind == EventType.SLIP_PRECURSOR for o in outs),
            "n_slip": sum(o.kind == EventType.SLIP for o in outs),
        }
    )
    return out


def drift_slip_trial(
    seed: int, config: SlipConfig | None = None, *, pipeline: str = "triggered"
) -> dict:
    """plane_slip with the contact drifting along +x: SLIP delay after the slip start and
    the angle between the reported direction and +x (projected on the tangent plane)."""
    rng = np.random.default_rng([7005, int(seed)])
    drift = float(rng.uniform(0.01, 0.04))
    rad = float(rng.uniform(1e-3, 2.5e-3))
    x0 = float(rng.uniform(-3e-3, 0.0))
    y0 = float(rng.uniform(-2e-3, 2e-3))
    dur_slip = 0.15
    spec = {
        "generator": "plane_slip",
        "duration_s": 0.2,
        "seed": int(seed) + 5000,
        "sensor": {"medium": "silicone"},
        "effects": {"attenuation": True},
        "noise": {"snr_db": 30.0},
        "params": {
            "x_m": x0,
            "y_m": y0,
            "start_s": 0.01,
            "slip_duration_s": dur_slip,
            "rate_hz": float(rng.uniform(150, 500)),
            "contact_radius_m": rad,
            "drift_m_s": drift,
        },
    }
    scene = load_scene(spec)
    end_ns = int(0.2 * NS)
    events, _ = scene_events(scene, None, end_ns, pipeline)
    det, outs, trace = run_detector(events, config, end_ns)
    slips = [o for o in outs if o.kind == EventType.SLIP]
    first = first_output(outs, EventType.SLIP)
    angles = []
    for o in slips:
        if np.all(np.isfinite(o.slip_direction)):
            n = o.position_m / np.linalg.norm(o.position_m)
            ex = np.array([1.0, 0.0, 0.0]) - n[0] * n
            ex /= np.linalg.norm(ex)
            angles.append(math.degrees(math.acos(float(np.clip(o.slip_direction @ ex, -1, 1)))))
    return {
        "seed": int(seed),
        "drift_m_s": drift,
        "contact_radius_m": rad,
        "rate_hz": spec["params"]["rate_hz"],
        "n_events": len(events),
        "slip_delay_ms": None if first is None else (first.time_ns - int(0.01 * NS)) / 1e6,
        "n_slip": len(slips),
        "n_with_direction": len(angles),
        "direction_error_deg_median": None if not angles else float(np.median(angles)),
        "direction_error_deg_mean": None if not angles else float(np.mean(angles)),
        "direction_errors_deg": [float(a) for a in angles],
        "direction_error_deg_max": None if not angles else float(np.max(angles)),
    }

