# SPDX-License-Identifier: Apache-2.0
"""The fast triggered-packet path (compiled kernels, windowed noise) against the reference
path (each window rendered by the stream renderer, numpy engine): bit for bit on every
built-in scene, noise and ADC quantization included."""
import glob
import os
import subprocess
import sys

import numpy as np
import pytest

from ae_tactile.sim import SimConfig
from ae_tactile.sim.kernels import HAVE_NUMBA
from ae_tactile.sim.response import default_engine
from ae_tactile.sim.scene import load_scene
from ae_tactile.sim.stream import EmissionList, StreamRenderer, TriggeredSource

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = sorted(glob.glob(os.path.join(ROOT, "config", "scenes", "*.yaml")))
ENGINES = ["numpy"] + (["numba"] if HAVE_NUMBA else [])
MAX_PACKETS = 250          # per scene: keeps the reference (slow) path short


def _packets(path, render_path, engine):
    """The device's use: 400-sample windows, 80 before the onset, served in batches of
    1, 3 and 16 up to the scene's end."""
    sc = load_scene(path)
    fs = sc.config.sample_rate_hz
    src = sc.triggered_source(pretrigger_s=80 / fs, window_s=400 / fs, keep_clean=True,
                              render_path=render_path, engine=engine)
    horizon = int(sc.duration_s * 1e9)
    out, sizes, i = [], (1, 3, 16), 0
    while sum(len(p) for p in out) < MAX_PACKETS:
        p = src.next_packets(sizes[i % 3], horizon_ns=horizon)
        i += 1
        if len(p) == 0:
            break
        out.append(p)
    cat = {k: np.concatenate([getattr(p, k) for p in out]) for k in
           ("samples_v", "clean_v", "start_index", "onset_index", "saturated", "n_overlapping")}
    cat["event_id"] = np.concatenate([p.emissions.event_id for p in out])
    return cat


@pytest.mark.parametrize("path", SCENES, ids=[os.path.basename(p) for p in SCENES])
def test_fast_path_equals_reference_on_every_builtin_scene(path):
    """Fast path (compiled kernel when numba is there) == reference path with the same
    engine, bit for bit: clean signal, noise, quantization, window positions; and the
    two engines give the same ADC output (their clean signals agree to rounding)."""
    ref = {e: _packets(path, "reference", e) for e in ENGINES}
    for e in ENGINES:
        fast = _packets(path, "fast", e)
        assert len(fast["event_id"]) > 0
        for key, val in ref[e].items():
            assert np.array_equal(fast[key], val), (e, key)
    if "numba" in ENGINES:
        a, b = ref["numba"], ref["numpy"]
        assert np.array_equal(a["samples_v"], b["samples_v"])
        scale = np.abs(b["clean_v"]).max()
        np.testing.assert_allclose(a["clean_v"], b["clean_v"], rtol=0, atol=1e-13 * scale)


def test_windowed_noise_equals_block_noise():
    """Noise drawn for a short window (PCG64 jumped ahead) is the block noise, bit for bit,
    also across block boundaries."""
    cfg = SimConfig()
    r = StreamRenderer(cfg, noise_rms_v=1.3e-3, seed=42, noise_block=4096)
    full = r.noise(0, 40_000)
    rng = np.random.default_rng(3)
    w = StreamRenderer(cfg, noise_rms_v=1.3e-3, seed=42, noise_block=4096)
    for _ in range(200):               # random order: the generator also rewinds
        a = int(rng.integers(0, 39_000))
        n = int(rng.integers(1, 1000))
        y = np.zeros((4, n))
        w.add_noise_window(y, a)
        assert np.array_equal(y, full[:, a:a + n])
    assert abs(full.std() / 1.3e-3 - 1) < 0.02


@pytest.mark.parametrize("cfg", [SimConfig(reflections=True),
                                 SimConfig.for_medium("silicone", attenuation=True)],
                         ids=["water-echoes", "silicone-lossy"])
