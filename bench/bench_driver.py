# SPDX-License-Identifier: Apache-2.0
"""Driver node throughput and CPU in raw-packet mode (pipeline:=false, the set-up for
recording): PACKET frames pushed through a pty at fixed rates, published as PacketArray.
(The in-process pipeline's latency and sustained rate: bench/bench_system.py.)

A writer thread plays the device: it ACKs the driver's commands and writes PACKET
frames (4 x 400 int16, the default window) at a target rate with proper sequence
numbers and device timestamps. The `driver` executable runs as its own process
(reliable QoS); this process subscribes to `packets` and counts what arrives.
For each rate: packets sent / published / received, drops counted by the driver,
bytes/s, and the driver process's CPU (user + system time from /proc) per second.

Run: make bench-driver   (results: bench/results/driver.json)

``--in-process``: the CPU time per packet of the driver's core path in this process, no
ROS (the reader thread's work for one packet at the rates where each read holds one frame):
decode (`StreamDecoder.feed`, one frame a read), build (`PacketBuilder.packet`: volts,
noise, onset, host stamp) and localize (`PacketLocalizer.process` of one packet: checks,
compiled fit, screens, weak-release gate, learning), over the packets of two simulator
scenes of random touches at 1,000 emissions/s; time.process_time, the best of
AE_BENCH_REPEATS runs (results: bench/results/driver_in_process.json, with the machine's
load).
"""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import sys
import threading
import time
import tty

import numpy as np

from ae_tactile.protocol import (
    Ack,
    AckResult,
    Command,
    DeviceState,
    Direction,
    FrameEncoder,
    Packet,
    Status,
    StreamDecoder,
)

RATES = [int(r) for r in os.environ.get("AE_BENCH_RATES", "500,1000,2000,5000,10000").split(",")]
SECONDS = 4.0
N = 400


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class FakeDevice(threading.Thread):
    """Writes PACKET frames at `rate` per second on the pty master; ACKs commands."""

    def __init__(self, master: int):
        super().__init__(daemon=True)
        self.master = master
        self.encoder = FrameEncoder(boot=True)
        self.decoder = StreamDecoder(direction=Direction.HOST_TO_DEVICE)
        rng = np.random.default_rng(0)
        self.samples = rng.integers(-300, 300, (4, N)).astype(np.int16)
        self.rate = 0.0
        self.sent = 0
        self.bytes = 0
        self.index = 0
        self.t0 = time.monotonic_ns()
        self.stop = False
        os.set_blocking(master, False)

    def now_us(self) -> int:
        return ((time.monotonic_ns() - self.t0) // 1000) & 0xFFFFFFFF

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self.master, view)
                view = view[n:]
            except BlockingIOError:
                time.sleep(0.0002)

    def run(self) -> None:
        next_status = 0.0
        due = time.monotonic()
        while not self.stop:
            try:
                data = os.read(self.master, 4096)
            except (BlockingIOError, OSError):
                data = b""
            for f in self.decoder.feed(data):
                if isinstance(f.body, Command):
                    self.write(
                        self.encoder.encode(
                            Ack(f.body.command_id, f.body.opcode, AckResult.OK, 0), self.now_us()
                        )
                    )
            now = time.monotonic()
            if now >= next_status:
                self.write(
                    self.encoder.encode(
                        Status(
                            self.now_us(),
                            DeviceState.TRIGGERED,
                            10_000_000,
                            2**-11,
                            10,
                            N,
                            80,
                            0,
                            0,
                            (0, 1, 0),
                            "BENCH",
                        ),
                        self.now_us(),
                    )
                )
                next_status = now + 1.0
            rate = self.rate
            if rate <= 0:
                time.sleep(0.001)
                due = time.monotonic()
                continue
            while due <= now:
                body = Packet(
                    self.samples, 10_000_000, 2**-11, first_sample_index=self.index, pre_trigger=80
                )
                frame = self.encoder.encode(body, self.now_us())
                self.write(frame)
                self.index += 1000
                self.sent += 1
                self.bytes += len(frame)
                due += 1.0 / rate
            time.sleep(0.0005)


def _scene_stream(seed: int):
    """(frames' bytes one per packet, counts, sample rate, v_per_count, geometry) of a
    random-touch scene at 1,000 emissions/s (4 s)."""
    import bench_system as bs

    from ae_tactile.geometry import FingertipGeometry

    counts, first, fs, vpc, body = bs.render_scene_packets(
        "random_touches", {"duration_s": 4.0, "seed": seed, "params": {"rate_hz": 500}})
    enc = FrameEncoder(boot=True)
    frames = [
        enc.encode(Packet(counts[k], int(fs), vpc, first_sample_index=int(first[k]),
                          pre_trigger=bs.PRE), int(first[k] * 1e6 / fs) & 0xFFFFFFFF)
        for k in range(len(counts))
    ]
    geo = FingertipGeometry(radius_m=body["radius_m"], element_offset_m=body["element_offset_m"],
                            sound_speed_m_s=body["sound_speed_m_s"])
    return frames, fs, geo


