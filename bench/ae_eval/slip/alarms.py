# SPDX-License-Identifier: Apache-2.0
"""False alarms: scenes without slip (touches held, tapped, released, grasped and
re-grasped) through a pipeline and the detector: any SLIP_PRECURSOR / SLIP / TEXTURE is
a false alarm; the latched state during the hold and after the release. Also the weak
releases of those scenes and the noise windows the weak-release gate must keep out."""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import Reason, localize
from ae_tactile.localization.weak_release import kept_with_weak_releases
from ae_tactile.sim.scene import load_scene
from ae_tactile.sim.stream import EmissionList
from ae_tactile.slip import SlipConfig

from .common import NS, NoEmissions, WithTouch, alarm_summary, cap_point_xy, cap_xy, state_at
from .pipelines import localized_events, run_detector, scene_events, triggered_source


def touch_hold_release_trial(
    seed: int,
    config: SlipConfig | None = None,
    *,
    pipeline: str = "triggered",
    hold_max_s: float = 30.0,
) -> dict:
    """Touch anywhere on the cap (polar <= 60 deg), hold 20 ms .. ``hold_max_s``
    (log-uniform: a grasp held for seconds, longer than the detector's 2 s evidence window,
    as well as a tap), release; random speeds, medium and SNR. False alarms and the latched
    state during the hold and 0.1 s after the release (NO_CONTACT once the release ended
    the contact)."""
    rng = np.random.default_rng([7002, int(seed)])
    medium = "silicone" if rng.uniform() < 0.5 else "water_skin"
    x, y = cap_point_xy(rng, 0.01, 60.0)
    hold = float(math.exp(rng.uniform(math.log(0.02), math.log(hold_max_s))))
    t0 = 0.005
    spec = {
        "generator": "touch_hold_release",
        "duration_s": t0 + hold + 0.1,
        "seed": int(seed) + 2000,
        "sensor": {"medium": medium},
        "effects": {"attenuation": medium == "silicone"},
        "noise": {"snr_db": float(rng.uniform(25, 35))},
        "params": {
            "x_m": x,
            "y_m": y,
            "time_s": t0,
            "hold_s": hold,
            "speed_m_s": float(rng.uniform(0.15, 0.5)),
            "release_speed_m_s": float(rng.uniform(0.1, 0.3)),
        },
    }
    scene = load_scene(spec)
    end_ns = int(round(scene.duration_s * NS))
    events, n_em = scene_events(scene, None, end_ns, pipeline)
    det, outs, trace = run_detector(events, config, end_ns, tick_ns=int(0.01 * NS))
    out = {
        "seed": int(seed),
        "duration_s": scene.duration_s,
        "hold_s": hold,
        "medium": medium,
        "pipeline": pipeline,
        "n_emissions": n_em,
        "n_events": len(events),
        "state_mid_hold": int(state_at(trace, int((t0 + hold / 2) * NS))),
        "state_end": int(det.state.state),
        "state_after_all_released": int(det.state.state),  # 0.1 s after the release
    }
    out.update(alarm_summary(outs))
    return out


def random_touches_trial(
    seed: int,
    config: SlipConfig | None = None,
    *,
    duration_s: float = 10.0,
    rate_hz: float = 20.0,
    hold_max_s: float = 0.05,
) -> dict:
    """The random_touches scene (Poisson touches over the cap with releases): false alarms."""
    rng = np.random.default_rng([7003, int(seed)])
    medium = "silicone" if rng.uniform() < 0.5 else "water_skin"
    spec = {
        "generator": "random_touches",
        "duration_s": duration_s,
        "seed": int(seed) + 3000,
        "sensor": {"medium": medium},
        "effects": {"attenuation": medium == "silicone", "release_emissions": True},
        "noise": {"snr_db": 30.0},
        "params": {
            "rate_hz": rate_hz,
            "max_polar_deg": 60.0,
            "hold_min_s": 0.005,
            "hold_max_s": hold_max_s,
        },
    }
    scene = load_scene(spec)
    end_ns = int(round(duration_s * NS))
    pk = scene.triggered_source().next_packets(1 << 30, horizon_ns=end_ns)
    events = localized_events(pk, scene.config.geometry)
    det, outs, trace = run_detector(events, config, end_ns, tick_ns=int(0.01 * NS))
    out = {
        "seed": int(seed),
        "duration_s": duration_s,
        "rate_hz": rate_hz,
        "hold_max_s": hold_max_s,
        "medium": medium,
        "n_emissions": int(len(pk.emissions)),
        "n_events": len(events),
        "counts": dict(det.counts),
    }
    out.update(alarm_summary(outs))
    return out


