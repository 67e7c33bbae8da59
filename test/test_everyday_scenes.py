# SPDX-License-Identifier: Apache-2.0
"""The everyday scene families' truth (ae_eval.everyday) against independent
expectations, and the scorer on hand-made outputs."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from ae_eval.everyday import (
    FAMILIES,
    SceneBuilder,
    broad_press,
    grasp_load,
    multi_point,
    renewal_times,
    score_trial,
    slide_restick_ramp,
    slide_start,
    slipped_fraction,
    stylus,
    summarize,
    to_events,
)
from ae_eval.everyday.loaded import add_load
from ae_eval.everyday.mixed import concat, mixed_stream
from ae_eval.everyday.truth import GROSS, INC, NO, STICK, disc_xy
from ae_tactile.records import EventType

NS = 1_000_000_000


def _kind(scene, name):
    return np.array(scene.kind_names()) == name


def _skin(p, q, radius_m=10e-3):
    """Great-circle distance [m] between the sphere points above in-plane p and q."""
    a, b = (np.array([x, y, math.sqrt(radius_m**2 - x * x - y * y)]) for x, y in (p, q))
    return radius_m * math.acos(min(1.0, float(a @ b) / radius_m**2))


def test_a_ring_round_a_contact_off_the_apex_is_round_on_the_skin():
    """Points drawn at one distance round a contact 5 mm off the apex are that far from
    it along the skin in every direction (in the x-y plane they would lie on an ellipse,
    ~15 % longer along the meridian)."""
    rng = np.random.default_rng(5)
    pts = disc_xy(rng, 5e-3, 0.0, 1e-3, 1e-3, 200)
    d = [_skin((5e-3, 0.0), p) for p in pts]
    assert np.allclose(d, 1e-3, rtol=1e-9)
    # towards the apex the ring reaches polar angle theta - phi (phi = 1 mm / R)
    theta, phi = math.asin(0.5), 0.1
    assert 5e-3 - pts[:, 0].min() == pytest.approx(10e-3 * (0.5 - math.sin(theta - phi)),
                                                   rel=1e-3)


@pytest.mark.parametrize("held_out", [False, True])
def test_multi_point_one_touch_and_one_release_per_point(held_out):
    for seed in range(40):
        sc = multi_point(seed, held_out)
        n = sc.params["n_points"]
        assert (2 <= n <= 4) or held_out
        touch, rel = _kind(sc, "touch"), _kind(sc, "release")
        assert touch.sum() == n and rel.sum() == n and sc.t_s.size == 2 * n
        assert np.all(sc.polarity[touch] == 1) and np.all(sc.polarity[rel] == -1)
        assert sorted(sc.contact[touch]) == list(range(n)) == sorted(sc.contact[rel])
        assert np.ptp(sc.t_s[touch]) <= sc.params["window_s"] + 1e-12
        assert np.ptp(sc.t_s[rel]) <= sc.params["release_window_s"] + 1e-12
        assert sc.t_s[touch].max() < sc.t_s[rel].min()
        pts = sc.xy_m[touch]
        d = [_skin(p, q) for i, p in enumerate(pts) for q in pts[i + 1:]]
        lo, hi = (1.0e-3, 9e-3) if held_out else (1.5e-3, 7e-3)
        assert lo - 1e-12 <= min(d) and max(d) <= hi + 1e-12
        tl = sc.finger_timeline()
        assert [s for _, s in tl] == [NO, STICK, NO]
        assert tl[-1][0] == pytest.approx(sc.t_s[rel].max())


def test_broad_press_emissions_on_its_disc():
    for seed in range(40):
        sc = broad_press(seed)
        p = sc.params
        assert 1 <= p["n_compressions"] <= 6 and 1 <= p["n_releases"] <= 6
        assert 1e-3 <= p["disc_radius_m"] <= 2e-3
        assert _kind(sc, "touch").sum() == p["n_compressions"]
        assert _kind(sc, "release").sum() == p["n_releases"]
        c = sc.contacts[0]
        r = np.array([_skin((c["x_m"], c["y_m"]), q) for q in sc.xy_m])
        assert np.all(r <= p["disc_radius_m"] + 1e-12) and len(sc.contacts) == 1
        assert np.ptp(sc.t_s[_kind(sc, "touch")]) <= p["window_s"]


def test_load_ramp_micro_slips_follow_cattaneo_mindlin():
    b = SceneBuilder("t", 0, False, np.random.default_rng(1))
    cid = b.contact(0.0, 0.0, 0.01, 0.0, touch=False, release=False)
    n, ramp, a = 300, 2.0, 1e-3
    add_load(b, cid, 0.0, 0.0, a, 0.1, ramp, n, gross=(100.0, 0.2))
    sc = b.build()
    ep = sc.episodes[0]
    mt = np.array(ep["micro_times_s"])
    for q in (0.1, 0.3, 0.5, 0.7, 0.9, 0.99):
        count = np.sum(mt <= 0.1 + q * ramp)
        assert abs(count - n * (1.0 - (1.0 - q) ** (2.0 / 3.0))) <= 1.0
    # each micro-slip at the stick front c(q) = a (1 - q)^(1/3) or just outside it
    q = np.array(ep["q_micro"])
    m = _kind(sc, "micro_slip")
    r = np.array([_skin((0.0, 0.0), p) for p in sc.xy_m[m]])
    c = a * (1.0 - q) ** (1.0 / 3.0)
    assert np.all(r >= c - 1e-12) and np.all(r <= c + 0.1 * (a - c) + 1e-12)
    assert ep["t_gross_s"] == pytest.approx(0.1 + ramp)
    assert np.all(sc.t_s[_kind(sc, "slip")] >= ep["t_gross_s"])
    assert [s for _, s in sc.finger_timeline()] == [NO, STICK, INC, GROSS]
    assert slipped_fraction(np.array([0.0, 1.0])).tolist() == [0.0, 1.0]


def test_renewal_processes():
    rng = np.random.default_rng(3)
    iv = np.diff(renewal_times(rng, "poisson", 100.0, 0.0, 200.0))
    assert iv.mean() == pytest.approx(0.01, rel=0.03)
    assert iv.std() / iv.mean() == pytest.approx(1.0, abs=0.05)  # exponential: CV 1
    # exponential quantiles: P(interval > x) = exp(-x / mean)
    for x in (0.005, 0.01, 0.03):
        assert np.mean(iv > x) == pytest.approx(math.exp(-x / 0.01), abs=0.02)
    iv = np.diff(renewal_times(rng, "periodic", 100.0, 0.0, 50.0, jitter=0.05))
    assert iv.mean() == pytest.approx(0.01, rel=0.01)
    assert iv.std() / iv.mean() == pytest.approx(0.05, abs=0.01)


def test_slide_start_is_gross_slip_from_the_start():
    for seed in range(20):
        sc = slide_start(seed)
        ep = sc.episodes[0]
        assert 20 <= ep["rate_hz"] <= 200 and ep["process"] in ("periodic", "poisson")
        assert [s for _, s in sc.finger_timeline()] == [NO, GROSS, NO]
        assert sc.t_s[0] == pytest.approx(ep["t_start_s"])


def test_mixed_stream_adds_up():
    parts = [(0.0, multi_point(1)), (5.0, slide_restick_ramp(2)), (12.0, grasp_load(3))]
    sc = concat(parts, "mixed", 0, False, 20.0)
    assert sc.t_s.size == sum(p.t_s.size for _, p in parts)
    assert len(sc.contacts) == sum(len(p.contacts) for _, p in parts)
    assert np.all(np.diff(sc.t_s) >= 0)
    ends = [t0 + p.duration_s for t0, p in parts]
    assert all(e <= n for e, (n, _) in zip(ends, parts[1:]))
    tl = sc.finger_timeline()
    assert tl[-1][1] == NO
    for t0, _ in parts[1:]:  # idle before each scene
        assert max(s for t, s in tl if t <= t0 - 1e-6) >= 0
        assert [s for t, s in tl if t < t0][-1] == NO
    m = mixed_stream(4)
    assert m.duration_s == 60.0 and m.t_s.max() < 60.0 and len(m.params["scenes"]) >= 3
    gross = [e["t_gross_s"] for e in m.episodes if e["type"] == "load" and e["t_gross_s"]]
    assert all(0 < g < 60 for g in gross)


def test_every_family_builds_nominal_and_held_out():
    for name, gen in FAMILIES.items():
        for ho in (False, True):
            sc = gen(7, ho)
            assert sc.t_s.size > 0 and sc.duration_s > sc.t_s.max(), name
            ev = to_events(sc, np.random.default_rng(0), drop=0.0)
            assert len(ev) == sc.t_s.size
            assert all(np.sign(e.amplitude_v) == e.polarity for e in ev)


def _out(kind, t_s, onset=True, rate=math.nan, sp=math.nan):
    return SimpleNamespace(kind=kind, time_ns=int(round(t_s * NS)), onset=onset,
                           emission_rate_hz=rate, spatial_period_m=sp)


def _perfect(sc):
    """What a perfect detector reports: the truth's states, a precursor at each load's
    first micro-slip, SLIP at gross slip and at each slide's start, TEXTURE at the
    third ridge of a stroke with its period."""
    outs = []
    for ep in sc.episodes:
        if ep["type"] == "load" and ep["t_gross_s"] is not None:
            outs.append(_out(EventType.SLIP_PRECURSOR, ep["micro_times_s"][0]))
            outs.append(_out(EventType.SLIP, ep["t_gross_s"]))
        if ep["type"] == "slide":
            outs.append(_out(EventType.SLIP, ep["times_s"][0]))
        if ep["type"] == "texture":
            t = ep["times_s"][2]
            T = float(np.interp(t, ep["times_s"], ep["period_s"]))
            outs.append(_out(EventType.TEXTURE, t, rate=1.0 / T, sp=ep["spatial_period_m"]))
    outs.sort(key=lambda o: o.time_ns)
    trace = [(int(round(t * NS)), s) for t, s in sc.finger_timeline()]
    return outs, trace


def test_perfect_detector_scores_full_marks():
    for name, gen in FAMILIES.items():
        trials = [score_trial(gen(s), *_perfect(gen(s))) for s in range(3)]
        s = summarize(name, trials)
        assert s["false_per_h"] == 0 and s["state_share"] == 1.0, name
        assert s["no_contact_after_release"] == 1.0, name
        assert all(v[1] in (True, None) for v in s["targets"].values()), (name, s["targets"])
    r = score_trial(stylus(1), *_perfect(stylus(1)))
    assert r["textures"][0]["pass"]


def test_slip_at_every_emission_counted_by_hand():
    b = SceneBuilder("hand", 0, False, np.random.default_rng(0))
    b.contact(0.0, 0.0, 0.01, 1.0)  # a hold: touch at 0.01 s, release at 1.0 s
    b.contact(3e-3, 0.0, 0.2, 0.4)  # a touch beside it, 0.2 .. 0.4 s
    sc = b.build()  # 4 emissions, 1.5 s long
    outs = [_out(EventType.SLIP, t) for t in sc.t_s]
    trace = [(int(round(t * NS)), s) for t, s in sc.finger_timeline()]
    r = score_trial(sc, outs, trace)
    assert r["false_slip"] == 4 and r["false_any"] == 4 and r["false_onsets_slip"] == 4
    s = summarize("hold", [r])
    assert s["false_per_h"] == pytest.approx(4 / (1.5 / 3600))
    assert s["targets"]["false_alarms==0"][1] is False
    # on a slide from the start the same detector is right at every emission but the lift
    sc = slide_start(0)
    outs = [_out(EventType.SLIP, t) for t in sc.t_s]
    r = score_trial(sc, outs, [(int(round(t * NS)), s) for t, s in sc.finger_timeline()])
    assert r["false_any"] == 0 and r["slides"][0]["pass"]
    # a precursor in the middle of a hold, and a state stuck in STICK after the release
    outs = [_out(EventType.SLIP_PRECURSOR, 0.5)]
    trace = [(int(0.01 * NS), STICK)]
    sc = b.build()
    r = score_trial(sc, outs, trace)
    assert r["false_precursor"] == 1 and r["released"] == 1 and r["released_ok"] == 0
    # scored time: 1.5 s minus 0.1 s after each of the 2 changes of the finger's truth
    assert r["state_ms"] == pytest.approx(1300, abs=2)
    # wrong: from the release's settling (1.1 s) to the end (1.5 s)
    assert r["state_ok_ms"] == pytest.approx(1300 - 400, abs=2)


def test_bounds():
    from ae_eval.everyday.bounds import (
        q_at_kth_micro_slip,
        slide_decision_bound,
        slide_touch_confusion,
        stick_zone_bound,
    )

    c, p, n95 = stick_zone_bound(0.9)
    assert c == pytest.approx(0.1 ** (1 / 3)) and p == pytest.approx(c * c)
    assert (1 - p) ** n95 == pytest.approx(0.05)
    assert slipped_fraction(q_at_kth_micro_slip(3, 10)) == pytest.approx(0.3)
    # Poisson at exactly 50 Hz, no loss: the 3rd emission (2 after t0) within 0.1 s
    exact = 1 - math.exp(-5) * (1 + 5)
    got = slide_decision_bound(3, rates=(50.0, 50.0), drop=0.0, n=40_000)
    assert got == pytest.approx(exact, abs=0.01)
    assert slide_touch_confusion(1, n=1000) == pytest.approx(0.5)
    assert slide_touch_confusion(3, n=20_000) < 0.01
