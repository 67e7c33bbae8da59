# SPDX-License-Identifier: Apache-2.0
"""Scenes: YAML validation errors, generators (Cattaneo-Mindlin slip, texture rate,
touch/release), the example scenes, and the command-line tool."""
import glob
import math
import os

import numpy as np
import pytest

from ae_tactile.sim.cli import main as cli_main
from ae_tactile.sim.generators import (
    hertz_contact_radius_m,
    slip_fraction,
    stick_radius_m,
    tangent_basis,
)
from ae_tactile.sim.scene import SceneError, load_scene
from ae_tactile.sim.stream import KIND_CODE, StreamRenderer

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXAMPLES = sorted(glob.glob(os.path.join(ROOT, "config", "scenes", "*.yaml")))


def _all(scene):
    return scene.process.advance(int(scene.duration_s * 1e9) + 1)


# ----------------------------------------------------------------- examples
def test_every_generator_has_an_example_scene():
    from ae_tactile.sim.scene import GENERATORS
    names = {load_scene(f).generator for f in EXAMPLES}
    assert names == set(GENERATORS)


@pytest.mark.parametrize("path", EXAMPLES, ids=[os.path.basename(p) for p in EXAMPLES])
def test_example_scenes_load_and_render(path):
    sc = load_scene(path)
    src = sc.streaming_source()
    c = src.next_chunk(min(sc.n_samples, 30_000))
    assert c.samples_v.shape == (4, min(sc.n_samples, 30_000))
    assert np.all(np.isfinite(c.samples_v))
    em = _all(load_scene(path))
    assert len(em) > 0
    r = np.linalg.norm(em.point_m, axis=1)
    np.testing.assert_allclose(r, sc.config.geometry.radius_m, rtol=1e-9)
    assert np.all(em.point_m[:, 2] >= 0)


# ----------------------------------------------------------------- validation
BASE = {"generator": "single_touch", "duration_s": 0.002}


@pytest.mark.parametrize("change,msg", [
    ({"colour": "red"}, r"scene: unknown key\(s\) \['colour'\]; allowed"),
    ({"generator": "earthquake"}, "unknown generator 'earthquake'"),
    ({"duration_s": "10 ms"}, r"duration_s: expected a number in SI units"),
    ({"duration_s": -1.0}, "outside the plausible range"),
    ({"sensor": {"radius_mm": 10}}, r"sensor: unknown key\(s\) \['radius_mm'\]"),
    ({"sensor": {"radius_m": 10}}, r"units are metres"),
    ({"sensor": {"medium": "honey"}}, "not one of"),
    ({"sensor": {"adc_bits": 12.5}}, "expected an integer"),
    ({"sensor": {"highpass_hz": 6.0e6}}, "Nyquist"),
    ({"sensor": {"lowpass_hz": "automatic"}}, "expected a number in SI units"),
    ({"sensor": {"lowpass_order": "auto8"}}, "lowpass_order: expected a number"),
    ({"effects": {"reflections": "yes"}}, "expected true or false"),
    ({"noise": {"snr_db": 20, "rms_v": 0.001}}, "exactly one of"),
    ({"params": {"x_m": 0.02}}, "outside the sensing surface"),
    ({"params": {"x_m": "2.5 mm"}}, r"params.x_m: expected a number in SI units"),
    ({"params": {"speed": 0.3}}, r"params: unknown key\(s\) \['speed'\]"),
])
def test_scene_validation_errors(change, msg):
    spec = {**BASE, **change}
    with pytest.raises(SceneError, match=msg):
        load_scene(spec)


def test_scene_low_pass_auto_number_or_null():
    fast = load_scene({**BASE, "sensor": {"lowpass_hz": "auto"}}).config
    slow = load_scene({**BASE, "sensor": {"sample_rate_hz": 2e6}}).config
    fixed = load_scene({**BASE, "sensor": {"lowpass_hz": 0.7e6, "lowpass_order": 6}}).config
    off = load_scene({**BASE, "sensor": {"lowpass_hz": None}}).config
    assert (fast.lowpass_hz, fast.lowpass_order) == (1e6, 4)
    assert (slow.lowpass_hz, slow.lowpass_order) == (pytest.approx(0.6e6), 8)
    assert (fixed.lowpass_hz, fixed.lowpass_order) == (0.7e6, 6)
    assert off.lowpass_hz is None