def _touch_list(scene, t_s, pts, pol, speed, ids):
    """Touch (polarity > 0) and release emissions at times ``t_s`` [s], points ``pts``
    (n, 3) [m], speeds ``speed`` [m/s], event ids ``ids``, on the scene's medium."""
    return EmissionList.create(
        np.round(np.asarray(t_s) * NS).astype(np.int64),
        pts,
        np.where(np.asarray(pol) > 0, "touch", "release") if np.ndim(pol) else "touch",
        polarity=pol,
        speed_m_s=speed,
        curvature_1_m=1000.0,
        alpha_1_s=3000.0,
        density_kg_m3=scene.config.density,
        event_id=ids,
    )


def _custom_trial(seed, spec, build, config, pipeline, tick=True):
    """Run a hand-built emission list (``build(scene, rng) -> EmissionList``) on the base
    scene ``spec``'s sensor and noise through a pipeline and the detector."""
    scene = load_scene(spec)
    rng = np.random.default_rng([7020, int(seed)])
    em = build(scene, rng)
    end_ns = int(round(scene.duration_s * NS))
    source = WithTouch(NoEmissions(), em)
    events, n_em = scene_events(scene, source, end_ns, pipeline)
    det, outs, trace = run_detector(
        events, config, end_ns, tick_ns=int(0.01 * NS) if tick else None
    )
    return scene, det, outs, trace, events, n_em


def tapping_trial(
    seed: int,
    config: SlipConfig | None = None,
    *,
    pipeline: str = "triggered",
    duration_s: float = 3.0,
) -> dict:
    """A touch held for the whole trial while another spot 1.5 .. 8 mm away is tapped at
    1 .. 10 Hz (each tap: a touch, held 10 .. 100 ms, and its release at the same spot):
    false alarms."""
    rng = np.random.default_rng([7021, int(seed)])
    medium = "silicone" if rng.uniform() < 0.5 else "water_skin"
    spec = {
        "generator": "single_touch",
        "duration_s": duration_s,
        "seed": int(seed) + 6000,
        "sensor": {"medium": medium},
        "effects": {"attenuation": medium == "silicone"},
        "noise": {"snr_db": float(rng.uniform(25, 35))},
    }
    x0, y0 = cap_xy(rng)
    d = float(rng.uniform(1.5e-3, 8e-3))
    ang = rng.uniform(0, 2 * math.pi)
    x1, y1 = x0 + d * math.cos(ang), y0 + d * math.sin(ang)
    if math.hypot(x1, y1) > 7.5e-3:
        x1, y1 = x0 - d * math.cos(ang), y0 - d * math.sin(ang)
    r1 = math.hypot(x1, y1)
    if r1 > 7.5e-3:
        x1, y1 = x1 * 7.5e-3 / r1, y1 * 7.5e-3 / r1
    rate = float(rng.uniform(1.0, 10.0))

    def build(scene, g):
        geo = scene.config.geometry
        p0, p1 = geo.surface_point_from_xy(x0, y0), geo.surface_point_from_xy(x1, y1)
        n = int(duration_s * rate)
        t = 0.05 + np.arange(n) / rate + g.uniform(0, 0.2 / rate, n)
        hold = g.uniform(0.01, 0.1, n)
        ok = t + hold < duration_s - 0.05
        t, hold = t[ok], hold[ok]
        times = np.concatenate([[0.01], t, t + hold, [duration_s - 0.02]])
        pts = np.vstack([p0[None], np.repeat(p1[None], 2 * t.size, 0), p0[None]])
        pol = np.concatenate([[1], np.ones(t.size), -np.ones(t.size), [-1]])
        spd = np.concatenate(
            [[0.3], g.uniform(0.1, 0.5, t.size), g.uniform(0.05, 0.2, t.size), [0.15]]
        )
        return _touch_list(scene, times, pts, pol, spd, np.arange(times.size))

    scene, det, outs, trace, events, n_em = _custom_trial(seed, spec, build, config, pipeline)
    out = {
        "seed": int(seed),
        "duration_s": duration_s,
        "distance_m": d,
        "tap_rate_hz": rate,
        "medium": medium,
        "pipeline": pipeline,
        "n_emissions": n_em,
        "n_events": len(events),
        "state_mid": int(state_at(trace, int(duration_s / 2 * NS))),
        "state_end": int(det.state.state),
    }
    out.update(alarm_summary(outs))
    return out


