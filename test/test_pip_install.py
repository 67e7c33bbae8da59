# SPDX-License-Identifier: Apache-2.0
"""`pip install .` into a fresh venv gives an importable core that never imports rclpy."""
import os
import pkgutil
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHECK = r"""
import importlib, pkgutil, sys
import ae_tactile
mods = [m.name for m in pkgutil.walk_packages(ae_tactile.__path__, "ae_tactile.")]
for name in mods:
    importlib.import_module(name)
assert "rclpy" not in sys.modules, "the core imported rclpy"
assert not any(m.startswith("ae_tactile.ros") for m in mods), "ROS layer must not be pip-installed"
try:
    import rclpy  # noqa: F401
    raise SystemExit("rclpy is importable in the fresh venv: the test proves nothing")
except ImportError:
    pass
from ae_tactile.geometry import FingertipGeometry
g = FingertipGeometry()
p = g.surface_point_from_xy(2.5e-3, 0.0)
print("OK", len(mods), "modules;", round(float(g.exact_delays_s(p)[0]) * 1e9, 3), "ns")
"""


def core_module_names():
    """Every module of the source tree's core (everything outside ae_tactile.ros)."""
    return [m.name for m in pkgutil.walk_packages([str(ROOT / "ae_tactile")], "ae_tactile.")
            if not m.name.startswith("ae_tactile.ros") and not m.name.startswith("ae_tactile.msg")]


def test_pip_install_core_without_ros(tmp_path):
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True, clear=True).create(env_dir)
    py = env_dir / "bin" / "python"
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "AMENT_PREFIX_PATH", "LD_LIBRARY_PATH", "VIRTUAL_ENV")}
    subprocess.run([str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check",
                    str(ROOT)], check=True, env=env, cwd=tmp_path, timeout=600)
    out = subprocess.run([str(py), "-c", CHECK], check=True, env=env, cwd=tmp_path,
                         capture_output=True, text=True, timeout=120).stdout
    n_modules = int(out.split()[1])
    assert out.startswith("OK") and "248.023 ns" in out, out
    assert n_modules == len(core_module_names()), (out, core_module_names())
    assert sys.executable != str(py)
