# SPDX-License-Identifier: Apache-2.0
"""The hand launch file (launch/hand.launch.py, one include of ae_tactile.launch.py per
finger) under a real `ros2 launch`, with test_launch's runner, probe and clean-stop checks.

Skipped, with the reason, where `ros2 launch` is not available (as test_launch). Waits are
on conditions with generous timeouts, never on speed.
"""
import pytest
from test_launch import (  # the runner of every launch test
    _qos,
    _touches,
    assert_clean_stop,
    launch,  # noqa: F401 - the fixture
    needs_launch,
)

HAND = "hand.launch.py"


@needs_launch
def test_two_fingers_each_with_its_own_driver_device_and_namespace_both_publish(launch):  # noqa: F811
    """fingers:=f1,f2 with a simulated fingertip each (three_pins, single_touch): two driver
    processes, /hand/f1 and /hand/f2, each on its own port and in its finger's frame; each
    finger's contacts are its own scene's touches (3 and 1), where its scene put them."""
    from ae_tactile.msg import ContactEvent
    _, events, truth_qos = _qos()
    s = launch()
    contacts = {f: s.probe.listen(ContactEvent, f"/hand/{f}/contacts", events)
                for f in ("f1", "f2")}
    truth = {f: s.probe.listen(ContactEvent, f"/hand/{f}/sim/ground_truth", truth_qos)
             for f in ("f1", "f2")}
    run = s.start(["fingers:=f1,f2", "scenes:=three_pins,single_touch",
                   "wait_for_subscribers:=1"], target=HAND)
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
    assert len(set(run.pids_of("lib/ae_tactile/driver "))) == 2, run.processes()
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
