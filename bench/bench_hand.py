# SPDX-License-Identifier: Apache-2.0
"""Hand benchmark: N fingertips on one computer, each within the reflex budget, measured from
the outside (issue 40 point 1).

As a user runs a hand: every fingertip is its own `driver` from the colcon install, on its
own port (a pty) and in its own namespace, all started by one `ros2 launch ae_tactile
hand.launch.py` (one include of ae_tactile.launch.py per finger). Each port is served by an
independent replay device (bench/fingertip_writer.py, one process per fingertip) writing
pre-rendered PACKET frames at the instant the device would: random touches and their
releases as the fingertip renders them (bench_system's 'natural' case: a window holds
whatever else falls into it, so some need the overlap resolver), each finger its own seed.
This process subscribes to every finger's `contacts` and `slip` like a hand controller.

Per finger: emission -> ContactEvent received latency (median / p99 / max; time the event
is received here - time the last byte of the packet that decided it was written on the
pty, both CLOCK_REALTIME) of the reflex events (TOUCH, SLIP_PRECURSOR, SLIP, TEXTURE), of
TOUCH and SLIP_PRECURSOR alone and of DETOUCH (decided release_confirm_s after the release
by design); the driver's CPU (% of one core, while its device plays) and memory (RSS, PSS,
peak RSS, threads), and those of its overlap worker (a child process); every packet
accounted for in the driver's /diagnostics (written = decoded + counted as dropped;
decoded = localized or rejected by a counted reason); the device's lateness (bytes written
after their instant: the port did not take them, the device fell behind). The two-hop
rclpy floor (bench_system.floor_ms) is measured in the same run, before and after, and the
machine's load average before and after.

Cases: N = 1, 3, 5 fingertips x 200, 1,000, 5,000 emissions/s each; drivers unpinned,
each pinned to a core of its own where cores allow (N <= CPUs; with N < CPUs the writers
and this process keep the other CPUs), and all N in one unpinned `hand_driver` process
(`hand.launch.py one_process:=true`; its CPU and memory are split evenly over the N
fingertips in the table). The knee: per N and placement the highest rate
tried without backlog (the device falls behind, the latency grows over the run, or
packets are not processed by the end).

Run (on an idle machine; 12 cases, ~6.5 minutes on 2 cores, at most ~9.5 if every case backs
up; the estimate is printed first):
    tools/run.sh python bench/bench_hand.py             # bench/results/hand.json, hand_table.md
    tools/run.sh python bench/bench_hand.py --quick --fingers 1,3 --rates 200 --out /tmp/h
Options: --quick (short runs, N = 1, 3 at 200 and 1,000/s), --fingers 1,3,5,
--rates 200,1000,5000, --duration-s S (every case; default by rate), --placement
unpinned|pinned|one_process|both (unpinned and pinned)|all (default), --out DIR.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import uuid

import bench_system as bs
import numpy as np
import yaml

ROOT = bs.ROOT
FINGER_NAMES = ("index", "middle", "thumb", "ring", "little")
HAND_NS = "bench_hand"
FULL_FINGERS, FULL_RATES = (1, 3, 5), (200, 1000, 5000)
QUICK_FINGERS, QUICK_RATES = (1, 3), (200, 1000)
#: [ms] device lateness p99 above which a fingertip has fallen behind: its bytes waited
#: that long for the port (a real fingertip's buffer fills; the scheduler's jitter on a
#: busy machine stays below it)
BEHIND_MS = 20.0
START_TIMEOUT_S = 240.0  # [s] launch -> every finger's first event (imports, JIT, discovery)
#: a device still playing PLAY_LIMIT x its schedule + 10 s after every finger's first event is
#: stopped (a backlog: the rest of its packets count as not written)
PLAY_LIMIT = 2.0
DRAIN_S = 1.5  # [s] after the last device's schedule: events still in flight arrive
COUNTS_STILL_S = 5.0  # [s] the drivers' packet counts not moving: every packet is in them
STOP_TIMEOUT_S = 60.0  # [s] Ctrl-C -> every process of the launch gone
#: [s] what a case costs besides its devices' schedule on an idle 2-core machine
#: (launch, imports and JIT per driver, discovery, drain, stop), for the run-time estimate
CASE_OVERHEAD_S, PER_DRIVER_START_S = 12.0, 6.0
ALL_CPUS = bs.ALL_CPUS
MB = 1024.0 * 1024.0


def default_duration_s(rate_hz: float, quick: bool) -> float:
    """[s] of each device's schedule: >= ~1,200 emissions per finger (quick: ~400), never
    below 2 s (1 s quick), never above 6 s (enough reflex events for a p99)."""
    if quick:
        return float(np.clip(400.0 / rate_hz, 1.0, 2.0))
    return float(np.clip(3000.0 / rate_hz, 2.0, 6.0))


# ---------------------------------------------------------------------------- devices
_RENDERED: dict = {}


def finger_packets(rate_hz: float, finger: int, duration_s: float):
    """A fingertip's packets for random touches and releases at ``rate_hz`` emissions/s as
    the fingertip renders them (its own seed), first window 50 ms after START. Cached: a
    finger plays the same scene in every case of one rate."""
    key = (rate_hz, finger, duration_s)
    if key not in _RENDERED:
        counts, first, fs, vpc, body = bs.render_scene_packets(
            "random_touches",
            {"duration_s": duration_s, "seed": 101 + finger, "params": {"rate_hz": rate_hz / 2}},
        )
        first = first - first[0] + int(0.05 * fs)
        _RENDERED[key] = (counts, first, fs, vpc, body)
    return _RENDERED[key]


class Device:
    """One replay fingertip: bench/fingertip_writer.py on its own pty."""

    def __init__(self, tmp: str, name: str, counts, first, fs: float, vpc: float):
        self.name = name
        self.due_s = (first + bs.N_SAMPLES) / fs
        self.packets = len(counts)
        pk = os.path.join(tmp, f"{name}_packets.npz")
        np.savez(pk, counts=counts, due_s=self.due_s, first_sample_index=first,
                 pre_trigger=bs.PRE, sample_rate_hz=int(fs), v_per_count=vpc)
        self.log = os.path.join(tmp, f"{name}_log.npz")
        port_file = os.path.join(tmp, f"{name}_port")
        self.proc = subprocess.Popen(
            [sys.executable, os.path.join(ROOT, "bench", "fingertip_writer.py"), pk, self.log,
             port_file, "pty"])
        t_end = time.monotonic() + 30.0
        while not os.path.exists(port_file) and time.monotonic() < t_end:
            time.sleep(0.01)
        with open(port_file) as fh:
            pty = fh.read().strip()
        # the driver opens a link of our own, removed once the device is done: the kernel
        # hands a freed pty number to the next process that asks, and a driver reconnecting
        # to its old path would read a stranger's bytes
        self.port = os.path.join(tmp, f"{name}_tty")
        os.symlink(pty, self.port)
        self.stopped = False

    def unlink(self) -> None:
        """The device is done: its port is gone for the driver (it retries, counted)."""
        if os.path.lexists(self.port):
            os.unlink(self.port)

    def stop(self) -> None:
        """Stop writing (the schedule could not be played): the device saves its log and
        keeps its port open, so the driver still reads what the port holds."""
        self.unlink()
        if self.proc.poll() is None and not self.stopped:
            self.proc.send_signal(signal.SIGINT)
            self.stopped = True
            t_end = time.monotonic() + 10.0
            while not os.path.exists(self.log) and self.proc.poll() is None \
                    and time.monotonic() < t_end:
                time.sleep(0.01)

    def close(self) -> None:
        """End the device process (its port closes)."""
        self.unlink()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)  # it saves its log if not yet saved
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)

    def result(self) -> dict:
        """written_ns (-1: not written), scheduled_ns and the lateness summary."""
        if os.path.exists(self.log):
            w = np.load(self.log)
            written, start_ns = w["written_ns"], int(w["start_ns"])
        else:  # the writer had to be killed: nothing it wrote can be told apart
            written, start_ns = np.full(self.packets, -1, dtype=np.int64), 0
        sched = start_ns + np.rint(self.due_s * 1e9).astype(np.int64)
        ok = written >= 0
        late = (written[ok] - sched[ok]) * 1e-6
        out = {"packets": self.packets, "written": int(ok.sum()),
               "not_written": int((~ok).sum()), "log_saved": os.path.exists(self.log)}
        if late.size:
            out.update(lateness_ms_median=float(np.median(late)),
                       lateness_ms_p99=float(np.percentile(late, 99)),
                       lateness_ms_max=float(late.max()))
        out["fell_behind"] = bool(out["not_written"] or out.get("lateness_ms_p99", 0) > BEHIND_MS)
        return out, written, sched


# ---------------------------------------------------------------------------- process facts
def proc_memory(pid: int) -> dict:
    """[MB] resident (RSS), proportional (PSS, shared pages split among their users) and
    peak resident (VmHWM) memory of a process, and its thread count."""
    out = {}
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                key, _, value = line.partition(":")
                if key in ("VmRSS", "VmHWM"):
                    out[{"VmRSS": "rss_mb", "VmHWM": "peak_rss_mb"}[key]] = \
                        int(value.split()[0]) / 1024.0
                elif key == "Threads":
                    out["threads"] = int(value)
    except OSError:
        return out
    try:
        with open(f"/proc/{pid}/smaps_rollup") as fh:
            for line in fh:
                if line.startswith("Pss:"):
                    out["pss_mb"] = int(line.split()[1]) / 1024.0
    except OSError:
        pass  # no smaps_rollup (old kernel, no permission): RSS only
    return out


def children(pid: int) -> list[int]:
    """Pids of the processes whose parent is ``pid`` (the driver's overlap worker)."""
    out = []
    for p in os.listdir("/proc"):
        if not p.isdigit():
            continue
        try:
            with open(f"/proc/{p}/stat") as fh:
                if int(fh.read().rsplit(")", 1)[1].split()[1]) == pid:
                    out.append(int(p))
        except (OSError, ValueError, IndexError):
            continue
    return out


def total_memory(pids: list[int]) -> dict:
    """[MB] RSS and PSS summed over processes (PSS: their shared pages counted once)."""
    facts = [proc_memory(p) for p in pids]
    return {k: sum(f.get(k, 0.0) for f in facts) for k in ("rss_mb", "pss_mb")} | \
        {"processes": len(facts)}


def marked_processes(marker: str) -> list[tuple[int, str]]:
    """(pid, command line) of live processes whose environment carries ``marker``."""
    found = []
    needle = f"AE_BENCH_HAND_MARKER={marker}".encode()
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            with open(f"/proc/{pid}/environ", "rb") as fh:
                if needle not in fh.read().split(b"\0"):
                    continue
            with open(f"/proc/{pid}/cmdline", "rb") as fh:
                found.append((int(pid), fh.read().replace(b"\0", b" ").decode(errors="replace")))
        except OSError:
            continue
    return found


class HandLaunch:
    """`ros2 launch ae_tactile hand.launch.py` in its own process group, output in a file,
    a marker in the environment of every process it starts."""

    def __init__(self, fingers, ports, params_file, cpus, log_path, one_process=False):
        self.marker = uuid.uuid4().hex
        self.one_process = one_process
        self.log_path = log_path
        args = [f"fingers:={','.join(fingers)}", "use_sim:=false", f"ports:={','.join(ports)}",
                f"namespace:={HAND_NS}", f"params_file:={params_file}",
                "wait_for_subscribers:=1"]
        if cpus:
            args.append(f"driver_cpus:={' '.join(str(c) for c in cpus)}")
        if one_process:
            args.append("one_process:=true")
        self.cmd = ["ros2", "launch", "ae_tactile", "hand.launch.py", *args]
        env = dict(os.environ, AE_BENCH_HAND_MARKER=self.marker, PYTHONUNBUFFERED="1")
        self._log = open(log_path, "w")
        self.proc = subprocess.Popen(self.cmd, stdout=self._log, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, env=env,
                                     start_new_session=True)

    def driver_pid(self, finger: str) -> int | None:
        for pid, cmd in marked_processes(self.marker):
            if self.one_process and "lib/ae_tactile/hand_driver " in cmd:
                return pid  # every finger's
            if "lib/ae_tactile/driver " in cmd and f"__ns:=/{HAND_NS}/{finger} " in cmd + " ":
                return pid
        return None

    def output(self) -> str:
        self._log.flush()
        with open(self.log_path, errors="replace") as fh:
            return fh.read()

    def stop(self) -> int | None:
        """Ctrl-C to the group; SIGKILL to whatever of the launch is left after
        STOP_TIMEOUT_S. The launch's exit code (None: it had to be killed)."""
        code = None
        try:
            os.killpg(self.proc.pid, signal.SIGINT)
            code = self.proc.wait(STOP_TIMEOUT_S)
        except ProcessLookupError:
            code = self.proc.poll()
        except subprocess.TimeoutExpired:
            pass
        for pid, _ in marked_processes(self.marker):
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        self._log.close()
        return code


# ---------------------------------------------------------------------------- subscriber
class HandListener:
    """One node in this process subscribed to every finger's `contacts` and `slip` and to
    /diagnostics: rows (receive ns, event type, deciding packet id, stamp ns) per finger and
    each finger's latest diagnostics values per status."""

    def __init__(self, fingers):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray

        from ae_tactile.msg import ContactEvent
        from ae_tactile.ros.driver_params import EVENT_QOS

        self.node = rclpy.create_node("bench_hand_listener")
        self.rows = {f: [] for f in fingers}
        self.first_event_wall = {}
        self.diag = {f: {} for f in fingers}
        self._prefix = {f"/{HAND_NS}/{f}/driver: ": f for f in fingers}
        for f in fingers:
            cb = self._on(f)
            self.node.create_subscription(ContactEvent, f"/{HAND_NS}/{f}/contacts", cb,
                                          EVENT_QOS)
            self.node.create_subscription(ContactEvent, f"/{HAND_NS}/{f}/slip", cb, EVENT_QOS)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 100)
        try:  # rclpy's events executor: the least dispatch overhead per message
            from rclpy.experimental import EventsExecutor

            self.ex = EventsExecutor()
        except ImportError:
            from rclpy.executors import SingleThreadedExecutor

            self.ex = SingleThreadedExecutor()
        self.ex.add_node(self.node)

    def _on(self, finger):
        rows = self.rows[finger]

        def on_event(msg) -> None:
            rows.append((time.time_ns(), msg.event_type,
                         msg.packet_ids[-1] if len(msg.packet_ids) else -1,
                         msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec))
        return on_event

    def _on_diag(self, msg) -> None:
        for st in msg.status:
            for prefix, finger in self._prefix.items():
                if st.name.startswith(prefix):
                    self.diag[finger][st.name[len(prefix):]] = {kv.key: kv.value
                                                                for kv in st.values}

    def spin_for(self, seconds: float) -> None:
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            self.ex.spin_once(timeout_sec=0.01)

    def close(self) -> None:
        self.ex.shutdown()
        self.node.destroy_node()


