# SPDX-License-Identifier: Apache-2.0
"""End to end with real rclpy: simulated fingertip (own process, pty) -> driver (in-process
localization and slip detection; or the split: driver -> localizer -> slip detector)
(-> grip reflex), scored against the scene's ground truth.

Each run is the `bringup` composition the demo uses; the simulated fingertip runs as a
separate process, like hardware on a USB port. No test here bounds wall-clock time: speed
is measured by bench/bench_system.py.
"""

import argparse
import json
import os
import subprocess
import time

import numpy as np
import pytest
import yaml

from conftest import installed_executable, require_ros
from ros_helpers import children

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = os.path.join(ROOT, "config", "scenes")


def run_system(
    ros_context,
    scene,
    *,
    grip_reflex=False,
    namespace="",
    method="",
    sliding_speed=0.0,
    split=False,
    speed=1.0,
):
    """Play a scene through the composed system; return (bringup, summary)."""
    require_ros()
    from ae_tactile.ros.bringup import Bringup, parse_args

    argv = ["--scene", scene, "--monitor"] + (["--grip-reflex"] if grip_reflex else [])
    argv += ["--split"] if split else []
    argv += ["--speed", str(speed)] if speed != 1.0 else []
    argv += ["--namespace", namespace] if namespace else []
    argv += ["--method", method] if method else []
    argv += ["--sliding-speed", str(sliding_speed)] if sliding_speed else []
    system = Bringup(parse_args(argv), context=ros_context)
    system.monitor.print_live = False
    try:
        system.spin(-1.0, drain_timeout_s=15.0)
        summary = system.monitor.summary(
            system.gross_slip_times_ns(), system.slip_part_starts_ns(), system.scene_truth()
        )
    except BaseException:
        system.close()
        raise
    return system, summary


def scene_file(tmp_path, name, **changes):
    """A copy of a built-in scene with top-level keys or params changed."""
    with open(os.path.join(SCENES, name + ".yaml")) as fh:
        spec = yaml.safe_load(fh)
    for k, v in changes.items():
        if k in ("duration_s", "seed", "noise", "effects"):
            spec[k] = v
        else:
            spec.setdefault("params", {})[k] = v
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(spec))
    return str(path)


@pytest.mark.parametrize(
    "scene",
    [
        "single_touch",
        "paper_positions",
        "three_pins",
        "touch_hold_release",
        "random_touches",
        "plane_slip",
        "texture",
        "incipient_slip",
    ],
)
def test_every_builtin_scene_is_found_and_localized(ros_context, scene):
    system, s = run_system(ros_context, os.path.join(SCENES, scene + ".yaml"))
    try:
        e, tr = s["emissions"], s["touch_release"]
        print(scene, s)
        assert e["truth"] >= 1
        assert e["recall"] >= 0.98 and e["precision"] >= 0.98, e
        assert e["rms_position_error_mm"] <= 0.3, e
        if tr["truth"]:
            assert tr["found"] / tr["truth"] >= 0.98 and tr["typed_correctly"] == tr["found"], tr
        # every packet the driver decoded was localized or rejected for a counted reason
        c = system.driver.pipeline.localizer.counts
        rejected = sum(
            v for k, v in c.items() if k.startswith("rejected_") or k == "below_min_confidence"
        )
        assert c["packets"] == c["events"] + rejected
        # ... and every emission it found was published (overlapping windows: one per
        # emission), each once, with a reading
        assert (
            system.driver.published_emissions
            == c["events"] + system.driver.pipeline.all_counts()["overlap_sources"]
            == len(system.monitor.emissions)
        )
    finally:
        system.close()


def test_split_pipeline_gives_the_same_events_through_the_separate_nodes(ros_context):
    """The velodyne-style split (driver -> packets -> localizer -> contacts -> slip detector)
    runs the same core code as the in-process pipeline."""
    system, s = run_system(ros_context, os.path.join(SCENES, "paper_positions.yaml"), split=True)
    try:
        assert system.driver.pipeline is None and system.localizer is not None
        e = s["emissions"]
        assert e["matched"] == e["truth"] == 3 and e["rms_position_error_mm"] < 0.05, e
        assert system.slip.received == system.localizer.counts["published_events"]
    finally:
        system.close()