def cycles_trial(
    seed: int,
    config: SlipConfig | None = None,
    *,
    pipeline: str = "triggered",
    duration_s: float = 3.0,
    hold_s: tuple[float, float] = (0.02, 0.5),
) -> dict:
    """Touch-release cycles: touches held ``hold_s`` (uniform; 20 .. 500 ms: a finger
    pressing and lifting; seconds: grasps, releases and re-grasps), 10 .. 300 ms apart,
    each within 3 mm of the previous one: false alarms, and the latched state 0.1 s after
    the scene's end (every touch released by then)."""
    spec, build, medium = _cycles_scene(seed, duration_s, hold_s)
    scene, det, outs, trace, events, n_em = _custom_trial(seed, spec, build, config, pipeline)
    out = {
        "seed": int(seed),
        "duration_s": duration_s,
        "medium": medium,
        "pipeline": pipeline,
        "n_emissions": n_em,
        "n_events": len(events),
        "state_end": int(det.state.state),
        "state_after_all_released": int(
            det.advance(int(round((duration_s + 0.1) * NS))).state
        ),
    }
    out.update(alarm_summary(outs))
    return out


#: grasp-release cycles: `cycles_trial`'s scene with a robot hand's holds (s)
GRASP_CYCLES = {"duration_s": 30.0, "hold_s": (0.5, 10.0)}


def grasp_cycles_trial(
    seed: int, config: SlipConfig | None = None, *, pipeline: str = "triggered"
) -> dict:
    """Grasp-release cycles: grasps held 0.5 .. 10 s (longer than the detector's evidence
    window), released, the next within 3 mm, over 30 s (``GRASP_CYCLES``): false alarms,
    and the latched state at the end (every touch released)."""
    return cycles_trial(seed, config, pipeline=pipeline, **GRASP_CYCLES)


def cycles_packets(seed: int, duration_s: float = 3.0, hold_s=(0.02, 0.5)):
    """(triggered packets, geometry) of `cycles_trial`'s scene: the waveforms the
    'triggered' pipeline localizes, with their emissions (the truth)."""
    spec, build, _ = _cycles_scene(seed, duration_s, hold_s)
    scene = load_scene(spec)
    em = build(scene, np.random.default_rng([7020, int(seed)]))  # as `_custom_trial`
    end_ns = int(round(scene.duration_s * NS))
    source = WithTouch(NoEmissions(), em)
    pk = triggered_source(scene, source).next_packets(1 << 30, horizon_ns=end_ns)
    return pk, scene.config.geometry


