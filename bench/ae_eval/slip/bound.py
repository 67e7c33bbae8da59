# SPDX-License-Identifier: Apache-2.0
"""The Bayes bound on SLIP decisions: on `incipient_slip_trial`'s scene, the posterior that
gross slip has begun, computed with the truth no detector has (the scene family's prior,
the ramp's start, the simulator's emission model, the contact's true centre and a_H)."""

from __future__ import annotations

import math

import numpy as np
from scipy.special import ndtr

from .common import EVENTS_DROP, NS
from .incipient import INCIPIENT_RANGES, incipient_slip_scene
from .pipelines import scene_events

#: thresholds on the gross-slip posterior reported by `summarize_gross_slip_bound`
BOUND_THRESHOLDS = (0.5, 0.8, 0.9, 0.95, 0.98, 0.99, 0.999)


def gross_slip_bound_trial(
    seed: int,
    *,
    micro_slip_count=(4.0, 12.0),
    slip_rate_hz=(100.0, 200.0),
    post_s: float = 0.25,
    use_position: bool = True,
    announce_touch: bool = False,
    n_t: int = 600,
) -> dict:
    """What any SLIP decision could do on `incipient_slip_trial`'s scene ('events'
    pipeline, the same seed: the same emissions; never announced, or ``announce_touch``:
    a grasp loaded 80 ms after its touch, the touch itself left out): the Bayes
    posterior that gross slip has begun, P(T <= t - t_0 | emissions up to t), at each
    emission, computed with what no detector has: the scene family's prior (T
    log-uniform over time_to_gross_slip_s, N uniform over ``micro_slip_count``, s
    log-uniform over ``slip_rate_hz``: a grid of ``n_t`` x 17 x 5), the ramp's start
    (t_0 = 0, or 0.1 s after a touch; q = (t - t_0) / T), the simulator's emission model,
    and (``use_position``) the contact's true centre and a_H:

      micro-slips (t < T): Poisson at k N (2/3) (1 - q)^(-1/3) / T (uniform in the slip
      fraction f = 1 - (1 - q)^(2/3)), radially uniform by area over kappa < rho < 1,
      kappa = (1 - q)^(1/3), rho = r / a_H; gross slip (t >= T): Poisson at k s, over
      0 < rho < 1; k = 1 - EVENTS_DROP; each radial density blurred by the emission's
      localization sigma_rho: [Phi((rho - kappa) / sigma_rho) - Phi((rho - 1) / sigma_rho)]
      / (1 - kappa^2); log L = sum log(rate x density) - k N f(min(t / T, 1)) - k s (t - T)+.

    A decision 'SLIP once the posterior reaches pi' (Shiryaev's rule) is the Bayes-optimal
    quickest detection for this prior; it bounds the detector, which knows none of that."""
    scene, source, params = incipient_slip_scene(
        seed,
        post_s=post_s,
        micro_slip_count=micro_slip_count,
        slip_rate_hz=slip_rate_hz,
        announce_touch=announce_touch,
    )
    end_ns = int(round(scene.duration_s * NS))
    events, _ = scene_events(scene, source, end_ns, "events")
    t0_ns = int(round(scene.process.t_start_ns))
    events = [e for e in events if e.time_ns >= t0_ns]  # the touch is no micro-slip
    t_g = scene.process.scene_truth(end_ns)["gross_slip_time_ns"]
    centre = np.asarray(scene.process.center, dtype=float)
    a_h = float(params["hertz_radius_m"])
    T, N, S = _prior_grid(micro_slip_count, slip_rate_hz, n_t)
    k = 1.0 - EVENTS_DROP
    log_sum = np.zeros(T.size)
    post = []
    for e in events:
        u = (e.time_ns - t0_ns) * 1e-9
        pre = u < T
        one_q = np.where(pre, 1.0 - u / T, 1.0)
        rate = np.where(pre, k * N * (2.0 / 3.0) * one_q ** (-1.0 / 3.0) / T, k * S)
        if use_position:
            rate = rate * np.maximum(_radial_density(e, centre, a_h, pre, one_q), 1e-300)
        log_sum += np.log(rate)
        f = np.where(pre, 1.0 - one_q ** (2.0 / 3.0), 1.0)  # slip fraction at t
        ll = log_sum - k * N * f - k * S * np.maximum(u - T, 0.0)
        w = np.exp(ll - ll.max())
        post.append(min(1.0, float(w[~pre].sum() / w.sum())))
    return {
        "seed": int(seed),
        "use_position": bool(use_position),
        "time_to_gross_slip_s": float(params["time_to_gross_slip_s"]),
        "ramp_start_ns": t0_ns,
        "gross_slip_time_ns": t_g,
        "times_ns": [int(e.time_ns) for e in events],
        "posterior": post,
    }


