# SPDX-License-Identifier: Apache-2.0
"""Every figure the README shows comes from a benchmark's result file (bench/results/)."""
import importlib.util
import os

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _figures():
    spec = importlib.util.spec_from_file_location(
        "readme_figures", os.path.join(ROOT, "bench", "readme_figures.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_readme_figures_are_generated_from_the_benchmark_results():
    mod = _figures()
    block = mod.markdown()
    readme = open(os.path.join(ROOT, "README.md"), encoding="utf-8").read()
    assert block in readme, "README figures are stale: run python bench/readme_figures.py --write"
    # the block is not empty: the live-path latency and the localization figures are there
    assert "device bytes -> the emission's event (Emission)" in block and "Cramer-Rao" in block