def _stage_us(frames, fs, geo) -> dict:
    """CPU time per packet [us] of decode, build and localize (one run)."""
    from ae_tactile.link.config import LinkConfig
    from ae_tactile.link.packets import PacketBuilder
    from ae_tactile.pipeline.localize import PacketLocalizer
    from ae_tactile.timesync import DeviceClockMapper

    mapper = DeviceClockMapper()
    mapper.update(0, 10**12)
    builder = PacketBuilder(LinkConfig("bench"), mapper, {}, lambda records: None)
    loc = PacketLocalizer(geometry=geo)
    loc.warm_up(fs, N)
    builder.packet(StreamDecoder().feed(frames[0])[0].body, 0)  # compiled front end
    dec, n = StreamDecoder(), len(frames)
    t0 = time.process_time()
    got = [f for b in frames for f in dec.feed(b)]
    t1 = time.process_time()
    records = [builder.packet(f.body, int(f.device_time_us) * 1000) for f in got]
    t2 = time.process_time()
    for r in records:
        loc.process([r])
    t3 = time.process_time()
    assert len(got) == n and loc.counts["packets"] == n
    return {"decode": (t1 - t0) / n * 1e6, "build": (t2 - t1) / n * 1e6,
            "localize": (t3 - t2) / n * 1e6}


def in_process() -> int:
    """``--in-process``: CPU time per packet of the core path (module docstring)."""
    repeats = int(os.environ.get("AE_BENCH_REPEATS", "3"))
    load0 = os.getloadavg()[0]
    scenes = [_scene_stream(seed) for seed in (101, 102)]
    best: dict = {}
    for _ in range(repeats):
        for frames, fs, geo in scenes:
            for k, v in _stage_us(frames, fs, geo).items():
                best[k] = min(best.get(k, math.inf), v)
    best["total"] = best["decode"] + best["build"] + best["localize"]
    load1 = os.getloadavg()[0]
    for k, v in best.items():
        print(f"{k:>9}: {v:7.1f} us/packet", flush=True)
    out = {
        "benchmark": "driver core path in process, CPU us per packet (best of runs)",
        "machine": platform.platform(), "cpus": os.cpu_count(),
        "load_average_1min_before_after": [load0, load1],
        "packets": sum(len(s[0]) for s in scenes), "repeats": repeats,
        "us_per_packet": {k: round(v, 2) for k, v in best.items()},
    }
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    os.makedirs(os.path.join(root, "bench", "results"), exist_ok=True)
    with open(os.path.join(root, "bench", "results", "driver_in_process.json"), "w") as fh:
        json.dump(out, fh, indent=2)
    return 0


def main() -> int:
    if "--in-process" in sys.argv[1:]:
        return in_process()
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from ae_tactile.msg import PacketArray

    root = os.environ.get(
        "AE_TACTILE_ROOT", os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    )
    exe = os.path.join(root, "install", "ae_tactile", "lib", "ae_tactile", "driver")
    os.environ.setdefault("ROS_DOMAIN_ID", "77")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    master, slave = os.openpty()
    tty.setraw(slave)
    port = os.ttyname(slave)
    dev = FakeDevice(master)
    dev.start()
    driver = subprocess.Popen(
        [
            exe,
            "--ros-args",
            "-p",
            f"port:={port}",
            "-p",
            "reliable_qos:=true",
            "-p",
            "pipeline:=false",
            "-p",
            "queue_max_batches:=100000",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    rclpy.init()
    node = rclpy.create_node("bench_listener")
    received = {"packets": 0, "dropped": 0}

    def on_msg(msg):
        received["packets"] += len(msg.packets)
        received["dropped"] = msg.packets_dropped

    node.create_subscription(
        PacketArray,
        "packets",
        on_msg,
        QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE),
    )
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    t_end = time.monotonic() + 5.0
    while time.monotonic() < t_end:  # discovery + driver start-up
        ex.spin_once(timeout_sec=0.05)
    rows = []
    for rate in RATES:
        sent0, bytes0, recv0 = dev.sent, dev.bytes, received["packets"]
        cpu0, t0 = cpu_seconds(driver.pid), time.monotonic()
        dev.rate = rate
        while time.monotonic() - t0 < SECONDS:
            ex.spin_once(timeout_sec=0.01)
        dev.rate = 0
        t1 = time.monotonic()
        cpu1 = cpu_seconds(driver.pid)
        drain = time.monotonic() + 3.0
        while time.monotonic() < drain and received["packets"] - recv0 < dev.sent - sent0:
            ex.spin_once(timeout_sec=0.01)
        sent, got = dev.sent - sent0, received["packets"] - recv0
        row = {
            "target_packets_per_s": rate,
            "sent": sent,
            "received": got,
            "lost": sent - got,
            "driver_reported_dropped_total": received["dropped"],
            "sent_packets_per_s": sent / (t1 - t0),
            "bytes_per_s": (dev.bytes - bytes0) / (t1 - t0),
            "driver_cpu_percent_of_one_core": 100.0 * (cpu1 - cpu0) / (t1 - t0),
        }
        rows.append(row)
        print(
            f"{rate:>6} pkt/s target: sent {sent} received {got} lost {sent - got} "
            f"| {row['bytes_per_s'] / 1e6:6.1f} MB/s "
            f"| driver CPU {row['driver_cpu_percent_of_one_core']:5.1f} %",
            flush=True,
        )
    dev.stop = True
    driver.send_signal(2)
    driver.wait(10)
    ex.shutdown()
    node.destroy_node()
    rclpy.shutdown()
    out = {
        "benchmark": "driver node over a pty, PACKET frames 4x400 int16, reliable QoS",
        "machine": platform.platform(),
        "cpus": os.cpu_count(),
        "seconds_per_rate": SECONDS,
        "rows": rows,
    }
    os.makedirs(os.path.join(root, "bench", "results"), exist_ok=True)
    with open(os.path.join(root, "bench", "results", "driver.json"), "w") as fh:
        json.dump(out, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