def test_engines_agree_on_a_stream(cfg):
    """Stream rendering: the numba and numpy engines agree to rounding (1e-13 of the
    peak); each engine is chunk-invariant bit for bit (windows = full render)."""
    rng = np.random.default_rng(0)
    n = 40
    pts = cfg.geometry.surface_point_from_angles(np.arccos(rng.uniform(0.1, 1, n)),
                                                 rng.uniform(0, 2 * np.pi, n))
    em = EmissionList.create(np.sort(rng.integers(0, 8_000_000, n)), pts, "touch",
                             polarity=np.where(np.arange(n) % 3, 1, -1),
                             speed_m_s=rng.uniform(0.1, 0.5, n), curvature_1_m=1000.0,
                             alpha_1_s=rng.choice([2000.0, 3000.0], n),
                             density_kg_m3=cfg.density, event_id=np.arange(n))
    full = {}
    for e in ENGINES:
        r = StreamRenderer(cfg, engine=e)
        full[e] = r.render_clean(em, 0, 90_000)
        for a, b in ((0, 1), (12_345, 20_000), (50_000, 90_000)):
            assert np.array_equal(StreamRenderer(cfg, engine=e).render_clean(em, a, b),
                                  full[e][:, a:b])
    assert np.abs(full["numpy"]).max() > 1e-3
    if "numba" in ENGINES:
        np.testing.assert_allclose(full["numba"], full["numpy"], rtol=0,
                                   atol=1e-13 * np.abs(full["numpy"]).max())


def test_engine_and_render_path_validation():
    with pytest.raises(ValueError, match="engine must be"):
        default_engine("fortran")
    with pytest.raises(ValueError, match="render_path"):
        TriggeredSource(EmissionList.empty(), SimConfig(), render_path="quick")
    assert default_engine("numpy") == "numpy"
    assert default_engine() == ("numba" if HAVE_NUMBA else "numpy")


def test_without_numba_the_numpy_engine_serves_the_same_packets():
    """AE_TACTILE_NO_NUMBA=1 (as on a machine without numba): the fallback gives the same
    packets, bit for bit."""
    path = os.path.join(ROOT, "config", "scenes", "three_pins.yaml")
    code = ("import numpy as np, sys\n"
            "from ae_tactile.sim.kernels import HAVE_NUMBA\n"
            "from ae_tactile.sim.scene import load_scene\n"
            f"sc = load_scene({path!r})\n"
            "p = sc.triggered_source().next_packets(10, horizon_ns=int(sc.duration_s * 1e9))\n"
            "sys.stdout.buffer.write(bytes([HAVE_NUMBA]) + p.samples_v.tobytes())\n")
    env = dict(os.environ, AE_TACTILE_NO_NUMBA="1")
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, check=True,
                         cwd=ROOT, timeout=300)
    assert res.stdout[0] == 0
    sc = load_scene(path)
    here = sc.triggered_source(engine="numpy").next_packets(
        10, horizon_ns=int(sc.duration_s * 1e9))
    assert len(here) == 3
    assert res.stdout[1:] == here.samples_v.tobytes()


def test_window_before_sample_zero():
    """An emission at t = 0: its window starts before the scene's first sample. Noise
    blocks before sample 0 have their own seeds; fast path = reference = the stream."""
    spec = {"generator": "single_touch", "duration_s": 0.002, "noise": {"snr_db": 30.0},
            "params": {"time_s": 0.0}}
    got = {}
    for rp in ("fast", "reference"):
        sc = load_scene(spec)
        got[rp] = sc.triggered_source(render_path=rp).next_packets(4, horizon_ns=2_000_000)
    assert len(got["fast"]) == 1 and got["fast"].start_index[0] < 0
    assert np.array_equal(got["fast"].samples_v, got["reference"].samples_v)
    sc = load_scene(spec)
    r = StreamRenderer(sc.config, noise_rms_v=sc.noise_rms_v, seed=sc.seed)
    n0 = -40_000                                   # two blocks before sample 0
    full, _ = r.render(sc.process.advance(3_000_000), n0, 20_000)
    s = int(got["fast"].start_index[0]) - n0
    assert np.array_equal(full[:, s:s + 400], got["fast"].samples_v[0])
    y = np.zeros((4, 1000))
    r.add_noise_window(y, -500)
    assert np.array_equal(y, r.noise(-500, 500))
    assert abs(r.noise(-40_000, 0).std() / sc.noise_rms_v - 1) < 0.02


def test_a_scene_source_ends_with_the_scene():
    """The incipient-slip process runs on after the scene's duration (gross slip); the
    scene's triggered source stops at duration_s without a horizon."""
    path = os.path.join(ROOT, "config", "scenes", "incipient_slip.yaml")
    sc = load_scene(path, overrides={"duration_s": 1.05})
    src = sc.triggered_source()
    got = [src.next_packets(256) for _ in range(10)]
    n = sum(len(p) for p in got)
    assert len(got[-1]) == 0 and n > 20
    t = np.concatenate([p.emissions.time_ns for p in got])
    assert t.max() < 1.05e9
    ref = load_scene(path, overrides={"duration_s": 1.05}).process.advance(int(1.05e9))
    assert n == len(ref) and np.array_equal(t, ref.time_ns)
