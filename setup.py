# SPDX-License-Identifier: Apache-2.0
"""pip-installable pure-Python core of ae_tactile (no ROS needed).

`pip install .` installs the physics simulator, DSP/localization, slip analysis and
serial protocol modules; the ROS 2 nodes (ae_tactile.ros) and messages are built by
colcon from CMakeLists.txt/package.xml instead.
"""
import re
from pathlib import Path

from setuptools import find_packages, setup

HERE = Path(__file__).resolve().parent
VERSION = re.search(r"<version>([^<]+)</version>", (HERE / "package.xml").read_text()).group(1)

setup(
    name="ae_tactile",
    version=VERSION,
    description="Ultrasonic acoustic-emission tactile fingertip: simulator, localization, "
                "slip detection and serial protocol (pure-Python core)",
    long_description=(HERE / "README.md").read_text(encoding="utf-8"),
    long_description_content_type="text/markdown",
    license="Apache-2.0",
    python_requires=">=3.10",
    packages=find_packages(include=["ae_tactile", "ae_tactile.*"],
                           exclude=["ae_tactile.ros", "ae_tactile.ros.*"]),
    install_requires=["numpy>=1.24", "scipy>=1.10", "pyserial>=3.5", "pyyaml>=6.0"],
    extras_require={"test": ["pytest>=7.0", "pytest-xdist>=3.5", "hypothesis>=6.80"],
                    "bag": ["rosbags>=0.10"],
                    "recordings": ["vallenae>=0.14"]},
    entry_points={"console_scripts": ["ae-tactile-sim = ae_tactile.sim.cli:main",
                                      "ae-tactile-replay = ae_tactile.bagtools:main",
                                      "ae-tactile-detect = ae_tactile.recordings.cli:main"]},
)
