# SPDX-License-Identifier: Apache-2.0
"""Scene validation checks what a scene will cost (memory, output size, emissions) before
anything is allocated, rejects bad seeds and over-deep YAML with SceneErrors, and a
failed render leaves no output file."""
import glob
import os
import tracemalloc

import numpy as np
import pytest

from ae_tactile.sim.cli import main as cli_main
from ae_tactile.sim.cli import render_to_npz
from ae_tactile.sim.scene import Budget, SceneError, load_scene

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = sorted(glob.glob(os.path.join(ROOT, "config", "scenes", "*.yaml")))


def _refused_without_allocating(spec, match, **kw):
    tracemalloc.start()
    try:
        with pytest.raises(SceneError, match=match):
            load_scene(spec, **kw)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20e6          # refused from the estimate, not by running out of memory


def test_emission_rate_times_duration_over_memory_budget():
    """1e6 touches/s for an hour: each value is plausible, their product is not (7.2e9
    emissions x >= 81 B)."""
    spec = {"generator": "random_touches", "duration_s": 3600.0, "params": {"rate_hz": 1e6}}
    _refused_without_allocating(spec, r"scene too costly: ~[0-9.e+]+ GiB of memory \(7.2e\+09 "
                                      r"emissions expected.*budget of 1 GiB")


def test_huge_response_tables_over_memory_budget():
    """1 GS/s with a 0.1 s response support: 1e8-sample exponential tables."""
    spec = {"generator": "single_touch", "duration_s": 0.002,
            "sensor": {"sample_rate_hz": 1e9, "max_support_s": 0.1}}
    _refused_without_allocating(spec, "GiB of memory")


def test_budget_can_be_raised_and_cost_is_reported():
    spec = {"generator": "random_touches", "duration_s": 2.0, "params": {"rate_hz": 5000.0}}
    sc = load_scene(spec)                                   # 2e4 emissions: within budget
    assert sc.cost.n_emissions == pytest.approx(2 * 5000.0 * 2.0)
    tight = Budget(max_memory_bytes=int(sc.cost.memory_bytes) - 1)
    with pytest.raises(SceneError, match="scene too costly"):
        load_scene(spec, budget=tight)
    load_scene(spec, budget=Budget(max_memory_bytes=None))


@pytest.mark.parametrize("path", SCENES, ids=[os.path.basename(p) for p in SCENES])
def test_emission_estimate_bounds_every_builtin_scene(path):
    """The estimate (from the keys alone) is within [1, 10] x the emissions generated (+5),
    for every example scene."""
    from ae_tactile.sim.interference import InterferenceSource

    sc = load_scene(path)
    em = sc.process.advance(int(sc.duration_s * 1e9) + 1)
    # the bursts the scene renders (on the host's clock for a shared-clock scene)
    bursts = InterferenceSource(sc).next_packets(int(sc.duration_s * 1e9) + 1)[0].size
    n = len(em) + bursts
    assert n > 0
    assert n <= sc.cost.n_emissions + 3 * np.sqrt(sc.cost.n_emissions) + 5
    assert sc.cost.n_emissions <= 10 * n + 5
    assert sc.cost.memory_bytes < (1 << 30) and sc.cost.output_bytes > 4 * sc.n_samples


def test_output_size_checked_before_the_file_is_opened(tmp_path, capsys):
    """1e9 samples/s for an hour: 28.8 TB of int16. The command line refuses it (exit 2,
    a clear message) and creates no file; --max-output-gib raises the limit."""
    scene = tmp_path / "big.yaml"
    scene.write_text("generator: single_touch\nduration_s: 3600\n"
                     "sensor: {sample_rate_hz: 1.0e9}\n")
    out = tmp_path / "big.npz"
    assert cli_main([str(scene), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "rendered file would be" in err and "--max-output-gib" in err
    assert list(tmp_path.iterdir()) == [scene]
    small = tmp_path / "small.yaml"
    small.write_text("generator: single_touch\nduration_s: 0.002\n")
    assert cli_main([str(small), "-o", str(out), "--max-output-gib", "1e-6", "--quiet"]) == 2
    assert not out.exists()
    assert cli_main([str(small), "-o", str(out), "--max-output-gib", "1", "--quiet"]) == 0
    assert np.load(out)["samples"].shape == (4, 20_000)


@pytest.mark.parametrize("seed,msg", [(-1, r"scene.seed=-1 is outside"),
                                      (1.5, "expected an integer"),
                                      ("abc", "expected a number"), (2 ** 64, "outside")])
def test_bad_seed_is_a_scene_error(seed, msg):
    with pytest.raises(SceneError, match=msg):
        load_scene({"generator": "single_touch", "duration_s": 0.002, "seed": seed})


def test_negative_seed_on_the_command_line_writes_nothing(tmp_path, capsys):
    out = tmp_path / "x.npz"
    path = os.path.join(ROOT, "config", "scenes", "single_touch.yaml")
    assert cli_main([path, "-o", str(out), "--seed", "-1"]) == 2
    assert "seed" in capsys.readouterr().err
    assert not out.exists()


def test_deeply_nested_yaml_is_a_scene_error(tmp_path):
    deep = "generator: single_touch\nduration_s: 0.002\nparams: " + "[" * 5000 + "]" * 5000 + "\n"
    with pytest.raises(SceneError, match="nested too deeply"):
        load_scene(deep)
    f = tmp_path / "deep.yaml"
    f.write_text("params: " + "{a: " * 3000 + "1" + "}" * 3000 + "\n")
    with pytest.raises(SceneError, match="nested too deeply"):
        load_scene(str(f))
    assert cli_main([str(f), "-o", str(tmp_path / "o.npz")]) == 2
    # moderately nested values still get the ordinary key errors
    with pytest.raises(SceneError, match="expected a number"):
        load_scene({"generator": "single_touch", "duration_s": 0.002,
                    "params": {"x_m": [[[[0.0]]]]}})


def test_failed_render_leaves_no_partial_file(tmp_path):
    """An error mid-render (here from the progress callback after the first chunk) leaves
    neither the output nor a temporary file; a later good render still succeeds."""
    path = os.path.join(ROOT, "config", "scenes", "three_pins.yaml")
    out = tmp_path / "pins.npz"

    def fail(pos, total):
        raise RuntimeError("disk on fire")

    with pytest.raises(RuntimeError, match="disk on fire"):
        render_to_npz(load_scene(path), out, chunk_samples=10_000, progress=fail)
    assert list(tmp_path.iterdir()) == []
    out.write_bytes(b"old file")             # an existing file survives a failed render
    with pytest.raises(RuntimeError):
        render_to_npz(load_scene(path), out, chunk_samples=10_000, progress=fail)
    assert out.read_bytes() == b"old file" and list(tmp_path.iterdir()) == [out]
    s = render_to_npz(load_scene(path), out, chunk_samples=10_000)
    assert s["path"] == str(out) and np.load(out)["samples"].shape == (4, 50_000)