def test_missing_keys_and_bad_yaml():
    with pytest.raises(SceneError, match="missing required key 'duration_s'"):
        load_scene({"generator": "single_touch"})
    with pytest.raises(SceneError, match="scene file not found"):
        load_scene("/no/such/scene.yaml")
    with pytest.raises(SceneError, match="not valid YAML"):
        load_scene("generator: [unclosed")
    with pytest.raises(SceneError, match="YAML mapping"):
        load_scene("- just\n- a list\n")
    with pytest.raises(SceneError, match="reaches below the sensing hemisphere"):
        load_scene({"generator": "texture", "duration_s": 0.01,
                    "params": {"x_m": 0.0099, "contact_radius_m": 0.002}})
    with pytest.raises(SceneError, match="points_xy_m"):
        load_scene({"generator": "three_pins", "duration_s": 0.01,
                    "params": {"points_xy_m": [[0, 0]], "times_s": [0.001, 0.002]}})


def test_snr_noise_is_relative_to_reference_touch():
    from ae_tactile.sim import render_triggered
    sc = load_scene({**BASE, "noise": {"snr_db": 20.0}})
    apex = np.array([[0, 0, sc.config.geometry.radius_m]])
    pk = render_triggered(apex, sc.config.replace(quantization=False), subsample_offset=0.0)
    snr = 10 * np.log10(pk.signal_power_v2[0] / sc.noise_rms_v ** 2)
    assert snr == pytest.approx(20.0, abs=1e-9)
    d = load_scene({**BASE, "noise": {"density_v_per_rthz": 1e-7}})
    assert d.noise_rms_v == pytest.approx(1e-7 * math.sqrt(5e6))


# ----------------------------------------------------------------- Cattaneo-Mindlin
def test_hertz_and_stick_radius_formulas():
    # a_H = (3 P R / (4 E*))^(1/3), E* = 4E/3 for nu = 0.5
    P, R, E = 1.0, 10e-3, 1e6
    aH = (3 * P * R / (4 * (4 * E / 3))) ** (1 / 3)
    assert hertz_contact_radius_m(P, R, E, 0.5) == pytest.approx(aH, rel=1e-12)
    assert aH == pytest.approx(1.778e-3, rel=1e-3)
    for q in (0.0, 0.3, 0.875, 1.0):
        assert stick_radius_m(aH, q * 0.8 * 2.0, 0.8, 2.0) == pytest.approx(
            aH * (1 - q) ** (1 / 3), abs=1e-15)
    # slipping area = 1 - (c / a_H)^2 = 1 - (1 - q)^(2/3)
    assert slip_fraction(0.875) == pytest.approx(1 - 0.5 ** 2)


def _slip_scene(**params):
    p = {"tangential_load_rate_n_per_s": 1.0, "normal_load_n": 1.0, "friction_coefficient": 0.8,
         "background_rate_hz": 0.0, "front_density_per_m2": 1e8}
    p.update(params)
    return load_scene({"generator": "incipient_slip", "duration_s": 1.5, "seed": 3, "params": p})


def _patch_radius(sc, pts):
    c0 = np.array(sc.truth["contact_center_m"])
    n = c0 / np.linalg.norm(c0)
    proj = pts * (np.linalg.norm(c0) / (pts @ n))[:, None]
    return np.linalg.norm(proj - c0, axis=1)


def test_incipient_slip_annulus_onset_and_rate():
    sc = _slip_scene()
    em = _all(sc)
    truth = sc.truth
    mu, P, qdot = 0.8, 1.0, 1.0
    # gross slip when Q = mu P: t = 0.8 s
    assert truth["gross_slip_time_ns"] == pytest.approx(mu * P / qdot * 1e9, abs=1)
    aH = hertz_contact_radius_m(P, sc.config.geometry.radius_m, 1e6, 0.5)
    assert truth["hertz_radius_m"] == pytest.approx(aH)
    micro = em.take(em.kind == KIND_CODE["micro_slip"])
    slip = em.take(em.kind == KIND_CODE["slip"])
    assert len(micro) > 500 and len(slip) > 100
    assert micro.time_ns.max() < truth["gross_slip_time_ns"] <= slip.time_ns.min()
    # every micro-slip lies in the annulus c(t) < r < a_H (Cattaneo-Mindlin)
    r = _patch_radius(sc, micro.point_m)
    c = stick_radius_m(aH, micro.time_ns * 1e-9 * qdot, mu, P)
    assert np.all(r >= c * (1 - 1e-9)) and np.all(r <= aH * (1 + 1e-9))
    # number of front emissions follows the slipped area: rho_A pi a_H^2 f(q)
    expected = 1e8 * math.pi * aH ** 2
    assert len(micro) == pytest.approx(expected, rel=4 / math.sqrt(expected))
    # the rate grows as the stick zone shrinks: f(q) = 1 - (1 - q)^(2/3) per quarter
    counts = np.histogram(micro.time_ns, bins=4, range=(0, 0.8e9))[0]
    f = slip_fraction(np.array([0, 0.25, 0.5, 0.75, 1.0]))
    np.testing.assert_allclose(counts / counts.sum(), np.diff(f), atol=0.04)
    assert np.all(np.diff(counts) > 0)


