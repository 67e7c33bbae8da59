# SPDX-License-Identifier: Apache-2.0
"""The package's layout rules (tools/check_layout.py) hold on this tree, and the checker
finds each kind of problem on a small tree that breaks them."""

import importlib.util
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("check_layout", ROOT / "tools" / "check_layout.py")
layout = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(layout)

SPDX = "# SPDX-License-Identifier: Apache-2.0\n"


@pytest.mark.parametrize("check", sorted(layout.CHECKS))
def test_the_package_follows_the_layout_rules(check):
    found = layout.CHECKS[check](ROOT)
    assert not found, f"{len(found)} findings:\n" + "\n".join(found[:40])


def _write(root: Path, rel: str, text: str) -> None:
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_the_checker_finds_every_kind_of_problem(tmp_path):
    body = "".join(f"    x{i} = {i}\n" for i in range(85))
    deep = ("def deep(a):\n    if a:\n        for b in a:\n            while b:\n"
            "                with b:\n                    try:\n                        pass\n"
            "                    except OSError:\n                        pass\n")
    elifs = ("def chain(a):\n" + "".join(
        f"    {'if' if i == 0 else 'elif'} a == {i}:\n        return {i}\n" for i in range(9)))
    _write(tmp_path, "ae_tactile/__init__.py", SPDX)
    _write(tmp_path, "ae_tactile/big.py", SPDX + "x = 1\n" * 601)
    _write(tmp_path, "ae_tactile/kernels.py",
           "# size: compiled kernels\n" + SPDX + "x = 1\n" * 601)
    _write(tmp_path, "ae_tactile/long.py", SPDX + "def long():\n" + body + deep + elifs)
    _write(tmp_path, "ae_tactile/nolicence.py", "x = 1\n")
    _write(tmp_path, "ae_tactile/geometry.py", SPDX + "from ae_tactile import records\n")
    _write(tmp_path, "ae_tactile/records.py", SPDX + "from ae_tactile import geometry\n")
    _write(tmp_path, "ae_tactile/slip/__init__.py",
           SPDX + "import ae_eval\n\n\ndef f():\n    from ae_tactile.pipeline import core\n"
           "    import numba  # lazy: optional compiler\n")
    _write(tmp_path, "ae_tactile/pipeline/core.py", SPDX + "import rclpy\n")
    _write(tmp_path, "ae_tactile/pipeline/__init__.py", SPDX)
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)

    found = [p for check in layout.CHECKS.values() for p in check(tmp_path)]
    text = "\n".join(found)
    assert "file_size: ae_tactile/big.py has 602 lines" in text
    assert "kernels.py" not in text  # a stated reason
    assert "long.py:2 long has 86 lines" in text
    assert "long.py:88 deep nests 5 deep" in text
    assert "chain" not in text  # an elif chain is one level
    assert "spdx: ae_tactile/nolicence.py" in text
    assert "import_cycle: ae_tactile.geometry <-> ae_tactile.records" in text
    assert "ae_tactile/slip/__init__.py:2 imports the evaluation package ae_eval" in text
    assert "(slip) imports ae_tactile.pipeline.core from a higher layer" in text
    assert "lazy_import: ae_tactile/slip/__init__.py:6" in text
    assert "numba" not in text  # a lazy import that says why
    assert "pipeline/core.py:2 imports rclpy outside ae_tactile.ros" in text
