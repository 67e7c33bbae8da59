# SPDX-License-Identifier: Apache-2.0
"""Reflex latency of the live path: device bytes -> events received by another process.

Three processes, as on a robot: a light fingertip (bench/fingertip_writer.py) writes
pre-rendered PACKET frames on a pty at real time; the `driver` executable (in-process
pipeline: decode, localize, slip detection, publish) reads it; this process subscribes to
`emissions` (every localized emission), `contacts` (a contact's TOUCH / DETOUCH) and `slip`
like a hand controller. Latency of an event = time it is received
here - time the last byte of the packet that produced it (for a slip event: the packet
of the emission that decided it, the last of its packet_ids) was written on the pty.
Both are CLOCK_REALTIME readings on this machine.

1. Floor: two bare rclpy hops (ping -> pong -> back, std_msgs/Empty), measured in this run.
2. Random touches (Poisson) at 20, 100, 1,000 and 5,000 emissions/s: median / p99 / max
   latency, events lost, the driver's CPU (% of one core).
3. Slip: the incipient-slip scene (packets from the simulator): SLIP_PRECURSOR / SLIP latency.
4. Knee: increasing rates until a backlog builds (latency grows during the run, or the
   writer cannot hand its bytes over on time).

Run: make bench-system   (bench/results/system.json, system_table.md; README figures)
     AE_BENCH_QUICK=1 for a short run; AE_BENCH_RATES=20,1000 for chosen rates;
     AE_BENCH_NO_SLIP_KNEE=1 without the slip scene and the knee; AE_BENCH_DUMP=DIR also
     writes each case's raw series (DIR/<case>.npz: events received, bytes written);
     AE_BENCH_EXTRA_PARAMS="name=value ..." adds driver parameters (e.g.
     localization.resolve_overlaps=false); AE_BENCH_DRIVER_CPU=N runs the driver on CPU N
     (default: the last CPU this process may use; the driver's cpu_affinity parameter),
     =none leaves it to the scheduler.

The driver runs on one core of its own, as on a robot whose driver is pinned (taskset, or a
launch prefix): the writer and this process (the hand) share the other cores. The natural
case is also run unpinned, so both are on record.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.environ.get(
    "AE_TACTILE_ROOT", os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
)
RESULTS = os.path.join(ROOT, "bench", "results")
QUICK = bool(os.environ.get("AE_BENCH_QUICK"))
#: how the light fingertip hands its bytes to the driver: "tcp" (a loopback connection, the
#: bytes arrive as written) or "pty" (the kernel's tty layer, as for a USB serial device)
TRANSPORT = os.environ.get("AE_BENCH_TRANSPORT", "pty")
N_SAMPLES, PRE = 400, 80


def driver_cpu() -> int | None:
    """The CPU the driver runs on (AE_BENCH_DRIVER_CPU; default the last one this process
    could use when it started), or None: no pinning (asked for, or fewer than two CPUs to
    share out)."""
    allowed = sorted(ALL_CPUS)
    want = os.environ.get("AE_BENCH_DRIVER_CPU", "last").strip().lower()
    if want in ("none", "") or len(allowed) < 2:
        return None
    cpu = allowed[-1] if want == "last" else int(want)
    if cpu not in allowed:
        raise SystemExit(f"AE_BENCH_DRIVER_CPU={cpu}: not one of this process's CPUs {allowed}")
    return cpu


#: CPUs this process could use when it started (the harness's, less the driver's one)
ALL_CPUS = frozenset(os.sched_getaffinity(0))


def _pin_harness(cpus) -> None:
    """This process, every thread of it (DDS's too), and what it starts later (the
    writer), on ``cpus``."""
    from ae_tactile.ros.cpus import pin_process

    pin_process(set(cpus))


# ---------------------------------------------------------------------------- packets
def render_scene_packets(scene: str, overrides: dict | None = None, max_packets: int = 100_000):
    """Packets of a scene as the virtual fingertip would send them: int16 counts, window
    first-sample index (at the scene's sample rate) and the scene's sensor body."""
    from ae_tactile.sim.scene import load_scene

    sc = load_scene(os.path.join(ROOT, "config", "scenes", scene + ".yaml"), overrides)
    cfg = sc.config
    fs = cfg.sample_rate_hz
    src = sc.triggered_source(pretrigger_s=PRE / fs, window_s=N_SAMPLES / fs)
    vpc = float(np.float32(cfg.lsb_v))
    adc_max = (1 << (cfg.adc_bits - 1)) - 1
    counts, first = [], []
    while len(counts) < max_packets:
        b = src.next_packets(256)
        if len(b) == 0:
            break
        counts.append(np.clip(np.rint(b.samples_v / vpc), -adc_max - 1, adc_max).astype(np.int16))
        first.append(np.asarray(b.start_index, dtype=np.int64))
    g = cfg.geometry
    body = {
        "medium": cfg.medium.name if hasattr(cfg.medium, "name") else str(cfg.medium),
        "radius_m": g.radius_m,
        "element_offset_m": g.element_offset_m,
        "sound_speed_m_s": g.sound_speed_m_s,
    }
    return np.concatenate(counts), np.concatenate(first), float(fs), vpc, body


def poisson_schedule(rate_hz: float, duration_s: float, fs: float, seed: int) -> np.ndarray:
    """Window first-sample indices of Poisson emissions at rate_hz (windows never overlap)."""
    rng = np.random.default_rng(seed)
    n = max(int(rate_hz * duration_s), 1)
    gaps = rng.exponential(1.0 / rate_hz, n)
    gaps = np.maximum(gaps, 1.2 * N_SAMPLES / fs)
    t = 0.05 + np.cumsum(gaps)
    return np.rint(t * fs).astype(np.int64)


# ---------------------------------------------------------------------------- one run
def cpu_seconds(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            f = fh.read().rsplit(")", 1)[1].split()
        return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")
    except OSError:
        return float("nan")


#: the row type of an Emission message (ContactEvent types are 1 .. 5)
EMISSION = 100


class Listener:
    """Subscribes to emissions, contacts and slip; records (receive ns, type, deciding
    packet id, the event's stamp)."""

    def __init__(self, namespace: str):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor

        from ae_tactile.msg import ContactEvent, Emission
        from ae_tactile.ros.driver_params import EMISSION_QOS, EVENT_QOS

        self.node = rclpy.create_node("bench_hand", namespace=namespace)
        self.rows: list[tuple[int, int, int]] = []
        #: the driver's latest diagnostics values (its counts), key -> text
        self.driver_values: dict[str, str] = {}
        self._diag_prefix = f"/{namespace}/driver: "
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)
        cb = self._on
        self.node.create_subscription(ContactEvent, "contacts", cb, EVENT_QOS)
        self.node.create_subscription(ContactEvent, "slip", cb, EVENT_QOS)
        self.node.create_subscription(Emission, "emissions", self._on_emission, EMISSION_QOS)
        try:  # rclpy's events executor: the least dispatch overhead per message
            from rclpy.experimental import EventsExecutor

            self.ex = EventsExecutor()
        except ImportError:
            self.ex = SingleThreadedExecutor()
        self.ex.add_node(self.node)

    def _on(self, msg) -> None:
        self.rows.append(
            (
                time.time_ns(),
                msg.event_type,
                msg.packet_ids[-1] if len(msg.packet_ids) else -1,
                msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec,
            )
        )

    def _on_emission(self, msg) -> None:
        """Every localized emission (its reading): the per-packet path, type EMISSION."""
        self.rows.append(
            (
                time.time_ns(),
                EMISSION,
                msg.packet_ids[-1] if len(msg.packet_ids) else -1,
                msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec,
            )
        )

    def _on_diag(self, msg) -> None:
        for st in msg.status:
            if st.name.startswith(self._diag_prefix):
                self.driver_values.update((kv.key, kv.value) for kv in st.values)

    def spin_for(self, seconds: float) -> None:
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            self.ex.spin_once(timeout_sec=0.01)

    def close(self) -> None:
        self.ex.shutdown()
        self.node.destroy_node()


def run_case(
    name: str, counts, first, fs, vpc, body, *, namespace: str, extra_params: dict | None = None,
    transport: str | None = None, pinned: bool = True,
) -> dict:
    """Play packets through writer -> driver -> this process; latencies by event type.
    pinned: the driver on its own core (`driver_cpu`), the writer and this process on the
    others; otherwise all three on all CPUs."""
    cpu = driver_cpu() if pinned else None
    harness = None if cpu is None else ALL_CPUS - {cpu}
    _pin_harness(harness or ALL_CPUS)
    exe = os.path.join(ROOT, "install", "ae_tactile", "lib", "ae_tactile", "driver")
    tmp = tempfile.mkdtemp(prefix="ae_bench_")
    pk = os.path.join(tmp, "packets.npz")
    due = (first + N_SAMPLES) / fs
    np.savez(
        pk,
        counts=counts,
        due_s=due,
        first_sample_index=first,
        pre_trigger=PRE,
        sample_rate_hz=int(fs),
        v_per_count=vpc,
    )
    log = os.path.join(tmp, "log.npz")
    port_file = os.path.join(tmp, "port")
    writer = subprocess.Popen(
        [sys.executable, os.path.join(ROOT, "bench", "fingertip_writer.py"), pk, log, port_file,
         transport or TRANSPORT],
    )
    t_end = time.monotonic() + 20
    while not os.path.exists(port_file) and time.monotonic() < t_end:
        time.sleep(0.01)
    port = open(port_file).read().strip()
    if port.startswith("/dev/"):
        # the driver opens a link of this case's own: the kernel hands a freed pty number
        # to the next process that asks, and a driver reconnecting after the writer is gone
        # would read a stranger's bytes from the old path (removed when the writer ends)
        os.symlink(port, os.path.join(tmp, "tty"))
        port = os.path.join(tmp, "tty")
    listener = Listener(namespace)
    params = {
        "port": port,
        "wait_for_subscribers": 1,
        "medium": body["medium"],
        "radius_m": body["radius_m"],
        "element_offset_m": body["element_offset_m"],
        "sound_speed_m_s": body["sound_speed_m_s"],
        "packet_samples": N_SAMPLES,
        "pre_trigger_samples": PRE,
    }
    for kv in os.environ.get("AE_BENCH_EXTRA_PARAMS", "").split():
        k, v = kv.split("=", 1)
        params[k] = v
    if cpu is not None:  # the driver pins itself (and its overlap worker)
        params["cpu_affinity"] = str(cpu)
    params.update(extra_params or {})
    cmd = [exe, "--ros-args", "-r", f"__ns:=/{namespace}", "--log-level", "warn"]
    for k, v in params.items():
        cmd += ["-p", f"{k}:={v}"]
    driver = subprocess.Popen(cmd)
    cpu0 = None
    t_start = time.monotonic()
    t_stop = None
    while True:
        listener.spin_for(0.05)
        if cpu0 is None and writer.poll() is None and time.monotonic() - t_start > 0.5:
            cpu0 = (cpu_seconds(driver.pid), time.monotonic())
        if writer.poll() is not None and t_stop is None:
            t_stop = time.monotonic()
            if os.path.islink(port):
                os.unlink(port)  # the device is gone: its port too (the driver retries)
            cpu1 = (cpu_seconds(driver.pid), time.monotonic())
        if t_stop is not None and time.monotonic() - t_stop > 1.5:
            break
        if time.monotonic() - t_start > 120:
            writer.terminate()
    driver.send_signal(2)
    try:
        driver.wait(10)
    except subprocess.TimeoutExpired:
        driver.kill()
    listener.close()
    w = np.load(log)
    written = w["written_ns"]
    rows = np.array(listener.rows, dtype=np.int64).reshape(-1, 4)
    out = {
        "case": name,
        "packets": int(len(counts)),
        "packets_written": int((written >= 0).sum()),
        "duration_s": float(due[-1] - due[0]) if len(due) > 1 else 0.0,
        "driver_cpu": cpu,
        "harness_cpus": sorted(harness) if harness else None,
        # what the driver counted (its /diagnostics): the overlap resolver's work, the slip
        # step's waits for it, rejections by reason
        "driver_counts": {
            k: int(v)
            for k, v in sorted(listener.driver_values.items())
            if k.startswith(("overlap_", "slip_hold", "rejected_", "slip_rejected"))
            and v.isdigit()
        },
    }
    if cpu0 is not None and t_stop is not None:
        out["driver_cpu_percent_of_one_core"] = (
            100.0 * (cpu1[0] - cpu0[0]) / max(cpu1[1] - cpu0[1], 1e-9)
        )
    sched = w["start_ns"] + np.rint(due * 1e9).astype(np.int64)
    if os.environ.get("AE_BENCH_DUMP"):  # raw series for a closer look (not in the results)
        np.savez(
            os.path.join(os.environ["AE_BENCH_DUMP"], f"{namespace}.npz"),
            rows=rows,
            written_ns=written,
            scheduled_ns=sched,
        )
    ok = written >= 0
    out["writer_lag_ms_p99"] = (
        float(np.percentile((written[ok] - sched[ok]) * 1e-6, 99)) if ok.any() else None
    )
    # A window the overlap resolver handles (quick fit ~1 ms in the reader or beside it;
    # the exhaustive search in a worker process) gives two emissions with its packet id.
    # 'contact*': every emission's event (Emission, one per localized emission: the
    # per-packet path); 'touch': a contact's TOUCH (begin); 'detouch': its DETOUCH (end,
    # decided release_confirm_s after the release by design).
    contact_ids = rows[rows[:, 1] == EMISSION, 2] if rows.size else np.zeros(0, np.int64)
    ids_seen, n_seen = np.unique(contact_ids, return_counts=True)
    overlapped = ids_seen[n_seen >= 2]
    out["overlapped_windows"] = int(overlapped.size)
    for label, types, windows in (
        ("contact", (EMISSION,), "all"),
        ("touch", (1,), "all"),
        ("detouch", (2,), "all"),
        ("slip_precursor", (3,), "all"),
        ("slip", (4,), "all"),
        ("slip_any", (3, 4), "all"),
        ("contact_single", (EMISSION,), "single"),
        ("slip_precursor_single", (3,), "single"),
        ("slip_single", (4,), "single"),
        ("contact_overlapped", (EMISSION,), "overlapped"),
    ):
        sel = rows[np.isin(rows[:, 1], types)] if rows.size else rows
        if windows != "all" and sel.size:
            sel = sel[np.isin(sel[:, 2], overlapped) == (windows == "overlapped")]
        ids = sel[:, 2] if sel.size else np.zeros(0, np.int64)
        good = (ids >= 0) & (ids < len(written))
        lat = (sel[good, 0] - written[ids[good]]) * 1e-6 if good.any() else np.zeros(0)
        lat = lat[np.isfinite(lat)]
        entry = {"events": int(lat.size)}
        if lat.size:
            entry.update(
                median_ms=float(np.median(lat)),
                p99_ms=float(np.percentile(lat, 99)),
                max_ms=float(lat.max()),
            )
            q = max(lat.size // 4, 1)
            entry["first_quarter_median_ms"] = float(np.median(lat[:q]))
            entry["last_quarter_median_ms"] = float(np.median(lat[-q:]))
            # where it goes: emission stamp (device clock mapped to the host) -> bytes written,
            # and -> received (the event's own stamp: what a subscriber can measure itself)
            stamp = sel[good, 3]
            entry["stamp_to_written_median_ms"] = float(
                np.median((written[ids[good]] - stamp) * 1e-6)
            )
            entry["stamp_to_received_median_ms"] = float(np.median((sel[good, 0] - stamp) * 1e-6))
        out[label] = entry
    return out


def backlog(r: dict) -> bool:
    """A backlog builds: latency grows over the run, or the port could not take the bytes."""
    c = r["contact"]
    if not c.get("events"):
        return True
    grows = c["last_quarter_median_ms"] > max(3.0 * c["first_quarter_median_ms"], 5.0)
    lost = c["events"] < 0.9 * r["packets_written"]
    stalled = (r.get("writer_lag_ms_p99") or 0.0) > 20.0
    return grows or lost or stalled


def floor_ms() -> dict:
    from ae_tactile.ros.monitor_node import two_hop_floor_ms

    return two_hop_floor_ms(n=200 if QUICK else 1000)


def fmt(e: dict) -> str:
    if not e.get("events"):
        return "n/a"
    return f"{e['median_ms']:.3f} / {e['p99_ms']:.3f} / {e['max_ms']:.2f}"


def markdown(res: dict) -> str:
    fl = res["floor_two_hop_ms"]
    cpu = res.get("driver_cpu")
    where = (
        f"The driver ran on CPU {cpu} alone; the writer and the hand on the other CPUs."
        if cpu is not None
        else "The driver was not pinned to a core."
    )
    lines = [
        f"Floor, two bare rclpy hops (same run): median {fl['median']:.3f} ms, "
        f"p99 {fl['p99']:.3f} ms. {where}",
        "",
        "| emissions/s | emission events | latency median / p99 / max (ms) | median / floor "
        "| TOUCH (a contact begins) median / p99 / max (ms) | driver CPU (% of a core) |",
        "|---|---|---|---|---|---|",
    ]
    for r in res["rates"]:
        c = r["contact"]
        ratio = (
            f"{c['median_ms'] / fl['median']:.0f}x"
            if c.get("events") and fl.get("median")
            else "n/a"
        )
        lines.append(
            f"| {r['rate_hz']:g} | {c['events']} of {r['packets_written']} | {fmt(c)} | {ratio} | "
            f"{fmt(r.get('touch', {}))} | "
            f"{r.get('driver_cpu_percent_of_one_core', float('nan')):.0f} |"
        )
    s = res.get("slip")
    if s:
        lines += [
            "",
            f"Slip (incipient-slip scene, {s['packets']} packets): SLIP_PRECURSOR "
            f"{fmt(s['slip_precursor'])} ms, SLIP {fmt(s['slip'])} ms (median / p99 / max, "
            f"{s['slip_precursor']['events']} and {s['slip']['events']} events); emission events "
            f"{fmt(s['contact'])} ms.",
        ]
        if s.get("overlapped_windows"):
            lines += [
                "",
                f"Of these, {s['overlapped_windows']} packet windows went to the overlap resolver "
                "(two emission events share their packet id; their "
                f"events {fmt(s.get('contact_overlapped', {}))} ms), and so did the "
                "slip events they decide. Without them: SLIP_PRECURSOR "
                f"{fmt(s['slip_precursor_single'])} ms, SLIP {fmt(s['slip_single'])} ms "
                f"({s['slip_precursor_single']['events']} and {s['slip_single']['events']} "
                f"events), emission events {fmt(s['contact_single'])} ms.",
            ]
    n = res.get("natural")
    if n:
        lines += [
            "",
            f"Random touches and releases at {n['rate_hz']:g} emissions/s as the fingertip "
            f"renders them ({n['packets']} packets; windows are not spaced apart): emission "
            f"events {fmt(n['contact'])} ms; {n['overlapped_windows']} windows held two "
            f"emissions and went to the overlap resolver, their emission events "
            f"{fmt(n.get('contact_overlapped', {}))} ms; the others "
            f"{fmt(n.get('contact_single', {}))} ms.",
        ]
    u = res.get("natural_unpinned")
    if u:
        lines += [
            "",
            f"The same random touches with the driver not pinned to a core (it shares both "
            f"with the writer and the hand): emission events {fmt(u['contact'])} ms; the "
            f"overlap resolver's {fmt(u.get('contact_overlapped', {}))} ms, the others "
            f"{fmt(u.get('contact_single', {}))} ms.",
        ]
    n, s = res.get("natural_variant"), res.get("slip_variant")
    if n and s:
        lines += [
            "",
            "With every overlapping window fitted in the resolver's thread, beside the reader "
            f"({', '.join(f'{k}:={v}' for k, v in VARIANT.items())}): the same random touches "
            f"{fmt(n['contact'])} ms, the resolver's events "
            f"{fmt(n.get('contact_overlapped', {}))} ms, the others "
            f"{fmt(n.get('contact_single', {}))} ms; the incipient-slip scene SLIP_PRECURSOR "
            f"{fmt(s['slip_precursor'])} ms, SLIP {fmt(s['slip'])} ms.",
        ]
    k = res.get("knee")
    if k:
        lines += [
            "",
            f"Sustained without backlog up to {k['sustained_hz']:g} emissions/s "
            f"(backlog from {k['backlog_from_hz']} emissions/s)"
            if k.get("backlog_from_hz")
            else f"Sustained without backlog up to {k['sustained_hz']:g} emissions/s "
            "(the highest rate tried).",
        ]
    return "\n".join(lines)


#: The driver setting of the variant cases: every overlapping window fitted in the overlap
#: resolver's thread, beside the reader (the default fits the first two of a batch in it).
VARIANT = {"localization.overlap_inline_max": 0}
VARIANT_TAG = " (every overlapping window fitted beside the reader)"
UNPINNED_TAG = " (driver not pinned to a core)"


def natural_case(rate: str, extra_params: dict | None = None, pinned: bool = True) -> dict | None:
    """Random touches and their releases at ``rate`` emissions/s as the fingertip renders
    them: each window holds whatever else falls into it, so some need the overlap resolver
    (the rate cases above space their windows apart)."""
    rate_hz = float(rate or 0)
    if rate_hz <= 0:
        return None
    dur = 1.2 if QUICK else 3.0
    counts, first, fs, vpc, body = render_scene_packets(
        "random_touches", {"duration_s": dur, "params": {"rate_hz": rate_hz / 2}}
    )
    first = first - first[0] + int(0.05 * fs)
    tag = (VARIANT_TAG if extra_params else "") + ("" if pinned else UNPINNED_TAG)
    r = run_case(
        f"natural {rate_hz:g}/s{tag}", counts, first, fs, vpc, body, namespace="bench_nat",
        extra_params=extra_params, pinned=pinned,
    )
    r["rate_hz"] = rate_hz
    r["driver_params"] = dict(extra_params or {})
    print(
        f"natural {rate_hz:g}/s{tag}: contact {fmt(r['contact'])} ms, "
        f"{r['overlapped_windows']} windows resolved as overlaps "
        f"({fmt(r['contact_overlapped'])} ms), the others {fmt(r['contact_single'])} ms",
        flush=True,
    )
    return r


def slip_case(extra_params: dict | None = None) -> dict:
    """The incipient-slip scene as rendered: latency of SLIP_PRECURSOR / SLIP after the
    emission that decides them."""
    counts, first, fs_s, vpc_s, body_s = render_scene_packets("incipient_slip")
    first = first - first[0] + int(0.05 * fs_s)
    tag = VARIANT_TAG if extra_params else ""
    r = run_case(
        f"incipient slip{tag}", counts, first, fs_s, vpc_s, body_s, namespace="bench_slip",
        extra_params=extra_params,
    )
    r["driver_params"] = dict(extra_params or {})
    print(f"slip{tag}: precursor {fmt(r['slip_precursor'])} ms, SLIP {fmt(r['slip'])} ms",
          flush=True)
    return r


def main() -> int:
    import rclpy

    os.environ.setdefault("ROS_DOMAIN_ID", str(60 + os.getpid() % 40))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    rclpy.init()
    load_before = os.getloadavg()
    pool_counts, _, fs, vpc, body = render_scene_packets(
        "random_touches", {"duration_s": 20.0}, 400
    )
    res = {
        "benchmark": __doc__.split("\n")[0],
        "machine": platform.platform(),
        "cpus": os.cpu_count(),
        "load_average_before": load_before,
        "rates": [],
    }
    cpu = driver_cpu()
    res["driver_cpu"] = cpu
    if cpu is not None:  # the floor where the hand runs
        _pin_harness(ALL_CPUS - {cpu})
    res["floor_two_hop_ms"] = floor_ms()
    print("floor:", res["floor_two_hop_ms"], flush=True)
    rates = [int(r) for r in os.environ.get("AE_BENCH_RATES", "20,100,1000,5000").split(",")]
    for i, rate in enumerate(rates):
        dur = max(3.0, min(10.0, 2000.0 / rate)) * (0.4 if QUICK else 1.0)  # >= 200 events for p99
        first = poisson_schedule(rate, dur, fs, seed=i)
        counts = pool_counts[np.arange(len(first)) % len(pool_counts)]
        r = run_case(
            f"random touches {rate}/s", counts, first, fs, vpc, body, namespace=f"bench{i}"
        )
        r["rate_hz"] = rate
        res["rates"].append(r)
        print(
            f"{rate:>6}/s: contact {fmt(r['contact'])} ms "
            f"({r['contact']['events']} of {r['packets_written']}),"
            f" driver CPU {r.get('driver_cpu_percent_of_one_core', float('nan')):.0f} %",
            flush=True,
        )
    natural_rate = os.environ.get("AE_BENCH_NATURAL_RATE", "1000")
    res["natural"] = natural_case(natural_rate)
    res["natural_variant"] = natural_case(natural_rate, VARIANT)
    res["natural_unpinned"] = natural_case(natural_rate, pinned=False)
    if os.environ.get("AE_BENCH_NO_SLIP_KNEE"):
        rclpy.shutdown()
        print(markdown(res))
        return 0
    res["slip"] = slip_case()
    res["slip_variant"] = slip_case(VARIANT)
    knee = {"tried": []}
    sustained, backlog_from = 0, None
    for j, rate in enumerate([1000, 1500, 2000, 3000, 5000, 8000, 12000]):
        first = poisson_schedule(rate, 1.5 if QUICK else 2.5, fs, seed=100 + j)
        counts = pool_counts[np.arange(len(first)) % len(pool_counts)]
        r = run_case(f"knee {rate}/s", counts, first, fs, vpc, body, namespace=f"bench_knee{j}")
        bl = backlog(r)
        knee["tried"].append(
            {
                "rate_hz": rate,
                "backlog": bl,
                "contact": r["contact"],
                "writer_lag_ms_p99": r["writer_lag_ms_p99"],
                "driver_cpu_percent_of_one_core": r.get("driver_cpu_percent_of_one_core"),
            }
        )
        print(f"knee {rate}/s: backlog {bl}, contact {fmt(r['contact'])} ms", flush=True)
        if bl:
            backlog_from = rate
            break
        sustained = rate
    knee.update(sustained_hz=sustained, backlog_from_hz=backlog_from)
    res["knee"] = knee
    res["floor_two_hop_ms_after"] = floor_ms()
    res["load_average_after"] = os.getloadavg()
    rclpy.shutdown()
    os.makedirs(RESULTS, exist_ok=True)
    with open(os.path.join(RESULTS, "system.json"), "w") as fh:
        json.dump(res, fh, indent=2)
    md = markdown(res)
    with open(os.path.join(RESULTS, "system_table.md"), "w") as fh:
        fh.write(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