def test_raising_normal_load_averts_gross_slip_and_keeps_the_past():
    ref = _slip_scene()
    ref_em = _all(ref)
    sc = _slip_scene()
    early = sc.process.advance(600_000_123)
    sc.process.set_normal_load(2.0, 600_000_123)
    rest = sc.process.advance(int(1.5e9))
    # the past is untouched
    before = ref_em.take(ref_em.time_ns < 600_000_123)
    np.testing.assert_array_equal(early.time_ns, before.time_ns)
    np.testing.assert_array_equal(early.point_m, before.point_m)
    # with P = 2 N gross slip moves to mu P / Qdot = 1.6 s: none within the scene
    assert sc.truth["gross_slip_time_ns"] is None
    assert np.all(rest.kind == KIND_CODE["micro_slip"])
    st = sc.process.state_at(1_000_000_000)
    assert st["load_ratio"] == pytest.approx(1.0 / 1.6)
    with pytest.raises(ValueError, match="already been produced"):
        sc.process.set_normal_load(3.0, 100)


def test_grip_reflex_in_a_streaming_loop():
    """Closed loop through the streaming source: raise P at the end of the chunk in which
    the micro-slip count crosses a threshold; gross slip is then averted."""
    sc = _slip_scene(front_density_per_m2=2e7)
    src = sc.streaming_source()
    seen, raised_at = 0, None
    for _ in range(30):                       # 30 x 50 ms = 1.5 s
        c = src.next_chunk(500_000)
        seen += int(np.sum(c.emissions.kind == KIND_CODE["micro_slip"]))
        assert np.all(c.emissions.kind != KIND_CODE["slip"])
        if raised_at is None and seen >= 30:
            raised_at = src.time_ns
            sc.process.set_normal_load(3.0, raised_at)
    assert raised_at is not None and raised_at < 0.8e9
    assert sc.truth["gross_slip_time_ns"] is None
    assert sc.truth["normal_load_changes"][-1] == [raised_at, 3.0]


def test_incipient_slip_is_chunk_invariant():
    a = _slip_scene(background_rate_hz=200.0)
    b = _slip_scene(background_rate_hz=200.0)
    whole = a.process.advance(int(1.5e9))
    rng = np.random.default_rng(0)
    parts, t = [], 0
    while t < int(1.5e9):
        t = min(int(1.5e9), t + int(rng.integers(1, 80_000_000)))
        parts.append(b.process.advance(t))
    from ae_tactile.sim.stream import EmissionList
    cat = EmissionList.concat(parts)
    np.testing.assert_array_equal(cat.time_ns, whole.time_ns)
    np.testing.assert_array_equal(cat.event_id, whole.event_id)
    np.testing.assert_array_equal(cat.point_m, whole.point_m)


def test_gross_slip_ends_when_load_raised_after_onset():
    sc = _slip_scene()
    sc.process.advance(900_000_000)
    sc.process.set_normal_load(1.5, 900_000_000)
    sc.process.advance(int(1.5e9))
    iv = sc.truth["gross_slip_intervals_ns"]
    assert iv[0][0] == pytest.approx(0.8e9, abs=1) and iv[0][1] == 900_000_000
    assert len(iv) == 2 and iv[1][0] == pytest.approx(1.2e9, abs=1)


# ----------------------------------------------------------------- other generators
def test_texture_rate_is_speed_over_period():
    for v, lam in ((0.02, 0.5e-3), (0.05, 0.2e-3)):
        sc = load_scene({"generator": "texture", "duration_s": 2.0, "seed": 1,
                         "params": {"slide_speed_m_s": v, "period_m": lam,
                                    "jitter_fraction": 0.1}})
        em = _all(sc)
        rate = v / lam
        assert len(em) / 2.0 == pytest.approx(rate, rel=0.01)
        dt = np.diff(em.time_ns) * 1e-9
        assert dt.mean() == pytest.approx(1 / rate, rel=0.01)
        assert dt.std() == pytest.approx(0.1 * math.sqrt(2) / rate, rel=0.15)
        assert np.all(em.kind == KIND_CODE["texture"])