def _cycles_scene(seed, duration_s, hold_s=(0.02, 0.5)):
    """(scene spec, emission builder, medium) of the touch-release cycles family."""
    rng = np.random.default_rng([7022, int(seed)])
    medium = "silicone" if rng.uniform() < 0.5 else "water_skin"
    spec = {
        "generator": "single_touch",
        "duration_s": duration_s,
        "seed": int(seed) + 7000,
        "sensor": {"medium": medium},
        "effects": {"attenuation": medium == "silicone"},
        "noise": {"snr_db": float(rng.uniform(25, 35))},
    }

    def build(scene, g):
        geo = scene.config.geometry
        times, pts, pol, spd = [], [], [], []
        t = 0.01
        x, y = cap_xy(g, 5e-3)
        while True:
            hold = g.uniform(*hold_s)
            if t + hold > duration_s - 0.01:
                break
            p = geo.surface_point_from_xy(x, y)
            times += [t, t + hold]
            pts += [p, p]
            pol += [1, -1]
            spd += [g.uniform(0.1, 0.5), g.uniform(0.05, 0.2)]
            t += hold + g.uniform(0.01, 0.3)
            r, a = g.uniform(0, 3e-3), g.uniform(0, 2 * math.pi)
            x, y = x + r * math.cos(a), y + r * math.sin(a)
            if math.hypot(x, y) > 7e-3:
                x, y = 0.5 * x, 0.5 * y
        return _touch_list(
            scene, times, np.array(pts), np.array(pol), np.array(spd), np.arange(len(times))
        )

    return spec, build, medium


def weak_release_trial(seed: int, duration_s: float = 3.0, hold_s=(0.02, 0.5)) -> dict:
    """The releases of a touch-release cycles scene (`cycles_trial`'s, waveforms) that the
    localizer rejects for low SNR alone, against the simulator's truth: estimated SNR,
    position error (m), polarity right, kept by the weak-release gate; and the packets the
    gate keeps that are not releases (should be none)."""
    pk, geo = cycles_packets(seed, duration_s, hold_s)
    res = localize(pk.samples_v, pk.sample_rate_hz, pk.onset_index, geometry=geo,
                   saturated=pk.saturated)
    kept, weak = kept_with_weak_releases(res, np.asarray(pk.emissions.time_ns, np.int64))
    truth_pol = np.sign(np.asarray(pk.emissions.strength_pa_m, float))
    err = np.linalg.norm(res.point_m - np.asarray(pk.emissions.point_m, float), axis=1)
    low = (np.asarray(res.reason_flags) == (1 << int(Reason.LOW_SNR))) & (truth_pol < 0)
    idx = np.flatnonzero(low)
    return {
        "seed": int(seed),
        "n_releases": int((truth_pol < 0).sum()),
        "low_snr_db": [float(res.snr_db_est[i]) for i in idx],
        "low_error_m": [float(err[i]) for i in idx],
        "low_polarity_right": [bool(res.polarity[i] < 0) for i in idx],
        "low_kept": [bool(weak[i]) for i in idx],
        "kept_not_release": int((weak & (truth_pol >= 0)).sum()),
    }


def noise_window_snr_db(n: int = 20000, sample_rate_hz: float = 5e6, seed: int = 0):
    """(estimated SNR dB, polarity, position 1-sigma per axis m, NaN unless the packet was
    rejected for low SNR alone) of ``n`` windows of white noise alone (the triggered
    windows' 40 us, onset 8 us in, at ``sample_rate_hz``): what the weak-release gate has
    to keep out."""
    rng = np.random.default_rng([7400, int(seed)])
    m = int(round(40e-6 * sample_rate_hz))
    x = rng.normal(0.0, 1e-3, (int(n), 4, m))
    on = np.full(int(n), int(round(8e-6 * sample_rate_hz)))
    res = localize(x, sample_rate_hz, on, geometry=FingertipGeometry())
    sd = np.sqrt(np.trace(res.covariance_m2, axis1=1, axis2=2) / 2.0)
    sd = np.where(np.asarray(res.reason_flags) == (1 << int(Reason.LOW_SNR)), sd, np.nan)
    return np.asarray(res.snr_db_est, float), np.asarray(res.polarity, int), sd