def test_a_contact_begins_and_ends_once_with_its_id(ros_context, tmp_path):
    """A touch held 0.2 s and released: `contacts` carries one TOUCH when it begins and one
    DETOUCH when it ends, with the same id; its two emissions go out on `emissions` read as
    the contact's touch and release; the state is back to NO_CONTACT with no contact."""
    path = scene_file(tmp_path, "touch_hold_release", duration_s=0.6, hold_s=0.2)
    system, s = run_system(ros_context, path)
    try:
        m = system.monitor
        kinds = [(x.msg.event_type, x.msg.contact_id) for x in m.contacts]
        assert len(kinds) == 2 and kinds[0][0] == 1 and kinds[1][0] == 2, kinds
        assert kinds[0][1] == kinds[1][1] > 0
        em = sorted(m.emissions, key=lambda x: x.stamp_ns)
        assert [(x.msg.reading, x.msg.contact_id, x.msg.polarity) for x in em] == [
            (1, kinds[0][1], 1), (2, kinds[0][1], -1)]
        # TOUCH at its first emission, DETOUCH once its release is confirmed, after it
        assert m.contacts[0].stamp_ns == em[0].stamp_ns
        assert m.contacts[1].stamp_ns >= em[1].stamp_ns
        assert m.states[-1][1] == 0 and m.states[-1][3] == 0
        assert max(st[3] for st in m.states) == 1  # one contact listed while it lasted
    finally:
        system.close()


def test_three_pins_are_three_contacts(ros_context, tmp_path):
    """Fig. 8's three pins within 2 ms, 5-6 mm apart: three TOUCHes with three ids, and the
    latched ContactState lists three contacts at their points."""
    system, s = run_system(ros_context, scene_file(tmp_path, "three_pins", duration_s=0.2))
    try:
        m = system.monitor
        touches = [x.msg for x in m.contacts if x.msg.event_type == 1]
        assert len({t.contact_id for t in touches}) == len(touches) == 3
        assert max(st[3] for st in m.states) == 3
        truth = [(t.position.x, t.position.y) for t in m.truth]
        for t in touches:  # each at one pin (within the localization error)
            assert min(np.hypot(t.position.x - x, t.position.y - y) for x, y in truth) < 0.3e-3
    finally:
        system.close()


def test_a_held_contacts_micro_slips_are_emissions_not_touches(ros_context, tmp_path):
    """The incipient-slip scene's first 0.4 s (a contact held and loaded, its micro-slips
    before gross slip): one TOUCH per contact begun, none per micro-slip; the micro-slips
    go out on `emissions` read as MICRO_SLIP of a contact whose TOUCH came first."""
    path = scene_file(tmp_path, "incipient_slip", duration_s=0.4)
    system, s = run_system(ros_context, path)
    try:
        m = system.monitor
        touch_ns = {x.msg.contact_id: x.stamp_ns for x in m.contacts if x.msg.event_type == 1}
        micro = [x for x in m.emissions if x.msg.reading == 3]
        print("readings", s["emission_readings"], "contact events", s["contact_events"])
        assert len(m.emissions) >= 20 and len(touch_ns) <= 3
        assert sum(1 for x in m.contacts if x.msg.event_type == 1) == len(touch_ns)
        assert micro, s["emission_readings"]
        assert all(x.msg.contact_id in touch_ns and touch_ns[x.msg.contact_id] <= x.stamp_ns
                   for x in micro)
    finally:
        system.close()