def test_touch_hold_release_polarity_and_switch():
    sc = load_scene({"generator": "touch_hold_release", "duration_s": 0.03,
                     "params": {"time_s": 0.002, "hold_s": 0.02}})
    em = _all(sc)
    assert em.kind_names == ["touch", "release"]
    assert em.polarity.tolist() == [1.0, -1.0]
    assert em.time_ns.tolist() == [2_000_000, 22_000_000]
    np.testing.assert_array_equal(em.point_m[0], em.point_m[1])
    off = load_scene({"generator": "touch_hold_release", "duration_s": 0.03,
                      "effects": {"release_emissions": False}})
    assert _all(off).kind_names == ["touch"]


def test_random_touches_on_cap_and_paper_cases():
    sc = load_scene({"generator": "random_touches", "duration_s": 2.0, "seed": 9,
                     "params": {"rate_hz": 50.0, "max_polar_deg": 40.0}})
    em = _all(sc)
    pol = np.degrees(np.arccos(em.point_m[:, 2] / sc.config.geometry.radius_m))
    assert pol.max() <= 40.0 + 1e-9
    n_touch = int(np.sum(em.kind == KIND_CODE["touch"]))
    assert n_touch == pytest.approx(100, abs=40)
    pp = _all(load_scene({"generator": "paper_positions", "duration_s": 0.02}))
    np.testing.assert_allclose(pp.point_m[:, 0], [0, 2.5e-3, 5e-3])
    tp = _all(load_scene({"generator": "three_pins", "duration_s": 0.005}))
    assert (tp.time_ns.max() - tp.time_ns.min()) <= 2_000_000


def test_paper_touches_and_pins_released_after_hold_s():
    """hold_s > 0: each touch is released hold_s after it, at its own point, with the
    opposite polarity (and not when releases do not emit); 0 keeps them to the end."""
    for gen, dur in (("paper_positions", 0.2), ("three_pins", 0.2)):
        em = _all(load_scene({"generator": gen, "duration_s": dur,
                              "params": {"hold_s": 0.1}}))
        touch = em.kind == KIND_CODE["touch"]
        release = em.kind == KIND_CODE["release"]
        assert touch.sum() == release.sum() == 3, gen
        order = np.argsort(em.time_ns[touch])
        t_t, t_r = em.time_ns[touch][order], np.sort(em.time_ns[release])
        np.testing.assert_array_equal(t_r - t_t, 100_000_000)
        np.testing.assert_allclose(em.point_m[release][np.argsort(em.time_ns[release])],
                                   em.point_m[touch][order])
        assert (em.polarity[touch] > 0).all() and (em.polarity[release] < 0).all()
        off = _all(load_scene({"generator": gen, "duration_s": dur,
                               "params": {"hold_s": 0.1},
                               "effects": {"release_emissions": False}}))
        assert (off.kind == KIND_CODE["touch"]).all()
        held = _all(load_scene({"generator": gen, "duration_s": dur}))
        assert (held.kind == KIND_CODE["touch"]).all()


def test_tangent_basis_is_orthonormal():
    c = np.array([[0, 0, 1.0], [1.0, 0, 0], [0.3, -0.4, 0.866]])
    e1, e2 = tangent_basis(c)
    n = c / np.linalg.norm(c, axis=1, keepdims=True)
    for a, b in ((e1, e2), (e1, n), (e2, n)):
        np.testing.assert_allclose((a * b).sum(1), 0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(e1, axis=1), 1)


# ----------------------------------------------------------------- CLI
def test_cli_writes_samples_and_truth(tmp_path, capsys):
    out = tmp_path / "pins.npz"
    path = os.path.join(ROOT, "config", "scenes", "three_pins.yaml")
    assert cli_main([path, "-o", str(out), "--duration", "0.004", "--chunk-samples", "7777"]) == 0
    printed = capsys.readouterr().out
    assert "emissions  3 touch: 3" in printed
    d = np.load(out)
    assert d["samples"].shape == (4, 40_000) and d["samples"].dtype == np.int16
    assert len(d["truth_time_ns"]) == 3
    sc = load_scene(path, overrides={"duration_s": 0.004})
    ref, _ = StreamRenderer(sc.config, noise_rms_v=sc.noise_rms_v, seed=sc.seed).render(
        _all(load_scene(path, overrides={"duration_s": 0.004})), 0, 40_000)
    np.testing.assert_array_equal(d["samples"] * d["lsb_v"], ref)
    assert cli_main([os.path.join(ROOT, "nope.yaml"), "-o", str(out)]) == 2