def _prior_grid(micro_slip_count, slip_rate_hz, n_t):
    """The prior's grid, flattened: time to gross slip T [s] (``n_t`` log-spaced over
    INCIPIENT_RANGES), mean micro-slip count N (17 over ``micro_slip_count``), gross-slip
    rate s [1/s] (5 log-spaced over ``slip_rate_hz``)."""
    lo, hi, _ = INCIPIENT_RANGES["time_to_gross_slip_s"]
    return (
        x.ravel()
        for x in np.meshgrid(
            np.exp(np.linspace(math.log(lo), math.log(hi), n_t)),
            np.linspace(*micro_slip_count, 17),
            np.exp(np.linspace(math.log(slip_rate_hz[0]), math.log(slip_rate_hz[1]), 5)),
            indexing="ij",
        )
    )


def _radial_density(e, centre, a_h, pre, one_q):
    """The density of event ``e``'s radius rho = r / a_H over the grid: micro-slips
    (``pre``) uniform by area over the annulus kappa < rho < 1, kappa = ``one_q``^(1/3);
    gross slip over the disc; blurred by the event's localization sigma."""
    # the simulator places emissions in the tangent plane at the centre, then on the
    # sphere along their radius: back into that plane
    pt = np.asarray(e.point_m, dtype=float)
    pt = pt * (float(centre @ centre) / float(pt @ centre))
    rho = float(np.linalg.norm(pt - centre)) / a_h
    s_rho = max(math.sqrt(max(float(np.trace(e.covariance_m2)), 0.0) / 2.0) / a_h, 1e-3)
    kap = np.where(pre, one_q ** (1.0 / 3.0), 0.0)
    outer = float(ndtr((rho - 1.0) / s_rho))
    return (ndtr((rho - kap) / s_rho) - outer) / np.maximum(1.0 - kap * kap, 1e-12)


def summarize_gross_slip_bound(trials: list[dict], thresholds=BOUND_THRESHOLDS) -> dict:
    """Per posterior threshold pi, the rule 'SLIP at the first emission whose posterior
    reaches pi': share of trials with SLIP within 50 ms of gross slip, with SLIP at
    q < 0.9 (t < 0.9 T: the ramp starts at 0), and the delay's p95 (none: infinite)."""
    out = {"n_trials": len(trials), "by_threshold": {}}
    for pi in thresholds:
        d, early = [], 0
        for r in trials:
            tg = r["gross_slip_time_ns"]
            t = next((t for t, p in zip(r["times_ns"], r["posterior"]) if p >= pi), None)
            d.append(math.inf if t is None else (t - tg) / 1e6)
            q090_ns = r["ramp_start_ns"] + 0.9 * r["time_to_gross_slip_s"] * NS
            early += t is not None and t < q090_ns
        n = max(len(trials), 1)
        out["by_threshold"][f"{pi:g}"] = {
            "slip_within_50ms_rate": sum(x <= 50.0 for x in d) / n,
            "slip_before_q090_rate": early / n,
            "slip_delay_p95_ms": float(np.percentile(d, 95, method="higher")) if d else None,
        }
    return out
