# SPDX-License-Identifier: Apache-2.0
"""Shared test set-up.

ROS tests need rclpy and the built messages. Outside `make test` (e.g. running the core
tests with a plain python3) they are skipped with that reason; under `make test`
AE_TACTILE_REQUIRE_ROS=1 turns a missing rclpy into a failure, so CI cannot skip them.
Each test session gets its own ROS domain id (held through a lock file, `claim_domain`)
and localhost-only discovery so parallel runs on one machine do not hear each other.
"""

import fcntl
import logging
import os
import random
import signal
import sys
import tempfile
import time

import pytest

# the evaluation package (trial generators, scoring, bounds) lives beside the benchmarks,
# outside the installed product: bench/ae_eval
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                                "bench"))

#: one lock file per ROS domain id: a test run holds the ids it uses until it ends
DOMAIN_LOCK_DIR = os.path.join(tempfile.gettempdir(), "ae_tactile_test_domains")
_held_domains: list = []


def claim_domain(candidates) -> int:
    """The first ROS domain id of ``candidates`` (an iterator; ids are taken from it) that
    no other test run on this machine holds: an exclusive flock on its file in
    DOMAIN_LOCK_DIR, held until this process ends (the kernel frees it even after a
    crash). Two runs at once (two CI jobs, `make test` twice) never share a domain."""
    os.makedirs(DOMAIN_LOCK_DIR, exist_ok=True)
    for domain_id in candidates:
        fh = open(os.path.join(DOMAIN_LOCK_DIR, f"{domain_id}.lock"), "a")
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.close()
            continue
        _held_domains.append(fh)
        return domain_id
    raise RuntimeError(f"every ROS domain id offered is held by another test run "
                       f"({DOMAIN_LOCK_DIR})")


if "ROS_DOMAIN_ID" not in os.environ:
    os.environ["ROS_DOMAIN_ID"] = str(
        claim_domain(iter(random.Random(os.getpid()).sample(range(1, 101), 100))))
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

# The processes the tests start (launches, nodes) begin as from a terminal, whoever started
# the tests: a test run started as a background job of a non-interactive shell (nohup,
# `cmd &` in a script) ignores SIGINT and would hand that on, so a node signalled in the
# first milliseconds of its life, before its own handler exists, would lose the Ctrl-C.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def require_ros():
    """Import rclpy + ae_tactile.msg, or skip (fail under AE_TACTILE_REQUIRE_ROS=1)."""
    try:
        import rclpy  # noqa: F401

        import ae_tactile.msg  # noqa: F401
    except ImportError as exc:
        if os.environ.get("AE_TACTILE_REQUIRE_ROS") == "1":
            raise
        pytest.skip(f"ROS 2 not available in this interpreter ({exc}); run `make test`")


@pytest.fixture(autouse=True)
def _own_ros_home(tmp_path_factory, monkeypatch):
    """Each test its own ROS_HOME: what a driver learns about a device (its calibration
    file, ``$ROS_HOME/ae_tactile/calibration``) and the logs never reach the user's home
    nor another test."""
    monkeypatch.setenv("ROS_HOME", str(tmp_path_factory.mktemp("ros_home")))


@pytest.fixture(autouse=True)
def _logger_class_kept():
    """A test that imports `launch` in this process (to call the launch file's own
    functions) leaves launch's logger class behind, whose loggers do not propagate: the
    core's loggers made after it would hand their records to no handler, and a later test
    of the log forwarding would fail by the order the tests ran in."""
    cls = logging.getLoggerClass()
    yield
    logging.setLoggerClass(cls)


@pytest.fixture(autouse=True)
def _pipelines_closed(monkeypatch):
    """Every `ContactPipeline` a test builds is closed when the test ends, as the driver
    closes its own: else its overlap resolver's worker process and its pulse learner's
    fit process (a niced fit of minutes) outlive the test and take CPU from the tests
    after it, until pytest exits. A pipeline a module-scoped fixture builds is made
    before this fixture and is that fixture's to close."""
    from ae_tactile.pipeline import core

    made = []
    init = core.ContactPipeline.__init__

    def tracked(self, *args, **kwargs):
        init(self, *args, **kwargs)
        made.append(self)

    monkeypatch.setattr(core.ContactPipeline, "__init__", tracked)
    yield
    for pipe in made:
        pipe.close()


#: the package's helper processes a pipeline starts (`python -m ...`)
_HELPERS = ("ae_tactile.localization.overlap_worker", "ae_tactile.localization.overlap.fit_job")


def _helper_children() -> dict:
    """{pid: command} of this process's children that are the package's helpers (a
    zombie's command line is empty: an ended helper not yet reaped is not one)."""
    from ros_helpers import children

    found = {}
    for pid in children(os.getpid()):
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as fh:
                cmd = fh.read().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if any(h in cmd for h in _HELPERS):
            found[pid] = cmd
    return found


@pytest.fixture(autouse=True, scope="module")
def _no_helper_process_left():
    """A test module leaves none of the helper processes it started running (a closed
    pipeline's worker and fit end at once; killed ones are given the hang guard's time to
    go)."""
    before = set(_helper_children())
    yield
    from ros_helpers import HANG_GUARD_S

    deadline = time.monotonic() + HANG_GUARD_S
    left = {}
    while time.monotonic() < deadline:
        left = {p: c for p, c in _helper_children().items() if p not in before}
        if not left:
            break
        time.sleep(0.1)
    assert not left, f"helper processes left running by this module: {left}"


@pytest.fixture
def ros_context():
    """A fresh rclpy context for one test; shut down afterwards."""
    require_ros()
    import rclpy

    context = rclpy.Context()
    rclpy.init(context=context)
    yield context
    rclpy.try_shutdown(context=context)


def installed_executable(name):
    """Path of a node executable in the colcon install space, or skip (fail under make test)."""
    require_ros()
    root = os.environ.get(
        "AE_TACTILE_ROOT", os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    )
    exe = os.path.join(root, "install", "ae_tactile", "lib", "ae_tactile", name)
    if not os.path.exists(exe):  # a workspace built by colcon (`colcon test`)
        try:
            from ament_index_python.packages import get_package_prefix

            exe = os.path.join(get_package_prefix("ae_tactile"), "lib", "ae_tactile", name)
        except Exception:  # noqa: BLE001 - not in an ament environment
            pass
    if not os.path.exists(exe):
        if os.environ.get("AE_TACTILE_REQUIRE_ROS") == "1":
            raise FileNotFoundError(f"{exe} missing: colcon install incomplete")
        pytest.skip(f"{name} executable not installed (run through `make test`)")
    return exe
