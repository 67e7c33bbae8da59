# SPDX-License-Identifier: Apache-2.0
"""The hand launch file (launch/hand.launch.py, one include of ae_tactile.launch.py per
finger) under a real `ros2 launch`, with test_launch's runner, probe and clean-stop checks.

Skipped, with the reason, where `ros2 launch` is not available (as test_launch). Waits are
on conditions with generous timeouts, never on speed.
"""
import subprocess

import pytest
import yaml
from test_launch import (  # the runner of every launch test
    _qos,
    _touches,
    assert_clean_stop,
    launch,  # noqa: F401 - the fixture
    needs_launch,
)

from conftest import installed_executable

HAND = "hand.launch.py"


@needs_launch
@pytest.mark.parametrize("one_process", [False, True], ids=["a process each", "one process"])
def test_two_fingers_each_with_its_own_driver_device_and_namespace_both_publish(
        launch, one_process):  # noqa: F811
    """fingers:=f1,f2 with a simulated fingertip each (three_pins, single_touch): two
    drivers, /hand/f1/driver and /hand/f2/driver, each on its own port and in its finger's
    frame, in a process each or (one_process:=true) both in one hand_driver process; each
    finger's contacts are its own scene's touches (3 and 1), where its scene put them."""
    from ae_tactile.msg import ContactEvent
    _, events, truth_qos = _qos()
    s = launch()
    contacts = {f: s.probe.listen(ContactEvent, f"/hand/{f}/contacts", events)
                for f in ("f1", "f2")}
    truth = {f: s.probe.listen(ContactEvent, f"/hand/{f}/sim/ground_truth", truth_qos)
             for f in ("f1", "f2")}
    run = s.start(["fingers:=f1,f2", "scenes:=three_pins,single_touch",
                   "wait_for_subscribers:=1", f"one_process:={str(one_process).lower()}"],
                  target=HAND)
    expected = {"f1": 3, "f2": 1}
    assert s.probe.spin_until(
        lambda: all(len(_touches(truth[f])) == n for f, n in expected.items()), run=run), \
        run.output()[-4000:]
    assert s.probe.spin_until(
        lambda: all(len(_touches(contacts[f])) >= n for f, n in expected.items()), run=run), \
        ({f: len(_touches(c)) for f, c in contacts.items()}, run.output()[-4000:])
    s.probe.spin_for(1.0)  # anything extra in flight arrives now
    for f, n in expected.items():
        got = _touches(contacts[f])
        assert len(got) == n, (f, [(m.position.x, m.position.y) for m in got])
        assert {m.header.frame_id for m in contacts[f]} == {f"{f}_tip"}
        pins = [(m.position.x, m.position.y) for m in _touches(truth[f])]
        for m in got:  # localization error well below the scenes' 5 mm pin spacing
            d = min(((m.position.x - x) ** 2 + (m.position.y - y) ** 2) ** 0.5 for x, y in pins)
            assert d < 1.5e-3, (f, m.position, pins)
    names = {"/hand/f1/driver", "/hand/f2/driver", "/hand/f1/sim_fingertip",
             "/hand/f2/sim_fingertip"}
    assert s.probe.spin_until(lambda: names <= s.probe.node_names(), run=run)
    drivers = set(run.pids_of("lib/ae_tactile/driver "))
    hand_drivers = set(run.pids_of("lib/ae_tactile/hand_driver "))
    assert (len(drivers), len(hand_drivers)) == ((0, 1) if one_process else (2, 0)), \
        run.processes()
    assert s.probe.get_parameter("/hand/f1/driver", "port") != \
        s.probe.get_parameter("/hand/f2/driver", "port")
    assert_clean_stop(run)


@needs_launch
@pytest.mark.parametrize("args, words", [
    (["fingers:=a,b", "use_sim:=false", "ports:=/dev/ttyACM0"], ["ports", "one value per finger"]),
    (["fingers:=a,b", "use_sim:=false"], ["ports", "use_sim:=false needs one port per finger"]),
    (["fingers:=a,a"], ["fingers", "twice"]),
    (["fingers:=a,2b"], ["fingers", "names"]),
    (["fingers:=a,b", "driver_cpus:=0"], ["driver_cpus", "one value per finger"]),
    (["fingers:=a,b", "scenes:=three_pins,texture,showcase"], ["scenes", "one for all"]),
    (["fingers:=a,b", "one_process:=true", "driver_cpus:=0 1"], ["driver_cpus", "one_process"]),
    (["fingers:=a,b", "one_process:=maybe"], ["one_process", "not a boolean"]),
])
def test_a_bad_hand_argument_is_a_clear_error_and_starts_nothing(launch, args, words):  # noqa: F811
    s = launch()
    run = s.start(args, target=HAND)
    code = run.wait_exit(180.0)
    out = run.output()
    assert code != 0, out
    error_lines = [line for line in out.splitlines() if "ERROR" in line]
    assert error_lines and all(w in error_lines[0] for w in words), out
    assert "process started" not in out, out
    assert not run.wait_gone(), "processes left"
    assert "Traceback" not in out


@pytest.mark.parametrize("args, words", [
    ([], ["--fingers"]),
    (["--fingers", "/hand/a,/hand/a"], ["twice"]),
    (["--fingers", "/hand/a,/hand/2b"], ["'/hand/2b'", "not a ROS namespace"]),
    (["--fingers", "a", "--extra"], ["unrecognized", "--extra"]),
])
def test_hand_driver_refuses_bad_fingers_before_starting_ros(args, words):
    """hand_driver's own argument is checked before ROS starts: exit code 2 and a message
    naming what is wrong."""
    out = subprocess.run([installed_executable("hand_driver"), *args], capture_output=True,
                         text=True, timeout=300)  # [s] only catches a hang
    assert out.returncode == 2, (out.stdout, out.stderr)
    assert all(w in out.stderr for w in words), out.stderr


def test_hand_driver_refuses_fingertips_pinned_apart(tmp_path):
    """One process runs on one set of CPUs: fingertips whose cpu_affinity differs stop the
    hand_driver with exit code 2 and a message naming the parameter (both nodes made
    before the check are destroyed: the process exits)."""
    params = tmp_path / "hand.yaml"
    params.write_text(yaml.safe_dump({
        f"/hand/{f}/driver": {"ros__parameters": {"port": "loop://", "cpu_affinity": cpu,
                                                 "pipeline": False}}
        for f, cpu in (("a", "0"), ("b", "0-1"))}))
    out = subprocess.run([installed_executable("hand_driver"), "--fingers", "/hand/a,/hand/b",
                          "--ros-args", "--params-file", str(params)],
                         capture_output=True, text=True, timeout=300)  # [s] catches a hang
    assert out.returncode == 2, (out.stdout, out.stderr)
    assert "'cpu_affinity' differs" in out.stderr, out.stderr
