# SPDX-License-Identifier: Apache-2.0
"""ruff over the whole package (configuration in pyproject.toml: ROS 2 line length 99,
rules E, W, F, I, B, T10) finds nothing."""
import collections
import json
import os
import shutil
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _ruff_command():
    exe = shutil.which("ruff")
    if exe:
        return [exe]
    try:
        import ruff  # noqa: F401
    except ImportError:
        return None
    return [sys.executable, "-m", "ruff"]


def test_ruff_finds_nothing():
    cmd = _ruff_command()
    if cmd is None:
        pytest.skip("ruff not installed (tools/requirements.txt; run through `make test`)")
    out = subprocess.run([*cmd, "check", "--output-format", "json", "--no-cache", "."],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode in (0, 1), out.stderr            # 2: ruff itself failed
    findings = json.loads(out.stdout or "[]")
    per_file = collections.Counter(os.path.relpath(f["filename"], ROOT) for f in findings)
    summary = "\n".join(f"{n:5d}  {path}" for path, n in sorted(per_file.items()))
    first = "\n".join(f"{os.path.relpath(f['filename'], ROOT)}:{f['location']['row']}: "
                      f"{f['code']} {f['message']}" for f in findings[:20])
    assert not findings, f"{len(findings)} ruff findings per file:\n{summary}\nfirst:\n{first}"