# ---------------------------------------------------------------------------- analysis
#: event kinds measured: (label, ContactEvent event types, which windows). The reflex events
#: are decided by the emission whose packet they name: TOUCH (a contact begins),
#: SLIP_PRECURSOR, SLIP, TEXTURE; DETOUCH is decided by design release_confirm_s after the
#: release (unless the contact slips meanwhile), so it is apart. At high rates most
#: emissions join a contact already there: TOUCHes are few, the slip events many.
KINDS = (("reflex", (1, 3, 4, 5), "all"), ("touch", (1,), "all"), ("detouch", (2,), "all"),
         ("contact", (1, 2), "all"),
         ("slip_precursor", (3,), "all"), ("slip", (4,), "all"),
         ("touch_single", (1,), "single"), ("touch_overlapped", (1,), "overlapped"))


def latency_stats(rows: np.ndarray, written: np.ndarray) -> dict:
    """Per event kind (KINDS): count and emission -> received median / p99 / max [ms] (from
    the last byte of the packet that decided the event), first/last-quarter medians (a
    growing latency is a backlog); TOUCH events of overlapped windows (two contact events
    share their packet id: the overlap resolver's) apart from the others."""
    contact_ids = rows[np.isin(rows[:, 1], (1, 2)), 2] if rows.size else np.zeros(0, np.int64)
    ids_seen, n_seen = np.unique(contact_ids, return_counts=True)
    overlapped = ids_seen[n_seen >= 2]
    out = {"overlapped_windows": int(overlapped.size)}
    for label, types, windows in KINDS:
        sel = rows[np.isin(rows[:, 1], types)] if rows.size else rows
        if windows != "all" and sel.size:
            sel = sel[np.isin(sel[:, 2], overlapped) == (windows == "overlapped")]
        ids = sel[:, 2] if sel.size else np.zeros(0, np.int64)
        good = (ids >= 0) & (ids < len(written))
        good[good] &= written[ids[good]] >= 0
        lat = (sel[good, 0] - written[ids[good]]) * 1e-6 if good.any() else np.zeros(0)
        entry = {"events": int(lat.size)}
        if lat.size:
            q = max(lat.size // 4, 1)
            entry.update(median_ms=float(np.median(lat)), p99_ms=float(np.percentile(lat, 99)),
                         max_ms=float(lat.max()),
                         first_quarter_median_ms=float(np.median(lat[:q])),
                         last_quarter_median_ms=float(np.median(lat[-q:])))
        out[label] = entry
    return out


def _int(values: dict, key: str) -> int:
    v = values.get(key, "0")
    return int(v) if str(v).lstrip("-").isdigit() else 0


def accounting(device: dict, diag: dict) -> dict:
    """Every packet accounted for, from the driver's last /diagnostics: the device's packets
    written = decoded (`packets_out`) + counted as lost on the link or dropped
    (`packets_dropped`); decoded = the pipeline's `packets`, each localized or rejected by a
    counted reason."""
    link = diag.get("fingertip link", {})
    loc = diag.get("localization", {})
    out = {
        "written": device["written"],
        "decoded": _int(link, "packets_out"),
        "dropped_counted": _int(link, "packets_dropped"),
        "crc_errors": _int(link, "crc_errors"),
        "pipeline_packets": _int(loc, "packets"),
        "rejected": {k: _int(loc, k) for k in sorted(loc) if k.startswith("rejected_")
                     and _int(loc, k)},
        "localized_events": _int(loc, "events"),
        "diagnostics_seen": bool(link) and bool(loc),
    }
    out["unaccounted"] = out["written"] - out["decoded"] - out["dropped_counted"]
    out["accounted"] = bool(out["diagnostics_seen"] and out["unaccounted"] == 0
                            and out["pipeline_packets"] == out["decoded"])
    return out


def backlog(finger: dict) -> bool:
    """A backlog builds: the device fell behind, the latency grows over the run, or packets
    were not processed by the end."""
    c = finger["latency"]["reflex"]
    if not c.get("events"):
        return True
    grows = c["last_quarter_median_ms"] > max(3.0 * c["first_quarter_median_ms"], 5.0)
    return bool(finger["device"]["fell_behind"] or grows or not finger["packets"]["accounted"])


def cpu_percent(samples: list, t0_ns: int, t1_ns: int) -> float | None:
    """[% of one core] from (wall ns, cpu s) samples between t0_ns and t1_ns."""
    inside = [(t, c) for t, c in samples if t0_ns <= t <= t1_ns and np.isfinite(c)]
    if len(inside) < 2 or inside[-1][0] - inside[0][0] < 2e8:
        return None
    return 100.0 * (inside[-1][1] - inside[0][1]) / ((inside[-1][0] - inside[0][0]) * 1e-9)


# ---------------------------------------------------------------------------- one case
def params_file(tmp: str, body: dict) -> str:
    """The package's parameter file with the replay device's body and packet shape."""
    with open(os.path.join(ROOT, "config", "water_skin.yaml")) as fh:
        params = yaml.safe_load(fh)
    driver = params["/**/driver"]["ros__parameters"]
    driver.update(medium=body["medium"], radius_m=body["radius_m"],
                  element_offset_m=body["element_offset_m"],
                  sound_speed_m_s=body["sound_speed_m_s"], packet_samples=bs.N_SAMPLES,
                  pre_trigger_samples=bs.PRE)
    path = os.path.join(tmp, "hand_params.yaml")
    with open(path, "w") as fh:
        yaml.safe_dump(params, fh)
    return path


def placement(n: int, pinned: bool) -> tuple[list[int] | None, set[int]]:
    """(CPU of each driver or None, CPUs of the writers and this process). Pinned: the
    drivers on the last n CPUs, one each; the harness on the others (all of them when the
    drivers take every CPU)."""
    cpus = sorted(ALL_CPUS)
    if not pinned:
        return None, set(cpus)
    if n > len(cpus):
        raise ValueError(f"{n} drivers cannot each have one of {len(cpus)} CPUs")
    drivers = cpus[-n:]
    rest = set(cpus) - set(drivers)
    return drivers, rest or set(cpus)


def _play(listener, launch, devices, duration_s) -> dict:
    """Spin the listener while the devices play (until each finger's device is done and
    DRAIN_S has passed, or START_TIMEOUT_S / the play limit is up: the devices are stopped, what
    they wrote counts). Returns (wall ns, CPU s) samples of each finger's driver and device
    and of this process, and each driver's memory once its device is done."""
    fingers = [d.name for d in devices]
    watch = {"driver": {f: [] for f in fingers}, "device": {f: [] for f in fingers},
             "worker": {f: [] for f in fingers}, "subscriber": [], "memory": {},
             "worker_memory": {}}
    pids, kids = {}, {}
    started, all_started, all_played = time.monotonic(), None, None
    while all_played is None or time.monotonic() - all_played < DRAIN_S:
        listener.spin_for(0.05)
        now_ns = time.time_ns()
        watch["subscriber"].append((now_ns, bs.cpu_seconds(os.getpid())))
        for d in devices:
            pids[d.name] = pids.get(d.name) or launch.driver_pid(d.name)
            if pids[d.name]:
                watch["driver"][d.name].append((now_ns, bs.cpu_seconds(pids[d.name])))
            if pids[d.name] and d.name not in kids and listener.rows[d.name]:
                kids[d.name] = children(pids[d.name])  # started before the driver acquires
            if kids.get(d.name):
                watch["worker"][d.name].append(
                    (now_ns, sum(bs.cpu_seconds(k) for k in kids[d.name])))
            if d.proc.poll() is None:
                watch["device"][d.name].append((now_ns, bs.cpu_seconds(d.proc.pid)))
            else:
                d.unlink()
        if launch.proc.poll() is not None:
            raise RuntimeError(f"the hand launch ended early (exit {launch.proc.poll()}):\n"
                               + launch.output()[-3000:])
        playing = [d for d in devices if d.proc.poll() is None and not d.stopped]
        if all_started is None and all(listener.rows[f] for f in fingers):
            all_started = time.monotonic()
        now = time.monotonic()
        if (all_started is None and now - started > START_TIMEOUT_S) or \
                (all_started is not None and now - all_started > PLAY_LIMIT * duration_s + 10.0):
            for d in playing:  # the schedule could not be played: what was written counts
                d.stop()
            playing = []
        elif all_started is None:
            continue
        if not playing and all_played is None:
            all_played = time.monotonic()
            watch["memory"] = {f: proc_memory(pid) for f, pid in pids.items() if pid}
            watch["worker_memory"] = {f: total_memory(k) for f, k in kids.items()}
    return watch


def run_case(n: int, rate_hz: float, mode: str, duration_s: float, log_dir: str) -> dict:
    """N fingertips at rate_hz emissions/s each through the hand launch, the drivers placed
    by ``mode`` (unpinned, pinned, one_process); per-finger facts."""
    from ae_tactile.ros.cpus import pin_process

    fingers = [FINGER_NAMES[k] if k < len(FINGER_NAMES) else f"finger{k}" for k in range(n)]
    pinned, one = mode == "pinned", mode == "one_process"
    driver_cpus, harness = placement(n, pinned)
    pin_process(harness)  # this process, its threads and what it starts (writers, launch)
    t_case = time.monotonic()
    tmp = tempfile.mkdtemp(prefix="ae_bench_hand_")
    devices = []
    listener = launch = None
    result = {"fingertips": n, "rate_hz": rate_hz, "pinned": pinned, "one_process": one,
              "driver_cpus": driver_cpus, "harness_cpus": sorted(harness),
              "duration_s": duration_s}
    try:
        body = None
        for k, f in enumerate(fingers):
            counts, first, fs, vpc, body = finger_packets(rate_hz, k, duration_s)
            devices.append(Device(tmp, f, counts, first, fs, vpc))
        listener = HandListener(fingers)
        launch = HandLaunch(fingers, [d.port for d in devices], params_file(tmp, body),
                            driver_cpus, os.path.join(log_dir, f"hand_{n}x{rate_hz:g}_{mode}.log"),
                            one_process=one)
        watch = _play(listener, launch, devices, duration_s)
        result["drain_s"] = _await_counts(listener, devices)
        result["fingers"] = {}
        t_first, t_last = np.iinfo(np.int64).max, 0
        for d in devices:
            dev, written, _ = d.result()
            rows = np.array(listener.rows[d.name], dtype=np.int64).reshape(-1, 4)
            ok = written >= 0
            t0 = int(written[ok].min()) if ok.any() else 0
            t1 = int(written[ok].max()) if ok.any() else 0
            finger = {
                "device": dev,
                "latency": latency_stats(rows, written),
                "packets": accounting(dev, listener.diag[d.name]),
                "driver_cpu_percent": cpu_percent(watch["driver"][d.name], t0, t1),
                "device_cpu_percent": cpu_percent(watch["device"][d.name], t0, t1),
                "worker_cpu_percent": cpu_percent(watch["worker"][d.name], t0, t1),
                "driver_memory": watch["memory"].get(d.name, {}),
                # the driver's child processes: its overlap resolver's worker
                "worker_memory": watch["worker_memory"].get(d.name, {}),
                "diagnostics": listener.diag[d.name],
            }
            if one:  # one process for the N: its share per fingertip
                finger["process"] = {k: finger[k] for k in (
                    "driver_cpu_percent", "worker_cpu_percent", "driver_memory",
                    "worker_memory")}
                finger.update(_shared(finger, n))
            finger["backlog"] = backlog(finger)
            result["fingers"][d.name] = finger
            t_first = min(t_first, t0)
            t_last = max(t_last, t1)
        result["subscriber_cpu_percent"] = cpu_percent(watch["subscriber"], t_first, t_last)
    finally:
        if launch is not None:
            result["launch_exit_code"] = launch.stop()
        for d in devices:
            d.close()
        if listener is not None:
            listener.close()
        shutil.rmtree(tmp, ignore_errors=True)
        pin_process(set(ALL_CPUS))
    result["backlog"] = any(f["backlog"] for f in result["fingers"].values())
    result["wall_s"] = time.monotonic() - t_case
    return result


def _await_counts(listener, devices) -> float:
    """Spin until every driver's diagnostics (period 1 s) count every packet its device
    wrote, or the counts stop moving for COUNTS_STILL_S (a driver that fell behind still
    reads what its port holds). Returns the wait [s]."""
    written = {d.name: d.result()[0]["written"] for d in devices}
    t0 = last_move = time.monotonic()
    seen = None
    while time.monotonic() - last_move < COUNTS_STILL_S:
        listener.spin_for(0.1)
        links = {d.name: listener.diag[d.name].get("fingertip link", {}) for d in devices}
        now = {f: _int(v, "packets_out") + _int(v, "packets_dropped") for f, v in links.items()}
        if now != seen:
            seen, last_move = now, time.monotonic()
        if all(now[f] >= written[f] for f in now) and time.monotonic() - t0 > 1.1:
            break
    return time.monotonic() - t0


def _shared(finger: dict, n: int) -> dict:
    """CPU and memory of the one process (and its workers) split evenly over n fingertips."""
    def part(v):
        return None if v is None else v / n

    mem = {k: part(v) if k in ("rss_mb", "pss_mb", "peak_rss_mb") else v
           for k, v in finger["driver_memory"].items()}
    wmem = {k: part(v) if k in ("rss_mb", "pss_mb") else v
            for k, v in finger["worker_memory"].items()}
    return {"driver_cpu_percent": part(finger["driver_cpu_percent"]),
            "worker_cpu_percent": part(finger["worker_cpu_percent"]),
            "driver_memory": mem, "worker_memory": wmem}


def _mode(c: dict) -> str:
    return "one_process" if c.get("one_process") else "pinned" if c["pinned"] else "unpinned"


# ---------------------------------------------------------------------------- report
def _span(values, fmt="{:.2f}") -> str:
    values = [v for v in values if v is not None and np.isfinite(v)]
    if not values:
        return "n/a"
    lo, hi = min(values), max(values)
    return fmt.format(lo) if fmt.format(lo) == fmt.format(hi) else \
        f"{fmt.format(lo)}-{fmt.format(hi)}"


def _lat(entries, key="p99_ms") -> str:
    return _span([x.get(key) for x in entries])


def case_row(c: dict) -> str:
    fs = list(c["fingers"].values())
    reflex = [f["latency"]["reflex"] for f in fs]
    touch = [f["latency"]["touch"] for f in fs]
    detouch = [f["latency"]["detouch"] for f in fs]
    pre = [f["latency"]["slip_precursor"] for f in fs]
    dev = [f["device"] for f in fs]
    mem = [f["driver_memory"] for f in fs]
    acc = [f["packets"] for f in fs]
    where = ("one process, unpinned" if c.get("one_process") else
             f"pinned (CPU {', '.join(map(str, c['driver_cpus']))})" if c["pinned"]
             else "unpinned")
    lost = sum(a["unaccounted"] for a in acc)
    return (
        f"| {c['fingertips']} x {c['rate_hz']:,.0f} | {where} "
        f"| {sum(a['written'] for a in acc)} "
        f"| {_lat(reflex, 'median_ms')} / {_lat(reflex)} / "
        f"{_span([x.get('max_ms') for x in reflex], '{:.1f}')} "
        f"({sum(x['events'] for x in reflex)}) "
        f"| {_lat(touch)} ({sum(x['events'] for x in touch)}) "
        f"| {_lat(detouch, 'median_ms')} / {_lat(detouch)} ({sum(x['events'] for x in detouch)}) "
        f"| {_lat(pre)} ({sum(x['events'] for x in pre)}) "
        f"| {_lat(dev, 'lateness_ms_p99')} / "
        f"{_span([d.get('lateness_ms_max') for d in dev], '{:.1f}')}"
        f"{' **behind**' if any(d['fell_behind'] for d in dev) else ''} "
        f"| {_span([f['driver_cpu_percent'] for f in fs], '{:.0f}')} "
        f"(+{_span([f['worker_cpu_percent'] for f in fs], '{:.0f}')}) "
        f"| {_span([m.get('rss_mb') for m in mem], '{:.0f}')} / "
        f"{_span([m.get('pss_mb') for m in mem], '{:.0f}')} "
        f"(+{_span([f['worker_memory'].get('rss_mb') for f in fs], '{:.0f}')} / "
        f"{_span([f['worker_memory'].get('pss_mb') for f in fs], '{:.0f}')}) "
        f"| {_span([m.get('threads') for m in mem], '{:.0f}')} "
        f"| {'all' if all(a['accounted'] for a in acc) else f'**{lost} unaccounted**'} "
        f"| {'**yes**' if c['backlog'] else 'no'} |"
    )


def targets(res: dict) -> list[str]:
    """Issue 40's targets against this run's cases (where they were run)."""
    out = []

    def case(n, rate, mode="unpinned"):
        return next((c for c in res["cases"] if c["fingertips"] == n
                     and c["rate_hz"] == rate and _mode(c) == mode), None)

    for n, rate, mode in ((3, 1000, "unpinned"), (3, 1000, "one_process"),
                          (5, 200, "unpinned"), (5, 200, "one_process")):
        c = case(n, rate, mode)
        if c is None:
            continue
        p99 = [f["latency"]["reflex"].get("p99_ms", np.inf) for f in c["fingers"].values()]
        pre = [f["latency"]["slip_precursor"].get("p99_ms") for f in c["fingers"].values()]
        pre = [p for p in pre if p is not None]
        out.append(f"{n} x {rate:,}/s {mode.replace('_', ' ')}: reflex events p99 <= 2 ms "
                   "per finger: "
                   f"{'met' if max(p99) <= 2.0 else 'NOT met'} (worst {max(p99):.2f} ms); "
                   "SLIP_PRECURSOR p99 <= 3 ms: "
                   + (f"{'met' if max(pre) <= 3.0 else 'NOT met'} (worst {max(pre):.2f} ms)"
                      if pre else "no precursor in these scenes"))
    c = case(1, 5000, "pinned") or case(1, 5000)
    if c is not None:
        f = next(iter(c["fingers"].values()))
        out.append(f"1 x 5,000/s: the device never falls behind: "
                   f"{'met' if not f['device']['fell_behind'] else 'NOT met'} (lateness p99 "
                   f"{f['device'].get('lateness_ms_p99', float('nan')):.1f} ms, max "
                   f"{f['device'].get('lateness_ms_max', float('nan')):.1f} ms)")
    for mode in ("unpinned", "pinned", "one_process"):  # the memory a placement needs
        worst = {}  # fingertips -> (PSS, RSS) of the worst fingertip [MB]
        for c in res["cases"]:
            for f in c["fingers"].values():
                if _mode(c) != mode or not f["driver_memory"]:
                    continue
                mem = [f["driver_memory"].get(k, 0.0) + f["worker_memory"].get(k, 0.0)
                       for k in ("pss_mb", "rss_mb")]
                worst[c["fingertips"]] = max(worst.get(c["fingertips"], (0.0, 0.0)), tuple(mem))
        if worst:
            cells = ", ".join(f"N = {n}: {'met' if p <= 100 else 'NOT met'} ({p:.0f} MB PSS, "
                              f"{r:.0f} MB RSS)" for n, (p, r) in sorted(worst.items()))
            out.append(f"memory <= 100 MB per fingertip (driver + its worker, PSS: shared "
                       f"pages counted once), {mode.replace('_', ' ')}: {cells}")
    return out


def markdown(res: dict) -> str:
    fl, fl2 = res["floor_two_hop_ms"], res.get("floor_two_hop_ms_after") or {}
    lines = [
        "Hand benchmark"
        f"{' (QUICK: short runs, not the figures of record)' if res['quick'] else ''}"
        f": {res['nproc']} CPUs, load average {res['load_average_before'][0]:.2f} before, "
        f"{res['load_average_after'][0]:.2f} after (1 min); {res['wall_s']:.0f} s in all.",
        f"Floor, two bare rclpy hops (same run): median {fl['median']:.3f} ms, p99 "
        f"{fl['p99']:.3f} ms before; median {fl2.get('median', float('nan')):.3f} ms, p99 "
        f"{fl2.get('p99', float('nan')):.3f} ms after.",
        "",
        "Each cell is the range over the fingers (min-max), events summed over them. Latency: "
        "emission (the last byte of the packet that decided the event, on the pty) -> "
        "ContactEvent received in another process. Reflex events: TOUCH (a contact begins), "
        "SLIP_PRECURSOR, SLIP, TEXTURE; DETOUCH is decided by design release_confirm_s after "
        "the release. Device "
        f"lateness: bytes written after their instant (p99 > {res['behind_ms']:g} ms or bytes "
        "never written: **behind**). Packets: each written one decoded or counted as lost, "
        "each decoded one localized or rejected by a counted reason (the drivers' "
        "/diagnostics). Each driver starts a worker process of its own (the overlap "
        "resolver's): its CPU and memory in parentheses. One process: the hand_driver's "
        "CPU and memory (and its workers') divided by the fingertips.",
        "",
        "| fingertips x emissions/s each | drivers | packets written "
        "| reflex events median / p99 / max (ms) (events) | TOUCH p99 (ms) (events) "
        "| DETOUCH median / p99 (ms) (events) "
        "| SLIP_PRECURSOR p99 (ms) (events) | device lateness p99 / max (ms) "
        "| driver CPU (% of a core) (+ its worker) "
        "| driver RSS / PSS (MB) (+ its worker) | driver threads | packets "
        "| backlog |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    lines += [case_row(c) for c in res["cases"]]
    lines += ["", "Knee (highest rate tried without backlog):", ""]
    for k in res["knee"]:
        lines.append(f"- {k['fingertips']} fingertip(s), {k['mode'].replace('_', ' ')}"
                     + (f": {k['sustained_hz']:,.0f}/s" if k["sustained_hz"]
                        else ": none of the rates tried")
                     + (f" (backlog at {k['backlog_from_hz']:,.0f}/s)" if k["backlog_from_hz"]
                        else " (the highest rate tried)"))
    for f in res.get("failed_cases", []):
        lines.append(f"- FAILED: {f['fingertips']} x {f['rate_hz']:,.0f}/s "
                     f"{f['mode']}: {f['error'].splitlines()[0]}")
    t = targets(res)
    if t:
        lines += ["", "Issue 40's targets:", ""] + [f"- {x}" for x in t]
    return "\n".join(lines)


def knees(cases: list) -> list:
    out = []
    for n, mode in sorted({(c["fingertips"], _mode(c)) for c in cases}):
        sustained, backlog_from = 0.0, None
        for c in sorted((c for c in cases if c["fingertips"] == n and _mode(c) == mode),
                        key=lambda c: c["rate_hz"]):
            if c["backlog"]:
                backlog_from = c["rate_hz"]
                break
            sustained = c["rate_hz"]
        out.append({"fingertips": n, "mode": mode, "sustained_hz": sustained,
                    "backlog_from_hz": backlog_from})
    return out


PLACEMENTS = {"unpinned": ("unpinned",), "pinned": ("pinned",),
              "one_process": ("one_process",), "both": ("unpinned", "pinned"),
              "all": ("unpinned", "pinned", "one_process")}


def plan(fingers, rates, placement_mode, duration_s, quick) -> list:
    """(N, rate, mode, duration) of every case, in order; pinned only where N <= CPUs, one
    process only for N > 1."""
    cases = []
    for n in fingers:
        for mode in PLACEMENTS[placement_mode]:
            if (mode == "pinned" and n > len(ALL_CPUS)) or (mode == "one_process" and n < 2):
                continue
            for rate in rates:
                cases.append((n, float(rate), mode,
                              duration_s or default_duration_s(rate, quick)))
    return cases


def estimate_s(cases) -> tuple[float, float]:
    """[s] the run takes on an idle 2-core machine (CASE_OVERHEAD_S, PER_DRIVER_START_S):
    every device on time, and every device held up by a backlog until its play limit."""
    start = sum(CASE_OVERHEAD_S + PER_DRIVER_START_S * n for n, _, _, _ in cases) + 20.0
    return (start + sum(d for _, _, _, d in cases),
            start + sum(PLAY_LIMIT * d + 10.0 for _, _, _, d in cases))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="short runs, N = 1, 3 at 200, 1000/s")
    ap.add_argument("--fingers", help="fingertip counts, e.g. 1,3,5")
    ap.add_argument("--rates", help="emissions/s per fingertip, e.g. 200,1000,5000")
    ap.add_argument("--duration-s", type=float, help="each device's schedule (s)")
    ap.add_argument("--placement", choices=tuple(PLACEMENTS), default="all")
    ap.add_argument("--out", default=bs.RESULTS, help="directory of hand.json, hand_table.md")
    a = ap.parse_args(argv)
    fingers = [int(x) for x in a.fingers.split(",")] if a.fingers else \
        list(QUICK_FINGERS if a.quick else FULL_FINGERS)
    rates = [float(x) for x in a.rates.split(",")] if a.rates else \
        list(QUICK_RATES if a.quick else FULL_RATES)
    cases = plan(fingers, rates, a.placement, a.duration_s, a.quick)
    est, bound = estimate_s(cases)
    print(f"{len(cases)} cases, about {est / 60:.1f} min on an idle 2-core machine (at most "
          f"~{bound / 60:.1f} min if every case backs up)", flush=True)
    os.makedirs(a.out, exist_ok=True)
    os.environ.setdefault("ROS_DOMAIN_ID", str(60 + os.getpid() % 40))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import rclpy

    rclpy.init()
    bs.QUICK = a.quick  # the floor's sample count
    t0 = time.monotonic()
    log_dir = tempfile.mkdtemp(prefix="ae_bench_hand_logs_")  # each case's launch output
    res = {"benchmark": __doc__.split("\n")[0], "machine": platform.platform(),
           "nproc": os.cpu_count(), "cpus_allowed": sorted(ALL_CPUS), "quick": a.quick,
           "load_average_before": os.getloadavg(), "estimate_s": est, "estimate_bound_s": bound,
           "behind_ms": BEHIND_MS, "command": " ".join(sys.argv),
           "launch_logs": log_dir}
    res["floor_two_hop_ms"] = bs.floor_ms()
    print("floor:", res["floor_two_hop_ms"], flush=True)
    res["cases"], res["failed_cases"] = [], []
    for n, rate, mode, dur in cases:
        try:
            c = run_case(n, rate, mode, dur, log_dir)
        except Exception as exc:  # noqa: BLE001 - one case's failure is recorded, not fatal
            res["failed_cases"].append({"fingertips": n, "rate_hz": rate, "mode": mode,
                                        "error": f"{type(exc).__name__}: {exc}"[-3000:]})
            print(f"case {n} x {rate:g}/s {mode} FAILED: {exc}",
                  flush=True)
            continue
        res["cases"].append(c)
        print(case_row(c), flush=True)
    res["floor_two_hop_ms_after"] = bs.floor_ms()
    res["load_average_after"] = os.getloadavg()
    res["wall_s"] = time.monotonic() - t0
    res["knee"] = knees(res["cases"])
    rclpy.shutdown()
    with open(os.path.join(a.out, "hand.json"), "w") as fh:
        json.dump(res, fh, indent=1)
    md = markdown(res)
    with open(os.path.join(a.out, "hand_table.md"), "w") as fh:
        fh.write(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