def test_the_summary_scores_the_contact_state_against_the_scenes_truth(ros_context, tmp_path):
    """touch_hold_release scored against its truth (ae_tactile.scoring): the finger is in
    contact from the touch to the release, NO_CONTACT before and after; the share of time
    the reported state is right counts the time the detector needs to confirm the release
    (its quiet time) as wrong, no slip alarm is false."""
    path = scene_file(tmp_path, "touch_hold_release", duration_s=0.6, hold_s=0.2)
    system, s = run_system(ros_context, path)
    try:
        tr = s["truth"]
        assert [st for _, st in tr["truth_timeline"]] == ["STICK", "NO_CONTACT"]
        t_touch, t_release = (t for t, _ in tr["truth_timeline"])
        assert abs(t_release - t_touch - 0.2) < 1e-3  # the scene's hold
        assert tr["contacts"] == {"truth_begun": 1, "truth_ended": 1, "touch_events": 1,
                                  "detouch_events": 1}
        assert tr["false_alarms"] == 0 and tr["true_alarms"] == 0
        # independent: the reported state's own changes, scored by hand on the same grid
        rep = [(t, st) for t, st in tr["reported_timeline"]]
        end = t_release + 0.1
        grid = np.arange(0.0, end, 1e-3)

        def at(timeline, t):
            cur = "NO_CONTACT"
            for t0, st in timeline:
                if t0 <= t:
                    cur = st
            return cur

        scored = [t for t in grid if not (t_release <= t < t_release + 0.1)]
        right = sum(at(rep, t) == at(tr["truth_timeline"], t) for t in scored)
        assert tr["state_right_share"] == pytest.approx(right / len(scored), abs=0.01)
        assert tr["state_right_share"] > 0.5
    finally:
        system.close()


def test_touch_hold_release_raises_no_slip_alarm(ros_context, tmp_path):
    path = scene_file(tmp_path, "touch_hold_release", duration_s=1.0, hold_s=0.8)
    system, s = run_system(ros_context, path)
    try:
        assert s["touch_release"] == {"truth": 2, "found": 2, "typed_correctly": 2}
        assert s["slip_events"] == {}, s["slip_events"]  # no false slip alarm
    finally:
        system.close()


@pytest.mark.parametrize("seed", [1, 2])
def test_incipient_slip_precursor_comes_before_gross_slip(ros_context, tmp_path, seed):
    system, s = run_system(ros_context, scene_file(tmp_path, "incipient_slip", seed=seed))
    try:
        gross = system.gross_slip_times_ns()
        assert len(gross) == 1  # the scene does slip
        lead = s["slip_precursor_lead_ms"][0]
        print(f"seed {seed}: precursor {lead} ms before gross slip")
        assert lead is not None and lead > 74.0  # earlier than a human reflex
        assert s["slip_events"].get("SLIP", 0) >= 1  # and gross slip is reported
    finally:
        system.close()


def test_grip_reflex_averts_gross_slip(ros_context, tmp_path):
    path = scene_file(tmp_path, "incipient_slip", duration_s=1.4)
    # The loop is closed in real time: the scene plays at half speed, so that the reflex's
    # margin does not depend on how busy the test machine is (its speed: bench/).
    off, s_off = run_system(ros_context, path, speed=0.5)
    try:
        assert len(off.gross_slip_times_ns()) == 1  # without the reflex it slips
    finally:
        off.close()
    on, s_on = run_system(ros_context, path, grip_reflex=True, speed=0.5)
    try:
        assert on.gross_slip_times_ns() == [], (
            on.scene_info,
            on.reflex.commands,
        )  # the reflex averted it
        assert on.reflex.commands and on.scene_info["load_changes"]
        first_micro = min(
            t
            for t, k in [
                (int(m.header.stamp.sec) * 10**9 + m.header.stamp.nanosec, m.event_type)
                for m in on.monitor.truth
            ]
            if k == 3
        )
        reaction_ms = (on.reflex.commands[0][0] - first_micro) * 1e-6
        print(
            f"reaction: first micro-slip emission -> force command {reaction_ms:.1f} ms; "
            f"precursor -> command {on.reflex.reactions_ms[0]:.1f} ms"
        )
        assert reaction_ms > 0  # the command followed the emission
    finally:
        on.close()


def test_texture_spatial_period_within_ten_percent(ros_context, tmp_path):
    path = scene_file(tmp_path, "texture", duration_s=1.0)
    with open(path) as fh:
        spec = yaml.safe_load(fh)
    speed, period = spec["params"]["slide_speed_m_s"], spec["params"]["period_m"]
    system, s = run_system(ros_context, path, sliding_speed=float(speed))
    try:
        periods = [x.msg.spatial_period_m for x in system.monitor.slip if x.msg.event_type == 5]
        assert periods, s["slip_events"]
        assert abs(np.median(periods) - period) / period < 0.10, (np.median(periods), period)
    finally:
        system.close()


def test_namespaced_bringup(ros_context):
    system, s = run_system(
        ros_context,
        os.path.join(SCENES, "paper_positions.yaml"),
        namespace="hand/index",
        method="gradient",
    )
    try:
        assert system.driver.get_namespace() == "/hand/index"
        assert system.driver.loc_params["method"] == "gradient"
        assert system.driver.pipeline.localizer.method == "gradient"
        names = dict(system.driver.get_topic_names_and_types())
        assert "/hand/index/contacts" in names and "/hand/index/slip" in names
        assert s["emissions"]["matched"] == 3
    finally:
        system.close()


def test_bringup_scene_is_a_file_or_a_built_in_name(capsys):
    """`bringup --scene` takes a YAML file or a built-in scene's name (as the launch
    file's ``scene``); anything else is a usage error naming the built-ins, before any
    node starts."""
    require_ros()
    from ae_tactile.ros.bringup import parse_args

    args = parse_args(["--scene", "incipient_slip"])
    assert os.path.samefile(args.scene, os.path.join(SCENES, "incipient_slip.yaml"))
    path = os.path.join(SCENES, "three_pins.yaml")
    assert os.path.samefile(parse_args(["--scene", path]).scene, path)
    assert os.path.basename(parse_args([]).scene) == "showcase.yaml"
    with pytest.raises(SystemExit) as e:
        parse_args(["--scene", "no_such_scene"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "no_such_scene" in err and "incipient_slip" in err and "Traceback" not in err


def test_bringup_executable_with_parameter_file_and_namespace(tmp_path):
    """The demo's entry point as a user runs it: parameter file, namespace, summary file."""
    exe = installed_executable("bringup")
    out = tmp_path / "summary.json"
    proc = subprocess.run(
        [
            exe,
            "--scene",
            os.path.join(SCENES, "three_pins.yaml"),
            "--monitor",
            "--namespace",
            "finger1",
            "--params-file",
            os.path.join(ROOT, "config", "water_skin.yaml"),
            "--summary-json",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "=== summary ===" in proc.stdout and "Traceback" not in proc.stderr
    s = json.loads(out.read_text())
    assert s["emissions"]["matched"] == 3 and s["touch_release"]["typed_correctly"] == 3
    assert s["emissions"]["rms_position_error_mm"] < 0.05
    bad = subprocess.run(
        [exe, "--params-file", str(tmp_path / "missing.yaml")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 2 and "not found" in bad.stderr


def _running(pid: int) -> bool:
    """pid exists and is not a zombie."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_a_bringup_killed_outright_leaves_no_process_behind():
    """SIGKILL gives bringup no chance to stop its children: the simulated fingertip (which
    would otherwise play into a pty nobody reads, using CPU, for ever) and the overlap
    resolver's worker end by themselves."""
    import signal

    kids: list[int] = []
    exe = installed_executable("bringup")
    proc = subprocess.Popen(
        [exe, "--scene", os.path.join(SCENES, "touch_hold_release.yaml"), "--duration", "0"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 300.0  # a liveness guard, not a speed bound
        while time.monotonic() < deadline and proc.poll() is None:
            kids = children(proc.pid)
            names = []
            for k in kids:
                try:
                    with open(f"/proc/{k}/cmdline", "rb") as fh:
                        names.append(fh.read())
                except OSError:
                    pass
            if any(b"sim_fingertip" in n for n in names) and any(
                b"overlap_worker" in n for n in names
            ):
                break
            time.sleep(0.1)
        assert proc.poll() is None, "bringup ended early"
        assert len(kids) >= 2, kids
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        deadline = time.monotonic() + 120.0
        while time.monotonic() < deadline and any(_running(k) for k in kids):
            time.sleep(0.1)
        left = [k for k in kids if _running(k)]
        assert not left, "children left running"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for k in kids:  # a failing run leaves nothing behind either
            if _running(k):
                os.kill(k, signal.SIGKILL)


def test_bringup_cli_parses_the_documented_arguments():
    from ae_tactile.ros.bringup import parse_args

    a = parse_args(
        [
            "--scene",
            "x.yaml",
            "--namespace",
            "f1",
            "--params-file",
            "p.yaml",
            "--no-sim",
            "--port",
            "socket://localhost:5000",
            "--method",
            "ml",
            "--grip-reflex",
            "--best-effort",
        ]
    )
    assert isinstance(a, argparse.Namespace)
    assert (
        a.scene,
        a.namespace,
        a.params_file,
        a.use_sim,
        a.port,
        a.method,
        a.grip_reflex,
        a.reliable,
    ) == ("x.yaml", "f1", "p.yaml", False, "socket://localhost:5000", "ml", True, False)


def test_interference_bursts_never_become_contacts_and_are_counted(ros_context):
    """A touch held while a motor driver switches at 1 kHz (common-mode bursts on the four
    channels, served by the simulated fingertip on the same stream): the touch and its
    release are found, the bursts are rejected and counted, and no slip event comes of them."""
    system, s = run_system(ros_context, os.path.join(SCENES, "interference.yaml"))
    try:
        c = system.driver.pipeline.all_counts()
        tr = s["touch_release"]
        assert tr["found"] == tr["truth"] == 2 and tr["typed_correctly"] == 2
        false_events = s["emissions"]["events"] - s["emissions"]["matched"]
        rejected = c["rejected_INTERFERENCE"]
        assert rejected >= 250  # ~300 bursts, nearly all caught
        assert false_events <= 0.02 * rejected  # a phantom touch is rare
        assert not {"SLIP", "TEXTURE"} & set(s["slip_events"]), s["slip_events"]
    finally:
        system.close()


def test_input_coupled_interference_rejected_once_the_wall_echo_is_learnt(ros_context, tmp_path):
    """A fingertip with wall echoes: three taps away from the apex, then switching edges
    entering the amplifier's input (shaped like an apex touch by the front end) at 1 kHz
    over a held touch. The driver learns the echo from the taps (default settings) and
    rejects every edge: the taps, the touch and its release are found, nothing else."""
    scene = scene_file(
        tmp_path, "interference", effects={"reflections": True}, coupling="input", kind="edge",
        taps_before=3, start_s=0.3, touch_time_s=0.305, hold_s=0.2, duration_s=0.55,
    )
    system, s = run_system(ros_context, scene)
    try:
        loc = system.driver.pipeline.localizer
        assert loc.echo_test_status().startswith("learnt"), loc.echo_test_status()
        assert loc.echo_learner.ratio == pytest.approx(0.5, abs=0.05)  # the wall's -0.5
        tr = s["touch_release"]
        assert tr["found"] == tr["truth"] == 8 and tr["typed_correctly"] == 8
        rejected = loc.counts["rejected_INTERFERENCE"]
        assert rejected >= 200  # ~250 edges
        assert s["emissions"]["events"] == s["emissions"]["matched"]  # no phantom touch
        assert not {"SLIP", "TEXTURE", "SLIP_PRECURSOR"} & set(s["slip_events"])
    finally:
        system.close()
